"""Lens refinement (geer_ns/refinement/lens.py): the gradient of a rendered image with respect to a camera's
focal lengths, principal point and distortion against float64 central differences of the whole render (the
camera module's own unprojection of the moved intrinsics, independent of the refinement's Newton refresh), the
refreshed rays against that unprojection, and a few steps of refinement pulling a perturbed focal length back
towards the truth, with native and with BEAP supervision."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from conftest import random_scene
from test_pose_gradients import with_dirs

from geer_ns.cameras import FOVCamera, MeiCamera, OpenCVFisheyeCamera, PinholeCamera
from geer_ns.data.beap import resample_to_beap
from geer_ns.data.views import NativeView, beap_view
from geer_ns.refinement.lens import LensRefinement, refined_fields, refined_parameters
from geer_ns.render import RayGrid, render

F64 = torch.float64
BG = torch.tensor((0.2, 0.3, 0.4), dtype=F64)
CAMERAS = {
    "fisheye": OpenCVFisheyeCamera(20, 18, 6.5, 6.8, 10.2, 8.9, k1=0.02, k2=-0.004),
    "pinhole_distorted": PinholeCamera(20, 18, 14.0, 14.5, 9.7, 9.2, k1=-0.08, k2=0.01, p1=0.002, p2=-0.001),
}


@pytest.fixture(scope="module")
def ops(cpu_ops, single_thread):
    return cpu_ops


def _view(camera, dtype=F64) -> NativeView:
    dirs, valid = camera.pixel_rays(dtype)
    return NativeView(camera, RayGrid.from_rays(dirs, valid, 8), 0.05)


def _scene(seed=5, n=50):
    means, quats, scales, opac, colors = random_scene(n, seed, spread=1.0, scale_range=(0.1, 0.5))
    return [means, quats, scales, opac, colors]


def _loss(out) -> torch.Tensor:
    gen = torch.Generator().manual_seed(0)
    h, w = out.rgb.shape[:2]
    target = torch.rand(h, w, 3, generator=gen, dtype=F64)
    return ((out.rgb - target) ** 2).sum() + 0.1 * (out.depth ** 2).sum()


def _render(scene, grid):
    return render(*scene, torch.eye(4, dtype=F64), grid, backend="cpu", background=BG)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_intrinsics_gradient_matches_finite_differences_of_the_render(ops, name):
    camera = CAMERAS[name]
    scene = _scene()
    view = _view(camera)
    grads = {}
    for aspect in (True, False):
        lens = LensRefinement.from_cameras([camera], "full", aspect=aspect)
        refined = lens.refine_view(view, camera, step=0)
        _loss(_render(scene, refined.rays)).backward()
        grads[aspect] = dict(zip(lens.delta_fields[0], lens.deltas.grad[0].tolist()))
    fds = {}
    for name_ in ("fx", "fy", "cx", "cy", "k1"):
        v0 = getattr(camera, name_)
        # delta -> value: fx0 exp(d) (focal), cx0 + sqrt(fx fy) d (principal point), k1 + d
        dv = v0 if name_ in ("fx", "fy") else (math.sqrt(camera.fx * camera.fy) if name_ in ("cx", "cy") else 1.0)
        h = 1e-6 * max(1.0, abs(v0))
        losses = []
        for sign in (1, -1):
            moved = dataclasses.replace(camera, **{name_: v0 + sign * h})
            dirs = moved.pixel_rays(F64)[0].reshape(-1, 3)  # the camera module's own unprojection
            with torch.no_grad():
                losses.append(float(_loss(_render(scene, with_dirs(view.rays, dirs)))))
        fds[name_] = (losses[0] - losses[1]) / (2 * h) * dv
    for name_, fd in fds.items():  # one delta per field
        assert abs(grads[True][(name_,)] - fd) <= 1e-4 * abs(fd) + 1e-7, (name_, grads[True][(name_,)], fd)
    shared = fds["fx"] + fds["fy"]  # one delta scaling fx and fy together
    assert abs(grads[False][("fx", "fy")] - shared) <= 1e-4 * abs(shared) + 1e-7, (grads[False], shared)
    assert abs(grads[False][("k1",)] - fds["k1"]) <= 1e-4 * abs(fds["k1"]) + 1e-7


@pytest.mark.parametrize("camera", [
    CAMERAS["fisheye"], CAMERAS["pinhole_distorted"], FOVCamera(20, 18, 9.0, 9.0, 10.0, 9.0, omega=0.9),
    MeiCamera(20, 18, 12.0, 12.5, 10.0, 9.0, xi=0.8, k1=-0.05, p1=0.001)])
def test_refreshed_rays_are_the_unprojection_through_the_refined_lens(camera):
    """After any change of every refined parameter the rays equal the camera module's unprojection of the pixel
    centres through the refined camera (float64)."""
    view = _view(camera)
    lens = LensRefinement.from_cameras([camera], "full", aspect=True)
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        lens.deltas.copy_(0.01 * torch.randn(lens.deltas.shape, generator=gen, dtype=F64))
    refined = lens.refine_view(view, camera, step=0)
    truth, valid = lens.refined_camera(0).pixel_rays(F64)
    ok = valid.reshape(-1) & view.rays.valid
    assert int(ok.sum()) > 0.5 * ok.numel()
    assert float((refined.rays.dirs - truth.reshape(-1, 3))[ok].abs().max()) < 1e-9
    assert refined.camera == lens.refined_camera(0)


def test_renders_without_gradients_reuse_the_rays_until_the_intrinsics_change():
    """The pose solve renders each image dozens of times under one lens: without gradients the refreshed rays
    (and the refined camera) are reused, each view size and kind its own, and a change of the deltas (here
    written through .data, which no autograd version counter sees) gives the unprojection through the new lens,
    never the old rays."""
    from geer_ns.data.views import native_view

    camera = CAMERAS["fisheye"]
    half = dataclasses.replace(camera, width=10, height=9, fx=camera.fx / 2, fy=camera.fy / 2, cx=camera.cx / 2,
                               cy=camera.cy / 2)
    views = {"full": native_view(camera), "half": native_view(half), "beap": beap_view(camera)}
    lens = LensRefinement.from_cameras([camera], "full")
    with torch.no_grad():
        first = {name: lens.refine_view(view, camera, step=0) for name, view in views.items()}
        again = {name: lens.refine_view(view, camera, step=0) for name, view in views.items()}
        assert all(again[name].rays is first[name].rays for name in views)
        assert [first[name].rays.dirs.shape[0] for name in views] == [view.rays.dirs.shape[0] for view in
                                                                       views.values()]
        assert again["full"].camera == lens.refined_camera(0)
        lens.deltas.data[0, 0] += 0.02
        moved = lens.refine_view(views["full"], camera, step=0)
    assert moved.rays is not first["full"].rays and moved.camera == lens.refined_camera(0) != first["full"].camera
    truth, valid = lens.refined_camera(0).pixel_rays(F64)
    ok = valid.reshape(-1) & views["full"].rays.valid
    assert float((moved.rays.dirs.double() - truth.reshape(-1, 3))[ok].abs().max()) < 1e-6
    attached = lens.refine_view(views["full"], camera, step=0)  # with gradients: a fresh, differentiable refresh
    assert attached.rays is not moved.rays and attached.rays.dirs.requires_grad


def test_modes_pick_the_fields():
    fisheye = CAMERAS["fisheye"]
    assert refined_fields(fisheye, "focal") == ("fx", "fy")
    assert refined_fields(fisheye, "focal+principal") == ("fx", "fy", "cx", "cy")
    assert refined_fields(fisheye, "full") == ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    assert refined_fields(fisheye, "off") == ()
    with pytest.raises(ValueError, match="lens_refinement"):
        refined_fields(fisheye, "everything")
    assert refined_parameters(fisheye, "focal") == (("fx", "fy"),)
    assert refined_parameters(fisheye, "focal", aspect=True) == (("fx",), ("fy",))
    assert refined_parameters(fisheye, "full")[:2] == (("fx", "fy"), ("cx",))


def test_the_default_keeps_the_aspect_ratio_and_aspect_refines_it():
    """Without `aspect` fx and fy move by one factor (fy / fx as calibrated); with it each moves alone."""
    camera = CAMERAS["fisheye"]
    shared = LensRefinement.from_cameras([camera], "focal")
    separate = LensRefinement.from_cameras([camera], "focal", aspect=True)
    assert shared.deltas.shape[-1] == 1 and separate.deltas.shape[-1] == 2
    with torch.no_grad():
        shared.deltas.fill_(0.03)
        separate.deltas.copy_(torch.tensor([[0.03, -0.01]], dtype=F64))
    a, b = shared.refined_camera(0), separate.refined_camera(0)
    assert a.fy / a.fx == pytest.approx(camera.fy / camera.fx, rel=1e-12)
    assert a.fx == pytest.approx(camera.fx * math.exp(0.03), rel=1e-12)
    assert b.fy / b.fx == pytest.approx(camera.fy / camera.fx * math.exp(-0.04), rel=1e-12)


def test_a_checkpoint_of_the_other_aspect_setting_names_the_option():
    camera = CAMERAS["fisheye"]
    saved = LensRefinement.from_cameras([camera], "full", aspect=True).state_dict()
    with pytest.raises(ValueError, match="lens-refinement-aspect True"):
        LensRefinement.from_cameras([camera], "full").load_state_dict(saved)


def _refine(lens, target, valid, make_view, truth_camera, scene, steps):
    opt = torch.optim.Adam([lens.deltas], lr=4e-3)
    for _ in range(steps):
        opt.zero_grad()
        view = make_view()
        out = render(*scene, torch.eye(4, dtype=torch.float32), view.rays, backend="cpu",
                     background=BG.float())
        mask = valid.reshape(out.rgb.shape[:2])[..., None]
        loss = torch.where(mask, (out.rgb - target).abs(), 0.0).sum() / mask.sum()
        loss.backward()
        opt.step()
    return lens.refined_camera(0)


@pytest.mark.parametrize("supervision", ["native", "beap"])
def test_refinement_pulls_a_perturbed_focal_towards_the_truth(ops, supervision):
    """The image of a tiny scene through the true fisheye; the lens starts with its focal lengths 4 % too long.
    BEAP: the target is resampled once through the perturbed lens (as the datamanager does), and never again."""
    truth = OpenCVFisheyeCamera(40, 40, 13.0, 13.0, 20.0, 20.0)
    wrong = dataclasses.replace(truth, fx=13.0 * 1.04, fy=13.0 * 1.04)
    means, quats, scales, opac, colors = random_scene(80, 11, spread=1.6, scale_range=(0.15, 0.45),
                                                      opacity_range=(0.6, 0.95), dtype=torch.float32)
    scene = [means, quats, scales, opac, colors]
    with torch.no_grad():
        image = render(*scene, torch.eye(4), _view(truth, torch.float32).rays, backend="cpu",
                       background=BG.float()).rgb
    lens = LensRefinement.from_cameras([wrong], "focal")
    if supervision == "native":
        target, valid = image, _view(wrong).rays.valid

        def make_view():
            return lens.refine_view(_view(wrong, torch.float32), wrong, step=0)
    else:
        view0 = beap_view(wrong)
        native_valid = _view(wrong).rays.valid.reshape(40, 40)
        target, valid = resample_to_beap(image, wrong, view0.grid, native_valid)
        valid = valid & view0.rays.valid.reshape(valid.shape)

        def make_view():
            return lens.refine_view(view0, wrong, step=0)
    refined = _refine(lens, target, valid, make_view, truth, scene, steps=25)
    before, after = abs(wrong.fx / truth.fx - 1), abs(refined.fx / truth.fx - 1)
    assert after < before / 3, (before, after)
    assert abs(refined.fy / truth.fy - 1) < before / 3


def test_model_trains_each_cameras_lens_and_vignetting(ops):
    """A tiny geer model with lens refinement and appearance: two distinct training cameras (four images) get
    one lens and one vignetting each; a BEAP training step of image 2 (camera 1) gives camera 1's lens deltas a
    gradient and camera 0's none; an evaluation camera with camera 1's intrinsics (no image index) is rendered
    through camera 1's refined lens."""
    from nerfstudio.cameras.cameras import Cameras as NsCameras

    from geer_ns.refinement.lens import attach
    from test_nerfstudio_model import fisheye_camera, make_model

    model = make_model(n=60, appearance="exposure", lens_refinement="focal+principal", lens_refinement_start=0)
    cams = [fisheye_camera(24, kind="beap") for _ in range(4)]
    for i in (2, 3):
        cams[i].fx[:] = cams[i].fy[:] = float(cams[i].fx) * 1.1
    train = NsCameras(camera_to_worlds=torch.cat([c.camera_to_worlds for c in cams]),
                      fx=torch.cat([c.fx for c in cams]), fy=torch.cat([c.fy for c in cams]),
                      cx=torch.cat([c.cx for c in cams]), cy=torch.cat([c.cy for c in cams]), width=24, height=24,
                      camera_type=cams[0].camera_type.expand(4, 1), distortion_params=torch.zeros(4, 6))
    attach(model, train)
    assert model.lens.image_camera == [0, 0, 1, 1] and model.appearance.vignetting.shape[0] == 2
    assert model.get_param_groups()["lens_opt"] == [model.lens.deltas]
    camera = cams[2]
    camera.metadata = {**camera.metadata, "cam_idx": 2}
    model.train()
    with torch.no_grad():
        model.lens.deltas[1, 0] = 0.01
    out = model.get_outputs(camera)
    out["rgb"].sum().backward()
    grad = model.lens.deltas.grad
    assert float(grad[1].abs().sum()) > 0 and float(grad[0].abs().sum()) == 0
    assert float(model.appearance.vignetting.grad[1].abs().sum()) > 0
    assert model.lens.refined_camera(1).fx == pytest.approx(24 / math.pi * 1.1 * math.exp(0.01), rel=1e-6)
    model.eval()
    viewer = fisheye_camera(24, kind="native")
    viewer.fx[:] = viewer.fy[:] = float(cams[2].fx)
    refined = model.get_outputs(viewer)["rgb"]
    with torch.no_grad():
        model.lens.deltas.zero_()
    assert float((model.get_outputs(viewer)["rgb"] - refined).abs().max()) > 1e-4
