"""appearance/: --appearance affine and bilateral-grid."""
