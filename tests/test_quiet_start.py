"""A quiet, honest start: geer's options first in --help, splatfacto options geer ignores marked (and said when
set), known host warnings filtered, a COLMAP dataset read once for both splits."""

from __future__ import annotations

import re
import warnings
from dataclasses import fields
from pathlib import Path

import pytest
import torch

from geer_ns import compat
from geer_ns.data import colmap_parser
from geer_ns.data.datamanager import GeerDataManagerConfig, GeerDataOptions
from geer_ns.model import GeerModelConfig
from geer_ns.options import IGNORED_OPTIONS, OWN_OPTIONS_HELP, GeerOwnOptions
from nerfstudio.models.base_model import ModelConfig

from test_nerfstudio_model import make_model

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "t265_colmap"


def ns_train(*args: str):
    """ns-train's own tyro call (the union of all methods), in process."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    return tyro.cli(AnnotatedBaseConfigUnion, args=list(args))


def method_help(method: str) -> str:
    """`ns-train METHOD --help` with the box drawing removed."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        ns_train(method, "--help")
    return re.sub(r"[│╭╮╰╯─]", " ", out.getvalue())


@pytest.fixture(scope="module")
def help_text():
    return method_help("geer")


def test_help_lists_geers_own_options_before_any_other(help_text):
    words = " ".join(help_text.split())
    first_option = words.index("--output-dir")
    assert words.index("--pipeline.model.renderer-backend") < first_option
    assert words.index("--pipeline.datamanager.supervision") < first_option
    assert " ".join(OWN_OPTIONS_HELP.split())[:60] in words


def listed_options(text: str) -> list:
    """The option flags of a help text, in the order they are listed (each starts a line)."""
    return re.findall(r"^\s*(--[\w.-]+)", text, re.M)


def _flags(prefix: str, names) -> list:
    return [f"--{prefix}.{name.replace('_', '-')}" for name in names]


@pytest.mark.parametrize("method", ["geer", "geer-mcmc"])
def test_help_lists_geers_own_options_first_in_their_groups(method, help_text):
    """tyro lists a dataclass's fields base class first; geer's own options come from a base listed last
    (GeerOwnOptions, GeerDataOptions), so they come before every inherited splatfacto / nerfstudio option."""
    listed = listed_options(help_text if method == "geer" else method_help(method))
    for prefix, own, config in (("pipeline.model", GeerOwnOptions, GeerModelConfig),
                                ("pipeline.datamanager", GeerDataOptions, GeerDataManagerConfig)):
        own_names = [f.name for f in fields(own)]
        group = [flag for flag in listed if flag.startswith(f"--{prefix}.") and flag.count(".") == prefix.count(".") + 1]
        assert group[: len(own_names)] == _flags(prefix, own_names), group
        inherited = set(_flags(prefix, [f.name for f in fields(config) if f.name not in own_names]))
        assert len(inherited & set(group)) > 10 and set(group[len(own_names):]) <= inherited


def test_help_hides_the_ray_marching_options_no_gaussian_model_reads(help_text):
    listed = listed_options(help_text)
    defaults, nerfstudio = GeerModelConfig(), ModelConfig()
    hidden = ("enable_collider", "collider_params", "loss_coefficients", "eval_num_rays_per_chunk", "prompt")
    for name, flag in zip(hidden, _flags("pipeline.model", hidden)):
        assert not [f for f in listed if f == flag or f.startswith(flag + ".")], flag
        assert getattr(defaults, name) == getattr(nerfstudio, name), name  # defaults stay nerfstudio's


def test_every_flag_the_project_uses_still_parses(help_text):
    """Flags in README, scripts and configs, plus the ignored splatfacto ones (splatfacto command lines)."""
    root = Path(__file__).resolve().parents[1]
    texts = [root / "README.md", *root.glob("scripts/*"), *root.glob("configs/*")]
    used = {flag for path in texts if path.is_file() for flag in re.findall(r"--pipeline\.[a-z.-]*[a-z]", path.read_text())}
    listed = set(listed_options(help_text))
    model_or_manager = [f for f in used if ".dataparser." not in f]
    assert model_or_manager and all(f in listed for f in model_or_manager), sorted(used)
    config = ns_train("geer", "--pipeline.model.rasterize-mode", "antialiased", "--pipeline.model.use-absgrad", "True",
                      "--pipeline.model.renderer-backend", "torch", "--pipeline.datamanager.supervision", "native")
    model = config.pipeline.model
    assert (model.rasterize_mode, model.use_absgrad, model.renderer_backend) == ("antialiased", True, "torch")
    assert config.pipeline.datamanager.supervision == "native" and ns_train("geer-mcmc").pipeline.model.strategy == "mcmc"


def test_help_marks_the_splatfacto_options_geer_ignores(help_text):
    blocks = re.split(r"\n\s*(?=--)", help_text)
    for name in IGNORED_OPTIONS:
        flag = "--pipeline.model." + name.replace("_", "-")
        block = next(b for b in blocks if b.strip().startswith(flag + " "))
        assert "IGNORED by geer" in " ".join(block.split()), flag


