"""The kernels as torch operators (geer_ns/render/ops.py) against the extension's functions themselves (the CPU
build), and ray grids cached per device (render/raygrid.py RayGrid.to).

The references are the CPU build's own outputs and gradients, called directly (the code path every
test_csrc_math test checks against the PyTorch renderer); the operators must reproduce them bit for bit, and
their fake implementations must give exactly the real outputs' shapes, dtypes and devices.
"""

from __future__ import annotations

import pytest
import torch
from torch._subclasses.fake_tensor import FakeTensorMode
from torch.fx.experimental.symbolic_shapes import ShapeEnv

from conftest import random_scene, reference_grids

GRIDS = ("beap", "fisheye180")


def _render(ops, scene, grid, sh: bool, absgrad: bool = False):
    from geer_ns.render import cuda_backend

    leaves = [t.clone().requires_grad_(True) for t in scene]
    if sh:
        gen = torch.Generator().manual_seed(3)
        leaves[4] = torch.randn(scene[0].shape[0], 4, 3, generator=gen, dtype=scene[0].dtype).requires_grad_(True)
    extra = {}
    if absgrad:
        sink = torch.zeros(scene[0].shape[0], 2, dtype=scene[0].dtype, requires_grad=True)
        extra["absgrad"] = (torch.eye(3, dtype=scene[0].dtype)[:, :2].expand(scene[0].shape[0], 3, 2), sink)
        leaves.append(sink)
    out = cuda_backend.render_cuda(*leaves[:5], torch.eye(4, dtype=scene[0].dtype), grid, ops=ops, **extra)
    (out.rgb.square().sum() + out.depth.sum() + out.accumulation.sum()).backward()
    return out, [t.grad for t in leaves]


@pytest.mark.parametrize("sh", [False, True])
@pytest.mark.parametrize("name", GRIDS)
def test_the_operators_equal_the_extension(cpu_ops, name, sh):
    """render_cuda through torch.ops.geer (ops=None) and through the CPU build's functions: the same images and
    gradients, bit for bit, absgrad included."""
    scene = random_scene(150, 7, around=True)
    grid = reference_grids(torch.float64)[name]
    (ours, g_ours), (ref, g_ref) = (_render(ops, scene, grid, sh, absgrad=True) for ops in (None, cpu_ops))
    assert float(ref.accumulation.max()) > 0.5
    for a, b in ((ours.rgb, ref.rgb), (ours.depth, ref.depth), (ours.accumulation, ref.accumulation),
                 (ours.max_weight, ref.max_weight)):
        assert torch.equal(a, b)
    for i, (a, b) in enumerate(zip(g_ours, g_ref)):
        assert torch.equal(a, b), i


def test_the_registered_backward_equals_the_autograd_wrappers(cpu_ops):
    """torch.ops.geer.preprocess_forward / render_forward differentiated on their own (register_autograd)
    give the gradients of cuda_backend's autograd wrappers."""
    from geer_ns.render import cuda_backend
    from geer_ns.render.associate import pbf_cull_pieces

    scene = random_scene(120, 9)
    grid = reference_grids(torch.float64)["beap"]
    means, quats, scales, opacities, colors = (t.clone().requires_grad_(True) for t in scene)
    n = means.shape[0]
    rot = torch.eye(3, dtype=torch.float64)
    sh, sh_dirs = means.new_zeros(n, 0, 3), means.new_zeros(n, 3)

    def render(preprocess, rasterize):
        whiten, o_u, _, bounds, alive, _ = preprocess(means, quats, scales, opacities.detach(), sh, sh_dirs, rot, -1,
                                                      False)
        ids, ranges, _, _ = torch.ops.geer.associate(bounds, alive, cuda_backend.depth_order_key(means.norm(dim=-1)),
                                                     grid.tile_pyramid().bounds, grid.tile_pyramid().active,
                                                     grid.tiles_x, grid.tiles_y, bounds.new_zeros(0), bounds.new_zeros(0))
        geometry = (pbf_cull_pieces(bounds), grid.dirs, grid.ray_cull_bounds(), grid.warp_cull_bounds(), grid.valid,
                    ids, ranges, grid.height, grid.width, grid.tile_size)
        rgb, depth, acc = rasterize(whiten, o_u, colors, opacities, geometry)[:3]
        grads = torch.autograd.grad(rgb.square().sum() + depth.sum() + acc.sum(), (means, quats, scales, opacities,
                                                                                    colors))
        return rgb.detach(), grads

    registered = render(torch.ops.geer.preprocess_forward,
                        lambda w, o, c, a, g: torch.ops.geer.render_forward(w, o, c, a, *g, True))
    wrapped = render(lambda m, q, s, o, sh, d, r, deg, paper: cuda_backend._Preprocess.apply(m, q, s, sh, d, o, r, deg,
                                                                                           paper, cpu_ops),
                     lambda w, o, c, a, g: cuda_backend._Rasterize.apply(w, o, c, a, *g, cpu_ops, None, None))
    assert float(registered[0].max()) > 0.1 and torch.equal(registered[0], wrapped[0])
    for a, b in zip(registered[1], wrapped[1]):
        assert torch.equal(a, b)


