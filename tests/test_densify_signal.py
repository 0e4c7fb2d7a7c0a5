"""The densification statistics mean the same at every field of view and projection, in the view's pixels.

One scene of small Gaussians near the optical axis, off by a small turn, seen by one pose through five
cameras: a 90-degree pinhole, the same at twice the resolution, a 180-degree equidistant fisheye supervised in
BEAP and on its native pixels, and the fisheye at twice the resolution. At the image centre the 64 x 64 pinhole,
the BEAP grid and the fisheye have the same angular pixel pitch (1/32 rad). Each view's loss is the mean
squared error over its supervised pixels, as training's loss is a mean; its gradient therefore shrinks with the
number of pixels (a 180-degree view has ~3.5x the pinhole's) and grows with their angular size. The statistics
of geer_ns/densify/signal.py undo both: at the same pixel pitch a Gaussian gets the same value in every view up
to the pixel grids' sampling of its footprint, and at twice the resolution twice the value (its footprint and
its error are twice as many pixels across: what the supervision resolves, not radians, sets its growth).
"""

from __future__ import annotations

import math

import pytest
import torch

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox

from geer_ns.data.datamanager import VIEW_KEY
from geer_ns.densify.signal import REFERENCE_WIDTH_PIXELS
from geer_ns.model import GeerModelConfig

N = 24
SCALE = 0.08  # a few pixels across at 1/32 rad


def _model(rim: bool = False):
    """N Gaussians within ~12 degrees of the axis, or (rim) 60-80 degrees off it all around."""
    gen = torch.Generator().manual_seed(4)
    if rim:
        off = torch.deg2rad(60.0 + 20.0 * torch.rand(N, generator=gen))
        around = 2 * math.pi * torch.rand(N, generator=gen)
        distance = 2.0 + torch.rand(N, generator=gen)
        xyz = torch.stack([torch.sin(off) * torch.cos(around), torch.sin(off) * torch.sin(around), -torch.cos(off)], -1)
        xyz = xyz * distance[:, None]
    else:
        xyz = torch.empty(N, 3)
        xyz[:, :2] = (torch.rand(N, 2, generator=gen) - 0.5) * 1.0
        xyz[:, 2] = -2.0 - torch.rand(N, generator=gen)  # nerfstudio's camera looks along world -z
    rgb = (torch.rand(N, 3, generator=gen) * 255).to(torch.uint8)
    # the reference camera's units, whose values grow with resolution (image units: gsplat's, checked below)
    config = GeerModelConfig(background_color="black", sh_degree=0, num_downscales=0, densify_units="reference")
    box = SceneBox(aabb=torch.tensor([[-2.0, -2.0, -4.0], [2.0, 2.0, 0.0]]))
    model = config.setup(scene_box=box, num_train_data=1, metadata={}, device="cpu", seed_points=(xyz, rgb))
    with torch.no_grad():
        model.gauss_params["opacities"].fill_(2.0)  # opaque enough to matter, thin enough to overlap
        model.gauss_params["scales"].clamp_(max=math.log(SCALE))
    return model.double().train()


def _camera(kind: str, scale: int) -> Cameras:
    c2w = torch.eye(4)[:3][None]
    if kind == "pinhole":  # 90 degrees across, f = 32 px per radian at the centre for scale 1
        size = 64 * scale
        cam = Cameras(camera_to_worlds=c2w, fx=size / 2.0, fy=size / 2.0, cx=size / 2.0, cy=size / 2.0,
                      width=size, height=size, camera_type=CameraType.PERSPECTIVE)
        view = "native"
    else:  # 180-degree equidistant fisheye, f = 32 px per radian for scale 1
        size = 100 * scale
        f = 32.0 * scale
        cam = Cameras(camera_to_worlds=c2w, fx=f, fy=f, cx=size / 2.0, cy=size / 2.0, width=size, height=size,
                      camera_type=CameraType.FISHEYE, distortion_params=torch.zeros(1, 6))
        view = "beap" if kind == "beap" else "native"
    cam.metadata = {VIEW_KEY: view}
    return cam


