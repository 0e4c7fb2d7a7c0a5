"""Processes that must agree: the start-up check that every process read the same dataset and configuration,
rank 0's state broadcast to every process, and checksums of replicas that must stay bit for bit the same."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import PurePath
from typing import Dict, List

from torch import Tensor

from geer_ns import resume
from geer_ns.distributed.world import World, all_gather_objects, broadcast_, broadcast_object


class ReplicaMismatchError(RuntimeError):
    """A process read another dataset or configuration than rank 0, or its replica drifted: said on every rank."""


def _digest(values) -> str:
    h = hashlib.sha256()
    for v in values:
        if isinstance(v, Tensor):
            h.update(v.detach().cpu().contiguous().numpy().tobytes())
        else:
            h.update(repr(v).encode())
    return h.hexdigest()[:16]


def _flat_config(obj, prefix: str = "") -> Dict[str, str]:
    """Config fields as 'a.b.c' -> repr, without paths (a dataset may sit elsewhere on every machine)."""
    out: Dict[str, str] = {}
    if dataclasses.is_dataclass(obj):
        items = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}.items()
    elif isinstance(obj, dict):
        items = obj.items()
    else:
        return {prefix: repr(obj)} if not isinstance(obj, PurePath) else {}
    for name, value in items:
        key = f"{prefix}.{name}" if prefix else str(name)
        if name == "_target":
            out[key] = repr(getattr(value, "__qualname__", value))
        elif isinstance(value, PurePath) or name in ("data", "output_dir"):
            continue
        else:
            out.update(_flat_config(value, key))
    return out


def fingerprint(trainer) -> Dict[str, str]:
    """What every process must agree on, each entry short enough to print."""
    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    cams = dm.train_dataset.cameras
    found = {
        "train images": f"{len(dm.train_dataset)} ({_digest([str(PurePath(f).name) for f in dm.train_dataset.image_filenames])})",
        "train cameras": _digest([cams.camera_to_worlds, cams.fx, cams.fy, cams.cx, cams.cy, cams.width, cams.height,
                                  cams.camera_type, cams.distortion_params if cams.distortion_params is not None else 0]),
        "eval images": f"{len(dm.eval_dataset)} ({_digest([str(PurePath(f).name) for f in dm.eval_dataset.image_filenames])})",
        "Gaussians": str(model.scene_gaussians or model.num_points),  # a shard's: the scene's
        "start step": str(trainer._start_step),
    }
    if trainer._start_step > 0 and model.scene_gaussians is None:  # resumed replicas must already agree
        found["loaded parameters"] = _digest(list(model.gauss_params.values()))
    config = getattr(trainer, "user_config", trainer.config)  # the values as given (before the batch rule)
    found.update({f"config {k}": v for k, v in _flat_config(config.pipeline, "pipeline").items()})
    found.update({f"config {k}": v for k, v in _flat_config(config.optimizers, "optimizers").items()})
    found["config max_num_iterations"] = str(config.max_num_iterations)
    return found


def check_consistent(world: World, mine: Dict[str, str]) -> None:
    """Raise ReplicaMismatchError on every rank when any rank's fingerprint differs from rank 0's."""
    every = all_gather_objects(mine)
    problems = []
    for rank, theirs in enumerate(every[1:], start=1):
        for key in sorted(set(every[0]) | set(theirs)):
            if every[0].get(key) != theirs.get(key):
                problems.append(f"rank {rank} has {key} = {theirs.get(key)!s:.80} where rank 0 has "
                                f"{every[0].get(key)!s:.80}")
    if problems:
        more = f" (+{len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ReplicaMismatchError("geer: the processes of this run disagree: " + "; ".join(problems[:3]) + more +
                                   ". Every process must read the same dataset with the same configuration.")


def broadcast_replica(world: World, model, optimizers) -> None:
    """Rank 0's model state (parameters, buffers), optimizer state and random-number states on every rank."""
    if not world.distributed:
        return
    broadcast_([t for t in model.state_dict().values() if isinstance(t, Tensor)])
    for opt in optimizers.optimizers.values():
        for state in opt.state.values():
            broadcast_([v for v in state.values() if isinstance(v, Tensor) and v.ndim > 0])
    resume.restore_rng_state(broadcast_object(resume.rng_state()))
    resume.restore_strategy_state(model.strategy_state, broadcast_object(resume.strategy_state(model.strategy_state)),
                                  model.device)


def replica_checksum(model) -> str:
    """An exact digest of the model's parameters (for replicas that must be bit for bit the same)."""
    return _digest(list(model.gauss_params.values()))


def check_replicas_identical(world: World, model, step: int) -> List[str]:
    """Every rank's checksum; raises ReplicaMismatchError when they differ."""
    sums = all_gather_objects(replica_checksum(model))
    if len(set(sums)) > 1:
        raise ReplicaMismatchError(f"geer: the replicas differ after step {step}: parameter checksums {sums} "
                                   "(a non-deterministic reduction or a process that skipped an update)")
    return sums
