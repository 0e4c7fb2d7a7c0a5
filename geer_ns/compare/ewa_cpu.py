"""gsplat 1.4.0's `rasterization` (classic EWA splatting) for a machine without CUDA, for comparisons only.

gsplat's own PyTorch projection, covariances and SH (geer_ns.gsplat_private: pinhole, fisheye, ortho), then the tiled
compositor of geer_ns.compare.ewa_tiles. The signature and the returned `info` are gsplat's (unpacked: `radii` [C,
N], `means2d` [C, N, 2] in pixels whose `.grad` / `.absgrad` DefaultStrategy reads, `width`, `height`, `n_cameras`,
`gaussian_ids` None), so splatfacto's model, schedule and densification run unchanged. geer-compare installs it in
splatfacto's module only for its own runs and only where CUDA is absent (geer_ns/compare/splatfacto.py); results are
labeled "CPU EWA".
"""

from __future__ import annotations

from typing import Dict, Literal, Optional, Tuple

import torch
from torch import Tensor

from geer_ns.compare.ewa_tiles import rasterize_to_pixels

LABEL = "gsplat EWA on CPU (geer_ns.compare.ewa_cpu)"


def project(means: Tensor, quats: Optional[Tensor], scales: Optional[Tensor], viewmats: Tensor, Ks: Tensor,
            width: int, height: int, eps2d: float = 0.3, near_plane: float = 0.01, far_plane: float = 1e10,
            radius_clip: float = 0.0, antialiased: bool = False, camera_model: str = "pinhole",
            covars: Optional[Tensor] = None):
    """gsplat's projection in PyTorch: (radii [C,N] int32, means2d [C,N,2], depths [C,N], conics [C,N,3],
    compensations [C,N] or None)."""
    from geer_ns.gsplat_private import fully_fused_projection, quat_scale_to_covar_preci

    if covars is None:
        covars, _ = quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, depths, conics, compensations = fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
        calc_compensations=antialiased, camera_model=camera_model)
    if radius_clip > 0:
        radii = torch.where(radii.float() <= radius_clip, torch.zeros_like(radii), radii)
    return radii, means2d, depths, conics, compensations


def _colors_of(means: Tensor, colors: Tensor, viewmats: Tensor, radii: Tensor, sh_degree: Optional[int]) -> Tensor:
    """[C, N, D]: post-activation colors, or gsplat's SH evaluation (+0.5, clamped at 0) toward each camera."""
    C, N = radii.shape
    if sh_degree is None:
        return colors.expand(C, -1, -1) if colors.dim() == 2 else colors
    from geer_ns.gsplat_private import spherical_harmonics

    camtoworlds = torch.inverse(viewmats)
    dirs = means[None, :, :] - camtoworlds[:, None, :3, 3]
    shs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
    rgb = spherical_harmonics(sh_degree, dirs, shs)
    rgb = torch.where((radii > 0)[..., None], rgb, torch.zeros_like(rgb))
    return torch.clamp_min(rgb + 0.5, 0.0)


def rasterization(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0,
    eps2d: float = 0.3, sh_degree: Optional[int] = None, packed: bool = True, tile_size: int = 16,
    backgrounds: Optional[Tensor] = None, render_mode: Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"] = "RGB",
    sparse_grad: bool = False, absgrad: bool = False, rasterize_mode: Literal["classic", "antialiased"] = "classic",
    channel_chunk: int = 32, distributed: bool = False,
    camera_model: Literal["pinhole", "ortho", "fisheye"] = "pinhole", covars: Optional[Tensor] = None,
) -> Tuple[Tensor, Tensor, Dict]:
    """gsplat.rendering.rasterization's arguments and results, computed on any device in PyTorch.

    `packed=True` is served unpacked (gaussian_ids None in `info`; DefaultStrategy reads it as splatfacto's
    packed=False); `distributed` is not supported; `sparse_grad` and `channel_chunk` have no effect.
    Returns (render_colors [C, H, W, X], render_alphas [C, H, W, 1], info).
    """
    if distributed:
        raise NotImplementedError("geer_ns.compare.ewa_cpu.rasterization: distributed=True is not supported")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode {rasterize_mode!r}: expected 'classic' or 'antialiased'")
    C, N = viewmats.shape[0], means.shape[0]
    radii, means2d, depths, conics, compensations = project(
        means, quats, scales, viewmats, Ks, width, height, eps2d, near_plane, far_plane, radius_clip,
        rasterize_mode == "antialiased", camera_model, covars)
    opacities_c = opacities.expand(C, -1)
    if compensations is not None:
        opacities_c = opacities_c * compensations
    rgb = _colors_of(means, colors, viewmats, radii, sh_degree)
    if render_mode in ("RGB+D", "RGB+ED"):
        channels = torch.cat([rgb, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, torch.zeros_like(backgrounds[..., :1])], dim=-1)
    elif render_mode in ("D", "ED"):
        channels = depths[..., None]
        backgrounds = None if backgrounds is None else torch.zeros_like(backgrounds[..., :1])
    else:
        channels = rgb
    render_colors, render_alphas = rasterize_to_pixels(
        means2d, conics, channels, opacities_c, radii, depths, width, height, tile_size, backgrounds, absgrad)
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat([render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)],
                                  dim=-1)
    tw, th = -(-width // tile_size), -(-height // tile_size)
    info = {"camera_ids": None, "gaussian_ids": None, "radii": radii, "means2d": means2d, "depths": depths,
            "conics": conics, "opacities": opacities_c, "tile_width": tw, "tile_height": th, "width": width,
            "height": height, "tile_size": tile_size, "n_cameras": C, "rasterizer": LABEL}
    return render_colors, render_alphas, info
