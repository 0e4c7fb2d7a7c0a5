"""Collectives get tensors on the device their backend serves: NCCL serves CUDA tensors only, so a flag or count
built on the CPU stops a multi-GPU run at step 0, while gloo (every other test) accepts it.

Two gloo processes through nerfstudio's launcher, under emulated NCCL (tests/nccl_emulation.py: the world says
NCCL, a collective refuses non-CUDA tensors, the engine's tensors are emulated CUDA tensors). The expected
values are sums worked out by hand and the one-process render of the whole scene.
"""

from __future__ import annotations

import torch

import distributed_harness as harness
from geer_ns.render import render
from test_distributed import _launch


def _results(tmp_path_factory):
    out = tmp_path_factory.mktemp("nccl_rule")
    config = harness.scenario_config(out / "no_data", out, "nccl")
    _launch(config, out / "log.txt", main=harness.nccl_rule_main)
    return [torch.load(out / f"nccl_{rank}.pt") for rank in (0, 1)]


def test_collectives_under_nccls_rule(tmp_path_factory):
    ranks = _results(tmp_path_factory)
    for rank, got in enumerate(ranks):
        # reduce_gradients: the has-gradient flags, then the sum over both processes / 2 images.
        grads = got["gradients"]
        assert not isinstance(grads, str), (rank, grads)
        assert grads[0][0] == "cuda" and torch.equal(grads[0][1], torch.full((4, 3), (1.0 + 3.0) / 2))
        assert grads[1][0] == "cuda" and torch.equal(grads[1][1], torch.full((5,), (2.0 + 0.0) / 2))
        assert grads[2] is None
        # render_sharded: the all-to-all's counts, then the rows; the render is the one-process render.
        shard = got["sharded_render"]
        assert not isinstance(shard, str), (rank, shard)
        scene, viewmats, grids, _ = harness.shard_case("fisheye180", torch.float64)
        whole = render(*scene, viewmats[rank], grids[rank], backend="torch")
        assert shard["device"] == "cuda" and shard["sent"] > 0
        assert torch.allclose(shard["rgb"], whole.rgb, atol=1e-12), float((shard["rgb"] - whole.rgb).abs().max())
    gathered = ranks[0]["gather_rows"]
    assert not isinstance(gathered, str), gathered
    assert gathered[0] == "cuda" and torch.equal(gathered[1], torch.tensor([0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 3.0]))
    assert ranks[1]["gather_rows"] is None
