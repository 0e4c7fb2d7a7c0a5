"""Checkpoints that hold each Gaussian's kept SH coefficients only.

A Gaussian of degree d keeps the first (d + 1)^2 - 1 of its `features_rest` rows' coefficients; the others are
zero and frozen (their Adam moments too). In a checkpoint `gauss_params.features_rest` [N, K, 3] becomes the kept
coefficients in row order, [M, 3], and so do that parameter's Adam moments; the degrees themselves are the
strategy state's `sh_degree` (uint8 [N], saved with the model). Packing row by row keeps a sharded checkpoint's
streaming intact: the packed rows of shards in rank order are the packed rows of the whole scene. A checkpoint
with a [N, K, 3] `features_rest` (every checkpoint before per-Gaussian degrees, or a run without them) loads
unchanged.
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Optional

import torch
from torch import Tensor

REST = "gauss_params.features_rest"
DEGREES = "sh_degree"  # the strategy state's entry (model extra state)
PIPELINE = "_model."


def kept(degrees: Tensor, columns: int) -> Tensor:
    """[N, columns] bool: which of each row's `features_rest` coefficients its degree keeps."""
    per_row = (degrees.long() + 1) ** 2 - 1
    return torch.arange(columns, device=degrees.device)[None] < per_row[:, None]


def pack(dense: Tensor, degrees: Tensor) -> Tensor:
    """[N, K, 3] -> [M, 3]: the kept coefficients, row after row."""
    return dense[kept(degrees.to(dense.device), dense.shape[1])]


def unpack(packed: Tensor, degrees: Tensor, columns: int) -> Tensor:
    """[M, 3] -> [N, columns, 3], zeros where a row's degree keeps nothing."""
    mask = kept(degrees.to(packed.device), columns)
    if int(mask.sum()) != packed.shape[0]:
        raise ValueError(f"checkpoint: {REST} holds {packed.shape[0]} kept SH coefficients, its {len(degrees)} "
                         f"Gaussians' degrees keep {int(mask.sum())}")
    dense = packed.new_zeros(len(degrees), columns, packed.shape[-1])
    dense[mask] = packed
    return dense


def _model_degrees(model_state: Mapping[str, Any], prefix: str = "") -> Optional[Tensor]:
    extra = model_state.get(prefix + "_extra_state")
    strategy = extra.get("strategy_state") if isinstance(extra, Mapping) else None
    degrees = strategy.get(DEGREES) if isinstance(strategy, Mapping) else None
    return degrees if isinstance(degrees, Tensor) else None


def _rest_moments(state: Mapping[str, Any]):
    """The Adam state entries of the features_rest optimizer in a nerfstudio checkpoint (dict, key) pairs."""
    opt = state.get("optimizers", {}).get("features_rest")
    for entry in (opt or {}).get("state", {}).values():
        for key, value in entry.items():
            if isinstance(value, Tensor) and value.dim() >= 2:
                yield entry, key


def packed_checkpoint(state: Dict[str, Any]) -> Dict[str, Any]:
    """A nerfstudio checkpoint (resume.trainer_state's dict) with features_rest and its Adam moments packed, where
    the model has per-Gaussian degrees; else unchanged. Modifies and returns `state`."""
    pipeline = state["pipeline"]
    degrees = _model_degrees(pipeline, PIPELINE)
    key = PIPELINE + REST
    if degrees is None or key not in pipeline or pipeline[key].dim() != 3:
        return state
    pipeline[key] = pack(pipeline[key], degrees)
    for entry, name in _rest_moments(state):
        entry[name] = pack(entry[name], degrees)
    return state


def unpacked_checkpoint(state: Dict[str, Any], columns: int) -> Dict[str, Any]:
    """packed_checkpoint undone (`columns`: K of the model's features_rest); a dense checkpoint is returned as it
    is. Modifies and returns `state`."""
    pipeline = state["pipeline"]
    key = PIPELINE + REST
    if key not in pipeline or pipeline[key].dim() != 2:
        return state
    degrees = _model_degrees(pipeline, PIPELINE)
    if degrees is None:
        raise ValueError(f"checkpoint: {key} is packed but the model's strategy state has no {DEGREES}")
    pipeline[key] = unpack(pipeline[key], degrees, columns)
    for entry, name in _rest_moments(state):
        if entry[name].dim() == 2:
            entry[name] = unpack(entry[name], degrees, columns)
    return state


def unpacked_model_state(model_state: Dict[str, Any], columns: int) -> Dict[str, Any]:
    """A model state dict (keys without "_model.", as load_state_dict gets them) with features_rest dense."""
    packed = model_state.get(REST)
    if packed is None or packed.dim() != 2:
        return model_state
    degrees = _model_degrees(model_state)
    if degrees is None:
        raise ValueError(f"checkpoint: {REST} is packed but the model's strategy state has no {DEGREES}")
    return {**model_state, REST: unpack(packed, degrees, columns)}