def _target(model, camera: Cameras) -> torch.Tensor:
    """The image of the scene turned by 1.5 degrees about the camera's vertical axis: every Gaussian is off by
    about a pixel's angle, so each has a clear positional gradient (no cancelling terms)."""
    a = math.radians(1.5)
    turn = torch.tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]],
                        dtype=torch.float64)  # the camera sits at the world origin
    means = model.gauss_params["means"]
    with torch.no_grad():
        original = means.clone()
        means.copy_(original @ turn.T)
        target = model.get_outputs(camera)["rgb"]
        means.copy_(original)
    return target


VIEWS = {"pinhole 90": ("pinhole", 1), "pinhole 90, 2x": ("pinhole", 2), "BEAP 180": ("beap", 1),
         "fisheye 180": ("fisheye", 1), "fisheye 180, 2x": ("fisheye", 2)}
RIM_VIEWS = {name: VIEWS[name] for name in ("fisheye 180", "BEAP 180", "fisheye 180, 2x")}  # no pinhole sees there


def _statistics(rim: bool = False) -> dict:
    """Per view: the gradient statistic and the screen statistic of every Gaussian, from one backward."""
    found = {}
    for name, (kind, scale) in (RIM_VIEWS if rim else VIEWS).items():
        model = _model(rim)
        camera = _camera(kind, scale)
        target = _target(model, camera)
        out = model.get_outputs(camera)
        valid = out["valid_rays"][..., 0]
        loss = ((out["rgb"] - target) ** 2)[valid].mean()
        loss.backward()
        stats = model.step_statistics()
        assert bool((stats.views == 1).all()), name  # every Gaussian is seen in every view
        found[name] = (stats.grad.double(), stats.radius.double(), scale)
    return found


@pytest.fixture(scope="module")
def statistics():
    return _statistics()


@pytest.fixture(scope="module")
def rim_statistics():
    return _statistics(rim=True)


def _ratios(found: dict, index: int, reference: str = "pinhole 90") -> dict:
    return {name: values[index] / found[reference][index] for name, values in found.items() if name != reference}


def _say(what: str, ratios: dict) -> None:
    for name, r in ratios.items():
        print(f"{name:16s} {what}: median {float(r.median()):.3f} [{float(r.min()):.3f}, {float(r.max()):.3f}]")


def _per_pitch(found: dict, ratios: dict, reference: str) -> dict:
    """Each view's ratios over its resolution's: 1/32 rad a pixel on the axis for the pinhole and the fisheye,
    twice as fine at 2x. The BEAP view counts its camera's pixels, not its grid's cells (112 across this
    fisheye's 100 pixels: 1.12x as fine, and finer still toward the rim): it resolves no more than them."""
    return {name: r / (found[name][2] / found[reference][2]) for name, r in ratios.items()}


def test_the_gradient_statistic_is_the_same_in_every_view(statistics):
    """Per Gaussian, each view's value over the 90-degree pinhole's, divided by the views' resolution ratio:
    within 15 % of 1 at the median and 35 % for every Gaussian (the grids sample a footprint of a few pixels
    differently; measured 0.75-1.17)."""
    new = _ratios(statistics, 0)
    _say("gradient / 90-degree pinhole's", new)
    for name, relative in _per_pitch(statistics, new, "pinhole 90").items():
        assert abs(float(relative.median()) - 1.0) <= 0.15, name
        assert float((relative - 1.0).abs().max()) <= 0.35, name


def test_at_the_rim_beap_and_native_fisheye_pixels_agree(rim_statistics):
    """Gaussians 60-80 degrees off-axis, where a BEAP cell is 1/cos(off-axis angle) (up to 5.8x) shorter than
    across the ray than along it: the statistic of the BEAP view over the fisheye's, and of the 2x fisheye over
    twice the fisheye's, within the same bounds (measured 0.84-1.05 and 0.98-1.03)."""
    new = _ratios(rim_statistics, 0, "fisheye 180")
    _say("gradient / fisheye 180's", new)
    for name, relative in _per_pitch(rim_statistics, new, "fisheye 180").items():
        assert abs(float(relative.median()) - 1.0) <= 0.15, name
        assert float((relative - 1.0).abs().max()) <= 0.35, name


