"""gsplat 1.4.0's private API as geer uses it (geer_ns/gsplat_private.py): the installed version, the signatures,
and the behaviour geer relies on, checked against hand-worked values. A gsplat upgrade that changes any of them
fails here rather than in training."""

from __future__ import annotations

import inspect
import math

import pytest
import torch

import gsplat
from gsplat.cuda import _torch_impl
from gsplat.strategy import DefaultStrategy
from gsplat.strategy import ops

from geer_ns import gsplat_private
from geer_ns.densify.strategy import GeerDefaultStrategy


def _parameters(fn) -> list:
    return list(inspect.signature(fn).parameters)


def test_the_installed_gsplat_is_the_one_the_adapter_was_written_for(monkeypatch):
    assert gsplat.__version__ == gsplat_private.WRITTEN_FOR == "1.4.0"
    gsplat_private.check_gsplat()
    monkeypatch.setattr(gsplat, "__version__", "1.5.0")
    with pytest.raises(RuntimeError, match=r"gsplat 1\.5\.0 is installed.*gsplat==1\.4\.0") as caught:
        GeerDefaultStrategy()
    assert "\n" not in str(caught.value)


def test_the_private_signatures_are_gsplat_1_4_0s():
    assert _parameters(DefaultStrategy._update_state) == ["self", "params", "state", "info", "packed"]
    assert _parameters(DefaultStrategy._grow_gs) == ["self", "params", "optimizers", "state", "step"]
    assert _parameters(DefaultStrategy._prune_gs) == ["self", "params", "optimizers", "state", "step"]
    assert _parameters(ops._update_param_with_optimizer) == ["param_fn", "optimizer_fn", "params", "optimizers", "names"]
    assert _parameters(_torch_impl._quat_scale_to_covar_preci) == ["quats", "scales", "compute_covar", "compute_preci",
                                                                   "triu"]
    assert _parameters(_torch_impl._fully_fused_projection) == [
        "means", "covars", "viewmats", "Ks", "width", "height", "eps2d", "near_plane", "far_plane",
        "calc_compensations", "camera_model"]
    assert _parameters(_torch_impl._spherical_harmonics) == ["degree", "dirs", "coeffs"]


def test_step_post_backward_calls_the_hooks_in_order():
    """Statistics after every backward; at a refinement step, growth then prune (then gsplat zeroes grad2d/count)."""
    calls = []

    class Recorder(gsplat_private.DefaultStrategyHooks):
        def update_statistics(self, params, state, info, packed=False):
            calls.append("statistics")
            state["grad2d"], state["count"] = torch.ones(3), torch.ones(3)

        def grow(self, params, optimizers, state, step):
            calls.append("grow")
            return 0, 0

        def prune(self, params, optimizers, state, step):
            calls.append("prune")
            return 0

    strategy = Recorder(refine_start_iter=0, refine_every=2, reset_every=1000, pause_refine_after_reset=0,
                        refine_scale2d_stop_iter=0)
    params = {"means": torch.nn.Parameter(torch.zeros(3, 3))}
    state = {}
    strategy.step_post_backward(params, {}, state, step=1, info={})
    assert calls == ["statistics"]
    strategy.step_post_backward(params, {}, state, step=2, info={})
    assert calls == ["statistics", "statistics", "grow", "prune"]
    assert torch.equal(state["grad2d"], torch.zeros(3)) and torch.equal(state["count"], torch.zeros(3))


def test_update_param_with_optimizer_replaces_a_parameter_and_its_adam_moments_together():
    """Rows 0 and 2 of a parameter kept: the new parameter is the one the optimizer steps, its moments are the
    old rows' moments, its step count is kept, and the old parameter has no state left."""
    old = torch.nn.Parameter(torch.arange(12.0).reshape(4, 3))
    params = {"means": old}
    optimizers = {"means": torch.optim.Adam([old], lr=0.1)}
    old.grad = torch.arange(12.0).reshape(4, 3) - 5.0
    optimizers["means"].step()
    before = {k: v.clone() for k, v in optimizers["means"].state[old].items()}
    keep = torch.tensor([0, 2])
    gsplat_private.update_param_with_optimizer(lambda name, p: torch.nn.Parameter(p.detach()[keep]),
                                               lambda key, v: v[keep], params, optimizers)
    new = params["means"]
    assert new is not old and optimizers["means"].param_groups[0]["params"] == [new]
    assert old not in optimizers["means"].state
    moved = optimizers["means"].state[new]
    assert torch.equal(moved["exp_avg"], before["exp_avg"][keep])
    assert torch.equal(moved["exp_avg_sq"], before["exp_avg_sq"][keep])
    assert torch.equal(moved["step"], before["step"])
    new.grad = torch.ones_like(new)
    optimizers["means"].step()  # Adam goes on with the replaced rows
    assert torch.equal(optimizers["means"].state[new]["step"], before["step"] + 1)


def test_the_torch_reference_ops_give_hand_worked_values():
    """Covariance of an axis-aligned Gaussian: diag(scales^2); SH degree 0: C0 x the coefficient; projection of a
    point on the axis 5 m ahead: the principal point, depth 5, a radius of 3 sigma in pixels (rounded up)."""
    scales = torch.tensor([[0.1, 0.2, 0.3]])
    covars, _ = gsplat_private.quat_scale_to_covar_preci(torch.tensor([[1.0, 0.0, 0.0, 0.0]]), scales,
                                                          compute_preci=False)
    assert torch.allclose(covars[0], torch.diag(scales[0] ** 2))
    coeffs = torch.tensor([[[0.5, -1.0, 2.0]]])
    rgb = gsplat_private.spherical_harmonics(0, torch.tensor([[0.0, 0.0, 1.0]]), coeffs)
    assert torch.allclose(rgb, 0.28209479177387814 * coeffs[:, 0])
    K = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])
    radii, means2d, depths, _, _ = gsplat_private.fully_fused_projection(
        torch.tensor([[0.0, 0.0, 5.0]]), torch.diag(torch.tensor([0.01, 0.01, 0.01]))[None], torch.eye(4)[None], K,
        100, 80, eps2d=0.0)
    assert torch.allclose(means2d[0, 0], torch.tensor([50.0, 40.0])) and float(depths[0, 0]) == pytest.approx(5.0)
    sigma = 100 * 0.1 / 5  # pixels; gsplat 1.4.0 clamps the eigenvalues' discriminant at 0.01: + sqrt(0.01)
    assert int(radii[0, 0]) == math.ceil(3 * math.sqrt(sigma**2 + 0.1)) == 7
