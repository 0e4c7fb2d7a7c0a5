"""Densification by identity (geer_ns/densify/identity.py, strategy.py): the hash against SplitMix64 written in
plain Python integers, its samples' distribution, and a split that does not depend on the Gaussians' rows."""

from __future__ import annotations

import math

import pytest
import torch

from geer_ns.densify.identity import child_ids, mix, normals, uniforms

MASK = (1 << 64) - 1


def _splitmix64(x: int) -> int:
    """The reference: SplitMix64's step and finaliser in Python's unbounded integers, reduced mod 2^64."""
    z = (x + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def _signed(x: int) -> int:
    return x - (1 << 64) if x >= 1 << 63 else x


def test_mix_is_splitmix64_in_wrapping_int64():
    values = [0, 1, 2, 12345, -1, -(1 << 63), (1 << 63) - 1, 0x9E3779B97F4A7C15 - (1 << 64)]
    ours = mix(torch.tensor(values, dtype=torch.int64)).tolist()
    assert ours == [_signed(_splitmix64(v & MASK)) for v in values]
    assert _splitmix64(0) == 0xE220A8397B1DCDAF  # SplitMix64's first output from seed 0 (its published sequence)


def test_samples_are_uniform_and_normal_and_ids_do_not_collide():
    ids = torch.arange(200_000, dtype=torch.int64)
    u = uniforms(ids, step=700, child=1, draw=0)
    assert float(u.min()) > 0.0 and float(u.max()) <= 1.0
    assert abs(float(u.mean()) - 0.5) < 3e-3 and abs(float(u.var()) - 1 / 12) < 2e-3
    z = normals(ids, step=700, child=1)
    assert z.shape == (200_000, 3)
    assert float(z.mean(0).abs().max()) < 0.01 and float((z.std(0) - 1).abs().max()) < 0.01
    assert abs(float((z[:, 0] * z[:, 1]).mean())) < 0.01  # independent components
    assert float((z.abs() > 3).float().mean()) == pytest.approx(2 * (1 - 0.99865), abs=5e-4)  # normal tails
    kids = torch.cat([ids, child_ids(ids, 700, 0), child_ids(ids, 700, 1), child_ids(ids, 700, 2),
                      child_ids(ids, 800, 1)])
    assert kids.unique().numel() == kids.numel()
    assert not torch.equal(normals(ids[:10], 700, 1), normals(ids[:10], 700, 2))
    assert not torch.equal(normals(ids[:10], 700, 1), normals(ids[:10], 800, 1))


def _gaussians(order):
    gen = torch.Generator().manual_seed(0)
    n = 12
    base = {"means": torch.randn(n, 3, generator=gen), "scales": torch.randn(n, 3, generator=gen) - 2,
            "quats": torch.randn(n, 4, generator=gen), "opacities": torch.randn(n, 1, generator=gen),
            "features_dc": torch.randn(n, 3, generator=gen)}
    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v[order].clone()) for k, v in base.items()})
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for p in params.values():  # give Adam some state to carry
        p.grad = torch.ones_like(p)
    for opt in optimizers.values():
        opt.step()
    state = {"id": torch.arange(n)[order].clone(), "grad2d": torch.arange(n, dtype=torch.float32)[order].clone()}
    return params, optimizers, state


def test_a_split_depends_on_the_gaussians_not_on_their_rows():
    from geer_ns.densify.strategy import GeerDefaultStrategy

    strategy = GeerDefaultStrategy()
    rows = {}
    for name, order in (("identity", torch.arange(12)), ("shuffled", torch.randperm(12, generator=torch.Generator().manual_seed(1)))):
        params, optimizers, state = _gaussians(order)
        split = torch.isin(state["id"], torch.tensor([1, 4, 7]))
        strategy._split(params, optimizers, state, torch.where(split)[0], step=300)
        by_id = torch.argsort(state["id"])
        rows[name] = {k: v.detach()[by_id] for k, v in params.items()}, state["id"][by_id], state["grad2d"][by_id], \
            {k: o.state[params[k]]["exp_avg"][by_id] for k, o in optimizers.items()}
    (a, ids_a, g_a, adam_a), (b, ids_b, g_b, adam_b) = rows["identity"], rows["shuffled"]
    assert len(ids_a) == 15 and torch.equal(ids_a, ids_b)
    for k in a:
        assert torch.equal(a[k], b[k]), k
        assert torch.equal(adam_a[k], adam_b[k]), k
    assert torch.equal(g_a, g_b)
    # each split Gaussian's two children: its own samples, 1/1.6 of its scale, a fresh optimizer state
    params0, _, state0 = _gaussians(torch.arange(12))
    for parent in (1, 4, 7):
        kids = [int((ids_a == child_ids(torch.tensor([parent]), 300, c)).nonzero()) for c in (1, 2)]
        scale = torch.exp(params0["scales"][parent].detach())
        rot = torch.tensor(__import__("scipy.spatial.transform", fromlist=["Rotation"]).Rotation.from_quat(
            params0["quats"][parent].detach()[[1, 2, 3, 0]].double().numpy()).as_matrix(), dtype=torch.float32)
        for c, k in zip((1, 2), kids):
            expected = params0["means"][parent].detach() + rot @ (scale * normals(torch.tensor([parent]), 300, c)[0].float())
            assert torch.allclose(a["means"][k], expected, atol=1e-5)
            assert torch.allclose(torch.exp(a["scales"][k]), scale / 1.6, rtol=1e-6)
            assert float(adam_a["means"][k].abs().max()) == 0.0
    assert float(adam_a["means"][ids_a == 0].abs().max()) > 0  # an unsplit Gaussian keeps its state
