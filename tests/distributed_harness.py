"""What the multi-process tests run inside nerfstudio's launcher (nerfstudio.scripts.train.launch, the code
`ns-train --machine.num-devices N` runs, with geer's launch fix): each process is a spawned interpreter that
imports this module. `main` (the launcher's main_func) runs the plans in one launch (interpreters are slow to
start) and leaves their results (checkpoints, JSON) under the config's output_dir for the tests to read.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path

import torch

from conftest import tiny_trainer_config

# In images: the schedule of a refinement-and-reset run at an effective batch of 2 (both processes x 1 image,
# or 1 process x 2 images): refine every 4 images (2 steps) after 4, opacity reset every 5 refinements. With
# 5 training images refinements pause for ceil(5 / 2) + 2 = 5 steps after a reset: refinements at steps 6 and
# 8, a reset at step 10, inside 12 steps.
STEPS = 12


def scenario_config(data: Path, out: Path, name: str, *, strategy: str = "default", images_per_step: int = 1,
                    steps: int = STEPS):
    config = tiny_trainer_config(data, out, name, steps * 2)  # images: 2 per step
    config.steps_per_save = 1_000_000  # the final checkpoint only
    config.machine.device_type = "cpu"
    config.machine.timeout_s = 60.0
    # The scenarios compare runs of different lengths and resumes with fresh runs step for step: the schedules as
    # written (a run's follow-run schedules depend on its length: training/horizon.py, test_schedule_horizon.py).
    config.schedules = "fixed"
    model = config.pipeline.model
    model.strategy = strategy
    model.warmup_length, model.refine_every, model.reset_alpha_every, model.stop_split_at = 4, 4, 5, 1000
    model.densify_grad_thresh = 1e-7  # every seen Gaussian grows: refinements visibly change the count
    model.mcmc_cap_max = 6000
    config.pipeline.datamanager.images_per_step = images_per_step
    return config


def train(local_rank: int, world_size: int, config, global_rank: int = 0, callbacks=()):
    """nerfstudio's train_loop (seed, set-up, train) with extra per-step callbacks."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()
    _set_random_seed(config.machine.seed + global_rank)
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    for fn in callbacks:
        trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                                  lambda step, fn=fn: fn(trainer, step)))
    trainer.train()
    writer.EVENT_WRITERS.clear()
    return trainer


def main(local_rank: int, world_size: int, config, global_rank: int = 0):
    """The replica plans, the sharded renders and training, the collectives under NCCL's rule, then the fault
    plan (which ends the launch: with exit status 1 when all is well)."""
    replicas_plan(local_rank, world_size, config, global_rank)
    resume_plan(local_rank, world_size, config, global_rank)
    budget_plan(global_rank, Path(config.output_dir))
    sharded_render_plan(global_rank, Path(config.output_dir))
    sharded_training_plan(local_rank, world_size, config, global_rank)
    nccl_rule_plan(global_rank, Path(config.output_dir))
    fault_plan(local_rank, world_size, config, global_rank)


def _write(path: Path, value) -> None:
    path.write_text(json.dumps(value))


def replicas_plan(local_rank, world_size, config, global_rank):
    from geer_ns.distributed import image_parallel as engine
    from geer_ns.distributed.consistency import ReplicaMismatchError, check_replicas_identical
    from geer_ns.distributed.world import current_world

    data, out = Path(config.pipeline.datamanager.data), Path(config.output_dir)
    world = current_world()
    results = {}

    # 1. A process with another configuration: every rank stops at start-up, naming the field.
    odd = scenario_config(data, out, "mismatch")
    if global_rank == 1:
        odd.pipeline.model.refine_every = 6
    try:
        train(local_rank, world_size, odd, global_rank)
        results["mismatch"] = "trained"
    except SystemExit as stop:
        results["mismatch"] = f"exit {stop.code}"

    # 2. The check can fail: without the gradient all-reduce the replicas drift apart at once.
    local_only = engine.reduce_gradients
    engine.reduce_gradients = lambda w, params, images: local_only(type(w)(), params, images)
    try:
        train(local_rank, world_size, scenario_config(data, out, "unsynced", steps=2), global_rank,
              callbacks=[lambda trainer, step: check_replicas_identical(world, trainer.pipeline.model, step)])
        results["unsynced"] = "identical"
    except SystemExit:
        results["unsynced"] = "diverged"
    except ReplicaMismatchError:
        results["unsynced"] = "diverged (raised)"
    finally:
        engine.reduce_gradients = local_only

    # 3. Both strategies, a refinement and an opacity reset inside: checksums and counts after every step.
    for strategy in ("default", "mcmc"):
        name = f"equal_{strategy}"
        per_step = []
        train(local_rank, world_size, scenario_config(data, out, name, strategy=strategy), global_rank,
              callbacks=[lambda trainer, step: per_step.append(
                  (step, trainer.pipeline.model.num_points,
                   check_replicas_identical(world, trainer.pipeline.model, step)))])
        results[name] = per_step
    if global_rank == 0:
        _write(out / "replicas.json", results)


