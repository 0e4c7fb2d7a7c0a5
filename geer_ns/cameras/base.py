"""The camera interface and the small tensor helpers every model shares (conventions: see :mod:`geer_ns.cameras`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import torch
from torch import Tensor


def _float_dtype(x: Tensor) -> torch.dtype:
    return x.dtype if x.dtype in (torch.float32, torch.float64) else torch.float32


def _safe_norm(v: Tensor) -> Tensor:
    """Euclidean norm over the last dim, never exactly 0 (finite gradients at the origin)."""
    return torch.sqrt(torch.clamp((v * v).sum(-1), min=torch.finfo(v.dtype).tiny))


def _is_zero(value) -> bool:
    """True for a coefficient that is exactly 0 and fixed; a tensor (a coefficient being refined, maybe 0 now)
    is never 'zero', so that the terms it scales stay in the graph (geer_ns/refinement/lens.py)."""
    return not isinstance(value, Tensor) and value == 0


def _tol_px(dtype: torch.dtype) -> float:
    """Residual (pixels) below which an inversion counts as converged."""
    return 1e-5 if dtype == torch.float64 else 2e-2


@dataclass(frozen=True)
class CameraModel:
    """Base class: an image of ``width`` x ``height`` pixels and a central projection."""

    width: int
    height: int

    # Float fields that must be > 0 (checked in __post_init__).
    _positive_fields: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in ("width", "height"):
                if isinstance(value, bool) or int(value) != value or value <= 0:
                    raise ValueError(f"{type(self).__name__}.{f.name} must be a positive integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))
                continue
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{type(self).__name__}.{f.name} must be a real number, got {value!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"{type(self).__name__}.{f.name} must be finite, got {value!r}")
            if f.name in self._positive_fields and value <= 0:
                raise ValueError(f"{type(self).__name__}.{f.name} must be > 0, got {value!r}")
            object.__setattr__(self, f.name, value)
        self._check_params()

    def _check_params(self) -> None:
        """Model-specific range checks (raise ValueError naming the field)."""

    # --- interface -------------------------------------------------------------------------------
    @cached_property
    def max_angle(self) -> float:
        """Largest valid angle (radians) from the optical axis; see the :mod:`geer_ns.cameras` docstring."""
        raise NotImplementedError

    def project(self, points_cam: Tensor) -> tuple[Tensor, Tensor]:
        """Project camera-frame points ``[..., 3]`` to pixels ``[..., 2]``; also returns ``valid [...]``."""
        raise NotImplementedError

    def unproject(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """Lift pixels ``[..., 2]`` to unit directions ``[..., 3]``; also returns ``valid [...]``."""
        raise NotImplementedError

    def pixel_centers(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """``[H, W, 2]`` pixel-center coordinates (u, v) = (j + 0.5, i + 0.5)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=dtype, device=device) + 0.5,
            torch.arange(self.width, dtype=dtype, device=device) + 0.5,
            indexing="ij",
        )
        return torch.stack([u, v], dim=-1)

    def pixel_rays(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor]:
        """Unit rays through all pixel centers: ``dirs [H, W, 3]`` and ``valid [H, W]``.

        Solved in float64 and cast to ``dtype`` so that float32 callers get accurate rays.
        """
        dirs, valid = self.unproject(self.pixel_centers(torch.float64, device))
        return dirs.to(dtype), valid