def test_the_fake_implementations_give_the_real_shapes(cpu_ops):
    """Every operator on fake copies of its real inputs: outputs of the real outputs' shapes (the pair count a
    symbolic size), dtypes and devices."""
    from geer_ns.render import cuda_backend
    from geer_ns.render.associate import pbf_cull_pieces

    scene = random_scene(80, 4, dtype=torch.float32)
    grid = reference_grids(torch.float32)["fisheye180"]
    means, quats, scales, opacities, colors = scene
    n = means.shape[0]
    pyr = grid.tile_pyramid()
    calls = []
    pre = (means, quats, scales, opacities, means.new_zeros(n, 0, 3), means.new_zeros(n, 3), torch.eye(3), -1, False)
    calls.append(("preprocess_forward", pre))
    whiten, o_u, rgb, bounds, alive, _ = torch.ops.geer.preprocess_forward(*pre)
    assoc = (bounds, alive, cuda_backend.depth_order_key(means.norm(dim=-1)), pyr.bounds, pyr.active, grid.tiles_x,
             grid.tiles_y, bounds.new_zeros(0), bounds.new_zeros(0))  # no cones: the box test alone
    calls.append(("associate", assoc))
    ids, ranges, _, _ = torch.ops.geer.associate(*assoc)
    geometry = (pbf_cull_pieces(bounds), grid.dirs, grid.ray_cull_bounds(), grid.warp_cull_bounds(), grid.valid, ids,
                ranges, grid.height, grid.width, grid.tile_size)
    fwd = (whiten, o_u, colors, opacities, *geometry, True)
    calls.append(("render_forward", fwd))
    _, _, _, t_final, n_contrib, lanes, _, _ = torch.ops.geer.render_forward(*fwd)
    r = grid.num_rays
    g_out = (torch.ones(r, 3), torch.ones(r), torch.ones(r))
    calls.append(("render_backward", (whiten, o_u, colors, opacities, *geometry, t_final, n_contrib, lanes, *g_out,
                                      whiten.new_zeros(n, 6), False)))
    calls.append(("preprocess_backward", (means, quats, scales, pre[4], pre[5], pre[6], -1, torch.ones(n, 3, 3),
                                          torch.ones(n, 3), torch.ones(n, 3), False)))
    for name, args in calls:
        real = getattr(torch.ops.geer, name)(*args)
        with FakeTensorMode(shape_env=ShapeEnv()) as mode:
            fake_args = [mode.from_tensor(a, static_shapes=True) if torch.is_tensor(a) else a for a in args]
            fake = getattr(torch.ops.geer, name)(*fake_args)
        assert len(fake) == len(real), name
        for i, (f, t) in enumerate(zip(fake, real)):
            assert (f.dtype, f.device, f.ndim) == (t.dtype, t.device, t.ndim), (name, i)
            for fs, ts in zip(f.shape, t.shape):  # an int where the size is a shape fact, else the pair count
                assert fs == ts if isinstance(fs, int) else (name, i) == ("associate", 0), (name, i, f.shape, t.shape)


def test_an_operator_refuses_a_tensor_on_another_device():
    from geer_ns.render import ops

    means = torch.zeros(2, 3)
    with FakeTensorMode(allow_non_fake_inputs=True):
        with pytest.raises(RuntimeError, match="expected all tensors on cuda:0, got one on cpu"):
            ops.preprocess_forward(means.to("cuda"), torch.zeros(2, 4), torch.ones(2, 3).to("cuda"),
                                   torch.ones(2).to("cuda"), means.new_zeros(2, 0, 3).to("cuda"),
                                   means.to("cuda"), torch.eye(3).to("cuda"), -1, False)


def test_ray_grids_are_cached_per_device():
    """A grid moved to a device is made once and kept with the facts computed so far (ray count, pyramid, cull
    bounds): a render's grid.to(device) uploads nothing after its first call. Fake CUDA tensors stand in for a
    GPU."""
    grid = reference_grids(torch.float32)["fisheye180"]
    pyramid, cull = grid.tile_pyramid(), grid.ray_cull_bounds()
    count = int(grid.valid.sum())
    with FakeTensorMode(allow_non_fake_inputs=True):
        on_gpu = grid.to("cuda:0")
        assert grid.to("cuda:0") is on_gpu and grid.to(torch.device("cuda", 0)) is on_gpu
        assert on_gpu.dirs.device.type == "cuda" and on_gpu.valid.device.type == "cuda"
        assert on_gpu.num_valid == count  # carried over: no read of the device's mask
        assert on_gpu.tile_pyramid() is not pyramid and on_gpu.tile_pyramid().bounds.device.type == "cuda"
        assert on_gpu.tile_pyramid() is on_gpu.tile_pyramid()  # moved once, kept
        assert on_gpu.ray_cull_bounds().shape == cull.shape and on_gpu.ray_cull_bounds().device.type == "cuda"
    assert grid.to("cpu") is grid
