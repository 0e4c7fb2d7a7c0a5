"""Self-test verdicts: whether the compiled renderer agrees with the PyTorch renderer on this device.

The first time a process would render CUDA tensors with the kernels, `verify` runs the self-test suite
(geer_ns/selftest) in a CHILD process, so that an illegal memory access, an abort or a hang in the kernels
cannot take the user's run with it: the child builds or loads the extension, renders the suite forward and
backward with the kernels and the PyTorch renderer and writes a JSON report; the parent reads its exit and the
report. A child that crashes, is killed or does not finish in time is a failed verdict that says so.

Verdicts are kept on disk beside the extension cache ($GEER_SELFTEST_DIR, else <build root>/selftest), one per
(backend, device name, compute capability, driver, torch, extension build key): a new GPU, driver, torch or
csrc/ change runs the test again; anything else reuses it. `geer-doctor --selftest` reruns it on request.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from . import extensions

PACKAGE_ROOT = Path(__file__).resolve().parents[2]  # the folder holding geer_ns/: the child imports this copy
# Seconds the child may spend building or loading the extension, and then on the suite (environment
# variables GEER_SELFTEST_BUILD_TIMEOUT_S and GEER_SELFTEST_TIMEOUT_S).
BUILD_TIMEOUT_S, SUITE_TIMEOUT_S = 3600.0, 900.0
EXTENSION = {"cuda": "geer_cuda", "cpu": "geer_cpu_ops"}


@dataclass
class Verdict:
    """One self-test outcome: passed or not, why in one line, and where the full report is."""

    passed: bool
    reason: str
    report: str
    facts: dict
    seconds: float
    when: str

    def line(self) -> str:
        return f"{'passed' if self.passed else 'FAILED'}: {self.reason} (report: {self.report})"


def verdict_dir() -> Path:
    """Where verdicts and reports are kept: $GEER_SELFTEST_DIR, else beside the extension builds."""
    env = os.environ.get("GEER_SELFTEST_DIR")
    return Path(env) if env else extensions.build_root() / "selftest"


def _driver_version() -> str:
    try:
        return str(torch._C._cuda_getDriverVersion())  # noqa: SLF001 - no public accessor in torch
    except Exception:  # noqa: BLE001 - a missing or older accessor
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=20)
            return out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else "unknown"
        except Exception:  # noqa: BLE001
            return "unknown"


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def device_facts(backend: str, device: torch.device) -> dict:
    """What a verdict holds for: device name, compute capability, driver, torch, the extension's build key."""
    facts = {"backend": backend, "torch": torch.__version__, "build_key": extensions.configuration_key(EXTENSION[backend])}
    if backend == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        props = torch.cuda.get_device_properties(index)
        facts.update(device=props.name, capability=f"{props.major}.{props.minor}", driver=_driver_version(),
                     cuda=torch.version.cuda)
    else:
        facts.update(device=_cpu_name(), capability=torch.backends.cpu.get_cpu_capability(), driver="")
    return facts


def _key(facts: dict) -> str:
    return hashlib.sha256(json.dumps(facts, sort_keys=True).encode()).hexdigest()[:16]


def _paths(facts: dict) -> tuple[Path, Path]:
    stem = f"{facts['backend']}_{_key(facts)}"
    return verdict_dir() / f"{stem}.verdict.json", verdict_dir() / f"{stem}.report.json"


