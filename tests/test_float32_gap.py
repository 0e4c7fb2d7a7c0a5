"""The float32 gap (docs/cuda.md), as a randomized stress test: on a BEAP grid with 1-pixel tiles, scenes mixing a
Gaussian behind the camera, the camera inside a huge opaque Gaussian, scales of 1e-8, a quaternion of tiny
norm and opacities of exactly 1 and 1/255 (geer_ns/selftest/scenes.gap_scene). The CPU build's float32
gradients must be no further from the float64 gradient than 10x the PyTorch renderer's float32 ones (plus 1e-6
relative). Before csrc/geer_ray.h's canonical moment the thin Gaussians' scale gradients were up to 10
(relative) off where the PyTorch renderer's were within 1e-5 (seeds 1131, 1282, 1370: docs/cuda.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from geer_ns.render import RayGrid, render
from geer_ns.render.transforms import canonical_frame, quat_to_rotmat
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


# ------------------------------------------------------------------------------------------------ the 1/255 case
# The case that found the gap (`../shared/data/float32_gap/case.pt`, copied as tests/fixtures/float32_gap_case.npz):
# Gaussian 18 on ray (3, 14) has q = D^2 1.1e-5 below its 1/255 level q_max (alpha 0.0039215908 against 1/255 =
# 0.0039215686). When W and o_u came out of a float32 chain (R_c R(q) in float32, then W, then -W mu_c), their
# roundings alone put q above q_max, the CPU build dropped the pair and its float32 gradients were 6e-2 (means) and
# 9e-2 (scales) off float64; the PyTorch renderer kept it by a tie (its q rounded to q_max exactly).
GAP_CASE = Path(__file__).parent / "fixtures" / "float32_gap_case.npz"


def _gap_case_grads(backend: str, dtype) -> dict[str, torch.Tensor]:
    case = {k: torch.from_numpy(v) for k, v in np.load(GAP_CASE).items()}
    leaves = {k: case[k].to(dtype).clone().requires_grad_(True) for k in FIELDS}
    h, w, fx, fy = case["grid"].tolist()
    grid = RayGrid.beap(int(h), int(w), fx, fy, tile_size=1, dtype=dtype)
    out = render(*(leaves[k] for k in FIELDS), case["viewmat"].to(dtype), grid, backend=backend,
                 background=case["background"].to(dtype))
    loss = ((out.rgb * case["w_rgb"].to(dtype)).sum() + (out.accumulation * case["w_acc"].to(dtype)).sum()
            + (out.depth * case["w_depth"].to(dtype)).sum())
    loss.backward()
    return {k: leaves[k].grad.double() for k in FIELDS}


def test_the_pair_on_the_threshold_is_kept_by_the_cpu_build_in_float32():
    truth, twin, ours = (_gap_case_grads("torch", F64), _gap_case_grads("torch", F32), _gap_case_grads("cpu", F32))
    for name in FIELDS:
        assert rel(ours[name], truth[name]) <= 10 * rel(twin[name], truth[name]) + 1e-6, (
            f"{name}: cpu {rel(ours[name], truth[name]):.2e}, PyTorch renderer {rel(twin[name], truth[name]):.2e}")
        assert rel(ours[name], truth[name]) < 1e-4, name  # the dropped pair cost 1.8e-3 to 9e-2 here


def _reference_frame(means_c, quats, scales, rot_c):
    """W = S^-1 R_v^T and o_u = -W mu_c in float64 with R(q) from the axis-angle (Rodrigues), not from the
    quaternion's polynomial as transforms.quat_to_rotmat and geer_math.h build it."""
    q = quats.double() / quats.double().abs().amax(-1, keepdim=True)
    q = q / q.norm(dim=-1, keepdim=True)
    v = q[:, 1:]
    s = v.norm(dim=-1)
    theta = 2.0 * torch.atan2(s, q[:, 0])
    axis = v / s[:, None]
    k = torch.zeros(len(q), 3, 3, dtype=torch.float64)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(1, 2)
    eye = torch.eye(3, dtype=torch.float64)
    rot = eye + torch.sin(theta)[:, None, None] * k + (1 - torch.cos(theta))[:, None, None] * (k @ k)
    w = (rot_c.double() @ rot).transpose(1, 2) / scales.double()[:, :, None]
    return w, -(w @ means_c.double()[:, :, None])[:, :, 0]


def _within_one_rounding(x32: torch.Tensor, x64: torch.Tensor) -> torch.Tensor:
    """|x32 - x64| per element over its float32 spacing; <= 0.5 (plus the float64 reference's own rounding, a few
    1e-16 of its row) when x32 is x64 rounded once."""
    spacing = (torch.nextafter(x32, torch.full_like(x32, float("inf"))) - x32).double()
    slack = 1e-13 * x64.abs().amax(-1, keepdim=True)
    return ((x32.double() - x64).abs() - slack).clamp_min(0) / spacing


def test_each_gaussians_frame_is_float64_rounded_once_in_both_backends(cpu_ops):
    """W and o_u leave the preprocess as their float64 values rounded once (geer_math.h canonical_frame and
    transforms.canonical_frame); a float32 chain is several roundings (up to ~4 float32 spacings) off."""
    gen = torch.Generator().manual_seed(5)
    n = 4000
    means_c = (torch.randn(n, 3, generator=gen) * 3.0 + torch.tensor([0.0, 0.0, 4.0])).float()
    quats = torch.randn(n, 4, generator=gen).float()
    scales = torch.exp(torch.empty(n, 3).uniform_(-6.0, 1.0, generator=gen)).float()
    rot_c = quat_to_rotmat(torch.randn(1, 4, generator=gen).double())[0].float()
    viewmat = torch.eye(4)
    viewmat[:3, :3] = rot_c
    w64, o64 = _reference_frame(means_c, quats, scales, rot_c)
    _, w_twin, o_twin = canonical_frame(means_c, quats, scales, viewmat)
    w_cpu, o_cpu = cpu_ops.preprocess_forward(means_c, quats, scales, torch.ones(n), torch.zeros(n, 0, 3),
                                              torch.zeros(n, 3), rot_c.contiguous(), -1, False, None)[:2]
    for name, x32, x64 in (("twin W", w_twin, w64), ("twin o_u", o_twin, o64), ("cpu W", w_cpu.reshape(n, 3, 3), w64),
                           ("cpu o_u", o_cpu, o64)):
        assert float(_within_one_rounding(x32, x64).max()) <= 0.5001, name
    # What the rule rejects: the same frame from a float32 chain.
    chain = (rot_c @ quat_to_rotmat(quats)).transpose(1, 2) / scales[:, :, None]
    assert float(_within_one_rounding(chain, w64).max()) > 1.0
