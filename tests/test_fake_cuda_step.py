"""A training step on a fake `cuda:0`, on a machine without a GPU: every model tensor a FakeTensor on CUDA
(torch._subclasses.fake_tensor: shapes, dtypes and devices, no data), the CUDA kernels as torch operators with
fake implementations (geer_ns/render/ops.py). A CPU tensor meeting a CUDA one raises, as on a GPU, so a
tensor left on (or created on) the host fails here instead of on a user's GPU. docs/gpu_correctness.md says
what this covers and what it cannot.

Carried: the batch, BEAP and native (pixel) supervision, the render (preprocess, association with its
data-dependent pair count as a symbolic size, render), metrics and losses, the backward through every node of
the graph, the optimiser step and the checkpoint state. Not carried (data, not shapes): the camera model and
ray grids (made on the host, then uploaded once: test_ray_grids_are_cached_per_device), the input value checks
(one host read), densification (masks of the data); and torch's autograd engine itself, which asks the CUDA
driver for its streams: the backward here calls the same graph nodes in the same order (_backward).
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch._subclasses.fake_tensor import FakeTensorMode
from torch.fx.experimental.symbolic_shapes import ShapeEnv

from conftest import copy_room, tiny_trainer_config

PLANTS = ("none", "opacities on the CPU", "ray grid on the CPU")


def _backward(root: torch.Tensor) -> None:
    """root's backward, node by node (reverse topological order), without torch's engine: each node gets the
    sum of its gradients, AccumulateGrad nodes fill the leaves' .grad."""
    order, seen, stack = [], set(), [(root.grad_fn, False)]
    while stack:
        node, finished = stack.pop()
        if finished:
            order.append(node)
            continue
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.append((node, True))
        stack.extend((nxt, False) for nxt, _ in node.next_functions if nxt is not None and nxt not in seen)
    grads = {root.grad_fn: [torch.ones_like(root)]}
    for node in reversed(order):
        inputs = grads.pop(node, None)
        if inputs is None:
            continue
        inputs += [None] * (len(node._input_metadata) - len(inputs))
        if hasattr(node, "needs_input_grad"):  # a Python Function's backward: one result per forward argument
            out = node.apply(*inputs)
            out = out if isinstance(out, tuple) else (out,)
            edges = zip([e for e in node.next_functions if e[0] is not None],
                        [g for g, needed in zip(out, node.needs_input_grad) if needed])
        else:
            out = node(*inputs)
            edges = zip(node.next_functions, out if isinstance(out, tuple) else (out,))
        for (nxt, slot), grad in edges:
            if nxt is None or grad is None:
                continue
            slots = grads.setdefault(nxt, [])
            slots += [None] * (slot + 1 - len(slots))
            slots[slot] = grad if slots[slot] is None else slots[slot] + grad


@pytest.fixture(scope="module")
def trainer(tmp_path_factory, single_thread):
    """A tiny geer trainer on the CPU (BEAP-supervised training images, SH colours), set up as ns-train does."""
    out = tmp_path_factory.mktemp("fake_cuda")
    config = tiny_trainer_config(copy_room(out / "data", 3), out, "fake", 10)
    config.pipeline.datamanager.supervision = "beap"
    config.pipeline.model.renderer_backend = "cuda"  # the kernels (their fake implementations here)
    config.pipeline.model.num_downscales = 0  # full resolution (a downscaled native view reads its camera back)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def _batches(trainer):
    """(camera, batch) of a BEAP-supervised and of a native-supervised training view (the CPU datamanager's)."""
    from geer_ns.data.datamanager import VIEW_KEY

    dm = trainer.pipeline.datamanager
    beap = dm.train_view(0)
    camera, _ = dm.train_view(1)
    camera.metadata[VIEW_KEY] = "native"
    native = (camera, {k: v for k, v in dm.train_dataset[1].items() if k in ("image", "mask")})
    return [beap, native]


@pytest.mark.parametrize("plant", PLANTS)
def test_a_training_step_on_fake_cuda(trainer, plant, monkeypatch):
    from nerfstudio.engine.optimizers import Optimizers

    from geer_ns.render import backend
    from geer_ns.render.raygrid import RayGrid

    model = copy.deepcopy(trainer.pipeline.model)  # each case moves its own copy
    batches = _batches(trainer)
    for camera, _ in batches:
        model.view_for(camera)  # the host's part: camera model and ray grids (cached per camera)
    monkeypatch.setattr(backend, "cuda_extension_available", lambda: True)  # fake kernels need no build
    if plant == "ray grid on the CPU":
        monkeypatch.setattr(RayGrid, "to", lambda grid, device: grid)
    mode = FakeTensorMode(allow_non_fake_inputs=True, shape_env=ShapeEnv())
    with mode:
        model._apply(lambda t: t.to("cuda"))
        if plant == "opacities on the CPU":
            model.gauss_params["opacities"] = torch.nn.Parameter(model.gauss_params["opacities"].to("cpu"))
        model.train()
        optimizers = Optimizers(trainer.config.optimizers, model.get_param_groups())
        step = lambda: _step(model, optimizers, batches)  # noqa: E731
        if plant != "none":
            with pytest.raises((RuntimeError, ValueError), match="cpu"):
                step()
            return
        state = step()
    assert model.means.device.type == "cuda" and all(p.grad.device.type == "cuda" for p in model.gauss_params.values())
    assert all(t.device.type == "cuda" for t in state["pipeline"].values() if torch.is_tensor(t) and t.ndim > 0)
    assert all(v.device.type == "cuda" for s in state["optimizers"].values() for slot in s["state"].values()
               for v in slot.values() if torch.is_tensor(v) and v.ndim > 0)


def _step(model, optimizers, batches) -> dict:
    """One step over both views (nerfstudio's order: outputs, metrics, losses; backward; step); its
    checkpoint state."""
    optimizers.zero_grad_all()
    total = 0
    for camera, batch in batches:
        camera = camera.to("cuda")
        batch = {k: v.to("cuda") if torch.is_tensor(v) else v for k, v in batch.items()}
        outputs = model.get_outputs(camera)
        for key in ("rgb", "depth", "accumulation", "valid_rays"):
            assert outputs[key].device.type == "cuda", key
        metrics = model.get_metrics_dict(outputs, batch)
        total = total + sum(model.get_loss_dict(outputs, batch, metrics).values())
    _backward(total)
    optimizers.optimizer_step_all()
    return {"pipeline": model.state_dict(), "optimizers": {k: o.state_dict() for k, o in optimizers.optimizers.items()}}
