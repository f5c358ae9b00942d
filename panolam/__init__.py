"""PanoLAM: one image in, a full head of 3D Gaussians out."""
