"""The self-test harness (geer_ns/render/verdict.py, geer_ns/selftest) against the CPU build: the same suite a
GPU runs, `cpu` backend vs the PyTorch renderer, in a child process; planted faults (a crash, a hang, a wrong
image) and the parent's fallback with its one line. Verdicts go to a temporary folder (GEER_SELFTEST_DIR)."""

from __future__ import annotations

import json

import pytest
import torch

from geer_ns.render import backend, verdict
from geer_ns.selftest.suite import run_case, suite

CPU = torch.device("cpu")
pytestmark = pytest.mark.usefixtures("cpu_ops")


@pytest.fixture
def fresh(tmp_path, monkeypatch):
    """Verdicts in tmp_path, nothing remembered from earlier tests, auto asking the CPU build's verdict."""
    monkeypatch.setenv("GEER_SELFTEST_DIR", str(tmp_path))
    monkeypatch.setenv("GEER_VERIFY_CPU_BUILD", "1")
    monkeypatch.delenv("GEER_SELFTEST_FAULT", raising=False)
    verdict._memo.clear()
    backend._warned.clear()
    yield tmp_path
    verdict._memo.clear()
    backend._warned.clear()


def test_the_suite_passes_on_the_cpu_build_in_a_child(fresh, monkeypatch):
    found = verdict.verify("cpu", CPU)
    report = json.loads(open(found.report).read())
    names = [c["case"] for c in report["cases"]]
    assert found.passed, found.line()
    assert {"stress-fisheye200-f32", "stress-panorama-f64", "random-beap-f32", "gap-beap1px-f32"} <= set(names)
    assert all(c["passed"] for c in report["cases"]) and report["facts"]["build_key"] == found.facts["build_key"]
    # Recorded: a new process (no memo) reads it from disk and runs no child.
    verdict._memo.clear()

    def no_child(*_):
        raise AssertionError("the recorded verdict was not used")

    monkeypatch.setattr(verdict, "run_child", no_child)
    assert verdict.verify("cpu", CPU).passed
    assert backend.resolve_backend("auto", CPU) == "cpu"


@pytest.mark.parametrize("fault, says", [("crash", "crashed (SIGABRT"), ("hang", "did not finish its suite"),
                                         ("raise", "cases failed against the PyTorch renderer (stress-fisheye200-f32: "
                                                   "raised RuntimeError: planted fault)")])
def test_a_planted_fault_falls_back_with_one_line(fresh, monkeypatch, capfd, fault, says):
    monkeypatch.setenv("GEER_SELFTEST_FAULT", fault)
    if fault == "hang":
        monkeypatch.setenv("GEER_SELFTEST_TIMEOUT_S", "2")
    assert backend.resolve_backend("auto", CPU) == "torch"
    assert backend.resolve_backend("auto", CPU) == "torch"  # said once
    lines = [line for line in capfd.readouterr().err.splitlines() if line.startswith("geer: not using")]
    assert len(lines) == 1, lines
    assert says in lines[0] and "rendering with the PyTorch renderer (report: " in lines[0]
    report = lines[0].rsplit("(report: ", 1)[1].rstrip(")")
    assert json.loads(open(report).read())["facts"]["backend"] == "cpu"
    # an explicit request is not second-guessed
    assert backend.resolve_backend("cpu", CPU) == "cpu"


def test_a_planted_disagreement_fails_its_case():
    case = suite("cpu")[0]
    assert run_case(case, "cpu", CPU)["passed"]
    result = run_case(case, "cpu", CPU, perturb=1e-3)
    assert not result["passed"] and "rgb" in result["failed"]
