"""Image-parallel training on 2 gloo processes (geer_ns/distributed) against 1 process with 2 images per step.

The 2-process runs go through nerfstudio's own launcher (`launch`, what `ns-train --machine.num-devices 2`
calls) with geer's launch fix; their plans are in distributed_harness.py. The reference is one process
training the same image pairs (--pipeline.datamanager.images-per-step 2), with one CPU thread like each of the
two processes: a step's gradient is then the same sum of the same two images' gradients (a + b = b + a in
IEEE arithmetic), so the runs must agree bit for bit, densification included.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import time
from pathlib import Path

import pytest
import torch

import distributed_harness as harness
from conftest import copy_room, train_in_process
from geer_ns.render import render as _render

GAUSS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")


@contextlib.contextmanager
def _output_to(log: Path):
    """This process's and its children's stdout and stderr into `log` (the file descriptors, which the spawned
    processes inherit, and Python's streams, which pytest replaces)."""
    saved = [os.dup(1), os.dup(2)]
    with open(log, "w", buffering=1) as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            with contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):  # pytest replaces sys.stdout/err
                yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def _launch(config, log: Path, main=harness.main) -> None:
    """Two CPU processes through nerfstudio's launcher, their output in `log`."""
    from nerfstudio.scripts.train import launch

    from geer_ns.training.trainer import install_run_fixes

    install_run_fixes()  # what ns-train's main does first for a geer config (GeerTrainerConfig.set_timestamp)
    with _output_to(log):
        launch(main, num_devices_per_machine=2, num_machines=1, machine_rank=0, dist_url="auto",
               config=config, device_type="cpu")


def _killed_launch(config, log: Path, main) -> tuple:
    """A launch whose rank 1 is killed: (the SystemExit it ended with, or None; the time it ended)."""
    try:
        _launch(config, log, main)
        stop = None
    except SystemExit as error:
        stop = error
    return stop, time.time()


def _text(log: Path) -> str:
    """The log as one line of words (rich wraps lines and adds times and source locations)."""
    text = re.sub(r"\S+\.py:\d+|\[\d\d:\d\d:\d\d\]", " ", log.read_text())
    return " ".join(text.split())


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return copy_room(tmp_path_factory.mktemp("dist_data"), 6, n_eval=1)  # 5 training images, 1 to evaluate


@pytest.fixture(scope="module")
def one_process(room, tmp_path_factory, single_thread):
    """The one-process references (one CPU thread, like each of the two processes): both strategies with 2 images
    per step, and the Gaussian-parallel plan's (black background)."""
    out = tmp_path_factory.mktemp("dist_reference")
    runs = {strategy: train_in_process(harness.scenario_config(
        room, out, f"equal_{strategy}", strategy=strategy, images_per_step=2)) for strategy in ("default", "mcmc")}
    runs["sharded"] = train_in_process(harness.sharded_config(room, out, "sharded", images_per_step=2))
    runs["kappa1"] = train_in_process(harness.scenario_config(room, out, "kappa1", steps=3))  # 6 steps of 1 image
    return {name: (path, torch.load(path, map_location="cpu")) for name, path in runs.items()}


@pytest.fixture(scope="module")
def two_processes(room, tmp_path_factory, one_process):
    """One launch of 2 processes: the replica plans, the sharded renders and training, then a run whose rank 1
    is killed (the launch's end)."""
    out = tmp_path_factory.mktemp("dist_runs")
    (out / "reference_checkpoints.txt").write_text(str(one_process["sharded"][0].parent))
    (out / "kappa1_checkpoints.txt").write_text(str(one_process["kappa1"][0].parent))
    config = harness.scenario_config(room, out, "replicas")
    start = time.perf_counter()
    stop, ended = _killed_launch(config, out / "log.txt", harness.main)
    print(f"2 processes, the replica plans and the fault: {time.perf_counter() - start:.0f} s")
    return out, json.loads((out / "replicas.json").read_text()), stop, ended, config


@pytest.fixture(scope="module")
def sharded_fault(room, tmp_path_factory):
    out = tmp_path_factory.mktemp("dist_sharded_fault")
    config = harness.scenario_config(room, out, "fault")
    stop, ended = _killed_launch(config, out / "log.txt", harness.sharded_fault_main)
    return out, None, stop, ended, config


