"""Lazy Adam: Adam whose rows step only when their own gradient is non-zero (one row per training camera), the
refinement benchmarks' alternative camera optimizer (`--pose-optimizer lazy`).

nerfstudio's camera optimizer keeps one row of pose adjustments per training image and trains them with Adam on
the whole tensor. A step draws one image, so a row's gradient is zero in all but about one step in N (N training
images); dense Adam still moves every row at every step along its decaying first moment, normalised by a second
moment that the zeros have shrunk, so each visit moves a camera by about sqrt(N) learning rates along that one
visit's gradient, with no averaging across visits. Lazy Adam (torch's
SparseAdam and TensorFlow's LazyAdam rule, for dense gradients) updates a row's moments and takes its step only in
the steps whose gradient reaches it, and bias-corrects by the row's own count of such steps: a visit moves a camera
by at most one learning rate, along the moment averaged over its last visits. It did not lower joint
refinement's error on the dev room (benchmarks/pose_solve.md, "Stop 42"), so geer keeps torch's Adam.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Type

import torch
from nerfstudio.engine.optimizers import OptimizerConfig


class LazyAdam(torch.optim.Optimizer):
    """Adam over the first dimension's rows, each with its own moments and step count, stepped only where its
    gradient is non-zero.

    Args:
        params: the parameters (tensors of at least one dimension) or parameter groups.
        lr: the learning rate.
        betas: the moments' decay rates.
        eps: added to the second moment's square root.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        if lr < 0 or eps < 0 or not all(0 <= b < 1 for b in betas):
            raise ValueError(f"LazyAdam: lr and eps must be >= 0 and betas in [0, 1) (got {lr}, {eps}, {betas})")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):
        """One step of every row whose gradient is non-zero; returns the closure's loss, if given."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for param in group["params"]:
                if param.grad is None:
                    continue
                if param.dim() == 0 or param.grad.is_sparse:
                    raise ValueError("LazyAdam steps the rows of dense tensors of at least one dimension")
                state = self.state[param]
                if not state:
                    state["step"] = torch.zeros(len(param), dtype=torch.float64, device=param.device)
                    state["exp_avg"] = torch.zeros_like(param)
                    state["exp_avg_sq"] = torch.zeros_like(param)
                grad = param.grad
                rows = grad.reshape(len(grad), -1).ne(0).any(dim=1).nonzero().squeeze(1)
                if len(rows) == 0:
                    continue
                state["step"][rows] += 1
                count = state["step"][rows].reshape(-1, *([1] * (param.dim() - 1)))
                exp_avg = state["exp_avg"][rows].mul_(beta1).add_(grad[rows], alpha=1 - beta1)
                exp_avg_sq = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(grad[rows], grad[rows], value=1 - beta2)
                state["exp_avg"][rows], state["exp_avg_sq"][rows] = exp_avg, exp_avg_sq
                first = exp_avg / (1 - beta1 ** count).to(param.dtype)
                second = (exp_avg_sq / (1 - beta2 ** count).to(param.dtype)).sqrt_().add_(group["eps"])
                param[rows] -= group["lr"] * first / second
        return loss


@dataclass
class LazyAdamOptimizerConfig(OptimizerConfig):
    """nerfstudio's optimizer entry for LazyAdam (the `camera_opt` of geer's configs)."""

    _target: Type = LazyAdam


def wander(optimizer: type, rows: int = 42, visits: int = 100, lr: float = 1e-3, seed: int = 0) -> float:
    """Mean distance from the start of `rows` rows of six, each reached in turn (one a step, `visits` times each)
    by a gradient of pure noise: how far the optimizer carries parameters that have nothing to learn."""
    generator = torch.Generator().manual_seed(seed)
    param = torch.zeros(rows, 6, dtype=torch.float64, requires_grad=True)
    opt = optimizer([param], lr=lr, eps=1e-15)
    for step in range(rows * visits):
        grad = torch.zeros(rows, 6, dtype=torch.float64)
        grad[step % rows] = torch.randn(6, dtype=torch.float64, generator=generator)
        param.grad = grad
        opt.step()
    return float(param.detach().norm(dim=1).mean())


if __name__ == "__main__":
    # python benchmarks/lazy_adam.py: the wander of torch's Adam and of LazyAdam on the same noise
    print(f"42 rows, 100 visits each, lr 1e-3, noise gradients: torch Adam {wander(torch.optim.Adam):.4f}, "
          f"LazyAdam {wander(LazyAdam):.4f}")
