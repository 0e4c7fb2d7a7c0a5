"""The training sentinel (geer_ns/selftest/sentinel.py): the compiled renderer checked against the PyTorch
renderer on a training view every kernel-check-every steps; a planted disagreement (the compiled renderer's
image scaled by 1 + 1e-3) switches the run to the PyTorch renderer, says so once and writes the inputs."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_nerfstudio_model import fisheye_camera, make_model

from geer_ns.render import rasterize

pytestmark = pytest.mark.usefixtures("cpu_ops")


def _plant_disagreement(monkeypatch):
    real = rasterize.render_cuda

    def wrong(*args, **kwargs):
        out = real(*args, **kwargs)
        return dataclasses.replace(out, rgb=out.rgb * (1.0 + 1e-3))

    monkeypatch.setattr(rasterize, "render_cuda", wrong)


@pytest.mark.parametrize("planted", [False, True])
def test_the_sentinel_switches_a_disagreeing_run_to_the_pytorch_renderer(tmp_path, monkeypatch, planted):
    monkeypatch.setenv("GEER_SELFTEST_DIR", str(tmp_path))
    model = make_model(60, renderer_backend="auto", kernel_check_every=2)
    model.train()
    said = []
    model.sentinel.say = said.append
    if planted:
        _plant_disagreement(monkeypatch)
    for step in range(5):
        model.step = step
        out = model.get_outputs(fisheye_camera(24))
        out["rgb"].sum().backward()
    if not planted:
        assert said == [] and model.render_options()["backend"] == "auto" and model.sentinel.last_step == 4
        return
    assert len(said) == 1 and "at step 2 the cpu renderer disagreed with the PyTorch renderer (rgb" in said[0]
    assert model.render_options()["backend"] == "torch" and model.config.renderer_backend == "auto"
    report = torch.load(model.sentinel.report, weights_only=False)
    assert str(model.sentinel.report) in said[0] and report["step"] == 2 and report["backend"] == "cpu"
    assert report["means"].shape == (60, 3) and report["grid"]["dirs"].shape[-1] == 3
    assert report["checks"]["rgb"].split()[0] != "0"  # pixels off


def test_the_default_check_is_rare():
    from geer_ns.model import GeerModelConfig

    assert GeerModelConfig().kernel_check_every >= 5000
