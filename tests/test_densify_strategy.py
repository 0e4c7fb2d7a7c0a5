"""GeerDefaultStrategy's own rules (geer_ns/densify/strategy.py): the refinement log counts each rule's Gaussians,
the Gaussian budget holds with the strongest candidates growing first, and the unseen prune waits for a pass."""

from __future__ import annotations

import math

import torch

from geer_ns.densify.signal import StepStatistics
from geer_ns.densify.strategy import VISIBLE_WEIGHT, GeerDefaultStrategy


def _model(n: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=gen)),
        "scales": torch.nn.Parameter(torch.log(torch.rand(n, 3, generator=gen) * 0.02 + 0.001)),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=gen)),
        "opacities": torch.nn.Parameter(torch.full((n, 1), 2.0)),
    })
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    return params, optimizers


def _stats(grad, radius=None, weight=None, pixels=None):
    n = grad.shape[0]
    return StepStatistics(grad, torch.ones(n), torch.zeros(n) if radius is None else radius,
                          torch.ones(n) if weight is None else weight, torch.full((n,), 10.0) if pixels is None else pixels)


def _refine(strategy, params, optimizers, state, stats, step=200):
    strategy.update_statistics(params, state, {"statistics": stats})
    strategy.grow(params, optimizers, state, step)
    strategy.prune(params, optimizers, state, step)
    return strategy.log[-1]


def test_the_log_counts_each_rule():
    params, optimizers = _model(100)
    with torch.no_grad():
        params["scales"][50:] = math.log(0.5)  # large: they split, the small ones duplicate
        params["opacities"][90:] = -10.0  # transparent: pruned
    grad = torch.zeros(100)
    grad[0:20] = 1.0  # small and high: duplicated
    grad[50:60] = 1.0  # large and high: split
    radius = torch.zeros(100)
    radius[70:75] = 1.0  # large on screen only: split
    strategy = GeerDefaultStrategy(grow_grad2d=0.5, grow_scale3d=0.1, grow_scale2d=0.5, refine_scale2d_stop_iter=10**6,
                                   reset_every=10**6, verbose=False)
    state = strategy.initialize_state()
    entry = _refine(strategy, params, optimizers, state, _stats(grad, radius))
    assert (entry["duplicated (gradient)"], entry["split (gradient)"], entry["split (screen size only)"]) == (20, 10, 5)
    assert entry["pruned (opacity)"] == 10
    assert entry["before"] == 100 and entry["after growth"] == 100 + 20 + 15 and entry["after"] == 125
    assert len(params["means"]) == 125 and len(state["id"]) == 125


def test_growth_stops_at_the_budget_strongest_first():
    params, optimizers = _model(100)
    grad = torch.linspace(0.0, 2.0, 100)  # everything above 0.5 wants to grow, the strongest at the end
    strategy = GeerDefaultStrategy(grow_grad2d=0.5, grow_scale3d=0.1, max_gaussians=110, reset_every=10**6,
                                   verbose=False)
    state = strategy.initialize_state()
    ids_before = torch.arange(100)
    entry = _refine(strategy, params, optimizers, state, _stats(grad))
    assert len(params["means"]) == 110
    assert entry["duplicated (gradient)"] == int((grad > 0.5).sum()) and entry["held back by max_gaussians"] > 0
    parents = ids_before[-10:]  # the ten strongest were duplicated: their copies carry child ids
    from geer_ns.densify.identity import child_ids

    assert torch.equal(torch.sort(state["id"][100:]).values, torch.sort(child_ids(parents, 200, 0)).values)
    # at the budget nothing grows
    entry = _refine(strategy, params, optimizers, state, _stats(torch.full((110,), 2.0)), step=300)
    assert len(params["means"]) == 110 and entry["held back by max_gaussians"] == 110


def test_unseen_gaussians_are_pruned_after_a_whole_pass_only():
    params, optimizers = _model(10)
    weight = torch.ones(10)
    weight[:3] = 0.5 * VISIBLE_WEIGHT  # never contributed 1/255 to any ray
    strategy = GeerDefaultStrategy(prune_unseen=True, images_per_pass=4, images_per_step=1, reset_every=10**6,
                                   verbose=False)
    state = strategy.initialize_state()
    for step in range(3):  # 3 images of a 4-image pass: too early to judge
        strategy.update_statistics(params, state, {"statistics": _stats(torch.zeros(10), weight=weight)})
    strategy.prune(params, optimizers, state, 3)
    assert len(params["means"]) == 10 and "pruned (unseen)" not in strategy.log[-1]
    strategy.update_statistics(params, state, {"statistics": _stats(torch.zeros(10), weight=weight)})
    strategy.prune(params, optimizers, state, 4)
    assert strategy.log[-1]["pruned (unseen)"] == 3 and len(params["means"]) == 7
    assert state["weight_images"] == 0 and float(state["weight"].max()) == 0.0  # a new window starts


def test_gaussians_finer_than_a_pixel_in_every_view_do_not_grow():
    params, optimizers = _model(40)
    grad = torch.ones(40)  # every Gaussian wants to grow
    pixels = torch.full((40,), 3.0)
    pixels[:25] = 0.6  # below one pixel of radius in every view of the window
    strategy = GeerDefaultStrategy(grow_grad2d=0.5, grow_scale3d=0.1, min_pixels=1.0, reset_every=10**6, verbose=False)
    state = strategy.initialize_state()
    entry = _refine(strategy, params, optimizers, state, _stats(grad, pixels=pixels))
    assert entry["duplicated (gradient)"] == 15 and entry["held back (finer than a pixel)"] == 25
    assert len(params["means"]) == 55
    assert float(state["pixels"].max()) == 0.0  # the next refinement judges its own window


def test_the_start_up_line_names_the_strategy_and_its_units():
    from geer_ns.model import GeerModelConfig
    from geer_ns.options import densification_line

    assert "densify-units image" in densification_line(GeerModelConfig())  # the default
    assert "300-pixel reference camera" in densification_line(GeerModelConfig(densify_units="reference"))
    assert "MCMCStrategy" in densification_line(GeerModelConfig(strategy="mcmc"))
