"""gsplat's DefaultStrategy fed geer's step statistics, with a record of why each Gaussian grew.

geer sums the statistics per view (densify.signal.StepStatistics) and hands them to the strategy as
`info["statistics"]`. When to refine and the optimizer-state surgery are gsplat's; the growth and prune rules are
gsplat's, written out to log each rule's counts per refinement, with three additions: a resolution floor
(`min_pixels`), a Gaussian budget (`max_gaussians`) and the unseen prune (`prune_unseen`). Splits draw from each
Gaussian's identity (densify/identity.py). Details: docs/densification.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional

import torch
import torch.nn.functional as F
from gsplat.strategy import MCMCStrategy
from gsplat.strategy.ops import duplicate, remove
from torch import Tensor

from geer_ns.densify.identity import child_ids, normals
from geer_ns.densify.mcmc_cpu import install_mcmc_cpu_ops
from geer_ns.densify.signal import StepStatistics
from geer_ns.gsplat_private import DefaultStrategyHooks
from geer_ns.render.transforms import quat_to_rotmat

VISIBLE_WEIGHT = 1.0 / 255.0  # the renderer's own threshold: a pair below it is skipped
# the strategy state's rows (sh_degree: each Gaussian's own SH degree, geer_ns/sh_degrees, carried with its row)
PER_GAUSSIAN_STATE = ("id", "grad2d", "count", "radii", "weight", "pixels", "sh_degree")

# (wanted [N] Gaussians each row would add, over [N] strength, ids [N], rows N here, budget) -> allowed [N] bool
Budget = Callable[[Tensor, Tensor, Tensor, int, int], Tensor]


def strongest_first(wanted: Tensor, over: Tensor, ids: Tensor, room: int) -> Tensor:
    """Which rows may grow when growth may add `room` Gaussians: candidates (wanted > 0, each adding `wanted`)
    by strength `over` descending, equal strengths by id ascending (an order independent of rows and
    shards), the longest run of them whose additions fit. Returns a [N] bool mask."""
    candidates = torch.nonzero(wanted > 0).squeeze(1)
    order = candidates[torch.argsort(ids[candidates], stable=True)]
    order = order[torch.argsort(over[order], descending=True, stable=True)]
    allowed = torch.zeros(wanted.shape[0], dtype=torch.bool, device=wanted.device)
    allowed[order[torch.cumsum(wanted[order], 0) <= room]] = True
    return allowed


def local_budget(wanted: Tensor, over: Tensor, ids: Tensor, n: int, budget: int) -> Tensor:
    """The budget over this process's `n` Gaussians (one process or replicas: the scene)."""
    return strongest_first(wanted, over, ids, max(budget - n, 0))


