"""Builds of the extensions are cached per configuration (geer_ns/render/extensions.py): two configurations of
one extension get two folders and, once built, load without a rebuild, in any order and in a new process; a
build says so before it starts and when it ends.

The two configurations are of a tiny pybind11 module (one define apart, seconds to build) going through the
same build_and_load as csrc/; the real CPU build is checked to live in the folder of its own key.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from geer_ns.render import extensions

ROOT = Path(__file__).resolve().parents[1]
TOY = """
#include <pybind11/pybind11.h>
#ifndef GEER_TOY_VALUE
#define GEER_TOY_VALUE 0
#endif
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("value", [] { return GEER_TOY_VALUE; }); }
"""


def _flags(value: int) -> list[str]:
    return ["-O0", f"-DGEER_TOY_VALUE={value}"]


def _python_by_another_path(tmp: Path) -> str:
    """This interpreter through a symlink to its virtual environment (as one venv is reached from two checkouts),
    so that torch's own paths differ; the interpreter itself where there is no venv."""
    if sys.prefix == sys.base_prefix:
        return sys.executable
    link = tmp / "venv_link"
    link.symlink_to(Path(sys.prefix), target_is_directory=True)
    python = link / Path(sys.executable).relative_to(sys.prefix)
    probe = subprocess.run([str(python), "-c", "import torch; print(torch.__file__)"], capture_output=True, text=True)
    assert probe.stdout.startswith(str(link)), probe.stdout + probe.stderr
    return str(python)


@pytest.fixture
def toy(tmp_path, monkeypatch):
    src = tmp_path / "src"
    src.mkdir()
    (src / "toy.cpp").write_text(TOY)
    (src / "toy.h").write_text("// a header: part of the key\n")
    monkeypatch.setenv("GEER_EXT_DIR", str(tmp_path / "ext"))
    return src / "toy.cpp"


def test_the_key_follows_sources_headers_and_flags(toy):
    key = lambda flags: extensions.build_key([toy], toy.parent, flags, [], False)  # noqa: E731
    first = key(_flags(1))
    assert key(_flags(1)) == first and key(_flags(2)) != first
    (toy.parent / "toy.h").write_text("// changed\n")
    assert key(_flags(1)) != first
    assert len(first) == 16


def test_two_configurations_build_once_and_then_only_load(toy, capfd):
    a = extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=_flags(1))
    b = extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=_flags(2))
    assert (a.value(), b.value()) == (1, 2)
    said = capfd.readouterr().err
    assert said.count("geer: building geer_toy (first use of this configuration") == 2
    assert said.count("geer: built geer_toy in ") == 2
    folders = sorted(p for p in (toy.parent.parent / "ext").iterdir())
    assert [p.name.rsplit("_", 1)[0] for p in folders] == ["geer_toy", "geer_toy"]
    built = {p: os.stat(p).st_mtime_ns for f in folders for p in f.iterdir() if p.suffix in (".so", ".o")}
    assert len(built) == 4
    # A new process loads both, B first: nothing is compiled again and nothing is announced, also where the
    # process reaches the same environment by another path (torch's include paths differ: its ninja rebuilt).
    code = textwrap.dedent(f"""
        from pathlib import Path
        from geer_ns.render import extensions
        toy = Path({str(toy)!r})
        for value in (2, 1):
            flags = ["-O0", f"-DGEER_TOY_VALUE={{value}}"]
            module = extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=flags)
            assert module.value() == value
        print("loaded")
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run([_python_by_another_path(toy.parent.parent), "-c", code], capture_output=True,
                            text=True, timeout=300, env=env)
    assert result.returncode == 0 and "loaded" in result.stdout, result.stderr[-3000:]
    assert "geer: build" not in result.stderr, result.stderr[-3000:]
    assert {p: os.stat(p).st_mtime_ns for p in built} == built


def test_the_cpu_build_lives_in_the_folder_of_its_key():
    ops = extensions.load_cpu_ops()
    sources = [extensions.CSRC / s for s in extensions._CPU_SOURCES]
    key = extensions.build_key(sources, extensions.CSRC, extensions.cpu_cflags(), [], False)
    assert Path(ops.__file__).parent == extensions.build_root() / f"geer_cpu_ops_{key}"
    assert key != extensions.build_key(sources, extensions.CSRC, extensions.cpu_cflags() + ["-DX"], [], False)


@pytest.fixture
def filebaton_torch(monkeypatch):
    """torch.utils.cpp_extension.load as torch up to 2.11 guards it: a FileBaton on the build folder's `lock`
    (created with O_EXCL, removed when the build ends; a build that finds the file waits until it is gone). The
    wait would last for ever with a file no one removes: here it raises instead (the GPU machine's torch 2.11
    hung there). Under such a torch, its own load. Returns the list of folders built."""
    from torch.utils import cpp_extension
    from torch.utils.file_baton import FileBaton

    real_load, built = cpp_extension.load, []
    if hasattr(cpp_extension, "FileBaton"):  # this torch takes the baton itself: no emulation, the real thing

        def load(*args, build_directory, **kwargs):
            built.append(Path(build_directory))
            return real_load(*args, build_directory=build_directory, **kwargs)

        monkeypatch.setattr(cpp_extension, "load", load)
        return built

    def load(*args, build_directory, **kwargs):
        baton = FileBaton(os.path.join(build_directory, "lock"))
        if not baton.try_acquire():
            raise AssertionError(f"torch <= 2.11 would wait for ever on {build_directory}/lock")
        try:
            built.append(Path(build_directory))
            return real_load(*args, build_directory=build_directory, **kwargs)
        finally:
            baton.release()

    monkeypatch.setattr(cpp_extension, "load", load)
    return built


def test_a_torch_with_a_filebaton_builds_and_loads(toy, filebaton_torch):
    """The check for a finished build leaves no file that torch's FileBaton takes for a build in progress."""
    module = extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=_flags(3))
    assert module.value() == 3 and len(filebaton_torch) == 1
    assert extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=_flags(3)).value() == 3
    assert len(filebaton_torch) == 1  # loaded, not built again


def test_a_stale_filebaton_of_a_killed_build_is_cleared(toy, filebaton_torch):
    """A build killed while torch held its FileBaton leaves `lock` behind; the next build goes ahead."""
    key = extensions.build_key([toy], toy.parent, _flags(4), [], False)
    folder = extensions.build_root() / f"geer_toy_{key}"
    folder.mkdir(parents=True)
    (folder / "lock").write_text("")  # what the killed build left
    assert extensions.build_and_load("geer_toy", [toy], cuda=False, cflags=_flags(4)).value() == 4
    assert filebaton_torch == [folder]
