"""`ns-train geer --load-dir` continues training (nerfstudio 1.1.5 issue 3554, fixed in geer_ns/resume.py).

Three runs of nerfstudio's own training loop (scripts.train.train_loop, what ns-train calls) on four frames
of the embedded room: N steps, then M more resumed from its checkpoint with a refinement inside, against one uninterrupted
N + M run with the same seed. The reference is the uninterrupted run, not the code under test.
"""

from __future__ import annotations

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
    model = config.pipeline.model
    model.warmup_length, model.refine_every, model.stop_split_at = 4, 2, 1000
    model.densify_grad_thresh = 1e-7  # every seen Gaussian grows: refinements visibly change the count
    return config


@pytest.fixture(scope="module")
def runs(tmp_path_factory, single_thread):
    out = tmp_path_factory.mktemp("resume")
    data = copy_room(out / "data", 4, n_eval=1)
    first = train_in_process(_config(data, out, "first", N))
    resumed = train_in_process(_config(data, out, "resumed", M, load_dir=first.parent))
    straight = train_in_process(_config(data, out, "straight", N + M))
    load = lambda p: torch.load(p, map_location="cpu")  # noqa: E731
    return load(first), load(resumed), load(straight)


def _gauss(ckpt, name):
    return ckpt["pipeline"][f"_model.gauss_params.{name}"]


def test_resume_continues_the_step_counter(runs):
    first, resumed, straight = runs
    assert first["step"] == N - 1
    assert resumed["step"] == straight["step"] == N + M - 1  # --max-num-iterations: M more steps


def test_resumed_parameters_change_and_adam_steps_on(runs):
    first, resumed, _ = runs
    assert _gauss(resumed, "means").shape[0] != _gauss(first, "means").shape[0]  # refined after resuming
    step_first = first["optimizers"]["features_dc"]["state"][0]["step"]
    step_resumed = resumed["optimizers"]["features_dc"]["state"][0]["step"]
    assert float(step_resumed) == float(step_first) + M


def test_resumed_run_equals_the_uninterrupted_run(runs):
    _, resumed, straight = runs
    for name in ("means", "scales", "quats", "features_dc", "features_rest", "opacities"):
        a, b = _gauss(resumed, name), _gauss(straight, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6), (name, float((a - b).abs().max()))
    for group, state in straight["optimizers"].items():
        for key, value in state["state"].get(0, {}).items():
            other = resumed["optimizers"][group]["state"][0][key]
            assert torch.allclose(torch.as_tensor(other), torch.as_tensor(value), rtol=1e-5, atol=1e-9), (group, key)