@dataclass
class GeerDefaultStrategy(DefaultStrategyHooks):
    """DefaultStrategy on geer's step statistics, with a per-rule log, a budget, a resolution floor and the unseen
    prune (module docstring)."""

    max_gaussians: int = 0  # 0: no budget
    min_pixels: float = 0.0  # 0: every candidate grows, resolved or not (gsplat's rule)
    prune_unseen: bool = False
    images_per_pass: int = 1  # training images: the unseen rule waits for a whole pass over them
    images_per_step: int = 1
    log: List[Dict[str, int]] = field(default_factory=list)  # one entry per refinement, counts by rule
    budget: Optional[Budget] = field(default=None, repr=False)  # None: local_budget
    # A refinement's counts over the scene (sharded: summed over the processes); None: these Gaussians'
    totals: Optional[Callable[[Dict[str, int]], Dict[str, int]]] = field(default=None, repr=False)

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        """Nothing to prepare: every view's offsets are leaves, whose gradients autograd keeps."""

    def update_statistics(self, params, state: Dict[str, Any], info: Dict[str, Any], packed: bool = False) -> None:
        stats: StepStatistics = info["statistics"]
        n = len(params["means"])
        device = params["means"].device
        if state.get("id") is None:  # a model's Gaussians are numbered once, in their first step
            state["id"] = torch.arange(n, device=device)
        for key in ("grad2d", "count", "weight", "pixels") + (("radii",) if self.refine_scale2d_stop_iter > 0 else ()):
            if state.get(key) is None:
                state[key] = torch.zeros(n, device=device)
        state["grad2d"] += stats.grad.to(state["grad2d"])
        state["count"] += stats.views.to(state["count"])
        if self.refine_scale2d_stop_iter > 0:
            state["radii"] = torch.maximum(state["radii"], stats.radius.to(state["radii"]))
        state["weight"] = torch.maximum(state["weight"], stats.weight.to(state["weight"]))
        state["pixels"] = torch.maximum(state["pixels"], stats.pixels.to(state["pixels"]))
        state["weight_images"] = int(state.get("weight_images", 0)) + self.images_per_step  # not per Gaussian

    @torch.no_grad()
    def grow(self, params, optimizers, state: Dict[str, Any], step: int):
        n = len(params["means"])
        grads = state["grad2d"] / state["count"].clamp_min(1)
        is_grad_high = grads > self.grow_grad2d
        largest = torch.exp(params["scales"]).max(dim=-1).values
        is_small = largest <= self.grow_scale3d * state["scene_scale"]
        is_dupli = is_grad_high & is_small
        is_split_grad = is_grad_high & ~is_small
        is_split_screen = torch.zeros_like(is_grad_high)
        over = grads / self.grow_grad2d
        if step < self.refine_scale2d_stop_iter:
            is_split_screen = state["radii"] > self.grow_scale2d
            over = torch.maximum(over, state["radii"] / self.grow_scale2d)
        is_split = is_split_grad | is_split_screen
        if self.min_pixels > 0:
            resolved = state["pixels"] >= self.min_pixels
            unresolved = int(((is_dupli | is_split) & ~resolved).sum())
            is_dupli, is_split_grad, is_split_screen = (m & resolved for m in (is_dupli, is_split_grad, is_split_screen))
            is_split = is_split_grad | is_split_screen
        entry = {"step": step, "before": n, "duplicated (gradient)": int(is_dupli.sum()),
                 "split (gradient)": int(is_split_grad.sum()),
                 "split (screen size only)": int((is_split_screen & ~is_split_grad).sum())}
        if self.min_pixels > 0:
            entry["held back (finer than a pixel)"] = unresolved
        if self.max_gaussians > 0:  # each duplicate and each split adds one Gaussian
            wanted = is_dupli.long() + is_split.long()
            allowed = (self.budget or local_budget)(wanted, over, state["id"], n, self.max_gaussians)
            is_dupli, is_split = is_dupli & allowed, is_split & allowed
            held = int(wanted.sum()) - int(is_dupli.sum() + is_split.sum())
            if held:
                entry["held back by max_gaussians"] = held
        n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
        if n_dupli > 0:
            ids = state["id"][is_dupli]
            duplicate(params=params, optimizers=optimizers, state=state, mask=is_dupli)
            state["id"][n:] = child_ids(ids, step, 0)
        if n_split > 0:
            self._split(params, optimizers, state, torch.where(is_split)[0], step)
        self._entry = entry
        return n_dupli, n_split

    @torch.no_grad()
    def _split(self, params, optimizers, state: Dict[str, Any], rows, step: int) -> None:
        """Each Gaussian of `rows` becomes two: itself and a duplicate appended, each moved by its own sample of
        the Gaussian (child 1 and 2 of its id), at 1/1.6 of its scale, with a fresh optimizer state."""
        n, ids = len(params["means"]), state["id"][rows]
        mask = torch.zeros(n, dtype=torch.bool, device=rows.device)
        mask[rows] = True
        duplicate(params=params, optimizers=optimizers, state=state, mask=mask)  # copies: rows n.., fresh state
        scales = torch.exp(params["scales"][rows])
        rot = quat_to_rotmat(F.normalize(params["quats"][rows], dim=-1))
        for child, where in ((1, rows), (2, torch.arange(n, n + len(rows), device=rows.device))):
            sample = torch.einsum("nij,nj->ni", rot, scales * normals(ids, step, child).to(scales))
            params["means"].data[where] += sample
            params["scales"].data[where] = torch.log(scales / 1.6)
            if self.revised_opacity:
                opacity = 1.0 - torch.sqrt(1.0 - torch.sigmoid(params["opacities"][rows]))
                params["opacities"].data[where] = torch.logit(opacity)
            state["id"][where] = child_ids(ids, step, child)
        for name in params:  # the rows that stay in place start afresh too
            for value in optimizers[name].state[params[name]].values():
                if isinstance(value, torch.Tensor) and value.dim() > 0:
                    value[rows] = 0

    @torch.no_grad()
    def prune(self, params, optimizers, state: Dict[str, Any], step: int) -> int:
        entry = getattr(self, "_entry", None) or {"step": step, "before": len(params["means"])}
        entry["after growth"] = len(params["means"])
        rules = {"pruned (opacity)": torch.sigmoid(params["opacities"].flatten()) < self.prune_opa}
        if step > self.reset_every:
            largest = torch.exp(params["scales"]).max(dim=-1).values
            rules["pruned (3D size)"] = largest > self.prune_scale3d * state["scene_scale"]
            if step < self.refine_scale2d_stop_iter:
                rules["pruned (screen size)"] = state["radii"] > self.prune_scale2d
        if self.prune_unseen and int(state.get("weight_images", 0)) >= self.images_per_pass:
            rules["pruned (unseen)"] = state["weight"] < VISIBLE_WEIGHT
            state["weight"] = torch.zeros_like(state["weight"])
            state["weight_images"] = 0
        is_prune = torch.zeros_like(rules["pruned (opacity)"])
        for name, mask in rules.items():
            entry[name] = int((mask & ~is_prune).sum())  # each Gaussian counted under its first rule
            is_prune |= mask
        n_prune = int(is_prune.sum())
        if n_prune > 0:
            remove(params=params, optimizers=optimizers, state=state, mask=is_prune)
        entry["after"] = len(params["means"])
        if self.totals is not None:
            entry = self.totals(entry)
        if state.get("pixels") is not None:
            state["pixels"] = torch.zeros_like(state["pixels"])  # a window of its own for the next refinement
        self.log.append(entry)
        if self.verbose:
            said = ", ".join(f"{k} {v}" for k, v in entry.items() if k not in ("step", "before", "after") and v)
            print(f"geer: step {step}: {entry['before']} -> {entry['after']} Gaussians ({said or 'no change'})")
        self._entry = None
        return n_prune


