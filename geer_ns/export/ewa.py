"""How far a standard (EWA splatting) viewer's image of an exported scene is from geer's exact image.

Viewers that read PLY, glTF KHR_gaussian_splatting or SPZ rasterize each Gaussian as the 2D Gaussian of its
linearized (EWA) projection; geer trained the scene with the exact ray response. On pinhole views at training
poses both images are rendered and compared (PSNR of the EWA image against geer's). The EWA image comes from
gsplat's `rasterization` where a GPU is at hand, else from gsplat's PyTorch projection
(geer_ns.gsplat_private) composited per pixel here, front to back by depth as 3DGS's rasterizer does
(alpha capped at 0.999, skipped below 1/255, stop before T < 1e-4). docs/export.md says what the figure means.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List

import torch
from torch import Tensor

from geer_ns.render import RayGrid, render

MAX_PAIRS = 1 << 24  # pixels x Gaussians composited at once on the CPU


@dataclass
class PinholeView:
    viewmat: Tensor  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor  # [3, 3]
    width: int
    height: int

    def rays(self) -> RayGrid:
        """geer's ray grid through this view's pixel centers."""
        v, u = torch.meshgrid(torch.arange(self.height, dtype=torch.float64) + 0.5,
                              torch.arange(self.width, dtype=torch.float64) + 0.5, indexing="ij")
        k = self.K.double()
        dirs = torch.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], torch.ones_like(u)], -1)
        return RayGrid.from_rays(dirs, None, tile_size=16)


def pinhole_at(camera_to_world: Tensor, width: int, height: int, fov_x_deg: float = 90.0) -> PinholeView:
    """A pinhole view at a nerfstudio pose c2w [3, 4] (OpenGL axes): width x height pixels, horizontal FoV."""
    rot = camera_to_world[:3, :3].double() * camera_to_world.new_tensor([1.0, -1.0, -1.0]).double()
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = rot.T
    viewmat[:3, 3] = -rot.T @ camera_to_world[:3, 3].double()
    f = (width / 2) / math.tan(math.radians(fov_x_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    return PinholeView(viewmat, K, width, height)


def _colors(means: Tensor, sh: Tensor, viewmat: Tensor, degree: int) -> Tensor:
    """[N, 3] SH colors seen from the view's camera center (3DGS's: + 0.5, clamped at 0), by gsplat's SH."""
    from geer_ns.gsplat_private import spherical_harmonics

    center = -viewmat[:3, :3].T @ viewmat[:3, 3]
    return (spherical_harmonics(degree, means - center.to(means), sh) + 0.5).clamp_min(0.0)


def ewa_image_cpu(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, degree: int,
                  view: PinholeView) -> Tensor:
    """[H, W, 3] the EWA splatting image (black background) from gsplat's PyTorch projection."""
    from geer_ns.gsplat_private import fully_fused_projection, quat_scale_to_covar_preci

    covars, _ = quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = fully_fused_projection(
        means, covars, view.viewmat[None].to(means), view.K[None].to(means), view.width, view.height)
    keep = radii[0] > 0
    order = torch.argsort(depths[0][keep], stable=True)
    xy, conic = means2d[0][keep][order], conics[0][keep][order]
    opac, rgb = opacities[keep][order], _colors(means, sh, view.viewmat, degree)[keep][order]
    v, u = torch.meshgrid(torch.arange(view.height, dtype=means.dtype) + 0.5,
                          torch.arange(view.width, dtype=means.dtype) + 0.5, indexing="ij")
    pixels = torch.stack([u.reshape(-1), v.reshape(-1)], -1)
    out = means.new_zeros(pixels.shape[0], 3)
    chunk = max(1, MAX_PAIRS // max(1, xy.shape[0]))
    for start in range(0, pixels.shape[0], chunk):
        d = pixels[start:start + chunk, None, :] - xy[None]  # [P, N, 2]
        power = 0.5 * (conic[:, 0] * d[..., 0] ** 2 + conic[:, 2] * d[..., 1] ** 2) + conic[:, 1] * d[..., 0] * d[..., 1]
        alpha = (opac * torch.exp(-power)).clamp_max(0.999)
        alpha = torch.where((power >= 0) & (alpha >= 1.0 / 255.0), alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1.0 - alpha, dim=-1)
        t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], -1)
        weights = torch.where(t_after >= 1e-4, alpha * t_before, torch.zeros_like(alpha))
        out[start:start + chunk] = weights @ rgb
    return out.reshape(view.height, view.width, 3)


def ewa_image_gpu(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, degree: int,
                  view: PinholeView) -> Tensor:
    """[H, W, 3] the same image from gsplat's CUDA `rasterization` (means on a CUDA device)."""
    from gsplat.rendering import rasterization

    colors, _, _ = rasterization(means, quats, scales, opacities, sh, view.viewmat[None].to(means),
                                 view.K[None].to(means), view.width, view.height, sh_degree=degree)
    return colors[0]


def exact_image(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, degree: int,
                view: PinholeView, backend: str = "auto") -> Tensor:
    """[H, W, 3] geer's exact image of the same view (black background)."""
    out = render(means, quats, scales, opacities, sh, view.viewmat.to(means.device), view.rays().to(means.device),
                 sh_degree=degree, backend=backend)
    return out.rgb


@dataclass
class EwaReport:
    psnr_db: List[float]  # per view, EWA image against geer's
    mean_abs: List[float]  # per view, mean |difference| per channel
    method: str  # "gsplat rasterization (CUDA)" or "gsplat projection + per-pixel compositing (CPU)"

    @property
    def mean_psnr_db(self) -> float:
        return sum(self.psnr_db) / max(1, len(self.psnr_db))

    def line(self) -> str:
        return (f"EWA splatting vs geer's exact rendering on {len(self.psnr_db)} training pose(s): PSNR "
                f"{self.mean_psnr_db:.2f} dB (min {min(self.psnr_db):.2f}), mean |difference| "
                f"{sum(self.mean_abs) / max(1, len(self.mean_abs)):.4f} ({self.method})")


@torch.no_grad()
def compare(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor, degree: int,
            views: List[PinholeView]) -> EwaReport:
    """EwaReport of these Gaussians (activated: scales, opacities in [0, 1]; sh [N, K, 3]) over `views`."""
    on_gpu = means.is_cuda
    ewa = ewa_image_gpu if on_gpu else ewa_image_cpu
    psnr, mean_abs = [], []
    for view in views:
        ours = exact_image(means, quats, scales, opacities, sh, degree, view).clamp(0, 1)
        theirs = ewa(means, quats, scales, opacities, sh, degree, view).clamp(0, 1)
        mse = float(((ours - theirs) ** 2).mean())
        psnr.append(-10.0 * math.log10(max(mse, 1e-10)))
        mean_abs.append(float((ours - theirs).abs().mean()))
    method = "gsplat rasterization (CUDA)" if on_gpu else "gsplat projection + per-pixel compositing (CPU)"
    return EwaReport(psnr, mean_abs, method)
