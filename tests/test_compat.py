"""Each host work-around in geer_ns.compat (and the two that moved where they are used), tested where the host
bug shows."""

from __future__ import annotations

import fractions
import logging
import subprocess
import sys

import numpy as np
import pytest
import torch

from geer_ns import compat
from geer_ns.metrics import perceptual
from geer_ns.data.datamanager import pin_if_possible
from geer_ns.data.ply import read_ply_points

TORCH_WEIGHTS_ONLY_DEFAULT = tuple(int(v) for v in torch.__version__.split(".")[:2]) >= (2, 6)


def _save_checkpoint_like(path):
    """What nerfstudio's trainer saves: dicts of tensors plus numpy scalars from optimizer/scheduler state."""
    torch.save({"step": 7, "pipeline": {"w": torch.ones(2)}, "schedulers": {"x": np.float64(0.5)}}, path)


@pytest.mark.skipif(not TORCH_WEIGHTS_ONLY_DEFAULT, reason="torch < 2.6 does not default to weights_only")
def test_checkpoint_loading_fails_without_the_fix(tmp_path):
    """The nerfstudio bug is real here: a plain torch.load of such a checkpoint raises."""
    path = tmp_path / "step-000000007.ckpt"
    _save_checkpoint_like(path)
    code = f"import torch; torch.load({str(path)!r}, map_location='cpu')"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "Weights only load failed" in result.stderr


def test_checkpoint_loads_with_the_allow_list_and_weights_only_stays_on(tmp_path):
    assert compat.allow_nerfstudio_checkpoints()
    path = tmp_path / "step-000000007.ckpt"
    _save_checkpoint_like(path)
    loaded = torch.load(path, map_location="cpu")  # nerfstudio's call: no weights_only argument
    assert loaded["step"] == 7 and float(loaded["schedulers"]["x"]) == 0.5
    arbitrary = tmp_path / "arbitrary.pt"
    torch.save({"x": fractions.Fraction(1, 3)}, arbitrary)
    if TORCH_WEIGHTS_ONLY_DEFAULT:
        with pytest.raises(Exception, match="Weights only load failed"):
            torch.load(arbitrary, map_location="cpu")


def test_lpips_is_built_lazily_and_reported_missing_without_weights(monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setattr(perceptual, "_warned", False)
    with caplog.at_level(logging.WARNING, logger="geer_ns"):
        assert perceptual.build_lpips_if_cached() is None
        assert perceptual.build_lpips_if_cached() is None
    assert sum("LPIPS unavailable" in r.message for r in caplog.records) == 1


def test_lpips_is_used_when_the_weights_are_cached():
    if not perceptual.alexnet_weights_path().is_file():
        pytest.skip(f"AlexNet weights not cached at {perceptual.alexnet_weights_path()}")
    metric = perceptual.build_lpips_if_cached()
    img = torch.rand(1, 3, 64, 64)
    assert float(metric(img, img)) == pytest.approx(0.0, abs=1e-5)


def test_model_construction_never_touches_lpips(monkeypatch):
    """splatfacto builds LPIPS (an AlexNet download) in populate_modules; geer must not."""
    import torchmetrics.image.lpip as lpip

    def no_download(*args, **kwargs):
        raise AssertionError("LPIPS built at model construction")

    monkeypatch.setattr(lpip.LearnedPerceptualImagePatchSimilarity, "__init__", no_download)
    from test_nerfstudio_model import make_model  # tests/ is importable under pytest (rootdir conftest)

    make_model(n=10)


def test_pin_if_possible_without_gpu():
    t = torch.zeros(3)
    out = pin_if_possible(t)
    if torch.cuda.is_available():
        assert out.is_pinned()
    else:
        assert out is t


def test_ply_points_are_read_without_open3d(tmp_path):
    from plyfile import PlyData, PlyElement

    vertex = np.array([(0.0, 1.0, 2.0, 10, 20, 30), (3.0, 4.0, 5.0, 40, 50, 60)],
                      dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    path = tmp_path / "p.ply"
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    xyz, rgb = read_ply_points(path)
    assert xyz.tolist() == [[0, 1, 2], [3, 4, 5]] and rgb.tolist() == [[10, 20, 30], [40, 50, 60]]
