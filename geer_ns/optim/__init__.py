"""Optimizers of the Gaussian parameters."""
