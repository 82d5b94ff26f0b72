            vi in_front_half = use & (transmittance[b] > median_transmittance);
            median[b] = (in_front_half & g) | (~in_front_half & median[b]);
