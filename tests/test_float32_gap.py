"""The float32 gap (docs/cuda.md), as a randomized stress test: on a BEAP grid with 1-pixel tiles, scenes mixing a
Gaussian behind the camera, the camera inside a huge opaque Gaussian, scales of 1e-8, a quaternion of tiny
norm and opacities of exactly 1 and 1/255 (geer_ns/selftest/scenes.gap_scene). The CPU build's float32
gradients must be no further from the float64 gradient than 10x the PyTorch renderer's float32 ones (plus 1e-6
relative). Before csrc/geer_ray.h's canonical moment the thin Gaussians' scale gradients were up to 10
(relative) off where the PyTorch renderer's were within 1e-5 (seeds 1131, 1282, 1370: docs/cuda.md)."""

from __future__ import annotations

import pytest
import torch

from geer_ns.render import render
from geer_ns.selftest.scenes import camera, gap_scene
from geer_ns.selftest.suite import FIELDS, rel

F32, F64 = torch.float32, torch.float64
# The seeds where the former headers failed this test (8 of 400), and a few others.
SEEDS = (1090, 1122, 1131, 1140, 1271, 1281, 1282, 1370, 1376, 0, 1, 2)

pytestmark = pytest.mark.usefixtures("single_thread", "cpu_ops")


def _grads(scene, backend: str, dtype) -> list[torch.Tensor]:
    grid = camera("beap1", 24, dtype)
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in scene]
    out = render(*leaves, torch.eye(4, dtype=dtype), grid, backend=backend,
                 background=torch.full((3,), 0.3, dtype=dtype))
    gen = torch.Generator().manual_seed(0)
    h, w = out.rgb.shape[:2]
    wr, wd, wa = (torch.randn(h, w, c, generator=gen, dtype=F64).to(dtype) for c in (3, 1, 1))
    ((wr * out.rgb).sum() + 0.1 * (wd * out.depth).sum() + (wa * out.accumulation).sum()).backward()
    return [t.grad for t in leaves]


@pytest.mark.parametrize("seed", SEEDS)
def test_cpu_build_float32_gradients_are_as_close_to_float64_as_the_twins(seed):
    scene = gap_scene(seed)
    truth, twin, ours = _grads(scene, "torch", F64), _grads(scene, "torch", F32), _grads(scene, "cpu", F32)
    for name, t, a, b in zip(FIELDS, truth, twin, ours):
        assert torch.isfinite(b).all(), name
        assert rel(b, t) <= 10 * rel(a, t) + 1e-6, f"{name}: cpu {rel(b, t):.2e}, PyTorch renderer {rel(a, t):.2e}"