def _checkpoint(out: Path, name: str) -> dict:
    return torch.load(sorted((out / name / "geer" / "run" / "nerfstudio_models").glob("*.ckpt"))[-1],
                      map_location="cpu")


def test_a_process_with_another_configuration_stops_every_rank_at_start_up(two_processes):
    out, results = two_processes[:2]
    assert results["mismatch"] == "exit 1"  # rank 0's; rank 1 stopped too, or it would not have reached plan 2
    text = _text(out / "log.txt")
    for rank in (0, 1):
        assert f"geer: rank {rank} of 2 stopped at step 0: failed: ReplicaMismatchError: geer: the processes of " \
               "this run disagree: rank 1 has config pipeline.model.refine_every = 6 where rank 0 has 4" in text


def test_the_replica_check_catches_replicas_that_drift(two_processes):
    results = two_processes[1]
    assert results["unsynced"].startswith("diverged")


@pytest.mark.parametrize("strategy", ["default", "mcmc"])
def test_replicas_are_identical_after_every_step(two_processes, strategy):
    results = two_processes[1]
    per_step = results[f"equal_{strategy}"]
    assert [step for step, _, _ in per_step] == list(range(harness.STEPS))
    for step, count, sums in per_step:
        assert len(sums) == 2 and sums[0] == sums[1], (step, sums)
    counts = [count for _, count, _ in per_step]
    assert len(set(counts)) > 1, counts  # the plan's refinements (or MCMC's relocation) changed the model


@pytest.mark.parametrize("strategy", ["default", "mcmc"])
def test_two_processes_equal_one_process_with_two_images_per_step(two_processes, one_process, strategy):
    out = two_processes[0]
    ranks, single = _checkpoint(out, f"equal_{strategy}"), one_process[strategy][1]
    assert ranks["step"] == single["step"] == harness.STEPS - 1
    for name in GAUSS:
        a, b = ranks["pipeline"][f"_model.gauss_params.{name}"], single["pipeline"][f"_model.gauss_params.{name}"]
        assert a.shape == b.shape, (name, a.shape, b.shape)
        assert torch.equal(a, b), (name, float((a - b).abs().max()))
    for group, state in single["optimizers"].items():
        for key, value in state["state"].get(0, {}).items():
            assert torch.equal(torch.as_tensor(ranks["optimizers"][group]["state"][0][key]), torch.as_tensor(value))


@pytest.mark.parametrize("launch", ["two_processes", "sharded_fault"])
def test_a_killed_process_stops_the_other_with_one_line_within_the_timeout(launch, request):
    """Image-parallel and Gaussian-parallel: one line from the survivor (naming rank 1 at step 5's gate, or the
    lost connection in a collective), one from the launcher, within --machine.timeout-s, nothing half written."""
    out, _, stop, ended, config = request.getfixturevalue(launch)
    assert stop is not None and stop.code == 1
    text = _text(out / "log.txt")  # the processes' and the launcher's lines
    gate = r"rank 1 stopped answering \(its process \d+ has ended\)"  # at step 5's gate (gate.py)
    collective = (r"lost the other processes \(gloo: connection (reset|closed) by peer: one died, hung past "
                  r"--machine.timeout-s or was unreachable; the first to fail says why\)")  # in a collective
    assert re.search(rf"geer: rank 0 of 2 stopped at step 5: ({gate}|{collective})", text), text[-2000:]
    assert re.search(r"geer: training stopped: rank 1 \(pid \d+\) was killed by signal SIGKILL; the other 1 "
                     r"process\(es\) of this machine were stopped", text), text[-2000:]
    killed_at = float((out / "killed_at").read_text())
    print(f"from the kill to the end of the launch: {ended - killed_at:.1f} s (timeout {config.machine.timeout_s} s)")
    assert ended - killed_at < config.machine.timeout_s
    assert not list((out / "killed").rglob("*.partial")) and not list((out / "killed").rglob("*.ckpt"))