# ------------------------------------------------------------------------------------ resume, schedule
def set_up(local_rank: int, world_size: int, config):
    """A trainer set up (its checkpoint loaded, if any), not trained."""
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()
    trainer = config.setup(local_rank=local_rank, world_size=world_size)
    trainer.setup()
    return trainer


def optimizer_record(trainer) -> dict:
    """What the optimisers will step with next: every group's hyper-parameters and Adam's step counts, every
    scheduler's base learning rates, position and learning rate; and the step the run starts at."""
    record = {"start": trainer._start_step, "groups": {}, "adam_steps": {}, "schedulers": {}}
    for name, opt in trainer.optimizers.optimizers.items():
        record["groups"][name] = [{k: (list(g[k]) if k == "betas" else g[k]) for k in ("lr", "betas", "eps")}
                                  for g in opt.param_groups]
        record["adam_steps"][name] = sorted({float(slot["step"]) for slot in opt.state.values() if "step" in slot})
    for name, scheduler in trainer.optimizers.schedulers.items():
        record["schedulers"][name] = {"base_lrs": list(scheduler.base_lrs), "last_epoch": scheduler.last_epoch,
                                      "lr": list(scheduler.get_last_lr())}
    return record


def fresh_record(trainer, start: int) -> dict:
    """optimizer_record of a fresh trainer brought to step `start` as training would (one scheduler step per
    step; Adam's step counts are then `start`)."""
    for _ in range(start):
        for scheduler in trainer.optimizers.schedulers.values():
            scheduler.step()
    record = optimizer_record(trainer)
    record["start"] = start
    record["adam_steps"] = {name: [float(start)] for name in record["adam_steps"]}
    return record


def resume_plan(local_rank, world_size, config, global_rank):
    """A one-process checkpoint (kappa = 1, the test's, made before the launch) resumed on 2 processes
    (kappa = 2), image- and Gaussian-parallel; and a fresh 2-process run at the resumed step."""
    data, out = Path(config.pipeline.datamanager.data), Path(config.output_dir)
    results = {}
    for engine in ("images", "gaussians"):
        cfg = scenario_config(data, out, f"resumed_{engine}")
        cfg.pipeline.model.distributed = engine
        cfg.load_dir = Path((out / "kappa1_checkpoints.txt").read_text())
        results[engine] = optimizer_record(set_up(local_rank, world_size, cfg))
    fresh = set_up(local_rank, world_size, scenario_config(data, out, "fresh"))
    results["fresh"] = fresh_record(fresh, results["images"]["start"])
    if global_rank == 0:
        _write(out / "resume.json", results)


