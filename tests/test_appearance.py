"""Exposure / white balance / vignetting (geer_ns/refinement/appearance.py) and the colour-corrected metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from geer_ns.refinement.appearance import Appearance, linear_to_srgb, ray_angles, srgb_to_linear
from geer_ns.metrics.color_corrected import affine_color_fit, color_corrected_metrics


def test_srgb_curve_matches_the_standard():
    # IEC 61966-2-1 reference points: 18 % grey encodes to 0.4614 (118/255), 0.5 linear to 0.7354 (188/255)
    x = torch.tensor([0.0, 0.002, 0.18, 0.5, 1.0], dtype=torch.float64)
    expected = torch.tensor([0.0, 0.02584, 0.46136, 0.73536, 1.0], dtype=torch.float64)
    assert torch.allclose(linear_to_srgb(x), expected, atol=1e-4)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)


def test_ray_angles_of_a_fisheye_beyond_90_degrees():
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, -1.0], [0.0, 0.0, -1.0]])
    assert torch.allclose(ray_angles(dirs), torch.tensor([0.0, math.pi / 2, 3 * math.pi / 4, math.pi]))


def _truth_image(base: np.ndarray, theta: np.ndarray, gain: np.ndarray, falloff: float) -> np.ndarray:
    """The sensor of the synthetic variants, written independently in numpy: cos^4-like falloff."""
    lin = np.where(base <= 0.04045, base / 12.92, ((base + 0.055) / 1.055) ** 2.4)
    lin = np.clip(lin * gain * (np.cos(theta / 2) ** falloff)[..., None], 0, 1)
    return np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)


def test_fitting_recovers_exposure_white_balance_and_vignetting():
    """Known scene, images at known gains through a known falloff: Adam on the model's parameters recovers the
    gains (up to the shared scale the regulariser fixes) and the falloff."""
    gen = np.random.default_rng(0)
    h = w = 24
    v, u = np.meshgrid(np.arange(h) + 0.5 - h / 2, np.arange(w) + 0.5 - w / 2, indexing="ij")
    theta = np.hypot(u, v) / (h / 2) * math.radians(95)  # a 190-degree equidistant fisheye
    dirs = np.stack([np.sin(theta) * np.cos(np.arctan2(v, u)), np.sin(theta) * np.sin(np.arctan2(v, u)), np.cos(theta)], -1)
    base = gen.uniform(0.1, 0.7, (h, w, 3))
    log_gains = gen.normal(0.0, 0.3, (4, 3))
    log_gains -= log_gains.mean()
    images = [_truth_image(base, theta, np.exp(g), 4.0) for g in log_gains]
    model = Appearance(4).double()
    opt = torch.optim.Adam(model.parameters(), lr=2e-2)
    scene = torch.from_numpy(base)
    d = torch.from_numpy(dirs)
    for _ in range(400):
        opt.zero_grad()
        loss = sum(((model(scene, d, i) - torch.from_numpy(img)) ** 2).mean() for i, img in enumerate(images))
        (loss + model.regularization()).backward()
        opt.step()
    assert float((model.log_gains.detach() - torch.from_numpy(log_gains)).abs().max()) < 0.02
    falloff = model.vignetting_factor(torch.from_numpy(theta)).detach().numpy()
    assert np.abs(falloff - np.cos(theta / 2) ** 4).max() < 0.02


def test_unknown_images_get_the_neutral_gain_and_the_cameras_vignetting():
    model = Appearance(2).double()
    with torch.no_grad():
        model.log_gains[1] = torch.tensor([0.3, 0.0, -0.2])
        model.vignetting[0, 0] = -0.5
    rgb = torch.full((2, 2, 3), 0.5, dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    neutral = model(rgb, dirs, None)
    assert torch.allclose(neutral[0], rgb[0])  # on the axis: no falloff
    assert bool((neutral[1] < 0.5).all())  # at 90 degrees: darker
    assert bool(model(rgb, dirs, 1)[0, 0, 0] > 0.5) and bool(model(rgb, dirs, 1)[0, 0, 2] < 0.5)


def test_affine_color_fit_is_the_least_squares_fit():
    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(16, 16, 3, generator=gen, dtype=torch.float64)
    gt = torch.rand(16, 16, 3, generator=gen, dtype=torch.float64)
    valid = torch.rand(16, 16, generator=gen) > 0.3
    ours = affine_color_fit(pred, gt, valid)
    a = np.concatenate([pred[valid].numpy(), np.ones((int(valid.sum()), 1))], 1)
    coeffs, *_ = np.linalg.lstsq(a, gt[valid].numpy(), rcond=None)
    ref = np.concatenate([pred.numpy(), np.ones((16, 16, 1))], -1) @ coeffs
    assert np.abs(ours.numpy() - ref).max() < 1e-6


def test_color_corrected_metrics_forgive_exposure_not_structure():
    from pytorch_msssim import SSIM

    ssim = SSIM(data_range=1.0, size_average=True, channel=3)
    gen = torch.Generator().manual_seed(1)
    gt = torch.rand(32, 32, 3, generator=gen) * 0.6 + 0.2
    valid = torch.ones(32, 32, dtype=torch.bool)
    darker = gt * torch.tensor([0.6, 0.7, 0.8]) + 0.05  # another exposure and white balance
    noisy = gt + 0.1 * torch.randn(32, 32, 3, generator=gen)
    plain = -10 * math.log10(float(((darker - gt) ** 2).mean()))
    cc = color_corrected_metrics(darker, gt, valid, ssim)
    assert plain < 20 and cc["psnr_cc"] > 60 and cc["ssim_cc"] > 0.999
    assert color_corrected_metrics(noisy, gt, valid, ssim)["psnr_cc"] < 25


@pytest.mark.parametrize("kind", ["beap", "native"])
def test_model_applies_the_appearance_while_training_and_reports_psnr_cc(kind, monkeypatch, tmp_path):
    from test_nerfstudio_model import fisheye_camera, make_model

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # no cached AlexNet weights
    model = make_model(n=60, appearance="exposure")
    assert "appearance" in model.get_param_groups()
    camera = fisheye_camera(32, kind=kind)
    camera.metadata["cam_idx"] = 2
    model.eval()
    with torch.no_grad():
        neutral = model.get_outputs(camera)["rgb"]
        model.appearance.log_gains[2] = 0.5
    model.train()
    trained = model.get_outputs(camera)["rgb"]
    lit = neutral > 0.05
    assert bool((trained[lit] > neutral[lit]).all())  # image 2 is brighter than the neutral render
    trained.mean().backward()
    assert float(model.appearance.log_gains.grad[2].abs().sum()) > 0
    assert "appearance_reg" in model.get_step_loss_dict()
    model.eval()
    out = model.get_outputs_for_camera(camera)
    gt = (out["rgb"] * 0.8 * 255).round().to(torch.uint8)  # the test image at another exposure
    metrics, _ = model.get_image_metrics_and_images(out, {"image": gt})
    assert metrics["psnr_cc"] > metrics["psnr"] + 10 and "ssim_cc" in metrics