def test_a_process_paused_in_the_viewer_past_the_timeout_does_not_stop_the_others(room, tmp_path):
    """Rank 0 paused (the viewer's "Pause training") for longer than --machine.timeout-s: rank 1 waits at the
    next step's gate, not in a collective that would time out, and both finish. Rank 1 never cached the eval
    images (rank 0 alone evaluates)."""
    config = harness.scenario_config(room, tmp_path, "pause")
    config.machine.timeout_s = 8.0  # above the processes' start-up skew on a loaded machine
    stop, _ = _killed_launch(config, tmp_path / "log.txt", harness.pause_main)
    log = tmp_path / "log.txt"
    assert stop is None or stop.code in (0, None), _text(log)[-2000:]
    finished = [json.loads((tmp_path / f"finished_{rank}.json").read_text()) for rank in range(2)]
    assert finished[1]["waited_s"] >= config.machine.timeout_s, finished  # it waited at the gate, past the timeout
    assert finished[0]["step"] == finished[1]["step"] == 4
    assert not finished[1]["cached_eval"]  # rank 0 alone evaluates: the others never load the eval images


# ---------------------------------------------------------------------------------- sharded renders
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", harness.SHARD_CASES)
def test_a_sharded_render_is_the_single_process_render(two_processes, case, dtype):
    """Each rank's camera, rendered from both ranks' shards (geer_ns/distributed/sharded_render.py), against one process
    rendering the whole scene: images and every gradient bit for bit (the same pairs in the same order, a sum of
    the same two per-camera gradients), on a 180-degree fisheye, a 360-degree panorama and a BEAP grid whose
    rank-0 camera sees only rank 1's Gaussians and rank-1 camera sees none."""
    out = two_processes[0]
    scene, viewmats, grids, weights = harness.shard_case(case, dtype)
    full = [t.clone().requires_grad_(True) for t in scene]
    renders = [_render(*full, viewmats[r], grids[r]) for r in range(2)]
    sum(harness.shard_loss(image, weights[r]) for r, image in enumerate(renders)).backward()
    ranks = [torch.load(out / f"shards_{case}_{str(dtype)[6:]}_{r}.pt") for r in range(2)]
    for r, (image, got) in enumerate(zip(renders, ranks)):
        for key, want in (("rgb", image.rgb), ("depth", image.depth), ("acc", image.accumulation)):
            assert torch.equal(got[key], want.detach()), (r, key, float((got[key] - want).abs().max()))
        rows = slice(r, None, 2)
        for name, mine, reference in zip(("means", "quats", "scales", "opacities", "colors"), got["grads"], full):
            assert torch.equal(mine, reference.grad[rows]), (r, name, float((mine - reference.grad[rows]).abs().max()))
    if case == "beap_other_rank_and_none":
        assert float(renders[0].accumulation.max()) > 0.5 and float(renders[1].accumulation.max()) == 0.0
        assert not ranks[0]["seen"][0].any() and ranks[1]["seen"][0].any()  # camera 0: rank 1's rows only
        assert not ranks[0]["seen"][1].any() and not ranks[1]["seen"][1].any()  # camera 1: nothing
    else:
        assert all(float(image.accumulation.max()) > 0.5 for image in renders)
        for got in ranks:  # what a rank sends is what the cameras see of its shard
            assert got["sent"] == sum(int(m.sum()) for m in got["seen"]) > 0
        if case == "fisheye180":
            assert ranks[0]["sent"] < 300  # a 180-degree camera does not see everything: not all rows travel


# ------------------------------------------------------------------------------ resume, schedule, budget
def _assert_same_optimisers(resumed: dict, fresh: dict) -> None:
    assert resumed["start"] == fresh["start"]
    assert resumed["groups"].keys() == fresh["groups"].keys()
    for name in fresh["groups"]:
        for got, want in zip(resumed["groups"][name], fresh["groups"][name]):
            assert got["betas"] == want["betas"] and got["eps"] == want["eps"], (name, got, want)
            assert got["lr"] == pytest.approx(want["lr"], rel=1e-12), (name, got, want)
        if resumed["adam_steps"][name]:  # the groups the checkpoint's run stepped
            assert resumed["adam_steps"][name] == fresh["adam_steps"][name], name
    assert resumed["schedulers"].keys() == fresh["schedulers"].keys() and fresh["schedulers"]
    for name, want in fresh["schedulers"].items():
        got = resumed["schedulers"][name]
        assert got["base_lrs"] == pytest.approx(want["base_lrs"], rel=1e-12), name
        assert got["last_epoch"] == want["last_epoch"], name
        assert got["lr"] == pytest.approx(want["lr"], rel=1e-12), name