def budget_plan(rank: int, out: Path) -> None:
    """The densification budget over 2 shards: the scene of budget_case, rank r holding rows r::2 except that
    rank 0 also holds the second half of the candidates (unequal candidates); one refinement's growth with the
    sharded engine's scene-wide budget. The ids grown go to budget_<rank>.pt."""
    from geer_ns.distributed.gaussian_parallel import scene_budget

    params, optimizers, state, strategy = budget_case()
    n = params["means"].shape[0]
    mine = torch.tensor([budget_owner(i, n) == rank for i in range(n)])
    keep = {k: torch.nn.Parameter(v[mine].clone()) for k, v in params.items()}
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in keep.items()}
    shard_state = {k: (v[mine].clone() if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in state.items()}
    strategy.budget = scene_budget
    strategy.grow(keep, optimizers, shard_state, step=100)
    torch.save({"ids": shard_state["id"], "n": keep["means"].shape[0], "candidates": int(mine[BUDGET_WANTED].sum())},
               out / f"budget_{rank}.pt")


BUDGET_GAUSSIANS, BUDGET = 60, 75
BUDGET_WANTED = slice(0, 40)  # the rows with a gradient above the threshold


def budget_owner(row: int, n: int) -> int:
    """Rank 0 holds rows 0::2 and every candidate row from 20 on: 30 of the 40 candidates."""
    return 0 if (row % 2 == 0 or 20 <= row < 40) else 1


def budget_case():
    """A model of BUDGET_GAUSSIANS Gaussians, 40 of them candidates for growth (gradients above the threshold,
    several equal: ties), a budget of BUDGET (room for 15 of them); (params, optimizers, state, strategy)."""
    from geer_ns.densify.strategy import GeerDefaultStrategy

    n = BUDGET_GAUSSIANS
    gen = torch.Generator().manual_seed(3)
    params = {"means": torch.randn(n, 3, generator=gen), "scales": torch.full((n, 3), -3.0),
              "quats": torch.randn(n, 4, generator=gen), "opacities": torch.zeros(n, 1),
              "features_dc": torch.rand(n, 3, generator=gen), "features_rest": torch.zeros(n, 15, 3)}
    params["scales"][::3] = 0.0  # large: these split, the others duplicate
    grad = torch.zeros(n)
    grad[BUDGET_WANTED] = torch.randint(1, 9, (40,), generator=gen).float() * 1e-3  # ties on purpose
    state = {"grad2d": grad, "count": torch.ones(n), "radii": torch.zeros(n), "weight": torch.ones(n),
             "pixels": torch.ones(n), "id": torch.arange(n) * 7 + 11, "scene_scale": 1.0}
    strategy = GeerDefaultStrategy(max_gaussians=BUDGET, grow_grad2d=5e-4, grow_scale3d=0.01,
                                   refine_scale2d_stop_iter=0, verbose=False)
    params = {k: torch.nn.Parameter(v) for k, v in params.items()}
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    return params, optimizers, state, strategy


def fault_plan(local_rank, world_size, config, global_rank, distributed: str = "images"):
    """Rank 1 is killed (SIGKILL, no goodbye) after its 5th step; rank 0 must notice and stop: in step 5's
    gradient all-reduce (image-parallel) or its first all-to-all (Gaussian-parallel)."""
    def kill_at(trainer, step):
        if global_rank == 1 and step == 4:
            (out / "killed_at").write_text(repr(time.time()))
            os.kill(os.getpid(), signal.SIGKILL)

    data, out = Path(config.pipeline.datamanager.data), Path(config.output_dir)
    cfg = scenario_config(data, out, "killed", steps=40)
    cfg.pipeline.model.distributed = distributed
    train(local_rank, world_size, cfg, global_rank, callbacks=[kill_at])


def sharded_fault_main(local_rank: int, world_size: int, config, global_rank: int = 0):
    """A launch of its own (a fault ends a launch): the fault plan, Gaussian-parallel."""
    fault_plan(local_rank, world_size, config, global_rank, distributed="gaussians")


PAUSE_S = 2.0  # how much longer than --machine.timeout-s rank 0 stays paused


def pause_main(local_rank: int, world_size: int, config, global_rank: int = 0):
    """A launch of its own: rank 0 is paused (as by the viewer's "Pause training") after its step 2 for longer
    than the timeout, then resumed; each rank that finishes training writes finished_<rank>."""
    import threading

    def pause_at(trainer, step):
        if global_rank == 0 and step == 2:
            trainer.training_state = "paused"
            resume = lambda: setattr(trainer, "training_state", "training")  # noqa: E731 - the viewer's click
            threading.Timer(config.machine.timeout_s + PAUSE_S, resume).start()

    data, out = Path(config.pipeline.datamanager.data), Path(config.output_dir)
    cfg = scenario_config(data, out, "paused", steps=5)
    cfg.machine.timeout_s = config.machine.timeout_s
    trainer = train(local_rank, world_size, cfg, global_rank, callbacks=[pause_at])
    dm = trainer.pipeline.datamanager
    _write(out / f"finished_{global_rank}.json", {"waited_s": trainer.gate.waited_s, "step": trainer.step,
                                                   "cached_eval": "cached_eval" in dm.__dict__})


# ------------------------------------------------------------------------------------- sharded renders
SHARD_CASES = ("fisheye180", "equirect360", "beap_other_rank_and_none")


def shard_case(name: str, dtype):
    """(scene, viewmats [2,4,4], grids, loss weights) of a sharded-render case; rank r holds rows r::2.
    beap_other_rank_and_none: rank 0's camera sees only rank 1's Gaussians (rank 0's are behind it), rank 1's
    camera sees none of them."""
    from conftest import random_scene, random_viewmat, reference_grids

    grids = reference_grids(dtype)
    if name == "beap_other_rank_and_none":
        scene = list(random_scene(240, 31, dtype=dtype))
        behind = torch.arange(240) % 2 == 0  # rank 0's rows
        scene[0] = torch.where(behind[:, None], scene[0] * torch.tensor([1.0, 1.0, -1.0], dtype=dtype), scene[0])
        away = torch.eye(4, dtype=dtype)
        away[:3, :3] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=dtype)  # looks along +x
        away[:3, 3] = -away[:3, :3] @ torch.tensor([0.0, 60.0, 0.0], dtype=dtype)  # from far above the scene
        viewmats = torch.stack([torch.eye(4, dtype=dtype), away])
        grid_pair = [grids["beap"], grids["beap"]]
    else:
        scene = list(random_scene(300, 32, dtype=dtype, around=True))
        viewmats = torch.stack([random_viewmat(7, dtype=dtype, translation_scale=0.2),
                                random_viewmat(8, dtype=dtype, translation_scale=0.2)])
        grid_pair = [grids[name], grids[name]]
    gen = torch.Generator().manual_seed(5)
    weights = [torch.randn(g.num_rays, 3, generator=gen, dtype=dtype) for g in grid_pair]
    return scene, viewmats, grid_pair, weights