def test_the_screen_statistic_is_the_same_in_every_view(statistics):
    """The radius in the view's pixels at the Gaussian: the same at the same pitch up to how each projection's
    pitch changes off the axis (within 20 degrees: the pinhole's pixel side shrinks as cos^1.5, the
    equidistant fisheye's as sqrt(sin/theta): up to 8 % apart), exactly twice at twice the resolution."""
    new = _ratios(statistics, 1)
    _say("screen / 90-degree pinhole's", new)
    for name, relative in _per_pitch(statistics, new, "pinhole 90").items():
        assert torch.allclose(relative, torch.ones_like(relative), rtol=0.1), name
    found = statistics
    for name, base in (("pinhole 90, 2x", "pinhole 90"), ("fisheye 180, 2x", "fisheye 180")):
        assert torch.allclose(found[name][1], 2.0 * found[base][1], rtol=1e-6), name
    assert torch.allclose(found["BEAP 180"][1], found["fisheye 180"][1], rtol=1e-6)  # the same camera's pixels


def _reference_pinhole(size: int):
    """A 60-degree pinhole `size` pixels across at the world origin, supervised on its own pixels; its focal."""
    f = (size / 2) / math.tan(math.radians(30))
    camera = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=f, fy=f, cx=size / 2, cy=size / 2, width=size,
                     height=size, camera_type=CameraType.PERSPECTIVE)
    camera.metadata = {VIEW_KEY: "native"}
    return camera, f


@pytest.mark.parametrize("units", ["reference", "image"])
@pytest.mark.parametrize("size", [int(REFERENCE_WIDTH_PIXELS), 128])
def test_at_the_reference_camera_the_statistics_are_gsplats(statistics, size, units):
    """For the reference camera, a 60-degree pinhole W_ref pixels across, at its centre the statistic is gsplat's
    |dL/d(position)| in units of half the image; for a `size`-pixel one it is gsplat's x size / W_ref (geer
    counts pixels of the reference camera, gsplat halves of this image), and gsplat's own with densify-units
    image, at every size. Checked on the Gaussian nearest the axis of a dedicated view."""
    model = _model()
    model.config.densify_units = units
    camera, f = _reference_pinhole(size)
    target = _target(model, camera)
    out = model.get_outputs(camera)
    loss = ((out["rgb"] - target) ** 2)[out["valid_rays"][..., 0]].mean()
    loss.backward()
    record = model.views[-1]
    means = model.gauss_params["means"].detach()
    k = int(torch.argmin(means[:, :2].norm(dim=-1)))  # nearest the optical axis
    off_axis = math.degrees(math.atan(float(means[k, :2].norm()) / float(-means[k, 2])))
    # gsplat's value: the pixel-position gradient (pixels = f x the angle near the centre) times size / 2, of the
    # gradient the statistic uses (AbsGS's per-pixel absolute sums by default, the signed sum without)
    leaf = record.absgrad if record.absgrad is not None else record.offsets
    gsplat = float(leaf.grad[k].norm()) / f * (size / 2)
    ours = float(model.step_statistics().grad[k])
    print(f"Gaussian {off_axis:.1f} deg off-axis: statistic {ours:.4g}, gsplat's {gsplat:.4g}")
    expected = gsplat if units == "image" else gsplat * size / REFERENCE_WIDTH_PIXELS
    assert ours == pytest.approx(expected, rel=0.05)  # cos^1.5 of a few degrees


def test_image_units_count_the_full_image_while_the_resolution_schedule_downscales():
    """During splatfacto's resolution schedule a view is rendered at half size; in image units its statistics
    still count the camera's full image (as thresholds scaled by the capture's size would), so they are the
    reference units' x W_ref / the full side, not / the downscaled one."""
    size = 128
    found = {}
    for units in ("reference", "image"):
        model = _model()
        model.config.densify_units, model.config.num_downscales = units, 1
        assert model._get_downscale_factor() == 2  # step 0 of the schedule
        camera, _ = _reference_pinhole(size)
        target = _target(model, camera)
        out = model.get_outputs(camera)
        assert out["rgb"].shape[0] == size // 2
        ((out["rgb"] - target) ** 2)[out["valid_rays"][..., 0]].mean().backward()
        stats = model.step_statistics()
        found[units] = (stats.grad.double(), stats.radius.double())
    for k in range(2):
        assert torch.allclose(found["image"][k], found["reference"][k] * REFERENCE_WIDTH_PIXELS / size, rtol=1e-6)
