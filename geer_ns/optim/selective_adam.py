"""Adam that steps only the rows a training step's views reached (gsplat's SelectiveAdam, Taming 3DGS).

A view sees a fraction of the scene, yet dense Adam rewrites every Gaussian's moments and moves every Gaussian
along its decaying momentum at every step. `SelectiveAdam` is torch's Adam (same state: `step`, `exp_avg`,
`exp_avg_sq`; a checkpoint of either loads into the other) whose step, when the trainer offers the step's rows
(`offer_rows`), reads and writes only those rows of each parameter, its gradient and its moments; the other rows
and their moments stay as they were. The bias correction is torch's, of the optimizer's step count: where every
row is offered the step is torch's Adam exactly (the same operations on the same tensors), and a row that is
offered in every step follows torch's Adam. gsplat 1.5's SelectiveAdam (the reference) leaves out the bias
correction; with it folded into the learning rate and epsilon the two take the same steps on the offered rows
(tests/test_selective_adam.py). Which rows, and the measurements: docs/training.md, benchmarks/skip_unneeded.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Optional, Tuple, Type

import torch
from nerfstudio.engine.optimizers import OptimizerConfig
from torch import Tensor
from torch.optim.optimizer import _get_scalar_dtype


class SelectiveAdam(torch.optim.Adam):
    """torch.optim.Adam whose next step touches only the rows given to `use_rows` (all rows when none are).

    Args: as torch.optim.Adam's; amsgrad, maximize, weight decay and capturable are not supported.
    """

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-8, weight_decay: float = 0.0,
                 **kwargs):
        if weight_decay != 0 or any(kwargs.get(k) for k in ("amsgrad", "maximize", "capturable", "differentiable")):
            raise ValueError("SelectiveAdam: weight_decay, amsgrad, maximize, capturable and differentiable are "
                             "not supported")
        super().__init__(params, lr=lr, betas=betas, eps=eps, **kwargs)
        self._rows: Optional[Tensor] = None

    def use_rows(self, rows: Optional[Tensor]) -> None:
        """The rows (first-dimension indices, long) the next step updates; None: every row (torch's Adam)."""
        self._rows = rows

    @torch.no_grad()
    def step(self, closure: Optional[Callable[[], float]] = None):
        rows, self._rows = self._rows, None
        params = [p for group in self.param_groups for p in group["params"] if p.grad is not None]
        if rows is None or all(len(rows) == p.shape[0] for p in params):  # every row: torch's Adam itself
            return super().step(closure)
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for param in group["params"]:
                if param.grad is None:
                    continue
                if param.grad.is_sparse or param.dim() == 0:
                    raise ValueError("SelectiveAdam steps the rows of dense tensors of at least one dimension")
                self._rows_step(group, param, rows.to(param.device))
        return loss

    def _state(self, param: Tensor) -> Dict[str, Tensor]:
        state = self.state[param]
        if len(state) == 0:  # torch's lazy initialization
            state["step"] = torch.tensor(0.0, dtype=_get_scalar_dtype())
            state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        return state

    def _rows_step(self, group, param: Tensor, rows: Tensor) -> None:
        """torch's _single_tensor_adam, operation for operation, on the gathered rows."""
        state = self._state(param)
        beta1, beta2 = group["betas"]
        state["step"] += 1
        if rows.numel() == 0:
            return
        grad = param.grad.index_select(0, rows)
        exp_avg = state["exp_avg"].index_select(0, rows)
        exp_avg_sq = state["exp_avg_sq"].index_select(0, rows)
        exp_avg.lerp_(grad, 1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step = float(state["step"])
        bias_correction1 = 1 - beta1**step
        bias_correction2 = 1 - beta2**step
        denom = (exp_avg_sq.sqrt() / bias_correction2**0.5).add_(group["eps"])
        moved = param.index_select(0, rows).addcdiv_(exp_avg, denom, value=-(group["lr"] / bias_correction1))
        param.index_copy_(0, rows, moved)
        state["exp_avg"].index_copy_(0, rows, exp_avg)
        state["exp_avg_sq"].index_copy_(0, rows, exp_avg_sq)


@dataclass
class SelectiveAdamOptimizerConfig(OptimizerConfig):
    """nerfstudio's optimizer entry for SelectiveAdam (geer's Gaussian parameter groups)."""

    _target: Type = SelectiveAdam
    weight_decay: float = 0
    betas: Tuple[float, float] = (0.9, 0.999)  # the distributed batch rule scales them (distributed/schedule.py)


def offer_rows(optimizers: Dict[str, torch.optim.Optimizer], rows: Callable[[], Optional[Tensor]]) -> bool:
    """Give every SelectiveAdam among `optimizers` (name -> optimizer) the rows `rows()` returns for its next step
    (`rows` is called only when there is one). Returns whether any was given rows."""
    selective = [opt for opt in optimizers.values() if isinstance(opt, SelectiveAdam)]
    if not selective:
        return False
    chosen = rows()
    for opt in selective:
        opt.use_rows(chosen)
    return chosen is not None