@pytest.mark.parametrize("engine", ["images", "gaussians"])
def test_a_resume_from_one_process_on_two_steps_with_a_fresh_two_process_runs_optimisers(two_processes, engine):
    """A kappa = 1 checkpoint (6 steps of one image) resumed on 2 processes (kappa = 2): learning rates, betas,
    epsilon, Adam's step counts and the schedulers are those of a 2-process run started afresh and brought
    to the same step (3), not the checkpoint's."""
    results = json.loads((two_processes[0] / "resume.json").read_text())
    assert results[engine]["start"] == 3
    _assert_same_optimisers(results[engine], results["fresh"])


def test_a_resume_from_two_processes_on_one_steps_with_a_fresh_one_process_runs_optimisers(two_processes, room):
    """The 2-process run's checkpoint (kappa = 2, 12 steps) resumed on 1 process with 1 image per step: the
    optimisers are a fresh kappa = 1 run's at step 24."""
    checkpoints = two_processes[0] / "equal_default" / "geer" / "run" / "nerfstudio_models"
    out = two_processes[0] / "back_on_one"
    config = harness.scenario_config(room, out, "resumed")
    config.load_dir = checkpoints
    resumed = harness.optimizer_record(harness.set_up(0, 1, config))
    fresh = harness.fresh_record(harness.set_up(0, 1, harness.scenario_config(room, out, "fresh")), 24)
    assert resumed["start"] == 24
    _assert_same_optimisers(resumed, fresh)


def test_the_batch_rule_keeps_each_images_decay_of_adams_moments():
    """8 processes x 2 images: a step's beta is the product of 16 one-image decays (the moments forget at the
    same rate per image), not the linear rule's 0 (clamped from kappa = 10)."""
    from geer_ns.distributed.schedule import EffectiveBatch

    lr, eps, betas = EffectiveBatch(8, 2).adam(1e-3, 1e-15, (0.9, 0.999))
    decay = [1.0, 1.0]
    for _ in range(16):
        decay = [d * b for d, b in zip(decay, (0.9, 0.999))]
    assert betas == pytest.approx(decay, rel=1e-12) and min(betas) > 0.18
    assert lr == pytest.approx(4e-3) and eps == pytest.approx(0.25e-15)


def test_the_densification_budget_is_the_scenes_over_shards_with_unequal_candidates(two_processes):
    """2 shards, one with 30 of the 40 candidates, a budget of 75 for 60 Gaussians: together they grow exactly
    the Gaussians (by id) one process holding the scene grows, and never more than the budget."""
    parts = [torch.load(two_processes[0] / f"budget_{r}.pt") for r in range(2)]
    assert [p["candidates"] for p in parts] == [30, 10]
    params, optimizers, state, strategy = harness.budget_case()
    strategy.grow(params, optimizers, state, step=100)
    one = state["id"]
    assert one.numel() == harness.BUDGET  # the budget binds: 40 candidates, room for 15
    assert sum(p["n"] for p in parts) <= harness.BUDGET
    assert torch.equal(torch.sort(torch.cat([p["ids"] for p in parts])).values, torch.sort(one).values)


def test_gaussian_parallel_evaluates_at_the_scaled_steps(room, tmp_path, single_thread):
    """kappa = 3 (one process, 3 images per step, Gaussian-parallel): --steps-per-eval-all-images 6 counts
    images, so the all-images evaluation runs at step 2 of the 4 steps (12 images), as nerfstudio's loop
    schedules it on the scaled configuration."""
    config = harness.sharded_config(room, tmp_path, "eval_kappa3", images_per_step=3, steps=2)
    from nerfstudio.utils import writer  # after the configs: nerfstudio's writer imported first is a circle

    config.max_num_iterations = 12
    config.steps_per_eval_all_images = 6
    config.pipeline.model.distributed = "gaussians"
    writer.EVENT_WRITERS.clear()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    evaluated = []
    average = trainer.pipeline.get_average_eval_image_metrics

    def spy(step=None, **kwargs):
        evaluated.append(step)
        return average(step=step, **kwargs)

    trainer.pipeline.get_average_eval_image_metrics = spy
    trainer.train()
    writer.EVENT_WRITERS.clear()
    assert trainer.config.steps_per_eval_all_images == 2 and evaluated == [2]


