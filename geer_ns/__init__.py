"""geer-ns: 3DGEER (exact, efficient 3D Gaussian rendering for generic cameras) as a nerfstudio plugin."""

__version__ = "0.1.0"
