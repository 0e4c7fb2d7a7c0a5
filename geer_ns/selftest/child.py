"""The self-test child: `python -m geer_ns.selftest --backend {cuda,cpu} --device D --report R --progress P`.

Run by geer_ns/render/verdict.py in a process of its own. Writes the phase it is in to P ("build", then
"suite") and the report R (JSON: facts, one entry per case, the case running) after every case, so that a
crash leaves the cases before it and the one it died in. Exit status 0 when every case passed.

Planted faults for tests ($GEER_SELFTEST_FAULT): "crash" aborts the child once the extension is loaded,
"hang" sleeps past any timeout, "raise" makes the first case raise, "wrong" perturbs the compiled renderer's
image in the first case.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

from geer_ns.render import extensions
from geer_ns.render.verdict import device_facts

from .suite import run_case, suite


def _write(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m geer_ns.selftest", description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=("cuda", "cpu"), required=True)
    parser.add_argument("--device", default=None)
    parser.add_argument("--report", type=Path, required=True)
    parser.add_argument("--progress", type=Path, default=None)
    args = parser.parse_args(argv)
    device = torch.device(args.device or args.backend)
    report = {"facts": {}, "cases": [], "running": "", "error": ""}

    def phase(name: str) -> None:
        if args.progress is not None:
            with open(args.progress, "a") as f:
                f.write(name + "\n")

    phase("build")
    try:
        report["facts"] = device_facts(args.backend, device)
        (extensions.load_extension if args.backend == "cuda" else extensions.load_cpu_ops)()
    except Exception as exc:  # noqa: BLE001 - reported, the parent falls back
        report["error"] = f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}"
        _write(args.report, report)
        return 2
    phase("suite")
    fault = os.environ.get("GEER_SELFTEST_FAULT", "")
    if fault == "crash":
        os.abort()
    if fault == "hang":
        time.sleep(3600)
    if args.backend == "cpu":
        torch.set_num_threads(min(4, torch.get_num_threads()))
    for k, case in enumerate(suite(device.type)):
        report["running"] = case.name
        _write(args.report, report)
        try:
            if fault == "raise" and k == 0:
                raise RuntimeError("planted fault")
            result = run_case(case, args.backend, device, perturb=1e-3 if fault == "wrong" and k == 0 else 0.0)
        except Exception as exc:  # noqa: BLE001 - a launch error, no kernel image for this GPU, ...: a failed case
            line = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
            result = {"case": case.name, "passed": False, "checks": {}, "failed": [f"raised {type(exc).__name__}: {line}"],
                      "seconds": 0.0}
        report["cases"].append(result)
        print(f"{'ok  ' if result['passed'] else 'FAIL'} {case.name} ({result['seconds']} s)"
              + ("" if result["passed"] else f": {', '.join(result['failed'])}"), flush=True)
    report["running"] = ""
    _write(args.report, report)
    return 0 if all(c["passed"] for c in report["cases"]) else 1