# ---------------------------------------------------------------------------------- sharded training
def _by_id(ckpt: dict) -> tuple:
    """(ids, {name: parameter rows}) in id order: shards keep no global row order, every Gaussian its id."""
    ids = ckpt["pipeline"]["_model._extra_state"]["strategy_state"]["id"]
    order = torch.argsort(ids)
    return ids[order], {name: ckpt["pipeline"][f"_model.gauss_params.{name}"][order] for name in GAUSS}


def test_gaussian_parallel_training_equals_one_process(two_processes, one_process):
    """2 processes, each with half the Gaussians, against 1 process with all of them and the same image pairs
    (2 per step), through refinements and an opacity reset: the same Gaussians (by id), with the same parameters
    bit for bit. (RGB colours: with SH the shards evaluate the colours in torch, one process in the kernels'
    C++, and the two round differently: equal within float32 rounding, not bit for bit.)"""
    out = two_processes[0]
    run = torch.load(out / "sharded.pt")
    shards, single = _checkpoint(out, "sharded"), one_process["sharded"][1]
    counts = [count for _, count, _ in run["per_step"]]
    totals = [total for _, _, total in run["per_step"]]
    assert len(set(totals)) > 1, totals  # refinements grew the scene
    assert all(c < t for c, t in zip(counts, totals))  # rank 0 held a shard, not the scene
    ids, params = _by_id(shards)
    ids_one, params_one = _by_id(single)
    assert ids.numel() == totals[-1] == ids_one.numel() and torch.equal(ids, ids_one)
    for name in GAUSS:
        assert torch.equal(params[name], params_one[name]), name


def _pipeline_from(config_or_ckpt_dir, ckpt: dict, data: Path):
    """A one-process pipeline holding a checkpoint (what ns-eval and ns-viewer load)."""
    config = harness.sharded_config(data, Path(config_or_ckpt_dir), "load")
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    pipeline.load_pipeline(ckpt["pipeline"], ckpt["step"])
    return pipeline


def _one_process_render(pipeline) -> torch.Tensor:
    camera = pipeline.datamanager.train_camera(0)
    pipeline.model.train()
    with torch.no_grad():
        return pipeline.model.get_outputs(camera)["rgb"]


def test_a_gathered_checkpoint_renders_in_one_process_as_the_shards_did(two_processes, room, tmp_path):
    out = two_processes[0]
    run = torch.load(out / "sharded.pt")
    image = _one_process_render(_pipeline_from(tmp_path, _checkpoint(out, "sharded"), room))
    assert float(image.max()) > 0.2
    assert torch.allclose(image, run["image"], atol=1e-5), float((image - run["image"]).abs().max())


def test_gaussian_parallel_evaluation_scores_as_one_process_holding_the_checkpoint(two_processes, room, tmp_path):
    """Rank 0's evaluation, each eval camera rendered from the rows both shards send it, against one process
    evaluating the written checkpoint (streamed, never gathered)."""
    run = torch.load(two_processes[0] / "sharded.pt")
    pipeline = _pipeline_from(tmp_path, _checkpoint(two_processes[0], "sharded"), room)
    one = pipeline.get_average_eval_image_metrics(step=1)
    assert run["evaluated"]["psnr"] > 8.0
    for key in ("psnr", "ssim"):
        assert run["evaluated"][key] == pytest.approx(one[key], abs=1e-4), key


