"""geer_ns.compare's CPU EWA rasterizer against a brute-force float64 evaluation of the same conics, pixel by
pixel and Gaussian by Gaussian, written from gsplat 1.4.0's kernel conventions (3-sigma tile boxes, alpha clamp
0.999, 1/255 skip, stop before the transmittance reaches 1e-4), forward and gradients (also AbsGS's absgrad)."""

from __future__ import annotations

import math

import pytest
import torch

from geer_ns.compare.ewa_cpu import rasterization
from geer_ns.compare.ewa_tiles import rasterize_to_pixels

TILE = 16


def reference(means2d, conics, colors, opacities, radii, depths, width, height, background):
    """The kernel's sequential blend, Gaussian after Gaussian in depth order, every pixel at once, float64:
    a Gaussian counts for a pixel only if the pixel's tile lies in its 3-sigma tile box."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    px, py = u + 0.5, v + 0.5
    tile_x, tile_y = torch.div(u, TILE, rounding_mode="floor"), torch.div(v, TILE, rounding_mode="floor")
    T = torch.ones(height, width, dtype=torch.float64)
    done = torch.zeros(height, width, dtype=torch.bool)
    acc = torch.zeros(height, width, colors.shape[-1], dtype=torch.float64)
    for g in sorted(range(means2d.shape[0]), key=lambda k: float(depths[k])):
        r = float(radii[g])
        if r <= 0:
            continue
        mx, my = (float(v) / TILE for v in means2d[g].detach())
        in_box = (tile_x >= math.floor(mx - r / TILE)) & (tile_x < math.ceil(mx + r / TILE)) & \
            (tile_y >= math.floor(my - r / TILE)) & (tile_y < math.ceil(my + r / TILE))
        dx, dy = means2d[g, 0] - px, means2d[g, 1] - py
        a, b, c = conics[g]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(opacities[g] * torch.exp(-sigma), 0.999)
        skip = ~in_box | (sigma < 0) | (alpha < 1.0 / 255.0) | done
        next_T = T * (1 - alpha)
        stop = ~skip & (next_T <= 1e-4)
        done = done | stop
        use = ~skip & ~stop
        acc = acc + torch.where(use[..., None], colors[g] * (alpha * T)[..., None], torch.zeros_like(acc))
        T = torch.where(use, next_T, T)
    return acc + T[..., None] * background, (1 - T)[..., None]


def random_conics(n, width, height, seed):
    gen = torch.Generator().manual_seed(seed)
    means2d = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([width + 20.0, height + 20.0]) - 10
    # covariances with sides 1.5 .. 8 px, any orientation; the radius is gsplat's 3-sigma rule
    s = 1.5 + 6.5 * torch.rand(n, 2, generator=gen, dtype=torch.float64)
    th = torch.rand(n, generator=gen, dtype=torch.float64) * math.pi
    R = torch.stack([torch.cos(th), -torch.sin(th), torch.sin(th), torch.cos(th)], -1).reshape(n, 2, 2)
    cov = R @ torch.diag_embed(s ** 2) @ R.transpose(1, 2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    conics = torch.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], -1)
    b = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    radii = torch.ceil(3 * torch.sqrt(b + torch.sqrt((b ** 2 - det).clamp_min(0.01)))).int()
    radii[torch.rand(n, generator=gen) < 0.1] = 0  # some not drawn
    opacities = 0.05 + 0.94 * torch.rand(n, generator=gen, dtype=torch.float64)
    opacities[:4] = 0.999  # opaque ones: the early stop
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    depths = torch.rand(n, generator=gen, dtype=torch.float64) * 5 + 1
    return means2d, conics, colors, opacities, radii, depths


@pytest.mark.parametrize("max_pairs", [1 << 21, 700])  # one chunk; many small recomputed chunks
@pytest.mark.parametrize("block", [16, 4, 1])  # whole tiles; the blocks whose pairs are culled
def test_forward_and_gradients_match_brute_force(max_pairs, block):
    width, height = 37, 21  # not a multiple of the tile size
    means2d, conics, colors, opacities, radii, depths = random_conics(40, width, height, seed=3)
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    weights = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    leaves = [t.clone().requires_grad_(True) for t in (means2d, conics, colors, opacities)]
    ref_rgb, ref_alpha = reference(*leaves, radii, depths, width, height, background)
    ref_grads = torch.autograd.grad((ref_rgb * weights).sum() + ref_alpha.sum(), leaves)

    mine = [t.clone()[None].requires_grad_(True) for t in (means2d, conics, colors, opacities)]
    rgb, alpha = rasterize_to_pixels(*mine, radii[None], depths[None], width, height, TILE,
                                     background[None], max_pairs=max_pairs, recompute_above=max_pairs,
                                     block=block)
    assert rgb.shape == (1, height, width, 3) and alpha.shape == (1, height, width, 1)
    torch.testing.assert_close(rgb[0], ref_rgb, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(alpha[0], ref_alpha, rtol=1e-9, atol=1e-10)
    assert (ref_alpha > 0.99).any(), "the scene should reach the early stop somewhere"
    grads = torch.autograd.grad((rgb[0] * weights).sum() + alpha.sum(), mine)
    for name, g, r in zip(("means2d", "conics", "colors", "opacities"), grads, ref_grads):
        torch.testing.assert_close(g[0], r, rtol=1e-7, atol=1e-9, msg=f"gradient of {name}")


def test_absgrad_sums_per_pixel_absolute_gradients():
    width, height = 35, 20
    means2d, conics, colors, opacities, radii, depths = random_conics(16, width, height, seed=7)
    background = torch.zeros(3, dtype=torch.float64)
    weights = torch.randn(height, width, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def per_pixel_losses(m):
        rgb, _ = reference(m, conics, colors, opacities, radii, depths, width, height, background)
        return (rgb * weights).sum(-1).reshape(-1)

    jacobian = torch.autograd.functional.jacobian(per_pixel_losses, means2d, vectorize=True)  # [H*W, N, 2]
    expected = jacobian.abs().sum(0)
    assert float(expected.sum()) > 0
    mine = means2d.clone()[None].requires_grad_(True)
    rgb, _ = rasterize_to_pixels(mine, conics[None], colors[None], opacities[None], radii[None], depths[None],
                                 width, height, TILE, background[None], absgrad=True)
    (rgb[0] * weights).sum().backward()
    torch.testing.assert_close(mine.absgrad[0], expected, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("camera_model", ["pinhole", "fisheye"])
def test_rasterization_gives_splatfacto_what_it_reads(camera_model):
    """splatfacto's call (nerfstudio 1.1.5): unpacked, RGB+ED, SH colours, absgrad; DefaultStrategy's fields."""
    from gsplat.strategy import DefaultStrategy

    gen = torch.Generator().manual_seed(0)
    n = 200
    means = (torch.randn(n, 3, generator=gen) * torch.tensor([1.5, 1.5, 0.5]) + torch.tensor([0, 0, 4.0]))
    params = torch.nn.ParameterDict({
        "means": means, "quats": torch.randn(n, 4, generator=gen), "scales": torch.rand(n, 3, generator=gen).log() - 3,
        "opacities": torch.zeros(n), "colors": torch.randn(n, 16, 3, generator=gen) * 0.3})
    viewmats = torch.eye(4)[None]
    Ks = torch.tensor([[[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]]])
    rgb, alpha, info = rasterization(params["means"], params["quats"], params["scales"].exp(),
                                     params["opacities"].sigmoid(), params["colors"], viewmats, Ks, 64, 48,
                                     packed=False, render_mode="RGB+ED", sh_degree=3, absgrad=True,
                                     camera_model=camera_model)
    assert rgb.shape == (1, 48, 64, 4) and alpha.shape == (1, 48, 64, 1)
    assert torch.isfinite(rgb).all() and float(alpha.detach().max()) > 0.5
    assert info["radii"].shape == (1, n) and info["gaussian_ids"] is None
    assert (info["width"], info["height"], info["n_cameras"]) == (64, 48, 1)
    strategy = DefaultStrategy(absgrad=True, refine_start_iter=100, verbose=False)  # statistics only
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    state = strategy.initialize_state(scene_scale=1.0)
    strategy.step_pre_backward(params, optimizers, state, 0, info)
    rgb[..., :3].mean().backward()
    grads = info["means2d"].absgrad
    assert torch.isfinite(grads).all() and float(grads.abs().sum()) > 0
    assert torch.isfinite(params["means"].grad).all() and float(params["means"].grad.abs().sum()) > 0
    strategy.step_post_backward(params, optimizers, state, 1, info, packed=False)
    assert int(state["count"].sum()) > 0
