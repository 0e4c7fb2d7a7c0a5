"""Every command README.md and docs/*.md show works as written: each fenced bash line and each inline
`.venv/bin/...` / `python -m geer_ns...` / `bash scripts/...` command is found, its program is installed (a console
script of this environment, a geer module or a file of the repository), and its `--help` (with the command's own
sub-commands, e.g. `ns-train geer`, `ns-render dataset`) exits 0. All --help calls run in one fresh interpreter,
which imports nerfstudio once."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
INLINE = re.compile(r"`((?:\.venv/bin/|bash scripts/|python -m geer_ns)[^`]+)`")


def shown_commands() -> list[tuple[str, list[str]]]:
    """(page, argv) of every command the pages show, placeholders and all."""
    found = []
    for page in PAGES:
        text = page.read_text()
        blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
        lines = [line for block in blocks for line in block.replace("\\\n", " ").splitlines()]
        lines += INLINE.findall(re.sub(r"```.*?```", "", text, flags=re.S))
        for line in lines:
            line = line.split(" #")[0].strip()
            line = re.sub(r"^\w+=\$\((.*)\)$", r"\1", line)  # VAR=$(command ...): the command
            if re.fullmatch(r"(export )?\w+=\S*", line):  # a plain shell assignment runs nothing
                continue
            if line and not line.startswith("#"):
                found.append((page.name, shlex.split(line.replace("<", "").replace(">", ""))))
    return found


def help_call(argv: list[str]) -> tuple[str, list[str]]:
    """(program, argv of its --help): the program and the sub-commands that lead its arguments."""
    words = [w for w in argv if "=" not in w or w.startswith("-")]
    if words[0].startswith("GEER_"):
        words = words[1:]
    if words[0] == ".venv/bin/python" and words[1] == "-m":
        program, rest = f"-m {words[2]}", words[3:]
    elif words[0] == ".venv/bin/python":
        program, rest = words[1], words[2:]
    elif words[0] == "python" and words[1] == "-m":
        program, rest = f"-m {words[2]}", words[3:]
    else:
        program, rest = words[0].removeprefix(".venv/bin/"), words[1:]
    subcommands = []
    for word in rest:
        if word.startswith("-"):
            break
        subcommands.append(word)
    return program, subcommands + ["--help"]


RUNNER = r"""
import contextlib, importlib.metadata, io, json, runpy, subprocess, sys
scripts = {e.name: e for e in importlib.metadata.entry_points(group="console_scripts")}
results = {}
for key, (program, argv) in json.loads(sys.argv[1]).items():
    out = io.StringIO()
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            sys.argv = [program, *argv]
            if program.startswith("-m "):  # its own interpreter: tyro reads a dataclass's module as __main__
                done = subprocess.run([sys.executable, "-m", program[3:], *argv], capture_output=True, text=True)
                print(done.stdout + done.stderr)
                code = done.returncode
            elif program.endswith(".py"):
                runpy.run_path(program, run_name="__main__")
            else:
                scripts[program].load()()
    except SystemExit as exit:
        code = exit.code if isinstance(exit.code, int) else (0 if exit.code is None else 1)
    except Exception as error:  # noqa: BLE001 - reported to the test
        code, out = 1, io.StringIO(repr(error))
    results[key] = [code, out.getvalue()[-600:]]
print("RESULTS " + json.dumps(results))
"""


def test_every_shown_command_exists_and_answers_help():
    calls, missing = {}, []
    for page, argv in shown_commands():
        if argv[0] == "bash":
            if not (ROOT / argv[1]).is_file():
                missing.append(f"{page}: {' '.join(argv)}: no file {argv[1]}")
            continue
        program, help_argv = help_call(argv)
        calls[f"{program} {' '.join(help_argv)}"] = (program, help_argv)
    assert len(calls) >= 8, sorted(calls)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", RUNNER, json.dumps(calls)], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=600)
    line = next((l for l in result.stdout.splitlines() if l.startswith("RESULTS ")), None)
    assert line is not None, result.stderr[-3000:]
    for key, (code, output) in json.loads(line[len("RESULTS "):]).items():
        if code != 0:
            missing.append(f"{key}: exit {code}: {output}")
    assert not missing, "\n".join(missing)


def test_every_benchmark_the_pages_name_exists():
    """Benchmark commands are not run for --help (some have no options and would run): their scripts must exist."""
    named = set()
    for page in [*PAGES, *sorted((ROOT / "benchmarks").glob("*.py"))]:
        text = page.read_text()
        named |= {(page.name, f"benchmarks/{m}.py") for m in re.findall(r"python -m benchmarks\.(\w+)", text)}
        named |= {(page.name, f"benchmarks/{s}") for s in re.findall(r"benchmarks/(\w+\.(?:sh|py))\b", text)}
    missing = [f"{page}: {path}" for page, path in sorted(named) if "/NAME." not in path
               and not (ROOT / path).is_file()]
    assert len(named) >= 10 and not missing, missing
