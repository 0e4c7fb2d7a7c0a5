"""Gaussian-parallel training keeps per-camera memory O(what the camera sees): sharded_outputs builds each
camera's densification probe and record over the rows of the shard it sees only, and the step's statistics and
gradients equal one process's dense ones bit for bit. One process, a world of 1 (two: tests/test_distributed.py)."""

from __future__ import annotations

import math

import torch

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import SceneBox

from geer_ns.data.datamanager import VIEW_KEY
from geer_ns.densify.signal import StepStatistics
from geer_ns.distributed.gaussian_parallel import sharded_outputs
from geer_ns.model import GeerModelConfig

N, IN_VIEW = 400, 24  # Gaussians, of which these lie inside the camera's field of view; the others behind it


def scene() -> tuple[torch.Tensor, torch.Tensor]:
    """IN_VIEW points in a 10-degree cone in front of an identity nerfstudio camera (which looks along world -z),
    the others behind it (z > 0: no pinhole camera sees them); the in-view ones spread over the rows."""
    gen = torch.Generator().manual_seed(0)
    xyz = torch.empty(N, 3)
    xyz[:, :2] = (torch.rand(N, 2, generator=gen) - 0.5) * 3.0
    xyz[:, 2] = 1.5 + torch.rand(N, generator=gen)
    front = torch.arange(IN_VIEW) * (N // IN_VIEW)
    depth = 2.0 + torch.rand(IN_VIEW, generator=gen)
    xyz[front, :2] = (torch.rand(IN_VIEW, 2, generator=gen) - 0.5) * 2 * depth[:, None] * math.tan(math.radians(8))
    xyz[front, 2] = -depth
    return xyz, (torch.rand(N, 3, generator=gen) * 255).to(torch.uint8)


def model():
    config = GeerModelConfig(background_color="black", sh_degree=0, num_downscales=0)
    box = SceneBox(aabb=torch.tensor([[-2.0, -2.0, -3.0], [2.0, 2.0, 3.0]]))
    built = config.setup(scene_box=box, num_train_data=4, metadata={}, device="cpu", seed_points=scene())
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():  # unequal scales: no ties in the largest scale, whose gradient would go either way
        built.gauss_params["scales"].copy_(math.log(0.03) + 0.3 * torch.randn(N, 3, generator=gen))
        built.gauss_params["opacities"].copy_(torch.randn(N, 1, generator=gen))
        built.gauss_params["quats"].copy_(torch.randn(N, 4, generator=gen))  # the model draws them unseeded
    built.train()
    return built


def pinhole(size: int = 32, fov_degrees: float = 20.0) -> Cameras:
    f = (size / 2) / math.tan(math.radians(fov_degrees / 2))
    camera = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=f, fy=f, cx=size / 2, cy=size / 2, width=size,
                     height=size, camera_type=CameraType.PERSPECTIVE)
    camera.metadata = {VIEW_KEY: "native"}
    return camera


def loss_of(outputs) -> torch.Tensor:
    weights = torch.randn(outputs["rgb"].shape, generator=torch.Generator().manual_seed(3))
    return (outputs["rgb"] * weights).sum() + outputs["accumulation"].sum()


def test_a_cameras_probe_and_record_hold_the_rows_it_sees_only():
    sharded = model()
    sharded_outputs(sharded, [pinhole()], 0)
    record = sharded.views[-1]
    leaves = [record.offsets, record.absgrad, record.scale, record.radius, record.weight, record.pixels,
              record.visible]
    shapes = [None if t is None else tuple(t.shape) for t in leaves]
    assert all(t is not None and 0 < t.shape[0] <= IN_VIEW for t in leaves), shapes  # not N rows
    front = set((torch.arange(IN_VIEW) * (N // IN_VIEW)).tolist())
    assert record.rows is not None and record.rows.numel() == record.offsets.shape[0]
    assert set(record.rows.tolist()) <= front  # nothing behind the camera


def test_sparse_statistics_and_gradients_equal_one_processs_dense_ones():
    """The same camera and loss through sharded_outputs (sparse probe, record scattered into the step's sums)
    and through GeerModel.get_outputs (one process: a dense probe over every Gaussian): equal bits."""
    results = []
    for render in (lambda m, c: sharded_outputs(m, [c], 0), lambda m, c: m.get_outputs(c)):
        trained = model()
        camera = pinhole()
        loss_of(render(trained, camera)).backward()
        stats = trained.step_statistics()
        results.append((stats, {name: p.grad for name, p in trained.gauss_params.items() if p.grad is not None}))
    (sparse, sparse_grads), (dense, dense_grads) = results
    assert int(dense.views.sum()) > 0 and float(dense.grad.max()) > 0
    for name in ("grad", "views", "radius", "weight", "pixels"):
        assert torch.equal(getattr(sparse, name), getattr(dense, name)), name
    assert set(sparse_grads) == set(dense_grads) and "means" in dense_grads
    for name, grad in dense_grads.items():
        assert torch.equal(sparse_grads[name], grad), name


def test_step_statistics_scatter_each_record_to_its_rows():
    """of_views against sums made by hand: two records over overlapping rows, one of them dense."""
    from geer_ns.densify.signal import ViewRecord

    def record(rows, radius):
        k = len(radius)
        offsets = torch.zeros(k, 2, requires_grad=True)
        offsets.grad = torch.tensor([[3.0, 4.0]] * k)  # norm 5
        return ViewRecord(offsets, None, torch.ones(k, dtype=torch.bool), torch.ones(k, 1), torch.tensor(radius),
                          torch.tensor(radius) / 10, torch.tensor(radius) * 2,
                          None if rows is None else torch.tensor(rows))

    stats = StepStatistics.of_views([record([1, 3], [0.5, 0.25]), record(None, [0.1, 0.2, 0.3, 0.4])], 4, "cpu")
    assert stats.grad.tolist() == [5.0, 10.0, 5.0, 10.0]
    assert stats.views.tolist() == [1.0, 2.0, 1.0, 2.0]
    assert torch.equal(stats.radius, torch.tensor([0.1, 0.5, 0.3, 0.4]))
    assert torch.equal(stats.pixels, torch.tensor([0.1, 0.5, 0.3, 0.4]) * 2)
