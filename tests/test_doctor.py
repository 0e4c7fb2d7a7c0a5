"""geer-doctor (geer_ns/doctor.py) on this machine: a few lines naming each device's renderer and why, the
self-test verdict it ran on request, and a timed training step per renderer."""

from __future__ import annotations

import pytest
import torch

from geer_ns import doctor
from geer_ns.render import backend, verdict


@pytest.mark.usefixtures("cpu_ops")
def test_doctor_says_which_renderer_each_device_gets_and_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GEER_SELFTEST_DIR", str(tmp_path))
    monkeypatch.delenv("GEER_SELFTEST_FAULT", raising=False)
    verdict._memo.clear()
    backend._warned.clear()
    assert doctor.main(["--selftest", "--gaussians", "40", "--size", "16"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) <= 12, lines  # a few lines
    text = "\n".join(lines)
    assert f"torch {torch.__version__}" in text and "extension cache:" in text
    cpu = lines.index(next(line for line in lines if line.startswith("cpu: ")))
    assert lines[cpu + 1].startswith("  auto -> cpu: the kernels' code compiled for the CPU")
    assert "self-test passed: all " in lines[cpu + 1] and str(tmp_path) in lines[cpu + 1]
    assert "one training step (40 Gaussians, 16x16 rays" in lines[cpu + 2]
    assert " cpu " in lines[cpu + 2] and " ms, torch " in lines[cpu + 2]
    if not torch.cuda.is_available():
        assert "cuda: no usable device" in text
    verdict._memo.clear()