def cached_verdict(backend: str, device: torch.device) -> Verdict | None:
    """The recorded verdict for this device as it is now, or None when there is none."""
    path, _ = _paths(device_facts(backend, device))
    try:
        return Verdict(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None


_memo: dict[tuple[str, str], Verdict] = {}
_lock = threading.Lock()


def verify(backend: str, device: torch.device, *, rerun: bool = False) -> Verdict:
    """The verdict for `backend` ("cuda" or "cpu") on `device`: from this process's memo or the disk, or
    measured now in a child process (and recorded) when there is none or `rerun`."""
    memo_key = (backend, str(device))
    with _lock:
        if not rerun and memo_key in _memo:
            return _memo[memo_key]
        found = None if rerun else cached_verdict(backend, device)
        if found is None:
            from filelock import FileLock  # a torch dependency (extensions.py builds under it too)

            verdict_dir().mkdir(parents=True, exist_ok=True)
            # One child per verdict at a time: the ranks of a multi-GPU run start together, and the first one's
            # verdict serves the others (same GPU model, driver, torch and build).
            with FileLock(str(_paths(device_facts(backend, device))[0]) + ".lock"):
                found = None if rerun else cached_verdict(backend, device)
                found = found or run_child(backend, device)
        _memo[memo_key] = found
        return found


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(-code).name
    except ValueError:
        return f"signal {-code}"


def run_child(backend: str, device: torch.device) -> Verdict:
    """Run the suite in a child process and record the verdict (also of a crash or a hang)."""
    facts = device_facts(backend, device)
    verdict_path, report = _paths(facts)
    verdict_path.parent.mkdir(parents=True, exist_ok=True)
    progress = report.with_suffix(".progress")
    for stale in (report, progress):
        stale.unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(PACKAGE_ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    cmd = [sys.executable, "-m", "geer_ns.selftest", "--backend", backend, "--device", str(device), "--report",
           str(report), "--progress", str(progress)]
    start = time.perf_counter()
    log = report.with_suffix(".log")
    with open(log, "w") as out:
        child = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        hung = _wait(child, progress)
    seconds = time.perf_counter() - start
    reason = _outcome(child.returncode, hung, report, log)
    if not report.exists():
        report.write_text(json.dumps({"facts": facts, "cases": [], "outcome": reason}, indent=1))
    verdict = Verdict(child.returncode == 0 and not hung and reason.startswith("all "), reason, str(report), facts,
                      round(seconds, 1), time.strftime("%Y-%m-%d %H:%M:%S"))
    verdict_path.write_text(json.dumps(asdict(verdict), indent=1))
    return verdict


def _wait(child: subprocess.Popen, progress: Path) -> str:
    """Wait for the child; kill it (its whole process group) past the build or suite timeout. Returns '' or
    the phase it hung in."""
    phase_start, phase = time.monotonic(), "build"
    while child.poll() is None:
        try:
            lines = progress.read_text().split()
        except OSError:
            lines = []
        if lines and lines[-1] != phase:
            phase, phase_start = lines[-1], time.monotonic()
        limit = _timeout("GEER_SELFTEST_BUILD_TIMEOUT_S", BUILD_TIMEOUT_S) if phase == "build" else \
            _timeout("GEER_SELFTEST_TIMEOUT_S", SUITE_TIMEOUT_S)
        if time.monotonic() - phase_start > limit:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
            return f"{phase} ({limit:.0f} s)"
        time.sleep(0.05)
    return ""


def _timeout(name: str, default: float) -> float:
    return float(os.environ.get(name, "") or default)


def _outcome(code: int, hung: str, report: Path, log: Path) -> str:
    """One line on how the child ended."""
    if hung:
        return f"the self-test did not finish its {hung} and was stopped"
    try:
        data = json.loads(report.read_text())
    except (OSError, ValueError):
        data = None
    if code < 0:
        running = f" in case {data['running']}" if data and data.get("running") else ""
        return f"the self-test crashed ({_signal_name(code)}{running})"
    if data is None:
        tail = [line for line in log.read_text(errors="replace").splitlines() if line.strip()][-1:] if log.exists() else []
        return f"the self-test exited with status {code} and no report ({tail[0][:160] if tail else 'no output'})"
    if data.get("error"):
        return f"the self-test could not run: {data['error']}"
    cases = data.get("cases", [])
    failed = [c for c in cases if not c["passed"]]
    if failed or code != 0:
        first = failed[0] if failed else None
        what = f"{first['case']}: {', '.join(first['failed'])}" if first else f"exit status {code}"
        return f"{len(failed)} of {len(cases)} self-test cases failed against the PyTorch renderer ({what})"
    return f"all {len(cases)} self-test cases agree with the PyTorch renderer"
