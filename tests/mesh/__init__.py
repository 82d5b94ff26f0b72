"""mesh/: meshes from Gaussians."""
