"""Per-Gaussian SH degrees through training (geer_ns/sh_degrees): chosen at the run's last step, stored packed
in checkpoints (features_rest and its Adam moments: the kept coefficients only; the first run's degrees set in turn
over the rows, _mixed_choice), loaded back dense, resumed, and a
checkpoint in the format before per-Gaussian degrees (dense, torch's Adam) resumed by today's defaults. Runs of
nerfstudio's own training loop on four frames of the embedded room."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import torch
from nerfstudio.engine.optimizers import AdamOptimizerConfig

from conftest import copy_room, tiny_trainer_config, train_in_process
from geer_ns.sh_degrees.packing import kept, pack, unpacked_checkpoint

REST = "_model.gauss_params.features_rest"
CHOICE = 11  # the first run's last step (12 steps): where the degrees are chosen (choice.last_step)


def _config(data: Path, out: Path, name: str, steps: int, load_dir=None, **model):
    config = tiny_trainer_config(data, out, name, steps)
    config.steps_per_save = 1_000_000
    config.load_dir = load_dir
    options = {"warmup_length": 4, "refine_every": 2, "stop_split_at": CHOICE, "sh_degree_interval": 2,
               "sh_budget_db": 0.003, **model}
    for key, value in options.items():
        setattr(config.pipeline.model, key, value)
    return config


def _mixed_choice(model, pipeline, budget_db):
    """Degrees 0-3 in turn over the rows (with their measured refits): on four frames after 8 steps every
    Gaussian's colour is its DC refit, so the measured choice puts all at one degree; the packing needs a mix."""
    from geer_ns.sh_degrees.choice import Choice, band_errors

    fits = band_errors(model, pipeline).fits
    return Choice((torch.arange(model.num_points) % 4).to(torch.uint8), 3, 0.0, 0.0, 1, fits)


def _degrees(ckpt):
    return ckpt["pipeline"]["_model._extra_state"]["strategy_state"].get("sh_degree")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, single_thread):
    out = tmp_path_factory.mktemp("sh_ckpt")
    data = copy_room(out / "data", 4, n_eval=1)
    first_config = _config(data, out, "first", 12)
    first_config.save_config()  # for geer-export / eval_setup
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("geer_ns.sh_degrees.choice.choose", _mixed_choice)
        first = train_in_process(first_config)
    resumed = train_in_process(_config(data, out, "resumed", 3, load_dir=first.parent))
    old_config = _config(data, out, "old", 6, sh_per_gaussian=False)  # the format before per-Gaussian degrees
    for group in ("means", "scales", "quats", "features_dc", "features_rest", "opacities"):
        old_config.optimizers[group]["optimizer"] = AdamOptimizerConfig(
            lr=old_config.optimizers[group]["optimizer"].lr, eps=1e-15)
    old = train_in_process(old_config)
    old_resumed = train_in_process(_config(data, out, "old_resumed", 6, load_dir=old.parent))
    load = lambda p: torch.load(p, map_location="cpu")  # noqa: E731
    return {"first": load(first), "resumed": load(resumed), "old": load(old), "old_resumed": load(old_resumed),
            "first_path": first, "first_config": first_config}


def test_checkpoint_holds_each_gaussians_kept_coefficients_only(runs):
    ckpt = runs["first"]
    degrees = _degrees(ckpt)
    assert degrees is not None and degrees.dtype == torch.uint8
    counts = torch.bincount(degrees.long(), minlength=4)
    n = len(degrees)
    assert int((counts > n // 10).sum()) >= 2, counts  # mixed degrees
    packed = ckpt["pipeline"][REST]
    assert packed.shape == (int(((degrees.long() + 1) ** 2 - 1).sum()), 3) and packed.shape[0] < 15 * n
    moments = ckpt["optimizers"]["features_rest"]["state"][0]
    assert moments["exp_avg"].shape == moments["exp_avg_sq"].shape == packed.shape
    dense = unpacked_checkpoint({**ckpt, "pipeline": dict(ckpt["pipeline"]),
                                 "optimizers": {k: {**v, "state": {i: dict(e) for i, e in v["state"].items()}}
                                                for k, v in ckpt["optimizers"].items()}}, 15)
    sizes = []
    for state in (ckpt, dense):
        buffer = io.BytesIO()
        torch.save(state, buffer)
        sizes.append(buffer.tell())
    assert dense["pipeline"][REST].shape == (n, 15, 3) and sizes[0] < sizes[1]


def test_a_loaded_model_is_dense_with_the_dropped_bands_zero(runs):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(runs["first_config"].get_base_dir() / "config.yml", test_mode="inference")
    model = pipeline.model
    rest = model.gauss_params["features_rest"].detach()
    degrees = model.strategy_state["sh_degree"]
    assert torch.equal(degrees, _degrees(runs["first"]))
    assert bool((rest[~kept(degrees, 15)] == 0).all())
    assert torch.equal(pack(rest, degrees), runs["first"]["pipeline"][REST])


def test_a_packed_checkpoint_resumes(runs):
    first, resumed = runs["first"], runs["resumed"]
    assert resumed["step"] == first["step"] + 3
    assert torch.equal(_degrees(resumed), _degrees(first))  # no densification after the choice: the same rows
    assert resumed["pipeline"][REST].shape == first["pipeline"][REST].shape
    assert not torch.equal(resumed["pipeline"][REST], first["pipeline"][REST])  # the kept bands trained on
    step = lambda c: float(c["optimizers"]["features_rest"]["state"][0]["step"])  # noqa: E731
    assert step(resumed) == step(first) + 3


def test_a_checkpoint_from_before_per_gaussian_degrees_resumes(runs):
    old, resumed = runs["old"], runs["old_resumed"]
    assert old["pipeline"][REST].dim() == 3 and _degrees(old) is None  # dense, no degrees: the former format
    assert resumed["step"] == old["step"] + 6 == CHOICE  # the resumed run ends at step 11 and chooses there
    degrees = _degrees(resumed)
    assert degrees is not None and resumed["pipeline"][REST].shape[0] == int(((degrees.long() + 1) ** 2 - 1).sum())


def test_geer_export_writes_the_highest_kept_degree(runs, tmp_path):
    from plyfile import PlyData

    from geer_ns.export.cli import ExportConfig, export

    metadata = export(ExportConfig(load_config=runs["first_config"].get_base_dir() / "config.yml",
                                   output_dir=tmp_path, formats=["ply"], ewa_views=0))
    degrees = _degrees(runs["first"])
    top = int(degrees.max())
    assert metadata["sh_degree"] == top and metadata["sh_degree_counts"] == torch.bincount(
        degrees.long(), minlength=4).tolist()
    vertex = PlyData.read(str(tmp_path / "splat.ply"))["vertex"]
    assert sum(p.name.startswith("f_rest_") for p in vertex.properties) == 3 * ((top + 1) ** 2 - 1)
