"""Each Gaussian's own SH degree: chosen from what the training images show (choice.py), evaluated only up to it
by the kernels and the twin (csrc/geer_math.h gaussian_sh_degree, render/sh.py), and stored so in checkpoints
(packing.py)."""
