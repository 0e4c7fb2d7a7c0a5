"""A plugin changes nothing for the host's other methods: nerfstudio's plugin discovery imports geer, and after it
torch.multiprocessing.spawn, sys.excepthook, PATH, the warning filters, splines and torch's safe globals are what
the same discovery leaves without geer's entry points; `ns-train splatfacto --help` prints the same text (but for
geer's dataparsers, listed for every method); a geer
run installs its fixes (geer_ns/compat.py, errors.py, distributed/launch.py) and then they are in place."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# One fresh interpreter: the host's state before discovery, after it (geer imported as ns-train imports it), after
# splatfacto's --help, and after a geer config is made ready to launch (what ns-train's main calls first).
PROBE = r"""
import contextlib, importlib.metadata, io, json, os, sys, warnings
import torch, torch.multiprocessing as mp

if sys.argv[1] == "without-geer":  # the same environment with geer's entry points hidden from discovery
    listed = importlib.metadata.entry_points
    def entry_points(**params):
        found = listed(**params)
        if not params:  # every group (fsspec asks so): not a plugin registry
            return found
        return importlib.metadata.EntryPoints(e for e in found if not e.value.startswith("geer_ns"))
    importlib.metadata.entry_points = entry_points

def name(fn):
    return f"{fn.__module__}.{fn.__qualname__}"

def state():
    import splines.quaternion as sq
    add = getattr(torch.serialization, "get_safe_globals", lambda: [])
    # The filters on the host's own warnings (other packages geer imports add filters of their own).
    host = [repr(f) for f in warnings.filters if f[1] is not None and any(
        word in f[1].pattern for word in ("jit", "custom_", "GradScaler", "Converting a tensor"))]
    return {"spawn": name(mp.spawn), "excepthook": name(sys.excepthook), "path": os.environ.get("PATH"),
            "host_filters": host, "spline": name(sq.KochanekBartels.__init__), "safe_globals": len(add())}

def help_of(method):
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        tyro.cli(AnnotatedBaseConfigUnion, args=[method, "--help"])
    return out.getvalue()

from nerfstudio.configs.method_configs import all_methods  # nerfstudio's discovery: imports geer_ns.config
assert ("geer" in all_methods) == (sys.argv[1] == "with-geer"), sorted(all_methods)
found = {"discovered": state(), "splatfacto_help": help_of("splatfacto")}
found["after_help"] = state()
if "geer" in all_methods:
    all_methods["geer"].set_timestamp()  # ns-train's main, before it launches a geer run
    found["after_geer"] = state()
print(json.dumps(found))
"""


def probe(which: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("PYTHONWARNINGS", None)
    return subprocess.Popen([sys.executable, "-c", PROBE, which], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_discovery_changes_nothing_until_a_geer_run_starts():
    running = {which: probe(which) for which in ("with-geer", "without-geer")}  # together: they share the cores
    found = {}
    for which, proc in running.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-3000:]
        found[which] = json.loads(out.strip().splitlines()[-1])
    geer, plain = found["with-geer"], found["without-geer"]
    assert geer["discovered"] == plain["discovered"], "importing the plugin changed the host"
    # The same help, but for the dataparsers geer registers, which nerfstudio offers to every method.
    listed = re.sub(r",geer-(?:nerfstudio|colmap)(?=[,}])", "", geer["splatfacto_help"])
    listed = [line for line in listed.splitlines() if line.strip() not in ("• geer-nerfstudio", "• geer-colmap")]
    assert listed == plain["splatfacto_help"].splitlines() and len(listed) > 100
    assert geer["after_help"] == plain["discovered"], "ns-train splatfacto --help changed the host"
    after = geer["after_geer"]
    # A geer run: its launcher router, its one-line dataset errors, its warning filters and the spline fix.
    for key in ("spawn", "excepthook", "host_filters", "spline", "safe_globals"):
        assert after[key] != plain["discovered"][key], key