def build_strategy(cfg, images_per_pass: int, images_per_step: int):
    """The densification strategy a model config asks for (cfg.strategy), and its fresh state.

    Args: cfg, a GeerModelConfig; images_per_pass, the training images; images_per_step, the images one step
    sees over all processes (cfg's step-valued options count steps of that many). Returns (strategy, state)."""
    if cfg.strategy == "mcmc":
        install_mcmc_cpu_ops()
        strategy = MCMCStrategy(
            cap_max=cfg.max_gaussians if cfg.max_gaussians > 0 else cfg.mcmc_cap_max,
            noise_lr=cfg.mcmc_noise_lr,
            refine_start_iter=cfg.warmup_length,
            refine_stop_iter=cfg.stop_split_at,
            refine_every=cfg.refine_every,
            min_opacity=cfg.mcmc_min_opacity,
            verbose=True,
        )
        return strategy, strategy.initialize_state()
    pause = -(-images_per_pass // images_per_step)  # one pass over the images, in steps
    strategy = GeerDefaultStrategy(
        max_gaussians=cfg.max_gaussians,
        min_pixels=cfg.densify_min_pixels,
        prune_unseen=cfg.prune_unseen,
        images_per_pass=images_per_pass,
        images_per_step=images_per_step,
        prune_opa=cfg.cull_alpha_thresh,
        grow_grad2d=cfg.densify_grad_thresh,
        grow_scale3d=cfg.densify_size_thresh,
        grow_scale2d=cfg.split_screen_size,
        prune_scale3d=cfg.cull_scale_thresh,
        prune_scale2d=cfg.cull_screen_size,
        refine_scale2d_stop_iter=cfg.stop_screen_size_at,
        refine_start_iter=cfg.warmup_length,
        refine_stop_iter=cfg.stop_split_at,
        reset_every=cfg.reset_alpha_every * cfg.refine_every,
        refine_every=cfg.refine_every,
        pause_refine_after_reset=pause + cfg.refine_every,
        revised_opacity=False,
        verbose=True,
    )
    return strategy, strategy.initialize_state(scene_scale=1.0)
