"""Densification: the statistics a training step gathers (signal), gsplat's DefaultStrategy fed with them
(strategy), and CPU versions of gsplat's CUDA-only MCMC ops (mcmc_cpu)."""