def payload_rows(shard):
    """render_sharded's rows_of for a shard of plain tensors (RGB colors): camera q's payload is the rows."""
    return lambda q, rows: tuple(t[rows] for t in shard)


def shard_loss(out, weights):
    return (out.rgb.reshape(-1, 3) * weights).sum() + 0.1 * out.depth.sum() + out.accumulation.sum()


def sharded_render_plan(rank: int, out: Path) -> None:
    """Each case and precision: this rank's camera rendered from both shards, one backward of the rank's loss;
    the image, the shard's gradients and what each camera saw of the shard go to shards_<case>_<dtype>_<rank>.pt."""
    from geer_ns.distributed.sharded_render import render_sharded, shard_rows

    for name in SHARD_CASES:
        for dtype in (torch.float32, torch.float64):
            scene, viewmats, grids, weights = shard_case(name, dtype)
            rows = shard_rows(rank, 2)
            shard = [t[rows].clone().requires_grad_(True) for t in scene]
            image, views = render_sharded(*shard[:4], viewmats, grids, payload_rows(shard))
            shard_loss(image, weights[rank]).backward()
            torch.save({"rgb": image.rgb.detach(), "depth": image.depth.detach(), "acc": image.accumulation.detach(),
                        "grads": [t.grad for t in shard], "sent": views.sent,
                        "seen": [torch.zeros(len(shard[0]), dtype=torch.bool).index_fill_(0, r, True)
                                 for r in views.rows]},
                       out / f"shards_{name}_{str(dtype)[6:]}_{rank}.pt")


# ---------------------------------------------------------------------------------- sharded training
def sharded_config(data: Path, out: Path, name: str, **kw):
    """The replica plans' schedule, Gaussian-parallel (or, images_per_step=2, its one-process reference),
    black background: final renders compare without a random colour."""
    config = scenario_config(data, out, name, **kw)
    config.pipeline.model.background_color = "black"
    config.pipeline.model.sh_degree = 0  # RGB colours: no SH, whose shards evaluate in torch, one process in C++
    return config


def sharded_render_of(trainer, index: int = 0):
    """Training camera `index` rendered by every process from its shard (both render the same camera)."""
    from geer_ns.distributed.gaussian_parallel import sharded_outputs
    from geer_ns.distributed.world import current_world

    dm, model = trainer.pipeline.datamanager, trainer.pipeline.model
    camera = dm.train_camera(index)
    with torch.no_grad():
        return sharded_outputs(model, [camera, camera], current_world().rank)["rgb"]


