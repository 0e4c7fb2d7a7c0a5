"""A checkpoint of sharded rows written without gathering them: one ordinary torch checkpoint file.

Each process holds its shard's rows of the per-Gaussian tensors (parameters, Adam's moments, densification
statistics). Rank 0 writes the file's frame first: torch.save of its state with every per-Gaussian tensor
replaced by a fake one of the scene's size, under torch.serialization.skip_data (the storages' places are
reserved, not written). It then fills every storage at its offset in the file: its own small tensors, its own
rows, and every other process's rows, which arrive by point-to-point messages of at most CHUNK_BYTES. No
process ever holds more than its shard plus two chunks; the result is the checkpoint one process would have
written with the shards' rows in rank order, which torch.load, ns-eval, ns-viewer, ns-export and a resume on
any number of processes read as they read any other.
"""

from __future__ import annotations

import math
import os
import pickle
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Tuple

import torch
import torch.distributed as dist
from torch import Tensor

from geer_ns.distributed.world import World, all_gather_objects, backend_device

CHUNK_BYTES = 32 << 20  # the most a message (and rank 0's receive buffer) holds
Path_ = Tuple[Any, ...]  # where a value sits in a nested dict / list / tuple: the keys on the way


def leaves(value: Any, path: Path_ = ()) -> List[Tuple[Path_, Any]]:
    """(path, leaf) of a nested structure of dicts, lists and tuples, in its own order."""
    if isinstance(value, dict):
        return [item for key, v in value.items() for item in leaves(v, path + (key,))]
    if isinstance(value, (list, tuple)):
        return [item for i, v in enumerate(value) for item in leaves(v, path + (i,))]
    return [(path, value)]


def replaced(value: Any, new: Dict[Path_, Any], path: Path_ = ()) -> Any:
    """A copy of the structure (its dicts, lists and tuples) with the leaves at `new`'s paths replaced."""
    if path in new:
        return new[path]
    if isinstance(value, dict):
        return {key: replaced(v, new, path + (key,)) for key, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(replaced(v, new, path + (i,)) for i, v in enumerate(value))
    return value


@dataclass(frozen=True)
class _Storage:
    key: str  # the record data/<key> of the checkpoint


class _StorageKeys(pickle.Unpickler):
    """Reads a checkpoint's data.pkl with every tensor replaced by the record key of its storage."""

    def persistent_load(self, saved_id):  # ('storage', storage type, key, location, numel)
        return _Storage(str(saved_id[2]))

    def find_class(self, module, name):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return lambda storage, *args, **kwargs: storage
        return super().find_class(module, name)


def storage_offsets(path: os.PathLike) -> Tuple[Any, Dict[str, int]]:
    """The structure of a torch checkpoint with a _Storage in place of each tensor, and each storage record's
    byte offset in the file."""
    reader = torch._C.PyTorchFileReader(str(path))
    structure = _StorageKeys(_BytesReader(reader.get_record("data.pkl"))).load()
    keys = {leaf.key for _, leaf in leaves(structure) if isinstance(leaf, _Storage)}
    return structure, {key: reader.get_record_offset(f"data/{key}") for key in keys}


class _BytesReader:
    def __init__(self, data) -> None:
        import io

        self._io = io.BytesIO(bytes(data))
        self.read, self.readline = self._io.read, self._io.readline


def _pwrite(fd: int, t: Tensor, offset: int) -> None:
    data = t.detach().reshape(-1).view(torch.uint8).cpu().numpy()
    written = 0
    while written < data.nbytes:
        written += os.pwrite(fd, memoryview(data[written:]), offset + written)


def save_rows_streamed(world: World, state: Dict[str, Any], per_gaussian: Callable[[Path_], bool],
                       path: os.PathLike) -> None:
    """Write `state` (this process's, with its shard's rows in the tensors `per_gaussian` names by path) to
    `path` as one checkpoint of every shard's rows in rank order (module docstring). A collective: every
    process calls it; rank 0 writes the file."""
    mine = [(p, t) for p, t in leaves(state) if isinstance(t, Tensor) and per_gaussian(p)]
    layout = [(p, int(t.shape[0]), str(t.dtype), tuple(t.shape[1:])) for p, t in mine]
    every = all_gather_objects(layout)
    for rank, theirs in enumerate(every):
        if [(p, d, s) for p, _, d, s in theirs] != [(p, d, s) for p, _, d, s in layout]:
            raise RuntimeError(f"geer: checkpoint: rank {rank}'s per-Gaussian tensors differ from rank "
                               f"{world.rank}'s: {[p for p, *_ in theirs]} against {[p for p, *_ in layout]}")
    counts = [[rows for _, rows, _, _ in theirs] for theirs in every]  # [rank][entry]
    if not world.is_main:
        for _, t in mine:
            for chunk in _chunks(t):
                dist.send(chunk.contiguous().to(backend_device(t)), dst=0)
        return
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode():
        fakes = {p: torch.empty((sum(c[i] for c in counts),) + tuple(t.shape[1:]), dtype=t.dtype)
                 for i, (p, t) in enumerate(mine)}
    frame = replaced(state, fakes)
    with torch.serialization.skip_data(materialize_fake_tensors=True):
        torch.save(frame, path)
    structure, offsets = storage_offsets(path)
    del frame, fakes
    where = {p: leaf.key for p, leaf in leaves(structure) if isinstance(leaf, _Storage)}
    rows = dict(mine)
    fd = os.open(path, os.O_WRONLY)
    try:
        for p, value in leaves(state):
            if isinstance(value, Tensor) and p not in rows:  # a small tensor: its whole storage
                storage = value.detach().cpu().untyped_storage()
                _pwrite(fd, torch.empty(0, dtype=torch.uint8).set_(storage), offsets[where[p]])
        for p, t in mine:
            row_bytes = math.prod(t.shape[1:]) * t.element_size()
            start = 0
            for chunk in _chunks(t):
                _pwrite(fd, chunk.contiguous(), offsets[where[p]] + start * row_bytes)
                start += chunk.shape[0]
        for rank in range(1, world.size):
            for i, (p, t) in enumerate(mine):
                row_bytes = math.prod(t.shape[1:]) * t.element_size()
                start = sum(counts[r][i] for r in range(rank))
                for n in _chunk_rows(counts[rank][i], t):
                    buffer = t.new_empty((n,) + tuple(t.shape[1:]), device=backend_device(t))
                    dist.recv(buffer, src=rank)
                    _pwrite(fd, buffer, offsets[where[p]] + start * row_bytes)
                    start += n
        os.fsync(fd)
    finally:
        os.close(fd)


def _chunk_rows(rows: int, like: Tensor) -> List[int]:
    """Row counts of the messages carrying `rows` rows of `like`'s kind."""
    per = max(1, CHUNK_BYTES // max(1, math.prod(like.shape[1:]) * like.element_size()))
    return [min(per, rows - start) for start in range(0, rows, per)]


def _chunks(t: Tensor) -> List[Tensor]:
    out, start = [], 0
    for n in _chunk_rows(t.shape[0], t):
        out.append(t[start : start + n])
        start += n
    return out
