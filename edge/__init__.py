"""Onboard part: frame sources, image encoders, PCA compression, the edge process."""
