"""render() refuses a camera it cannot render, with one line naming the tensor and the fix: a viewmat that is no
rigid world-to-camera transform (singular, scaled, sheared, a reflection, transposed), tensors on another device
than the Gaussians (the grid's too). Rounding-level departures (float32 poses, the model's own viewmats) render.
The checks keep render's one host sync per call."""

from __future__ import annotations

import re

import pytest
import torch

from conftest import random_scene, random_viewmat
from geer_ns.render import RayGrid, render
from geer_ns.render.validate import ROTATION_TOLERANCE, check_gaussians

GRID = RayGrid.beap(16, 16, 1.0, 1.0, tile_size=8)


def _viewmat(case: str, dtype) -> torch.Tensor:
    vm = random_viewmat(4, dtype=torch.float64)
    if case == "singular":
        vm = torch.zeros(4, 4, dtype=torch.float64)
    elif case == "scaled":
        vm[:3] *= 2.0
    elif case == "scaled by 1 %":
        vm[:3, :3] *= 1.01
    elif case == "sheared":
        vm[0, :3] += 0.1 * vm[1, :3]
    elif case == "reflection":
        vm[2, :3] *= -1.0
    elif case == "transposed":
        vm = vm.T.contiguous()
    return vm.to(dtype)


EXPECTED = {
    "singular": r"viewmat: the rotation block viewmat\[:3, :3\] is singular \(det 0\)",
    "scaled": r"viewmat: the rotation block viewmat\[:3, :3\] is not orthonormal .*row lengths 2, 2, 2",
    "scaled by 1 %": r"viewmat: the rotation block viewmat\[:3, :3\] is not orthonormal",
    "sheared": r"viewmat: the rotation block viewmat\[:3, :3\] is not orthonormal",
    "reflection": r"viewmat: the rotation block viewmat\[:3, :3\] has det -1, a reflection; expected det \+1",
    "transposed": r"viewmat: last row is \[.*\]; expected \[0, 0, 0, 1\] .*transposed",
}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", list(EXPECTED))
def test_a_viewmat_that_is_no_rigid_transform_is_refused(case, dtype):
    scene = random_scene(5, 0, dtype=dtype)
    with pytest.raises(ValueError, match=EXPECTED[case]) as caught:
        render(*scene, _viewmat(case, dtype), GRID)
    assert "\n" not in str(caught.value)
    if case != "transposed" and case != "reflection":
        assert "pass a rigid world-to-camera transform" in str(caught.value)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rounding_level_departures_render(dtype):
    """A rotation 1e-4 off orthonormal (|R R^T - I| = 3.5e-4, three times inside the tolerance) renders;
    so does a float32 pose."""
    scene = random_scene(5, 0, dtype=dtype)
    vm = random_viewmat(4, dtype=torch.float64)
    vm[:3, :3] *= 1.0001
    rot = vm[:3, :3]
    assert torch.linalg.matrix_norm(rot @ rot.T - torch.eye(3, dtype=torch.float64)) < ROTATION_TOLERANCE / 2
    out = render(*scene, vm.to(dtype), GRID)
    assert torch.isfinite(out.rgb).all()


def test_the_models_own_viewmats_pass():
    """Every training camera of the synthetic room through geer's parser (float32 poses after nerfstudio's
    orientation and scaling) and the model's world_to_camera_opencv (float64)."""
    from geer_ns.data.nerfstudio_parser import GeerNerfstudioDataParserConfig
    from geer_ns.data.synthetic_room import default_scene_dir
    from geer_ns.render.transforms import world_to_camera_opencv

    cameras = GeerNerfstudioDataParserConfig(data=default_scene_dir()).setup().get_dataparser_outputs("train").cameras
    scene = random_scene(5, 0, dtype=torch.float32)
    assert cameras.camera_to_worlds.dtype == torch.float32 and len(cameras) > 10
    for c2w in cameras.camera_to_worlds:
        check_gaussians(*scene, viewmat=world_to_camera_opencv(c2w.double()), grid=GRID)


@pytest.mark.parametrize("where", ["viewmat", "grid", "quats", "background"])
def test_tensors_on_another_device_are_named(where):
    """The Gaussians on the CPU, one input on another device ("meta": no GPU needed to have two devices)."""
    means, quats, scales, opacities, colors = random_scene(5, 0, dtype=torch.float32)
    viewmat, grid, background = torch.eye(4), GRID, torch.zeros(3)
    if where == "viewmat":
        viewmat = viewmat.to("meta")
    elif where == "grid":
        grid = grid.to("meta")
    elif where == "quats":
        quats = quats.to("meta")
    else:
        background = background.to("meta")
    name = "grid.dirs" if where == "grid" else where
    fix = "grid.to(means.device)" if where == "grid" else f"{where}.to(means.device)"
    with pytest.raises(ValueError, match=rf"^{name}: on meta, but means are on cpu; .* \(pass {re.escape(fix)}\)$"):
        render(means, quats, scales, opacities, colors, viewmat, grid, background=background)


def test_the_checks_read_the_device_once(monkeypatch):
    """Every value rule, the rigid viewmat's included, is one reduction read with one host sync."""
    scene = random_scene(50, 1, dtype=torch.float32)
    reads = []
    for method in ("__bool__", "item", "tolist", "__float__", "__int__"):
        original = getattr(torch.Tensor, method)
        monkeypatch.setattr(torch.Tensor, method,
                            lambda self, *a, _o=original, _m=method, **k: reads.append(_m) or _o(self, *a, **k))
    check_gaussians(*scene, viewmat=random_viewmat(2, dtype=torch.float32), background=torch.zeros(3), grid=GRID)
    assert reads == ["__bool__"]

