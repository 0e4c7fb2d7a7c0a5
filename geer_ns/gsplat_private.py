"""Every gsplat private name geer uses, named once, for the gsplat version they were read from.

gsplat's private API may change in any release. geer uses it where gsplat has no public equivalent: the three
steps DefaultStrategy.step_post_backward calls (statistics, growth, prune: geer feeds its own statistics and
logs each rule), the parameter-and-optimizer-state replacement of gsplat.strategy.ops, and gsplat's PyTorch
reference projection and SH (geer's CPU twins of gsplat's EWA rendering). Each use checks the installed gsplat
(`check_gsplat`); tests/test_gsplat_private.py pins the behavior geer relies on.
"""

from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional, Tuple

import gsplat
from gsplat.cuda import _torch_impl
from gsplat.strategy import DefaultStrategy
from gsplat.strategy import ops as _ops
from torch import Tensor

WRITTEN_FOR = "1.4.0"  # the gsplat version whose private API this module names


def check_gsplat() -> None:
    """Raise one clear line unless the installed gsplat is the version this module was written for."""
    found = getattr(gsplat, "__version__", "unknown")
    if found != WRITTEN_FOR:
        raise RuntimeError(f"geer: gsplat {found} is installed, but geer uses gsplat {WRITTEN_FOR}'s private API "
                           f"(geer_ns/gsplat_private.py): pip install gsplat=={WRITTEN_FOR}")


class DefaultStrategyHooks(DefaultStrategy):
    """DefaultStrategy whose private steps, called by its step_post_backward, are public methods to override:
    `update_statistics` (after every backward), then at a refinement `grow` and `prune`."""

    def __post_init__(self) -> None:
        check_gsplat()

    def update_statistics(self, params, state: Dict[str, Any], info: Dict[str, Any], packed: bool = False) -> None:
        """Accumulate the step's statistics into `state` (gsplat: from info["means2d"].grad)."""
        DefaultStrategy._update_state(self, params, state, info, packed=packed)

    def grow(self, params, optimizers, state: Dict[str, Any], step: int) -> Tuple[int, int]:
        """Duplicate and split; returns (duplicated, split)."""
        return DefaultStrategy._grow_gs(self, params, optimizers, state, step)

    def prune(self, params, optimizers, state: Dict[str, Any], step: int) -> int:
        """Prune; returns the number pruned."""
        return DefaultStrategy._prune_gs(self, params, optimizers, state, step)

    def _update_state(self, params, state, info, packed: bool = False) -> None:
        self.update_statistics(params, state, info, packed=packed)

    def _grow_gs(self, params, optimizers, state, step):
        return self.grow(params, optimizers, state, step)

    def _prune_gs(self, params, optimizers, state, step):
        return self.prune(params, optimizers, state, step)


def update_param_with_optimizer(param_fn: Callable[[str, Tensor], Tensor], optimizer_fn: Callable[[str, Tensor], Tensor],
                                params, optimizers, names: Optional[List[str]] = None) -> None:
    """Replace each named parameter by param_fn(name, p) and each of its optimizer state entries (all but
    "step") by optimizer_fn(key, value), in place in `params` and `optimizers` (gsplat.strategy.ops')."""
    check_gsplat()
    _ops._update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers, names=names)


def quat_scale_to_covar_preci(quats: Tensor, scales: Tensor, **kwargs):
    """gsplat's PyTorch covariance / precision from quaternions and scales: (covars, precis)."""
    check_gsplat()
    return _torch_impl._quat_scale_to_covar_preci(quats, scales, **kwargs)


def fully_fused_projection(means: Tensor, covars: Tensor, viewmats: Tensor, Ks: Tensor, width: int, height: int,
                           **kwargs):
    """gsplat's PyTorch EWA projection: (radii, means2d, depths, conics, compensations), per camera."""
    check_gsplat()
    return _torch_impl._fully_fused_projection(means, covars, viewmats, Ks, width, height, **kwargs)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """gsplat's PyTorch SH evaluation of `coeffs` [..., K, 3] along `dirs` [..., 3] (no +0.5 offset)."""
    check_gsplat()
    return _torch_impl._spherical_harmonics(degree, dirs, coeffs)
