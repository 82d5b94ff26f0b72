            median_out[pixel] = median[b][l];
