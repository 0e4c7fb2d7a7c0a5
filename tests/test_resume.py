"""`ns-train geer --load-dir` continues training (a nerfstudio 1.1.5 bug, fixed in geer_ns/resume.py:
docs/training.md).

Three runs of nerfstudio's own training loop (scripts.train.train_loop, what ns-train calls) on four frames
of the embedded room: N steps, then M more resumed from its checkpoint with a refinement inside, against one uninterrupted
N + M run with the same seed. The reference is the uninterrupted run, not the code under test.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import pytest
import torch

from conftest import copy_room, tiny_trainer_config, train_in_process

# gsplat refines at steps > warm-up that are multiples of refine_every and at least num_train_data +
# refine_every past a reset: with 3 training images, warm-up 4 and refine_every 2, at steps 6, 8, 10 (reset
# every 30 refinements). N steps, then M resumed: refinements at 8 and 10 inside the resumed range, with
# densification statistics gathered on both sides of the checkpoint (steps 7 and 8).
N, M = 8, 4


def _config(data: Path, out: Path, name: str, steps: int, load_dir=None):
    config = tiny_trainer_config(data, out, name, steps)
    config.steps_per_save = 1_000_000
    config.load_dir = load_dir
    # An N-step run is a whole run whose schedules follow its N steps (training/horizon.py), not the first part of
    # an N + M run: the resume itself is compared with the schedules as written (test_schedule_horizon.py
    # checks that a resumed run's schedules follow its checkpoint's step + M).
    config.schedules = "fixed"
    model = config.pipeline.model
    model.warmup_length, model.refine_every, model.stop_split_at = 4, 2, 1000
    model.densify_grad_thresh = 1e-7  # every seen Gaussian grows: refinements visibly change the count
    return config


@pytest.fixture(scope="module")
def runs(tmp_path_factory, single_thread):
    out = tmp_path_factory.mktemp("resume")
    data = copy_room(out / "data", 4, n_eval=1)
    first_config = _config(data, out, "first", N)
    first_config.save_config()  # config.yml, as ns-train writes it (ns-eval reads the run through it)
    first = train_in_process(first_config)
    resumed = train_in_process(_config(data, out, "resumed", M, load_dir=first.parent))
    straight = train_in_process(_config(data, out, "straight", N + M))
    load = lambda p: torch.load(p, map_location="cpu")  # noqa: E731
    return load(first), load(resumed), load(straight), first


def _gauss(ckpt, name):
    return ckpt["pipeline"][f"_model.gauss_params.{name}"]


def test_resume_continues_the_step_counter(runs):
    first, resumed, straight, _ = runs
    assert first["step"] == N - 1
    assert resumed["step"] == straight["step"] == N + M - 1  # --max-num-iterations: M more steps


def test_resumed_parameters_change_and_adam_steps_on(runs):
    first, resumed, _, _ = runs
    assert _gauss(resumed, "means").shape[0] != _gauss(first, "means").shape[0]  # refined after resuming
    step_first = first["optimizers"]["features_dc"]["state"][0]["step"]
    step_resumed = resumed["optimizers"]["features_dc"]["state"][0]["step"]
    assert float(step_resumed) == float(step_first) + M


def test_resumed_run_equals_the_uninterrupted_run(runs):
    _, resumed, straight, _ = runs
    for name in ("means", "scales", "quats", "features_dc", "features_rest", "opacities"):
        a, b = _gauss(resumed, name), _gauss(straight, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6), (name, float((a - b).abs().max()))
    for group, state in straight["optimizers"].items():
        for key, value in state["state"].get(0, {}).items():
            other = resumed["optimizers"][group]["state"][0][key]
            assert torch.allclose(torch.as_tensor(other), torch.as_tensor(value), rtol=1e-5, atol=1e-9), (group, key)


# ------------------------------------------------------------------------------------- RNG states
@contextlib.contextmanager
def _emulated_gpus(count: int, current: int = 0):
    """torch.cuda's RNG functions on a machine without a GPU, as on one with `count` GPUs: each device's
    generator is a CPU generator of its own (seeded by its index), an index past `count` raises IndexError as
    an invalid device ordinal does; yields the generators."""
    import torch.cuda.random as cuda_random

    gens = tuple(torch.Generator().manual_seed(1000 + i) for i in range(count))
    patched = {(torch.cuda, "is_available"): lambda: True, (torch.cuda, "is_initialized"): lambda: True,
               (torch.cuda, "default_generators"): gens, (cuda_random, "_lazy_init"): lambda: None,
               (cuda_random, "current_device"): lambda: current, (cuda_random, "device_count"): lambda: count}
    saved = {key: getattr(*key) for key in patched}
    for (module, name), value in patched.items():
        setattr(module, name, value)
    try:
        yield gens
    finally:
        for (module, name), value in saved.items():
            setattr(module, name, value)


def _with_old_rng(ckpt: dict, gpus: int) -> dict:
    """The checkpoint as geer wrote it before: every visible GPU's CUDA RNG state in the model's extra state."""
    ckpt, pipeline = dict(ckpt), dict(ckpt["pipeline"])
    extra = dict(pipeline["_model._extra_state"])
    rng = dict(ckpt.pop("rng", None) or extra["rng"])
    rng["cuda"] = [torch.Generator().manual_seed(i).get_state() for i in range(gpus)]
    pipeline["_model._extra_state"] = {**extra, "rng": rng}
    ckpt["pipeline"] = pipeline
    return ckpt


def test_rng_states_are_the_trainers_not_the_models(runs):
    first = runs[0]
    assert "rng" in first and "rng" not in first["pipeline"]["_model._extra_state"]
    assert torch.is_tensor(first["rng"]["torch"])


def test_every_rank_restores_the_saving_ranks_cuda_state():
    """Rank 0 (device 0) saves; rank 1 (device 1 of the same machine) restores: its device must draw what rank
    0's drew, not its own index's old state."""
    from geer_ns import resume

    with _emulated_gpus(2, current=0) as gens:
        saved = resume.rng_state()
    with _emulated_gpus(2, current=1) as gens:
        resume.restore_rng_state(saved)
        assert torch.equal(gens[1].get_state(), torch.Generator().manual_seed(1000).get_state())


def test_a_checkpoint_with_8_cuda_states_loads_on_a_machine_with_one_gpu(runs):
    from geer_ns import resume

    ckpt = _with_old_rng(runs[0], gpus=8)
    assert resume.checkpoint_rng_state(ckpt)["cuda"][0].shape == ckpt["pipeline"]["_model._extra_state"]["rng"][
        "cuda"][0].shape
    out = Path(runs[3]).parents[4]
    config = _config(out / "data", out, "first", N)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    with _emulated_gpus(1) as gens:
        before = gens[0].get_state()
        pipeline.load_pipeline(ckpt["pipeline"], ckpt["step"])  # what ns-eval, ns-viewer and ns-export do
        assert torch.equal(gens[0].get_state(), before)  # loading a model draws on no RNG state
        resume.restore_rng_state(resume.checkpoint_rng_state(ckpt))  # a resumed run: one state, device 0's
        assert torch.equal(gens[0].get_state(), ckpt["pipeline"]["_model._extra_state"]["rng"]["cuda"][0])


def test_ns_eval_opens_a_checkpoint_with_8_cuda_states_on_the_cpu(runs, tmp_path):
    from nerfstudio.scripts.eval import ComputePSNR

    run = Path(runs[3]).parents[1]
    torch.save(_with_old_rng(runs[0], gpus=8), runs[3])  # the run's one checkpoint (the others read it before)
    ComputePSNR(load_config=run / "config.yml", output_path=tmp_path / "eval.json").main()
    metrics = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert metrics["psnr"] > 8.0 and 0.0 < metrics["ssim"] <= 1.0
