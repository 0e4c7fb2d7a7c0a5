"""The refit of a Gaussian's kept SH bands to the colours its views saw (geer_ns/sh_degrees/refit.py): its solve
against NumPy's least squares on the stacked system, the truncation it reduces to over the whole sphere (the
bands' orthogonality), and what it gains over truncation on a cone of view directions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geer_ns.render.sh import sh_band_colors
from geer_ns.sh_degrees.refit import FIT_BASES, RIDGE, SeenColours, basis_up_to_fit, refit


def _views(coeffs: torch.Tensor, dirs: torch.Tensor, weights: torch.Tensor) -> SeenColours:
    """One Gaussian per row of coeffs [N, 16, 3], each seen along dirs [N, V, 3] with weights [N, V] (all the
    (Gaussian, view) pairs added at once: rows repeat)."""
    n, v = weights.shape
    seen = SeenColours.zeros(n, "cpu")
    flat = dirs.reshape(n * v, 3)
    colours = sh_band_colors(coeffs.repeat_interleave(v, 0), flat, 3).sum(1)
    seen.add(torch.arange(n).repeat_interleave(v), weights.reshape(-1), basis_up_to_fit(flat), colours)
    return seen


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_refit_solves_the_ridge_least_squares_numpy_solves(degree):
    gen = torch.Generator().manual_seed(degree)
    n, v = 6, 9
    coeffs = torch.randn(n, 16, 3, generator=gen, dtype=torch.float64) * 0.3
    dirs = torch.randn(n, v, 3, generator=gen, dtype=torch.float64)
    weights = torch.rand(n, v, generator=gen, dtype=torch.float64) * 5.0
    seen = _views(coeffs, dirs, weights)
    fit, errors = refit(seen, coeffs, degree)
    m = (degree + 1) ** 2
    for i in range(n):
        y = np.stack([basis_up_to_fit(dirs[i, k : k + 1])[0, :m].numpy() for k in range(v)])
        f = np.stack([sh_band_colors(coeffs[i : i + 1], dirs[i, k : k + 1], 3).sum(1)[0].numpy() for k in range(v)])
        sw = np.sqrt(weights[i].numpy())[:, None]
        rho = RIDGE * float(np.mean(np.sum(weights[i].numpy()[:, None] * y**2, 0)))
        a = np.vstack([sw * y, np.sqrt(rho) * np.eye(m)])
        b = np.vstack([sw * f, np.sqrt(rho) * coeffs[i, :m].numpy()])
        expected = np.linalg.lstsq(a, b, rcond=None)[0]
        np.testing.assert_allclose(fit[i].numpy(), expected, rtol=1e-8, atol=1e-10)
        residual = float(np.sum(weights[i].numpy()[:, None] * (y @ expected - f) ** 2))
        assert float(errors[i]) == pytest.approx(residual, rel=1e-7, abs=1e-12)


def test_over_the_whole_sphere_the_refit_is_the_truncation():
    """Directions of a spherical design (a dense Fibonacci sphere), equal weights: the bands are orthogonal there,
    so the least-squares fit of the low bands is the coefficients themselves (up to the ridge and the design)."""
    k = 4000
    i = torch.arange(k, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / k
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    sphere = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
    coeffs = torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.3
    seen = _views(coeffs, sphere[None].expand(2, k, 3), torch.ones(2, k, dtype=torch.float64))
    for degree in (0, 1, 2):
        fit, _ = refit(seen, coeffs, degree)
        assert torch.allclose(fit, coeffs[:, : (degree + 1) ** 2], atol=2e-3), degree


def test_on_a_cone_of_views_the_refit_keeps_far_more_of_the_colour_than_truncation():
    """Views within 25 degrees of one direction (a Gaussian on a wall seen along a path): degree 1 refit leaves a
    small part of the colour change that cutting bands 2 and 3 off makes."""
    gen = torch.Generator().manual_seed(7)
    n, v = 50, 24
    coeffs = torch.randn(n, 16, 3, generator=gen, dtype=torch.float64) * 0.2
    axis = torch.nn.functional.normalize(torch.randn(n, 1, 3, generator=gen, dtype=torch.float64), dim=-1)
    jitter = (torch.rand(n, v, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.5  # |tangent| <= 0.43: <= 23 deg
    dirs = torch.nn.functional.normalize(axis + jitter - (jitter * axis).sum(-1, keepdim=True) * axis, dim=-1)
    assert float((dirs * axis).sum(-1).min()) > np.cos(np.radians(25))
    weights = torch.rand(n, v, generator=gen, dtype=torch.float64) + 0.1
    seen = _views(coeffs, dirs, weights)
    _, refit_errors = refit(seen, coeffs, 1)
    cut = torch.stack([sh_band_colors(coeffs, dirs[:, k], 3)[:, 2:].sum(1) for k in range(v)], 1)  # [N, V, 3]
    cut_errors = (weights * cut.square().sum(-1)).sum(-1)
    assert float(refit_errors.sum()) < 0.1 * float(cut_errors.sum())
    assert bool((refit_errors <= cut_errors * (1 + 1e-9)).all())  # never worse, Gaussian by Gaussian


def test_a_gaussian_no_view_saw_keeps_its_coefficients():
    coeffs = torch.randn(3, 16, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    seen = SeenColours.zeros(3, "cpu")
    fit, errors = refit(seen, coeffs, 2)
    assert torch.allclose(fit, coeffs[:, :FIT_BASES], rtol=1e-12, atol=0) and bool((errors == 0).all())


def test_kept_refit_coefficients_render_the_colour_the_choice_measured():
    """keep_degrees writes each Gaussian's refit coefficients where the renderer reads them: sh_to_color of the
    model's coefficients at its own degree equals the colour the choice measured it with (choice._color)."""
    from types import SimpleNamespace

    from geer_ns.render.sh import sh_to_color
    from geer_ns.sh_degrees.choice import _color, keep_degrees

    gen = torch.Generator().manual_seed(11)
    n, v = 40, 6
    dc, rest = torch.randn(n, 3, generator=gen) * 0.3, torch.randn(n, 15, 3, generator=gen) * 0.3
    coeffs = torch.cat([dc[:, None], rest], 1)
    seen = _views(coeffs.double(), torch.randn(n, v, 3, generator=gen, dtype=torch.float64),
                  torch.rand(n, v, generator=gen, dtype=torch.float64))
    fits = [refit(seen, coeffs, d)[0] for d in range(3)]
    degrees = (torch.arange(n) % 4).to(torch.uint8)
    params = {"features_dc": torch.nn.Parameter(dc.clone()), "features_rest": torch.nn.Parameter(rest.clone())}
    model = SimpleNamespace(gauss_params=params, strategy_state={})
    keep_degrees(model, {"features_rest": SimpleNamespace(state={})}, degrees, fits)
    dirs = torch.randn(n, 3, generator=gen)
    stored = torch.cat([params["features_dc"][:, None], params["features_rest"]], 1).detach()
    rendered = sh_to_color(stored, dirs, degrees.long())
    rows = torch.arange(n)
    measured = _color(rows, sh_band_colors(coeffs, dirs, 3), basis_up_to_fit(dirs), degrees, fits)
    assert torch.allclose(rendered, measured, atol=1e-6)
    assert not torch.allclose(stored[degrees < 3, 0], coeffs[degrees < 3, 0])  # the refit moved the kept bands


def test_a_run_that_ends_before_its_highest_band_trained_keeps_every_band():
    """At the last step of a run whose SH schedule has not trained degree 3 yet (the CPU demo: 800 steps, a band
    every 1000) no degree is chosen, so that a resumed run still gains its bands; it says so."""
    from types import SimpleNamespace

    from geer_ns.sh_degrees.choice import BandChoice
    from geer_ns.sh_degrees.packing import DEGREES

    model = SimpleNamespace(config=SimpleNamespace(sh_degree=3, sh_degree_interval=1000), strategy_state={})
    trainer = SimpleNamespace(_start_step=0, config=SimpleNamespace(max_num_iterations=800))
    said = []
    choice = BandChoice(SimpleNamespace(model=model), None, trainer, 0.05, said.append)
    choice(798)
    assert said == []
    choice(799)
    assert DEGREES not in model.strategy_state and len(said) == 1 and "every SH band kept" in said[0]
