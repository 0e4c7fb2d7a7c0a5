"""Gaussian-parallel evaluation split by pixels (geer_ns/distributed/split_eval.py) on one process: a band's grid
is the grid of its own rays, the bands cover the image once, and the image made of bands is the whole image's
render while no render holds more than a part of what the camera sees. Two processes: tests/test_distributed.py."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import copy_room, equidistant_fisheye_rays, tiny_trainer_config
from geer_ns.distributed import split_eval
from geer_ns.distributed.split_eval import band_grid, bands, split_outputs
from geer_ns.render import RayGrid


@pytest.mark.parametrize("first,stop", [(0, 1), (1, 3), (2, 3)])
def test_a_band_grid_is_the_grid_made_from_its_own_rays(first, stop):
    dirs, valid = equidistant_fisheye_rays(40, 180.0)  # 3 tile rows of 16, the last one 8 pixels high
    grid = RayGrid.from_rays(dirs, valid, tile_size=16)
    top, bottom = first * 16, min(stop * 16, 40)
    reference = RayGrid.from_rays(dirs[top:bottom], valid[top:bottom], tile_size=16)
    band = band_grid(grid, first, stop)
    assert (band.height, band.width, band.num_tiles) == (reference.height, reference.width, reference.num_tiles)
    assert torch.equal(band.tile_rays, reference.tile_rays)
    assert torch.equal(band.valid, reference.valid) and torch.equal(band.tile_active, reference.tile_active)
    assert band.num_valid == reference.num_valid
    for name in ("dirs", "tile_theta", "tile_phi"):
        assert torch.allclose(getattr(band, name), getattr(reference, name), rtol=0, atol=1e-12), name


@pytest.mark.parametrize("rows,processes", [(6, 2), (1, 2), (68, 2), (7, 3)])
def test_the_bands_cover_every_tile_row_once(rows, processes):
    cut = bands(rows, processes)
    assert cut[0][0] == 0 and cut[-1][1] == rows
    assert all(a < b for a, b in cut) and all(cut[i][1] == cut[i + 1][0] for i in range(len(cut) - 1))
    assert len(cut) == min(rows, split_eval.BANDS_PER_PROCESS * processes)
    sizes = [b - a for a, b in cut]
    assert max(sizes) - min(sizes) <= 1


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """A model of the room's 4,000 seed points with SH degree 3 (random higher bands), in eval mode, and its
    evaluation camera."""
    root = tmp_path_factory.mktemp("split_eval")
    data = copy_room(root / "data", 4, n_eval=1)
    config = tiny_trainer_config(data, root / "out", "split", 1)
    config.pipeline.model.sh_degree = 3
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    model = pipeline.model
    with torch.no_grad():
        model.gauss_params["features_rest"].copy_(
            torch.randn(model.gauss_params["features_rest"].shape, generator=torch.Generator().manual_seed(0)) * 0.2)
    model.step = 1_000_000  # every SH band on
    model.eval()
    return model, pipeline.datamanager.eval_dataset.cameras[0:1]


def test_the_image_made_of_bands_is_the_whole_images_render(model, monkeypatch):
    """Every output of the split evaluation equals one process's whole-image render of the camera (colors within
    float32 rounding: the bands' rows carry SH colors evaluated in torch, the whole render evaluates them in the
    kernels), and no band's render holds half the Gaussians the whole image's render sees."""
    model, camera = model
    import geer_ns.model as model_module

    seen, held = [], []
    whole, banded = model_module.render, split_eval.render

    def whole_render(*args, **kwargs):
        out = whole(*args, **kwargs)
        seen.append(int(out.visible.sum()))
        return out

    def band_render(means, *args, **kwargs):
        held.append(means.shape[0])
        return banded(means, *args, **kwargs)

    monkeypatch.setattr(model_module, "render", whole_render)
    monkeypatch.setattr(split_eval, "render", band_render)
    with torch.no_grad():
        reference = model.get_outputs(camera)
        outputs = split_outputs(model, camera)
    assert set(outputs) == set(reference)
    for name, value in reference.items():
        if value.is_floating_point():
            atol = 1e-6 if name == "rgb" else 0.0
            error = float((outputs[name] - value).abs().max())
            assert torch.allclose(outputs[name], value, rtol=0, atol=atol), (name, error)
        else:
            assert torch.equal(outputs[name], value), name
    assert float(reference["rgb"].std()) > 0.05  # an image, not a blank
    assert len(held) == len(bands(math.ceil(96 / 16), 1)) and seen[0] > 1000
    assert max(held) < seen[0] / 2, (held, seen)
