"""render/: the rasterizer's stages (projection, binning, compositing) and outputs against the dense reference."""
