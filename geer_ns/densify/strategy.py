"""gsplat's DefaultStrategy fed geer's step statistics.

gsplat computes its statistics from `info["means2d"].grad` of one batch of cameras in one process. geer's
training step renders its views one by one (each its own backward) and may run on several processes, so the
statistics are summed per view by geer (densify.signal.StepStatistics), reduced over the processes by the
engine, and handed to the strategy as `info["statistics"]`; everything else (when to refine, split / duplicate
/ prune / reset, the optimizer-state surgery) is gsplat's.
"""

from __future__ import annotations

from typing import Any, Dict

import torch
from gsplat.strategy import DefaultStrategy

from geer_ns.densify.signal import StepStatistics


class GeerDefaultStrategy(DefaultStrategy):
    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        """Nothing to prepare: every view's offsets are leaves, whose gradients autograd keeps."""

    def _update_state(self, params, state: Dict[str, Any], info: Dict[str, Any], packed: bool = False) -> None:
        stats: StepStatistics = info["statistics"]
        n = len(params["means"])
        device = params["means"].device
        for key in ("grad2d", "count") + (("radii",) if self.refine_scale2d_stop_iter > 0 else ()):
            if state.get(key) is None:
                state[key] = torch.zeros(n, device=device)
        state["grad2d"] += stats.grad.to(state["grad2d"])
        state["count"] += stats.views.to(state["count"])
        if self.refine_scale2d_stop_iter > 0:
            state["radii"] = torch.maximum(state["radii"], stats.radius.to(state["radii"]))
