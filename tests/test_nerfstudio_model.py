"""geer's nerfstudio model: densification signal, strategies, camera types, masked metrics, shared views."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox

from geer_ns.data.datamanager import VIEW_KEY
from geer_ns.data.views import beap_view
from geer_ns.densify.mcmc_cpu import relocation_torch
from geer_ns.model import GeerModelConfig
from geer_ns.render.transforms import world_to_camera_opencv

ROOT = Path(__file__).resolve().parents[1]


def seed_cloud(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """n points in front of an identity nerfstudio camera (which looks along world -z)."""
    gen = torch.Generator().manual_seed(seed)
    xyz = torch.empty(n, 3)
    xyz[:, :2] = (torch.rand(n, 2, generator=gen) - 0.5) * 3.0
    xyz[:, 2] = -1.5 - torch.rand(n, generator=gen)
    rgb = (torch.rand(n, 3, generator=gen) * 255).to(torch.uint8)
    return xyz, rgb


def make_model(n: int = 40, **overrides):
    cfg = dict(background_color="black", sh_degree=0, num_downscales=0)
    cfg.update(overrides)
    config = GeerModelConfig(**cfg)
    box = SceneBox(aabb=torch.tensor([[-2.0, -2.0, -3.0], [2.0, 2.0, 0.0]]))
    model = config.setup(scene_box=box, num_train_data=4, metadata={}, device="cpu", seed_points=seed_cloud(n))
    model.optimizers = {}
    return model


def fisheye_camera(size: int = 32, c2w: torch.Tensor | None = None, kind: str = "beap") -> Cameras:
    f = size / math.pi  # 180 degree circle
    cam = Cameras(
        camera_to_worlds=(torch.eye(4)[:3] if c2w is None else c2w)[None],
        fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size,
        camera_type=CameraType.FISHEYE, distortion_params=torch.zeros(1, 6),
    )
    cam.metadata = {VIEW_KEY: kind}
    return cam


def four_fisheye_views(model, size: int = 32):
    """Four 180-degree fisheye cameras (native rays, cam_idx 0-3) a few degrees and tenths of a unit apart, the
    model's renders from them as their images, and a datamanager-like object whose train_view serves them: the
    rig the pose and lens solve tests recover known cameras from. Returns (cameras, images, views)."""
    cams = []
    for i, (angle, shift) in enumerate([(0.0, 0.0), (8.0, 0.2), (-6.0, -0.15), (4.0, 0.1)]):
        c2w = torch.eye(4)[:3].clone()
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        c2w[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        c2w[0, 3] = shift
        camera = fisheye_camera(size, c2w, kind="native")
        camera.metadata = {**camera.metadata, "cam_idx": i}
        cams.append(camera)
    model.train()
    with torch.no_grad():
        images = [model.get_outputs(camera)["rgb"].clone() for camera in cams]

    class Views:  # the datamanager's train_view, for these images
        def train_view(self, index):
            return cams[index], {"image": images[index]}

    return cams, images, Views()


def adam_optimizers(model) -> dict:
    return {name: torch.optim.Adam([p], lr=1e-3) for name, p in model.gauss_params.items()}


# --------------------------------------------------------------------------------- densification


def _beap_loss(model, camera, target):
    return ((model.get_outputs(camera)["rgb"] - target) ** 2).sum()


def _moved_mean(mean_w: torch.Tensor, viewmat: torch.Tensor, h: float) -> torch.Tensor:
    """The mean moved by h along the first offset, at its distance from the camera: its direction turns by h
    radians towards increasing theta."""
    rot, t = viewmat[:3, :3], viewmat[:3, 3]
    p = rot @ mean_w + t
    u = p / p.norm()
    e1 = torch.stack([u[2], torch.zeros_like(u[0]), -u[0]])
    e1 = e1 / e1.norm()
    p_new = p.norm() * (math.cos(h) * u + math.sin(h) * e1)
    return rot.T @ (p_new - t)


def test_the_offsets_gradient_is_the_loss_gradient_of_the_image_position():
    """offsets.grad against central differences of the loss under the move the offsets define: a radian of
    direction across the viewing ray."""
    torch.manual_seed(0)
    model = make_model(n=25).double()
    model.train()
    camera = fisheye_camera(32)
    view = beap_view(_model_camera(camera))
    target = torch.rand(*view.size, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    loss = _beap_loss(model, camera, target)
    loss.backward()
    record = model.views[-1]
    grad = record.offsets.grad  # [N, 2]
    assert record.radius.shape == (model.num_points,)
    k = int(torch.argmax(grad[:, 0].abs() * record.visible))
    assert grad[k, 0].abs() > 1e-6

    viewmat = world_to_camera_opencv(camera.camera_to_worlds[0].double())
    h = 1e-3  # radians
    mean0 = model.gauss_params["means"].data[k].clone()
    losses = []
    with torch.no_grad():
        for sign in (1.0, -1.0):
            model.gauss_params["means"].data[k] = _moved_mean(mean0, viewmat, sign * h)
            losses.append(float(_beap_loss(model, camera, target)))
    model.gauss_params["means"].data[k] = mean0
    finite_difference = (losses[0] - losses[1]) / (2 * h)
    assert finite_difference == pytest.approx(float(grad[k, 0]), rel=2e-3, abs=1e-8)


def _train_step(model, camera, step: int):
    model.step = step
    target = torch.full((*beap_view(_model_camera(camera)).size, 3), 0.7)
    loss = ((model.get_outputs(camera)["rgb"] - target) ** 2).mean()
    loss.backward()
    model.step_post_backward(step)


def _model_camera(camera):
    from geer_ns.cameras import from_nerfstudio

    return from_nerfstudio(camera, 0)


def test_default_strategy_densifies_with_a_forced_refine():
    model = make_model(n=40, warmup_length=0, refine_every=1, densify_grad_thresh=1e-12, stop_screen_size_at=0)
    model.train()
    model.optimizers = adam_optimizers(model)
    before = model.num_points
    _train_step(model, fisheye_camera(32), step=5)
    assert model.num_points > before
    # the optimizers now hold the grown parameters (gsplat's ops replaced them in place)
    assert model.optimizers["means"].param_groups[0]["params"][0] is model.gauss_params["means"]


def test_mcmc_strategy_relocates_and_grows_on_cpu():
    model = make_model(n=40, strategy="mcmc", warmup_length=0, refine_every=1)
    model.train()
    model.optimizers = adam_optimizers(model)
    with torch.no_grad():
        model.gauss_params["opacities"][:5] = -10.0  # dead: must be relocated
    before = model.num_points
    _train_step(model, fisheye_camera(32), step=3)
    assert model.num_points == before + max(1, int(0.05 * before))
    assert (torch.sigmoid(model.gauss_params["opacities"][:5]) > 0.005).all()


def test_relocation_keeps_a_single_gaussian_and_splits_opacity():
    binoms = torch.tensor([[math.comb(n, k) for k in range(51)] for n in range(51)], dtype=torch.float32)
    opac = torch.tensor([0.6, 0.6])
    scales = torch.ones(2, 3)
    new_o, new_s = relocation_torch(opac, scales, torch.tensor([1, 2]), binoms)
    assert new_o[0] == pytest.approx(0.6) and torch.allclose(new_s[0], scales[0])
    assert new_o[1] == pytest.approx(1 - 0.4**0.5)  # two copies composite to the original opacity
    assert (1 - (1 - new_o[1]) ** 2) == pytest.approx(0.6)


# -------------------------------------------------------------------------------- eval / viewer


def _viewer_cameras() -> dict:
    c2w = torch.eye(4)[:3][None]
    common = dict(camera_to_worlds=c2w)
    return {
        "perspective": Cameras(fx=20.0, fy=20.0, cx=16.0, cy=12.0, width=32, height=24,
                               camera_type=CameraType.PERSPECTIVE, **common),
        "fisheye": Cameras(fx=10.0, fy=10.0, cx=16.0, cy=16.0, width=32, height=32,
                           camera_type=CameraType.FISHEYE, distortion_params=torch.tensor([[0.01, 0, 0, 0, 0, 0]]),
                           **common),
        "fisheye624": Cameras(fx=10.0, fy=10.0, cx=16.0, cy=16.0, width=32, height=32,
                              camera_type=CameraType.FISHEYE624,
                              distortion_params=torch.tensor([[0.01, 0, 0, 0, 0, 0, 1e-4, 0, 0, 0, 0, 0]]), **common),
        "equirectangular": Cameras(fx=32.0, fy=32.0, cx=32.0, cy=16.0, width=64, height=32,
                                   camera_type=CameraType.EQUIRECTANGULAR, **common),
    }


@pytest.mark.parametrize("name", ["perspective", "fisheye", "fisheye624", "equirectangular"])
def test_viewer_renders_every_camera_type_from_its_own_rays(name):
    model = make_model(n=60)
    model.eval()
    camera = _viewer_cameras()[name]
    out = model.get_outputs_for_camera(camera)
    h, w = int(camera.height), int(camera.width)
    assert out["rgb"].shape == (h, w, 3) and out["depth"].shape == (h, w, 1) and out["accumulation"].shape == (h, w, 1)
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all()
    assert out["accumulation"].max() > 0.05  # the Gaussians in front of the camera are seen


def test_eval_metrics_are_masked_with_central_and_peripheral_psnr(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # no cached AlexNet weights
    model = make_model(n=60, central_half_angles_deg=(45.0, 45.0))
    model.eval()
    camera = fisheye_camera(32, kind="native")
    out = model.get_outputs_for_camera(camera)
    gt = (out["rgb"] * 255).round().to(torch.uint8)
    mask = torch.zeros(32, 32, 1, dtype=torch.bool)
    mask[4:28, 4:28] = True
    gt_bad_outside = gt.clone()
    gt_bad_outside[~mask[..., 0]] = 255 - gt_bad_outside[~mask[..., 0]]  # garbage where invalid: must not count
    metrics, images = model.get_image_metrics_and_images(out, {"image": gt_bad_outside, "mask": mask})
    assert metrics["psnr"] > 45  # only quantisation error inside the mask
    assert {"psnr", "ssim", "central_psnr", "peripheral_psnr"} <= set(metrics)
    assert "lpips" not in metrics  # reported as missing, not as a number
    assert images["img"].shape == (32, 64, 3)


def test_paper_central_region_of_a_pinhole_is_the_whole_image():
    model = make_model(n=20)
    model.eval()
    camera = _viewer_cameras()["perspective"]
    out = model.get_outputs_for_camera(camera)
    assert out["central_region"].all()  # tan(theta) <= w / (2 fx) => theta <= w / (2 fx)


def test_datamanager_and_model_share_one_beap_view():
    from geer_ns.data.datamanager import camera_model

    camera = fisheye_camera(32)
    model = make_model(n=10)
    model.train()
    assert model.view_for(camera) is beap_view(camera_model(camera, 0))


def test_no_hard_coded_cuda_calls():
    for rel in ("geer_ns/model.py", "geer_ns/data/datamanager.py", "geer_ns/data/views.py", "geer_ns/config.py"):
        assert not re.search(r"\.cuda\(", (ROOT / rel).read_text()), rel


def test_native_supervision_renders_the_camera_pixels_with_downscale():
    model = make_model(n=30, num_downscales=1, resolution_schedule=10**6)
    model.train()
    camera = fisheye_camera(32, kind="native")
    out = model.get_outputs(camera)
    assert out["rgb"].shape == (16, 16, 3)  # splatfacto's resolution schedule on the native rays
    assert model.views[-1].radius.shape == (model.num_points,)
    assert camera.width.item() == 32  # the batch camera is not modified


def test_training_loss_ignores_invalid_pixels():
    model = make_model(n=30)
    model.train()
    camera = fisheye_camera(32)
    out = model.get_outputs(camera)
    gt = (out["rgb"].detach() * 255).round().to(torch.uint8)
    mask = torch.ones(*gt.shape[:2], 1, dtype=torch.bool)
    mask[:, :8] = False
    gt[:, :8] = 255 - gt[:, :8]
    losses = model.get_loss_dict(out, {"image": gt, "mask": mask})
    assert float(losses["main_loss"].detach()) < 0.01


def test_bilateral_grid_applies_its_images_affine_colour_map_and_trains_only_that_grid():
    """A grid holding one affine map A (3x4) in every cell maps each pixel's colour c to A [c; 1]; the loss
    sum(w * rgb) then has d/dA summed over the cells = sum over pixels of w [c; 1]^T (the cells' interpolation
    weights sum to 1), and no gradient reaches the other images' grids."""
    model = make_model(n=20, use_bilateral_grid=True)
    model.train()
    camera = fisheye_camera(32)
    plain = model.get_outputs(camera)["rgb"].detach()  # no cam_idx: no grid
    affine = torch.tensor([[0.8, 0.1, 0.0, 0.05], [0.0, 1.2, -0.1, 0.0], [0.1, 0.0, 0.7, -0.02]])
    with torch.no_grad():
        model.bil_grids.grids[1] = affine.reshape(12, 1, 1, 1)
    camera.metadata["cam_idx"] = 1
    rgb = model.get_outputs(camera)["rgb"]
    colour1 = torch.cat([plain, torch.ones_like(plain[..., :1])], -1)  # [H, W, 4]
    assert torch.allclose(rgb, colour1 @ affine.T, atol=1e-5)
    weight = torch.rand(rgb.shape, generator=torch.Generator().manual_seed(0))
    (rgb * weight).sum().backward()
    grad = model.bil_grids.grids.grad
    expected = torch.einsum("hwi,hwj->ij", weight, colour1)
    assert torch.allclose(grad[1].sum((1, 2, 3)).reshape(3, 4), expected, rtol=1e-4, atol=1e-4)
    assert float(grad[[0, 2, 3]].abs().max()) == 0.0
