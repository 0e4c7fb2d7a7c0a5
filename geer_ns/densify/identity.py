"""Gaussians with an identity: densification's random draws belong to the Gaussian, not to its row.

Every Gaussian of DefaultStrategy carries a 64-bit id in the strategy state (`state["id"]`; gsplat's ops keep
every per-Gaussian state tensor's rows in step with the parameters). A split's two samples and the ids of new
Gaussians are counter-based: a hash of the parent's id, the step and the child, not draws from the global
random stream, whose order depends on where each Gaussian sits. The same Gaussian therefore splits the same way
in one process, in a replica, or in a shard held by another process (geer_ns/distributed): sharded training
equals single-process training through its refinements, whatever the shards.

The hash is SplitMix64's finalizer (Steele, Lea, Flood 2014), in torch's wrapping int64 arithmetic with logical
shifts; uniforms take its top 53 bits, normals come from the Box-Muller transform.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

_GOLDEN = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed 64-bit integer
_MUL1 = -4658895280553007687  # 0xBF58476D1CE4E5B9
_MUL2 = -7723592293110705685  # 0x94D049BB133111EB


def _shift_right(x: Tensor, k: int) -> Tensor:
    """Logical shift of int64 (torch's >> is arithmetic on negative values)."""
    return torch.bitwise_and(torch.bitwise_right_shift(x, k), (1 << (64 - k)) - 1)


def mix(x: Tensor) -> Tensor:
    """SplitMix64 of int64 values: x + golden ratio, then the finalizer (a bijection of 64-bit words)."""
    z = x + _GOLDEN
    z = torch.bitwise_xor(z, _shift_right(z, 30)) * _MUL1
    z = torch.bitwise_xor(z, _shift_right(z, 27)) * _MUL2
    return torch.bitwise_xor(z, _shift_right(z, 31))


def _key(ids: Tensor, step: int, child: int, draw: int) -> Tensor:
    return mix(ids + mix(torch.full_like(ids, step) + mix(torch.full_like(ids, child * 64 + draw))))


def child_ids(ids: Tensor, step: int, child: int) -> Tensor:
    """The id of child `child` (0: a duplicate, 1 and 2: the halves of a split) of each Gaussian at `step`."""
    return _key(ids, step, child, 63)


def uniforms(ids: Tensor, step: int, child: int, draw: int) -> Tensor:
    """float64 in (0, 1], one per id: the top 53 bits of the hash, + 1."""
    bits = _shift_right(_key(ids, step, child, draw), 11)
    return (bits.double() + 1.0) * 2.0**-53


def normals(ids: Tensor, step: int, child: int) -> Tensor:
    """[S, 3] standard normal samples, one row per id (Box-Muller over four uniforms)."""
    u = [uniforms(ids, step, child, d) for d in range(4)]
    r1, r2 = torch.sqrt(-2.0 * torch.log(u[0])), torch.sqrt(-2.0 * torch.log(u[2]))
    return torch.stack([r1 * torch.cos(2 * math.pi * u[1]), r1 * torch.sin(2 * math.pi * u[1]),
                        r2 * torch.cos(2 * math.pi * u[3])], -1)
