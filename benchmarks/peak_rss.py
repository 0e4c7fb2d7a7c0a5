"""Peak resident memory of this process, for measurements run in a fresh subprocess.

torch has no CPU allocator statistics; RSS sees everything (autograd's saved tensors included). The peak
(VmHWM) is reset to the current RSS just before the measured work, so what importing torch touched does
not hide it. Used by benchmarks/bench_camera_inside.py and tests/test_blend_memory.py.
"""

from __future__ import annotations

import resource


def status_kib(key: str) -> int | None:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    return None


def peak_reset() -> int:
    """Current RSS in KiB, with the peak reset to it (falls back to ru_maxrss, which over-, never
    under-estimates the growth)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return status_kib("VmRSS") or 0
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def peak_kib() -> int:
    return max(status_kib("VmHWM") or 0, 0)
