"""Checkpoint state that makes `ns-train --load-dir` continue training exactly where it stopped.

A nerfstudio 1.1.5 bug (docs/training.md): splatfacto's `load_state_dict` swaps fresh `nn.Parameter`s into
`gauss_params` after the trainer built the optimizers (and gsplat's strategy state) on the old ones, so
a resumed run steps parameters nobody renders (every loaded Gaussian stays bit-identical, Adam's step
count stalls) and the first refinement indexes the stale optimizer state out of bounds. geer instead:

* resizes the existing Parameters in place, so the optimizers the trainer built, and then filled with
  the checkpoint's optimizer state, hold the very tensors the model renders;
* saves with the model (nn.Module extra state, plain tensors / numbers: loadable by torch's
  weights_only loader) what nerfstudio leaves out: the training step and gsplat's strategy state (the
  densification statistics gathered since the last refinement);
* saves in the trainer's part of the checkpoint (key "rng") the torch CPU, current CUDA device, numpy and
  Python RNG states, so refinement and random backgrounds go on as in an uninterrupted run. Only the
  current device's CUDA state: a list of every visible GPU's (what geer wrote before) made ns-eval on a
  machine with fewer GPUs fail, and made every rank restore its own index's state, so replicas drew
  different CUDA numbers. Loading the model (ns-eval, ns-viewer, ns-export) touches no RNG;
* the datamanager saves its camera queue and sampler state (which image comes next).
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import numpy as np
import torch

from geer_ns.sh_degrees.packing import packed_checkpoint

GAUSS_PREFIX = "gauss_params."


def resize_in_place(gauss_params: torch.nn.ParameterDict, state_dict: Mapping[str, Any]) -> None:
    """Give each Gaussian Parameter the checkpoint's row count, keeping the Parameter objects."""
    key = GAUSS_PREFIX + "means"
    if key not in state_dict:
        return
    n = state_dict[key].shape[0]
    with torch.no_grad():
        for name, param in gauss_params.items():
            if param.shape[0] != n:
                param.data = param.new_zeros((n,) + tuple(param.shape[1:]))


def convert_step(step: int, saved_images_per_step: int, images_per_step: int) -> int:
    """The index of the last completed step `step` of a run whose steps saw `saved_images_per_step` images
    each, in steps of `images_per_step` images: what carries over is the number of images seen."""
    if saved_images_per_step == images_per_step:
        return step
    completed = round((step + 1) * saved_images_per_step / images_per_step)
    return max(completed - 1, 0)


def rng_state() -> Dict[str, Any]:
    """torch (CPU and the current CUDA device), numpy and Python RNG states as tensors, ints and tuples."""
    np_state = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": (str(np_state[0]), torch.from_numpy(np_state[1].astype(np.int64)), *map(_plain, np_state[2:])),
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state()
    return state


def restore_rng_state(state: Mapping[str, Any]) -> None:
    """rng_state()'s states back; the CUDA one into the current device (every rank restores the same one)."""
    torch.set_rng_state(state["torch"].cpu())
    name, keys, *rest = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), *rest))
    random.setstate(_tuples(state["python"]))
    cuda = state.get("cuda")
    if isinstance(cuda, (list, tuple)):  # an older checkpoint: every visible GPU's; the saving rank's device 0
        cuda = cuda[0] if cuda else None
    if cuda is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state(cuda.cpu())


def checkpoint_rng_state(checkpoint: Mapping[str, Any]) -> Optional[Mapping[str, Any]]:
    """The RNG states of a nerfstudio checkpoint: the trainer's part ("rng"), or where older geer checkpoints
    kept them (the model's extra state); None when it has none."""
    if "rng" in checkpoint:
        return checkpoint["rng"]
    extra = checkpoint.get("pipeline", {}).get("_model._extra_state")
    return extra.get("rng") if isinstance(extra, Mapping) else None


def checkpoint_images_per_step(checkpoint: Mapping[str, Any]) -> int:
    """The images per step a nerfstudio checkpoint's steps count (the model's extra state; 1 where absent)."""
    extra = checkpoint.get("pipeline", {}).get("_model._extra_state")
    return int(extra.get("images_per_step", 1)) if isinstance(extra, Mapping) else 1