def test_setting_an_ignored_option_is_said_once(capsys):
    make_model(rasterize_mode="antialiased", n_split_samples=3)
    printed = " ".join(capsys.readouterr().out.split())
    assert "ignoring splatfacto option(s) rasterize_mode='antialiased', n_split_samples=3" in printed
    make_model()
    assert "ignoring" not in capsys.readouterr().out


def test_known_host_warnings_are_filtered_and_others_are_not():
    """In a geer run, each known message is filtered only from the host module that raises it (whether importing
    geer leaves the filters alone: tests/test_plugin_scope.py)."""
    compat.quiet_known_warnings()
    known = (
        (FutureWarning, "`torch.jit.script` is deprecated. Please switch to `torch.compile` or `torch.export`.",
         "torch.jit._script"),
        (FutureWarning, "`torch.cuda.amp.custom_fwd(args...)` is deprecated. Please use ...",
         "nerfstudio.field_components.activations"),
        (FutureWarning, "`torch.cuda.amp.custom_bwd(args...)` is deprecated. Please use ...",
         "nerfstudio.field_components.activations"),
        (FutureWarning, "`torch.cuda.amp.GradScaler(args...)` is deprecated. Please use ...", "nerfstudio.engine.trainer"),
        (UserWarning, "Converting a tensor with requires_grad=True to a scalar may lead to unexpected behavior.",
         "nerfstudio.utils.writer"),
    )
    with warnings.catch_warnings(record=True) as caught:
        for category, message, module in known:
            warnings.warn_explicit(message, category, "host.py", 1, module=module)
            warnings.warn_explicit(message, category, "mine.py", 1, module="geer_ns.somewhere")  # shown
        warnings.warn_explicit("something else is deprecated", FutureWarning, "host.py", 1,
                               module="nerfstudio.field_components.activations")  # shown
    assert [str(w.message) for w in caught] == [m for _, m, _ in known] + ["something else is deprecated"]


def test_colmap_dataset_is_read_once_for_both_splits(monkeypatch):
    calls = []
    original = colmap_parser._read_reconstruction
    monkeypatch.setattr(colmap_parser, "_read_reconstruction", lambda d: calls.append(d) or original(d))
    parser = colmap_parser.GeerColmapDataParserConfig(data=FIXTURE).setup()
    train = parser.get_dataparser_outputs("train")
    val = parser.get_dataparser_outputs("val")
    assert len(calls) == 1
    assert len(train.image_filenames) == 5 and len(val.image_filenames) == 1
    assert not set(train.image_filenames) & set(val.image_filenames)


def test_nerfstudio_dataset_is_checked_and_parsed_once_for_both_splits(monkeypatch):
    """ns-train's datamanager asks its dataparser once per split; geer's parser reads, checks and parses
    transforms.json once and gives each split its part (the same files and cameras nerfstudio gives)."""
    from nerfstudio.data.dataparsers import nerfstudio_dataparser
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig

    from geer_ns.data import dataset_checks, nerfstudio_parser
    from geer_ns.data import datamanager as dm
    from geer_ns.data.synthetic_room import default_scene_dir

    calls = {"check": 0, "json": 0, "parse": 0}

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapper

    monkeypatch.setattr(nerfstudio_parser, "check_transforms_json", counted("check", nerfstudio_parser.check_transforms_json))
    monkeypatch.setattr(dataset_checks, "_load_json", counted("json", dataset_checks._load_json))
    monkeypatch.setattr(nerfstudio_dataparser, "load_from_json", counted("json", nerfstudio_dataparser.load_from_json))
    monkeypatch.setattr(dm, "load_from_json", counted("json", dm.load_from_json))
    monkeypatch.setattr(Nerfstudio, "_generate_dataparser_outputs", counted("parse", Nerfstudio._generate_dataparser_outputs))
    config = dm.GeerDataManagerConfig(data=default_scene_dir(), cache_images="cpu")
    manager = config.setup(device="cpu", test_mode="val")
    assert isinstance(manager.dataparser, nerfstudio_parser.GeerNerfstudio)
    assert calls == {"check": 1, "json": 1, "parse": 1}
    assert len(manager.train_dataset) == 21 and len(manager.eval_dataset) > 0
    # Each split is what nerfstudio's own parser gives for it.
    monkeypatch.undo()
    for split, dataset in (("train", manager.train_dataset), ("val", manager.eval_dataset)):
        ref = NerfstudioDataParserConfig(data=default_scene_dir()).setup().get_dataparser_outputs(split)
        got = dataset._dataparser_outputs
        assert got.image_filenames == ref.image_filenames and got.mask_filenames == ref.mask_filenames
        assert torch.equal(got.cameras.camera_to_worlds, ref.cameras.camera_to_worlds)
        assert torch.equal(got.cameras.fx, ref.cameras.fx) and torch.equal(got.dataparser_transform, ref.dataparser_transform)