def test_rank_0_logs_and_scores_the_scenes_gaussian_count_not_its_shards(two_processes):
    run = torch.load(two_processes[0] / "sharded.pt")
    counts = [count for _, count, _ in run["per_step"]]
    totals = [total for _, _, total in run["per_step"]]
    assert run["gaussian_count"] == totals[-1] > counts[-1]
    assert run["refined_to"] and all(after in totals for after in run["refined_to"])
    assert max(run["refined_to"]) > max(counts)


def test_rank_0_holds_a_part_of_the_scene_while_it_evaluates_and_saves(two_processes, room, tmp_path, monkeypatch):
    """While rank 0 evaluates, no render it makes holds half the Gaussians one process's render of the same
    camera sees (the evaluation is split by pixels); while it saves with 1 KiB messages, no message brings it
    more than 1 KiB, and the file is the checkpoint written with 32 MiB ones."""
    import geer_ns.model as model_module
    from geer_ns.distributed.streamed_checkpoint import leaves

    out = two_processes[0]
    run = torch.load(out / "sharded.pt")
    seen, render = [], model_module.render
    monkeypatch.setattr(model_module, "render", lambda *a, **k: (lambda o: (seen.append(int(o.visible.sum())), o)[1])(
        render(*a, **k)))
    _pipeline_from(tmp_path, _checkpoint(out, "sharded"), room).get_average_eval_image_metrics(step=1)
    assert len(seen) == 1 and seen[0] > 1000
    assert 0 < run["eval_rows_held"] < seen[0] / 2, (run["eval_rows_held"], seen)
    assert 0 < run["save_bytes_held"] <= 1024
    small, usual = torch.load(out / "small_messages.ckpt"), _checkpoint(out, "sharded")
    tensors = [(path, t) for path, t in leaves({k: usual[k] for k in ("pipeline", "optimizers")})
               if isinstance(t, torch.Tensor)]
    assert sum(t.numel() for _, t in tensors) > 100_000
    for path, t in tensors:
        other = small[path[0]]
        for key in path[1:]:
            other = other[key]
        assert torch.equal(other, t), path


def test_a_one_process_checkpoint_resharded_over_two_renders_the_same(two_processes, one_process, room, tmp_path):
    run = torch.load(two_processes[0] / "sharded.pt")
    single = one_process["sharded"][1]
    n = single["pipeline"]["_model.gauss_params.means"].shape[0]
    assert run["shard_back"] == (n + 1) // 2  # rank 0's round-robin half of the loaded checkpoint
    image = _one_process_render(_pipeline_from(tmp_path, single, room))
    assert torch.allclose(image, run["image_back"], atol=1e-5), float((image - run["image_back"]).abs().max())


def test_shards_that_drift_apart_are_rebalanced_with_their_state(two_processes):
    run = torch.load(two_processes[0] / "sharded.pt")
    (ids0, rows0, adam0, sizes0), (ids1, rows1, adam1, sizes1) = run["rebalance_before"], run["rebalance_after"]
    assert max(sizes0) > 1.5 * min(sizes0)  # the plan's imbalance
    assert max(sizes1) - min(sizes1) <= 1 and sum(sizes1) == sum(sizes0)
    order0, order1 = torch.argsort(ids0), torch.argsort(ids1)
    assert torch.equal(ids0[order0], ids1[order1])
    for name in rows0:
        assert torch.equal(rows0[name][order0], rows1[name][order1]), name
        assert torch.equal(adam0[name][order0], adam1[name][order1]), name


def test_ns_eval_scores_the_gathered_checkpoint_in_one_process(two_processes, tmp_path):
    from nerfstudio.scripts.eval import ComputePSNR

    run = two_processes[0] / "sharded" / "geer" / "run"
    ComputePSNR(load_config=run / "config.yml", output_path=tmp_path / "eval.json").main()
    metrics = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert metrics["psnr"] > 8.0 and 0.0 < metrics["ssim"] <= 1.0


