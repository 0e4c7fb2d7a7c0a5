"""A quiet, honest start: geer's options first in --help, splatfacto options geer ignores marked (and said when
set), known host warnings filtered, a COLMAP dataset read once for both splits."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
import torch

from geer_ns import host_fixes
from geer_ns.data import colmap_parser
from geer_ns.model import IGNORED_OPTIONS, OWN_OPTIONS_HELP

from test_nerfstudio_model import make_model

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "t265_colmap"


@pytest.fixture(scope="module")
def help_text():
    """`ns-train geer --help`, in process (ns-train's own tyro union of all methods)."""
    import contextlib
    import io

    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        tyro.cli(AnnotatedBaseConfigUnion, args=["geer", "--help"])
    return re.sub(r"[│╭╮╰╯─]", " ", out.getvalue())


def test_help_lists_geers_own_options_before_any_other(help_text):
    words = " ".join(help_text.split())
    first_option = words.index("--output-dir")
    assert words.index("--pipeline.model.renderer-backend") < first_option
    assert words.index("--pipeline.datamanager.supervision") < first_option
    assert " ".join(OWN_OPTIONS_HELP.split())[:60] in words


def test_help_marks_the_splatfacto_options_geer_ignores(help_text):
    blocks = re.split(r"\n\s*(?=--)", help_text)
    for name in IGNORED_OPTIONS:
        flag = "--pipeline.model." + name.replace("_", "-")
        block = next(b for b in blocks if b.strip().startswith(flag + " "))
        assert "IGNORED by geer" in " ".join(block.split()), flag


def test_setting_an_ignored_option_is_said_once(capsys):
    make_model(rasterize_mode="antialiased", use_absgrad=True)
    printed = " ".join(capsys.readouterr().out.split())
    assert "ignoring splatfacto option(s) use_absgrad=True, rasterize_mode='antialiased'" in printed
    make_model()
    assert "ignoring" not in capsys.readouterr().out


def test_known_host_warnings_are_filtered_and_others_are_not():
    host_fixes.quiet_known_warnings()
    with warnings.catch_warnings(record=True) as caught:
        for category, message in (
            (FutureWarning, "`torch.cuda.amp.GradScaler(args...)` is deprecated. Please use ..."),
            (FutureWarning, "`torch.jit.script` is deprecated. Please switch to `torch.compile`"),
            (UserWarning, "Converting a tensor with requires_grad=True to a scalar may lead to unexpected behavior."),
        ):
            warnings.warn(message, category)
        torch.cuda.amp.GradScaler(enabled=False)  # nerfstudio's trainer does this on every run
        warnings.warn("something else is deprecated", FutureWarning)
    assert [str(w.message) for w in caught] == ["something else is deprecated"]


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
