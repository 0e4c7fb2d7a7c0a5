"""The render backward's warp reduction (csrc/geer_blocks.h: transposing reduce-scatter, 16 shuffles, the even
lanes writing one slot each), run through the CPU build, which steps the 32 lanes in lock-step through the same
per-stage functions the kernel calls. Each slot of the gradient row is checked against a float64 numpy sum of
the contributing lanes' values, and lanes whose ray does not blend the pair contribute nothing, not even NaN."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from geer_ns.render import cuda_backend

LANES, VALUES = 32, 16


@pytest.fixture(scope="module")
def ops():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: cannot build csrc/cpu_ops.cpp")
    return cuda_backend.load_cpu_ops()


def _reference(values: np.ndarray, contrib: np.ndarray) -> np.ndarray:
    return values.astype(np.float64)[contrib].sum(axis=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_every_slot_is_the_sum_of_the_contributing_lanes(ops, dtype):
    rng = np.random.default_rng(3)
    values = rng.normal(size=(LANES, VALUES)) * 10.0 ** rng.integers(-3, 4, size=(LANES, VALUES))
    contrib = rng.random(LANES) < 0.7
    contrib[[0, 1, 31]] = [True, False, False]  # a writer lane and its partner, and the last lane
    values[~contrib] = np.nan  # never read: a lane that does not contribute adds exactly nothing
    values[np.ix_(~contrib, [3])] = np.inf
    v = torch.tensor(values, dtype=dtype)
    row, totals, _ = ops.warp_grad_sum(v, torch.tensor(contrib))
    ref = _reference(v.numpy(), contrib)
    eps = torch.finfo(dtype).eps
    bound = LANES * eps * np.abs(v.numpy().astype(np.float64))[contrib].sum(axis=0)  # the sum's rounding
    assert np.isfinite(row.numpy()).all()
    assert (np.abs(row.numpy() - ref) <= bound).all(), (row.numpy(), ref)
    # Value k's total sits in lanes 2k and 2k + 1 (the same two numbers added), and the even lane wrote it.
    t = totals.numpy()
    assert np.array_equal(t[0::2], t[1::2]) and np.array_equal(t[0::2], row.numpy())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_each_lane_and_value_reaches_its_own_slot_once(ops, dtype):
    """One 1 at (lane, k), every other input 0: the row is the k-th unit vector, for all 32 x 16 inputs (a
    dropped or doubled lane, or a value sent to the wrong slot, shows here)."""
    contrib = torch.ones(LANES, dtype=torch.bool)
    for lane in range(LANES):
        for k in range(VALUES):
            v = torch.zeros(LANES, VALUES, dtype=dtype)
            v[lane, k] = 1.0
            row, _, _ = ops.warp_grad_sum(v, contrib)
            assert torch.equal(row, torch.eye(VALUES, dtype=dtype)[k]), (lane, k, row)


def test_no_contributing_lane_gives_zeros(ops):
    v = torch.full((LANES, VALUES), float("nan"))
    row, totals, _ = ops.warp_grad_sum(v, torch.zeros(LANES, dtype=torch.bool))
    assert torch.equal(row, torch.zeros(VALUES)) and torch.equal(totals, torch.zeros(LANES))


def test_wrong_shape_names_the_argument(ops):
    with pytest.raises(RuntimeError, match=r"warp_grad_sum: values must be \[32, 16\]"):
        ops.warp_grad_sum(torch.zeros(16, 16), torch.ones(LANES, dtype=torch.bool))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_cpu_backwards_sparse_sum_is_the_butterflys_bit_for_bit(ops, dtype):
    """The CPU backward sums only the contributing lanes (cpu_render_backward.cpp warp_sum_sparse); it must give
    the lock-step butterfly's bits (the GPU's summation order), for any set of lanes and magnitudes where
    rounding order shows: mixed scales, cancellation, signed zeros, subnormals."""
    rng = np.random.default_rng(11)
    tiny = float(torch.finfo(dtype).tiny)
    differs_from_sequential = 0
    for trial in range(400):
        k = int(rng.integers(0, LANES + 1))
        contrib = np.zeros(LANES, dtype=bool)
        contrib[rng.choice(LANES, size=k, replace=False)] = True
        values = rng.normal(size=(LANES, VALUES)) * 10.0 ** rng.integers(-8, 9, size=(LANES, VALUES))
        values[rng.random((LANES, VALUES)) < 0.1] = -0.0
        values[rng.random((LANES, VALUES)) < 0.05] = tiny / 3
        v = torch.tensor(values, dtype=dtype)
        row, _, sparse = ops.warp_grad_sum(v, torch.tensor(contrib))
        assert torch.equal(row.view(torch.int64 if dtype == torch.float64 else torch.int32),
                           sparse.view(torch.int64 if dtype == torch.float64 else torch.int32)) or \
            torch.equal(row, sparse), (trial, k)
        sequential = v[torch.tensor(contrib)].sum(0) if k else torch.zeros(VALUES, dtype=dtype)
        differs_from_sequential += int(not torch.equal(row, sequential))
    # The order matters: a plain left-to-right sum gives other bits for many of these warps.
    assert differs_from_sequential > 50


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_absgrad_sum_follows_the_same_tree(ops, dtype):
    """absgrad's 2 values per lane: the kernel's butterfly (render.cu warp_tree_sum, here in lock-step) and the
    CPU backward's sparse sum give the same bits (the masks of geer_blocks.h for_each_tree_mask), within the
    rounding bound of a float64 sum, and in an order of their own (not left to right). Values >= 0: |.|'s."""
    rng = np.random.default_rng(12)
    differs_from_sequential = 0
    for trial in range(400):
        k = int(rng.integers(0, LANES + 1))
        contrib = np.zeros(LANES, dtype=bool)
        contrib[rng.choice(LANES, size=k, replace=False)] = True
        values = np.abs(rng.normal(size=(LANES, 2))) * 10.0 ** rng.integers(-8, 9, size=(LANES, 2))
        values[rng.random((LANES, 2)) < 0.1] = 0.0
        v = torch.tensor(values, dtype=dtype)
        butterfly, sparse = ops.warp_tree_sum(v, torch.tensor(contrib))
        bits = torch.int64 if dtype == torch.float64 else torch.int32
        assert torch.equal(butterfly.view(bits), sparse.view(bits)), (trial, k)
        exact = v.double().numpy()[contrib].sum(axis=0)
        bound = LANES * float(torch.finfo(dtype).eps) * exact
        assert (np.abs(butterfly.double().numpy() - exact) <= bound).all()
        sequential = v[torch.tensor(contrib)].sum(0) if k else torch.zeros(2, dtype=dtype)
        differs_from_sequential += int(not torch.equal(butterfly, sequential))
    assert differs_from_sequential > 50
    with pytest.raises(RuntimeError, match=r"warp_tree_sum: values must be \[32, 2\]"):
        ops.warp_tree_sum(torch.zeros(32, 16), torch.ones(LANES, dtype=torch.bool))
