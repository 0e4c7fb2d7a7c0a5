"""The Levenberg-Marquardt lens solve (geer_ns/refinement/lens_solve.py): a geer model's refined lens solved back to
the lens its training images were rendered with."""

from __future__ import annotations

import math

import pytest
import torch

from geer_ns.refinement.lens_solve import solve_lens, spread


def _lens_setup(mode: str, start: int = 0):
    """A model with lens refinement `mode`, four 180-degree fisheye training images (32^2, native rays) rendered
    from known poses through the true lens (deltas zero), and their train_view."""
    from nerfstudio.cameras.cameras import Cameras as NsCameras

    from geer_ns.refinement.lens import attach
    from test_nerfstudio_model import four_fisheye_views, make_model

    model = make_model(n=80, lens_refinement=mode, lens_refinement_start=start, renderer_backend="cpu")
    cameras, _, _ = four_fisheye_views(model)  # rendered below, once the model knows these cameras' lens
    train = NsCameras(camera_to_worlds=torch.cat([c.camera_to_worlds for c in cameras]),
                      fx=torch.cat([c.fx for c in cameras]), fy=torch.cat([c.fy for c in cameras]),
                      cx=torch.cat([c.cx for c in cameras]), cy=torch.cat([c.cy for c in cameras]), width=32,
                      height=32, camera_type=cameras[0].camera_type.expand(4, 1), distortion_params=torch.zeros(4, 6))
    attach(model, train)
    _, _, views = four_fisheye_views(model)
    return model, views


@pytest.mark.parametrize("mode, wrong", [("focal", (0.02,)), ("focal+principal", (-0.02, 0.01, -0.008))])
def test_lens_solve_brings_a_wrong_lens_back_to_the_one_the_images_were_rendered_with(cpu_ops, mode, wrong):
    """Focal 2 % off (and the principal point 0.01 / 0.008 focal lengths, ~0.1 px, off): the solve returns every
    delta within 1e-4 of zero (the true lens) and lowers the residuals by more than 99 %."""
    model, views = _lens_setup(mode)
    with torch.no_grad():
        model.lens.deltas[0, : len(wrong)] = torch.tensor(wrong, dtype=torch.float64)
    summary = solve_lens(model, views, range(4), iterations=4)
    deltas = model.lens.deltas.detach()[0]
    assert float(deltas.abs().max()) < 1e-4, deltas
    assert summary["lenses"] == 1 and summary["residual_change"] < -0.99
    assert summary["focal_change"] == pytest.approx(1 - math.exp(-abs(wrong[0])), rel=0.05)
    assert model.training and model.views == []  # the mode it found; the solve's renders are not training views


def _equidistant_map_px(camera, true_focal: float, radius: float) -> float:
    """Mean distance (px, over the image disc out to `radius` px, area-weighted) between where `camera` (an
    OPENCV_FISHEYE lens: fx, k1..k4) and the true distortion-free equidistant lens of focal `true_focal` put the
    same ray; OpenCV's fisheye model written out here, not the code under test."""
    theta = torch.linspace(0.0, radius / true_focal, 4001, dtype=torch.float64)
    k = [float(getattr(camera, name)) for name in ("k1", "k2", "k3", "k4")]
    distorted = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    moved = (float(camera.fx) * distorted - true_focal * theta).abs()
    weight = theta / theta.sum()  # the disc's area grows with the radius
    return float((moved * weight).sum())


def test_lens_solve_brings_the_lens_map_back_though_the_distortion_coefficients_trade_off(cpu_ops):
    """Full refinement, focal +2 % and k1 +0.02 (0.54 px mean off the true map over the 16 px disc): one solve
    brings the map within 0.03 px of the truth. The four coefficients are close to collinear over the image, so
    each alone may stay ~1e-3 off; the map, what the images see, is what must come back."""
    model, views = _lens_setup("full")
    true_focal = 32 / math.pi
    fields = model.lens.delta_fields[0]
    with torch.no_grad():
        model.lens.deltas[0, fields.index(("fx", "fy"))] = 0.02
        model.lens.deltas[0, fields.index(("k1",))] = 0.02
    before = _equidistant_map_px(model.lens.refined_camera(0), true_focal, 16.0)
    summary = solve_lens(model, views, range(4), iterations=4)
    after = _equidistant_map_px(model.lens.refined_camera(0), true_focal, 16.0)
    assert before > 0.4 and after < 0.03, (before, after)
    assert summary["residual_change"] < -0.99


def test_lens_solve_leaves_an_inactive_lens_alone(cpu_ops):
    """Before lens-refinement-start the renders do not use the refined lens: nothing is solved or moved."""
    model, views = _lens_setup("focal", start=100)
    with torch.no_grad():
        model.lens.deltas[0, 0] = 0.02
    assert solve_lens(model, views, range(4), iterations=2)["lenses"] == 0
    assert float(model.lens.deltas.detach()[0, 0]) == 0.02


def test_spread_picks_images_evenly_along_the_path():
    assert spread([3, 5, 7], 12) == [3, 5, 7]
    assert spread(list(range(10)), 4) == [0, 3, 6, 9]
    assert spread(list(range(10)), 1) == [0]