def sharded_training_plan(local_rank, world_size, config, global_rank):
    """Gaussian-parallel training (a refinement and a reset inside), its gathered checkpoint and a collective
    render; then a one-process checkpoint (the test's reference, made before the launch) re-sharded over the
    two processes and rendered."""
    data, out = Path(config.pipeline.datamanager.data), Path(config.output_dir)
    cfg = sharded_config(data, out, "sharded")
    cfg.pipeline.model.distributed = "gaussians"
    per_step = []
    if global_rank == 0:
        cfg.save_config()  # config.yml, as ns-train writes it: ns-eval reads the gathered checkpoint through it
    trainer = train(local_rank, world_size, cfg, global_rank, callbacks=[lambda t, step: per_step.append(
        (step, t.pipeline.model.num_points, t.pipeline.model.scene_gaussians))])
    image = sharded_render_of(trainer)
    counts = scene_counts(trainer, global_rank)
    evaluated = {}
    trainer.config.steps_per_eval_all_images = 1  # due now: rank 0 evaluates, rendering from both shards
    with held_rows() as held:
        trainer.engine.evaluate(1, lambda: evaluated.update(trainer.pipeline.get_average_eval_image_metrics(step=1)))
    held_save = small_message_save(trainer, out / "small_messages.ckpt")
    back = sharded_config(data, out, "from_one_process")
    back.pipeline.model.distributed = "gaussians"
    back.load_dir = Path((out / "reference_checkpoints.txt").read_text())
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()
    resumed = back.setup(local_rank=local_rank, world_size=world_size)
    resumed.setup()
    image_back = sharded_render_of(resumed)
    shard_back = resumed.pipeline.model.num_points
    rebalanced = rebalance_plan(resumed, global_rank)
    if global_rank == 0:
        torch.save({"per_step": per_step, "image": image, "image_back": image_back, "shard_back": shard_back,
                    "evaluated": evaluated, "eval_rows_held": max(held), "save_bytes_held": held_save, **counts,
                    **rebalanced}, out / "sharded.pt")


def scene_counts(trainer, rank: int) -> dict:
    """What rank 0 logs: the refinement lines' counts (after each refinement) and the `gaussian_count` metric of
    a training image rendered from both shards."""
    from geer_ns.distributed.gaussian_parallel import sharded_outputs

    model = trainer.pipeline.model
    camera, batch = trainer.pipeline.datamanager.train_view(0)
    with torch.no_grad():
        outputs = sharded_outputs(model, [camera, camera], rank)
    return {"gaussian_count": int(model.get_metrics_dict(outputs, batch)["gaussian_count"]),
            "refined_to": [entry["after"] for entry in model.strategy.log]}


