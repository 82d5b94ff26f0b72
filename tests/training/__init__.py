"""The top-level modules of the method and the step: the Gaussians, the optimizers, the loss terms and features
(--surface, depth terms, depth correlation, pose refinement), metrics and SSIM, visibility, and training end to end."""