# ----------------------------------------------------------------------------------------- ns-train
def test_ns_train_on_two_cpu_processes_then_ns_eval_and_a_resume_on_one(tmp_path):
    """The real command line on 2 gloo processes: it trains, rank 0 alone speaks and writes one checkpoint,
    ns-eval scores it, and a run resumed from it on one process carries the images seen over."""
    import subprocess
    import sys

    from nerfstudio.scripts.eval import ComputePSNR

    from conftest import tiny_trainer_config

    data = copy_room(tmp_path / "data", 8, n_eval=2)
    images = 40  # 20 steps of 2 images
    args = [str(Path(sys.executable).parent / "ns-train"), "geer", "--data", str(data),
            "--output-dir", str(tmp_path), "--experiment-name", "room", "--timestamp", "two",
            "--max-num-iterations", str(images), "--vis", "tensorboard", "--steps-per-eval-image", "0",
            "--steps-per-eval-all-images", "0", "--pipeline.model.num-downscales", "1",
            "--pipeline.model.resolution-schedule", "1000000", "--machine.num-devices", "2",
            "--machine.device-type", "cpu"]
    result = subprocess.run(args, capture_output=True, text=True, timeout=600,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    log = " ".join(re.sub(r"\S+\.py:\d+|\[\d\d:\d\d:\d\d\]", " ", result.stdout + result.stderr).split())
    assert result.returncode == 0, log[-3000:]
    assert log.count("geer: training on 2 process(es) (gloo, 1 CPU thread(s) each), 1 image(s) per process per "
                     "step: an effective batch of 2 images") == 1, log[-3000:]
    assert log.count("Training Finished") == 1 and log.count("geer: caching 6 train images") == 1  # rank 0 only
    run = tmp_path / "room" / "geer" / "two"
    assert [p.name for p in (run / "nerfstudio_models").iterdir()] == ["step-000000019.ckpt"]

    ComputePSNR(load_config=run / "config.yml", output_path=tmp_path / "eval.json").main()
    metrics = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert metrics["psnr"] > 10.0 and 0.0 < metrics["ssim"] <= 1.0

    resumed = tiny_trainer_config(data, tmp_path, "resumed", 3)
    resumed.load_dir = run / "nerfstudio_models"
    last = torch.load(train_in_process(resumed), map_location="cpu")
    # 20 steps of 2 images = 40 steps of 1: the resumed run goes on at step 40 for its 3 steps
    assert last["step"] == 42
    assert last["pipeline"]["_model._extra_state"]["images_per_step"] == 1


# ------------------------------------------------------------------------------------------ NCCL's rule
def test_collectives_under_nccls_rule(two_processes):
    """Collectives get tensors on the device their backend serves: NCCL serves CUDA tensors only, and a flag or
    count built on the CPU stops a multi-GPU run at step 0 while gloo accepts it. The launch's nccl plan runs
    the engine's collectives under emulated NCCL (nccl_emulation.py: the world says NCCL, a collective refuses
    non-CUDA tensors, the engine's tensors are emulated CUDA tensors); expected: sums worked out by hand and
    the one-process render of the whole scene."""
    ranks = [torch.load(two_processes[0] / f"nccl_{rank}.pt") for rank in (0, 1)]
    for rank, got in enumerate(ranks):
        # reduce_gradients: the has-gradient flags, then the sum over both processes / 2 images.
        grads = got["gradients"]
        assert not isinstance(grads, str), (rank, grads)
        assert grads[0][0] == "cuda" and torch.equal(grads[0][1], torch.full((4, 3), (1.0 + 3.0) / 2))
        assert grads[1][0] == "cuda" and torch.equal(grads[1][1], torch.full((5,), (2.0 + 0.0) / 2))
        assert grads[2] is None
        # render_sharded: the all-to-all's counts, then the rows; the render is the one-process render.
        shard = got["sharded_render"]
        assert not isinstance(shard, str), (rank, shard)
        scene, viewmats, grids, _ = harness.shard_case("fisheye180", torch.float64)
        whole = _render(*scene, viewmats[rank], grids[rank], backend="torch")
        assert shard["device"] == "cuda" and shard["sent"] > 0
        assert torch.allclose(shard["rgb"], whole.rgb, atol=1e-12), float((shard["rgb"] - whole.rgb).abs().max())
    gathered = ranks[0]["gather_rows"]
    assert not isinstance(gathered, str), gathered
    assert gathered[0] == "cuda" and torch.equal(gathered[1], torch.tensor([0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 3.0]))
    assert ranks[1]["gather_rows"] is None