def checkpoint_path(config) -> Optional[Path]:
    """The checkpoint a TrainerConfig resumes from (--load-dir with --load-step, else nerfstudio's rule: the latest
    step-*.ckpt; or --load-checkpoint), None for a fresh run; a named checkpoint that does not exist is an error."""
    if config.load_dir is not None:
        step = config.load_step
        if step is None:
            step = sorted(int(x[x.find("-") + 1 : x.find(".")]) for x in os.listdir(config.load_dir))[-1]
        path = Path(config.load_dir) / f"step-{step:09d}.ckpt"
    elif config.load_checkpoint is not None:
        path = Path(config.load_checkpoint)
    else:
        return None
    if not path.exists():
        raise FileNotFoundError(f"geer: checkpoint {path} does not exist")
    return path


def images_seen(config) -> int:
    """How many one-image steps the checkpoint `config` resumes from had completed (0 for a fresh run): where a
    resumed run's schedules start (training/horizon.py)."""
    path = checkpoint_path(config)
    if path is None:
        return 0
    state = torch.load(path, map_location="cpu", mmap=True)
    return convert_step(int(state["step"]), checkpoint_images_per_step(state), 1) + 1


def trainer_state(trainer, step: int) -> Dict[str, Any]:
    """nerfstudio's checkpoint of a Trainer at `step` (pipeline, optimizers, schedulers, scaler) with the RNG
    states (rng_state), as a dict for torch.save; with per-Gaussian SH degrees, features_rest and its moments
    hold the kept coefficients only (geer_ns/sh_degrees/packing.py)."""
    return packed_checkpoint({
        "step": step, "pipeline": trainer.pipeline.state_dict(),
        "optimizers": {k: v.state_dict() for k, v in trainer.optimizers.optimizers.items()},
        "schedulers": {k: v.state_dict() for k, v in trainer.optimizers.schedulers.items()},
        "scalers": trainer.grad_scaler.state_dict(), "rng": rng_state()})


def strategy_state(state: Mapping[str, Any]) -> Dict[str, Any]:
    return {k: (v.detach().clone() if isinstance(v, torch.Tensor) else v) for k, v in state.items()}


def restore_strategy_state(target: Dict[str, Any], saved: Mapping[str, Any], device) -> None:
    """Into the model's own dict (gsplat keeps a reference to it)."""
    target.clear()
    target.update({k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in saved.items()})


def sampler_state(datamanager) -> Dict[str, Any]:
    """Which training images come next (FullImageDatamanager's queue and its samplers)."""
    state: Dict[str, Any] = {"train_unseen_cameras": list(getattr(datamanager, "train_unseen_cameras", []))}
    if hasattr(datamanager, "random_generator"):
        state["random_generator"] = datamanager.random_generator.getstate()
    if hasattr(datamanager, "train_unsampled_epoch_count"):
        state["train_unsampled_epoch_count"] = torch.from_numpy(np.asarray(datamanager.train_unsampled_epoch_count))
    return state


def restore_sampler_state(datamanager, state: Mapping[str, Any]) -> None:
    """Restored only when it fits the training set now loaded (a changed dataset keeps its fresh queue)."""
    n = len(getattr(datamanager, "train_dataset", None) or [])
    if not state or any(not 0 <= int(i) < n for i in state["train_unseen_cameras"]):
        return
    datamanager.train_unseen_cameras = [int(i) for i in state["train_unseen_cameras"]]
    if "random_generator" in state:
        datamanager.random_generator = random.Random()
        datamanager.random_generator.setstate(_tuples(state["random_generator"]))
    if "train_unsampled_epoch_count" in state:
        datamanager.train_unsampled_epoch_count = state["train_unsampled_epoch_count"].numpy().copy()


def _plain(value):
    return value.item() if hasattr(value, "item") else value


def _tuples(value):
    """Python's Random.setstate wants tuples; a checkpoint round trip may hand back lists."""
    if isinstance(value, (list, tuple)):
        return tuple(_tuples(v) for v in value)
    return value
