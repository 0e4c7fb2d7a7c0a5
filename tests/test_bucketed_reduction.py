"""all_reduce_'s buckets (geer_ns/distributed/world.py): at most `in_flight` flat copies alive at once, every
tensor reduced. The collective is played by a recorder that doubles each bucket when it is waited for."""

from __future__ import annotations

import gc
import weakref

import pytest
import torch

from geer_ns.distributed.world import reduce_in_buckets


class _Work:
    def __init__(self, flat, alive):
        self.flat, self.alive = flat, alive

    def wait(self):
        self.flat.mul_(2.0)  # the "sum" over two processes holding the same values


@pytest.mark.parametrize("in_flight", [1, 2, 3])
def test_at_most_in_flight_bucket_copies_are_alive_and_every_tensor_is_reduced(in_flight):
    tensors = [torch.full((1000,), float(i)) for i in range(12)]  # 4000 bytes each
    expected = [2.0 * t for t in tensors]
    alive = []
    peak = 0

    def start(flat):
        nonlocal peak
        alive.append(weakref.ref(flat))
        gc.collect()
        peak = max(peak, sum(ref() is not None for ref in alive))
        return _Work(flat, alive)

    reduce_in_buckets(tensors, start, bucket_bytes=8000, in_flight=in_flight)  # 6 buckets of 2 tensors
    assert len(alive) == 6
    assert peak == in_flight
    for t, e in zip(tensors, expected):
        assert torch.equal(t, e)
