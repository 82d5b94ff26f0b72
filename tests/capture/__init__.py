"""capture/: `mcsplat process` (frames, registration, SfM) and the cache of triangulated points."""
