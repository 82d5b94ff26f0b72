"""Depth supervision as loss terms on the per-view seams: terms.py holds the rendered depth to the SfM points and to
depth maps (metric or up to scale and shift), correlation.py to a monocular prior by Pearson's correlation."""
