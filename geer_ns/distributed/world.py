"""The process group a training run is part of, and the few collectives the engine uses (torch.distributed).

One process: no process group, every collective is the identity. Several (nerfstudio's launcher,
`--machine.num-devices N`, `--machine.num-machines M`): gloo on CPU tensors, NCCL on CUDA tensors; the
same calls either way, so one engine trains on 1 or N processes. Every tensor a collective takes goes through
`on_backend_device` first: NCCL serves CUDA tensors only, and a flag or count built on the CPU would stop a
multi-GPU run at its first step while gloo, which every CPU test uses, accepts it (docs/gpu_correctness.md:
tests/test_distributed.py emulates NCCL's rule).
"""

from __future__ import annotations

from dataclasses import dataclass
from collections import deque
from typing import Any, Callable, Deque, List, Sequence

import torch
import torch.distributed as dist
from torch import Tensor

# Gradient buckets of at most this many bytes (DistributedDataParallel's default bucket_cap_mb is 25).
BUCKET_BYTES = 25 << 20
BUCKETS_IN_FLIGHT = 2  # one reducing while the next is copied out: overlap without a second copy of everything


@dataclass(frozen=True)
class World:
    """Where this process stands: its global rank, the number of processes, the backend."""

    rank: int = 0
    size: int = 1
    backend: str = "none"

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1


def current_world() -> World:
    if dist.is_available() and dist.is_initialized():
        return World(dist.get_rank(), dist.get_world_size(), str(dist.get_backend()))
    return World()


def backend_device(like: Tensor) -> torch.device:
    """The device the process group's backend takes `like` on: its own device when the backend serves that
    device type, else the served one. NCCL serves CUDA tensors only (the process's current CUDA device); gloo
    serves CPU tensors (it would copy CUDA ones through the host); a group with a backend per device type
    ("cpu:gloo,cuda:nccl") serves each type."""
    backend = str(dist.get_backend())
    if ":" in backend:
        served = [part.split(":")[0] for part in backend.split(",")]
    else:
        served = ["cuda" if backend == "nccl" else "cpu"]
    return like.device if like.device.type in served else torch.device(served[0])


def on_backend_device(t: Tensor) -> Tensor:
    """`t`, contiguous, on backend_device(t): what every collective takes (a copy only where the device or
    layout differs; differentiable, for torch.distributed.nn)."""
    return t.contiguous().to(backend_device(t))


def exchange_counts(send: Sequence[int]) -> List[int]:
    """All-to-all of one count per process: send[q] goes to rank q; returns what each rank sent to this one."""
    counts = on_backend_device(torch.tensor(list(send), dtype=torch.int64))
    received = torch.empty_like(counts)
    dist.all_to_all_single(received, counts)
    return received.cpu().tolist()


def all_reduce_(tensors: Sequence[Tensor], op: str = "sum", bucket_bytes: int = BUCKET_BYTES,
                in_flight: int = BUCKETS_IN_FLIGHT) -> None:
    """Reduce every tensor in place over all processes, flattened into buckets of one dtype and device, at most
    `in_flight` buckets' collectives at once (each bucket is a copy: more in flight would hold a second copy of
    every gradient). op: "sum" or "max". No-op on one process."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1 or not tensors:
        return
    reduce_op = {"sum": dist.ReduceOp.SUM, "max": dist.ReduceOp.MAX}[op]
    reduce_in_buckets(tensors, lambda flat: dist.all_reduce(flat, op=reduce_op, async_op=True), bucket_bytes,
                      in_flight, place=on_backend_device)


def reduce_in_buckets(tensors: Sequence[Tensor], start: Callable[[Tensor], Any], bucket_bytes: int,
                      in_flight: int, place: Callable[[Tensor], Tensor] = lambda t: t) -> None:
    """all_reduce_'s bucketing: `start(flat)` launches a bucket's collective on its flat copy (`place`d on the
    backend's device) and returns what to `wait()` for; the oldest bucket is finished (copied back, freed)
    before another beyond `in_flight` starts."""
    pending: Deque = deque()

    def finish() -> None:
        bucket, flat, work = pending.popleft()
        work.wait()
        offset = 0
        for t in bucket:
            t.copy_(flat[offset : offset + t.numel()].view_as(t))
            offset += t.numel()

    for bucket in _buckets(tensors, bucket_bytes):
        if len(pending) >= max(1, in_flight):
            finish()
        flat = place(torch.cat([t.reshape(-1) for t in bucket]))
        pending.append((bucket, flat, start(flat)))
        del flat
    while pending:
        finish()


def _buckets(tensors: Sequence[Tensor], bucket_bytes: int) -> List[List[Tensor]]:
    """Consecutive runs of tensors with one dtype and device, each run cut at bucket_bytes."""
    buckets: List[List[Tensor]] = []
    size = 0
    for t in tensors:
        nbytes = t.numel() * t.element_size()
        last = buckets[-1] if buckets else None
        if last is None or last[0].dtype != t.dtype or last[0].device != t.device or size + nbytes > bucket_bytes:
            buckets.append([t])
            size = nbytes
        else:
            last.append(t)
            size += nbytes
    return buckets


def all_gather_counts(count: int) -> List[int]:
    """[count of rank 0, count of rank 1, ...]: one small tensor collective (no pickling, unlike
    all_gather_objects: what runs every step); [count] on one process."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [int(count)]
    mine = on_backend_device(torch.tensor([int(count)], dtype=torch.int64))
    every = mine.new_empty(dist.get_world_size())
    dist.all_gather_into_tensor(every, mine)
    return every.cpu().tolist()


def all_gather_objects(obj: Any) -> List[Any]:
    """[obj of rank 0, obj of rank 1, ...] (picklable objects); [obj] on one process."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [obj]
    out: List[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj: Any, src: int = 0) -> Any:
    """Rank src's obj on every rank."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=src)
    return box[0]


def broadcast_(tensors: Sequence[Tensor], src: int = 0) -> None:
    """Rank src's values into every rank's tensors, in place (the tensors match in shape on every rank)."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return
    for t in tensors:
        if t.numel() == 0:
            continue
        buffer = on_backend_device(t.detach())
        dist.broadcast(buffer, src=src)
        t.detach().copy_(buffer.view_as(t))
