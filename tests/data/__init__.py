"""data/: the scene loaders, their errors, undistortion, the image store."""