@contextlib.contextmanager
def held_rows():
    """The Gaussians of every render this process makes meanwhile (each module's `render` an evaluation can go
    through: the model's, the normals', the split evaluation's), as a list."""
    import importlib

    held, patched = [0], []
    for name in ("geer_ns.model", "geer_ns.render.normals", "geer_ns.distributed.split_eval"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        original = module.render
        patched.append((module, original))
        module.render = lambda means, *a, _original=original, **k: (held.append(int(means.shape[0])),
                                                                    _original(means, *a, **k))[1]
    try:
        yield held
    finally:
        for module, original in patched:
            module.render = original


def small_message_save(trainer, path: Path) -> int:
    """The engine's checkpoint written again at `path` with 1 KiB messages: the most bytes one message, gather
    or broadcast brought this process meanwhile."""
    import torch.distributed as dist

    from geer_ns.distributed import streamed_checkpoint

    largest, originals = [0], {name: getattr(dist, name) for name in ("recv", "gather", "all_gather", "broadcast")}

    def watched(name):
        def call(tensor, *args, **kwargs):
            out = originals[name](tensor, *args, **kwargs)
            tensors = tensor if isinstance(tensor, list) else [tensor]
            tensors += [t for a in list(args) + list(kwargs.values()) if isinstance(a, list) for t in a
                        if isinstance(t, torch.Tensor)]
            largest[0] = max([largest[0]] + [t.numel() * t.element_size() for t in tensors])
            return out
        return call

    chunk, streamed_checkpoint.CHUNK_BYTES = streamed_checkpoint.CHUNK_BYTES, 1024
    for name in originals:
        setattr(dist, name, watched(name))
    try:
        trainer.engine.write_checkpoint(trainer.pipeline.model.step, path)
    finally:
        streamed_checkpoint.CHUNK_BYTES = chunk
        for name, original in originals.items():
            setattr(dist, name, original)
    return largest[0]


def rebalance_plan(trainer, rank: int) -> dict:
    """Rank 1 drops 40 % of its shard (a 1.7x imbalance); the engine's after-step callback must rebalance: the
    shards' sizes end within one, and every surviving Gaussian's parameters and optimiser state (by id) are
    unchanged by the move. An unrelated state entry of the shard's length on rank 0 alone must not make rank 0
    enter a collective the others do not (a deadlock)."""
    from gsplat.strategy.ops import remove

    from geer_ns.distributed.gaussian_parallel import gather_rows
    from geer_ns.distributed.world import all_gather_objects, current_world

    world, model, engine = current_world(), trainer.pipeline.model, trainer.engine
    optimizers = trainer.optimizers.optimizers
    for p in model.gauss_params.values():  # an optimiser state to carry
        p.grad = torch.full_like(p, 0.5)
    for name in model.gauss_params:
        optimizers[name].step()
    if rank == 1:
        drop = torch.zeros(model.num_points, dtype=torch.bool)
        drop[: int(0.4 * model.num_points)] = True
        remove(params=model.gauss_params, optimizers=optimizers, state=model.strategy_state, mask=drop)

    def snapshot():
        ids = gather_rows(world, model.strategy_state["id"])
        rows = {name: gather_rows(world, p.detach()) for name, p in model.gauss_params.items()}
        adam = {name: gather_rows(world, optimizers[name].state[p]["exp_avg"]) for name, p in model.gauss_params.items()}
        return ids, rows, adam, all_gather_objects(model.num_points)

    before = snapshot()
    if rank == 0:  # a state entry of the shard's length on one rank only: rows are moved by name, not by length
        model.strategy_state["scratch"] = torch.zeros(model.num_points)
    engine._after_step(0)
    model.strategy_state.pop("scratch", None)
    after = snapshot()
    return {"rebalance_before": before, "rebalance_after": after}


# ------------------------------------------------------------------------------------------ NCCL's rule
def nccl_rule_plan(global_rank: int, out: Path) -> None:
    """The engine's collectives under emulated NCCL (nccl_emulation.py), every tensor the engine holds on
    (emulated) CUDA as on a GPU machine. Each case's outcome (or its error) goes to nccl_<rank>.pt."""
    from nccl_emulation import cuda, nccl_rule

    from geer_ns.distributed.reductions import reduce_gradients
    from geer_ns.distributed.gaussian_parallel import gather_rows
    from geer_ns.distributed.sharded_render import render_sharded, shard_rows
    from geer_ns.distributed.world import current_world

    results = {}

    def attempt(name, fn):
        try:
            results[name] = fn()
        except Exception as error:  # noqa: BLE001 - recorded for the test; the launch goes on to the fault plan
            results[name] = f"{type(error).__name__}: {error}"

    with nccl_rule():
        world = current_world()

        def gradients():  # rank 0 has gradients for parameters 0 and 1, rank 1 for 0 only, nobody for 2
            params = [cuda(torch.zeros(4, 3)), cuda(torch.zeros(5)), cuda(torch.zeros(2, 2))]
            params[0].grad = cuda(torch.full((4, 3), 1.0 + 2 * global_rank))
            if global_rank == 0:
                params[1].grad = cuda(torch.full((5,), 2.0))
            reduce_gradients(world, params, images=2)
            return [None if p.grad is None else (p.grad.device.type, p.grad.cpu()) for p in params]

        def sharded_render():
            scene, viewmats, grids, _ = shard_case("fisheye180", torch.float64)
            shard = [cuda(t[shard_rows(global_rank, 2)]) for t in scene]
            image, views = render_sharded(*shard[:4], cuda(viewmats), [g.to("cuda") for g in grids],
                                          payload_rows(shard), backend="torch")
            return {"device": image.rgb.device.type, "rgb": image.rgb.cpu(), "sent": views.sent}

        def gathered():
            rows = gather_rows(world, cuda(torch.arange(3.0 + global_rank)))
            return None if rows is None else (rows.device.type, rows.cpu())

        attempt("gradients", gradients)
        attempt("sharded_render", sharded_render)
        attempt("gather_rows", gathered)
    torch.save(results, out / f"nccl_{global_rank}.pt")
