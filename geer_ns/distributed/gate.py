"""The step gate: processes meet at the start of every training step on the rendezvous store, not in a collective.

A collective waits for a late process only until the process group's timeout, and on NCCL its watchdog then
tears every process down in pages of logs. A process that is late for a good reason (rank 0 paused in the
viewer, evaluating or saving while the others go on) must not look like one that died. So each step starts
at this gate: a process announces its arrival on the store and waits there, polling, until every process has
arrived. While it waits it watches the others through the store:

- a process on the same machine whose process has ended is named at once; on another machine, every process
  beats a counter from a thread (`beat_s`), and a counter that stops for `dead_after_s` means the process died
  or froze: one error naming it;
- a late process that says it is paused, evaluating or saving is waited for without limit (it beats);
- a late process that says it is training and does not arrive within `timeout_s` is stuck: one error naming it.

The collectives of a step then start with every process present, so they never wait for long. Cost: one store
increment and a few reads per step (tens of microseconds on a local store).
"""

from __future__ import annotations

import os
import socket
import threading
import time
from typing import Dict, Optional

WAITING_STATES = ("paused", "evaluating", "saving")  # a late process in one of these is waited for, without limit

_STORE = None  # the rendezvous store of this process's run, registered by launch.distributed_worker


class GateError(RuntimeError):
    """Another process stopped answering or did not reach a step in time (the message names it)."""


def use_store(store) -> None:
    """Register the run's rendezvous store (a torch.distributed Store) for the trainer's gate."""
    global _STORE
    _STORE = store


def registered_store():
    return _STORE


class StepGate:
    """Each process's side of the gate over `store` (keys under a prefix of their own: see module docstring).

    Args:
        store: a torch.distributed Store every process of the run reaches (TCPStore: thread-safe).
        rank, size: this process and the number of processes.
        timeout_s: how long a late process that says it is training is waited for.
        beat_s: the heartbeat period; dead_after_s: a heartbeat silent this long is a dead process.
    """

    def __init__(self, store, rank: int, size: int, timeout_s: float, beat_s: float = 1.0,
                 dead_after_s: Optional[float] = None):
        import torch.distributed as dist

        self.store = dist.PrefixStore("geer-gate/", store)
        self.rank, self.size, self.timeout_s, self.beat_s = rank, size, float(timeout_s), float(beat_s)
        self.dead_after_s = float(dead_after_s) if dead_after_s is not None else max(10 * beat_s,
                                                                                   min(self.timeout_s, 120.0))
        self.passed = 0  # gates this process has passed
        self.waited_s = 0.0  # time spent waiting at the gate (all steps)
        self._stop = threading.Event()
        self._beats: Dict[int, tuple] = {}  # peer -> (last count, when it last changed: monotonic)
        self.set_state("training")
        self.store.set(f"where/{rank}", f"{socket.gethostname()} {os.getpid()}")
        self.store.add(f"beat/{rank}", 1)
        self._thread = threading.Thread(target=self._beat, name=f"geer-gate-beat-{rank}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(self.beat_s):
            try:
                self.store.add(f"beat/{self.rank}", 1)
            except Exception:  # noqa: BLE001 - the store is gone: the main thread will say why
                return

    def set_state(self, state: str) -> None:
        """What this process is doing ("training", or one of WAITING_STATES), for those waiting on it."""
        self.store.set(f"state/{self.rank}", state)

    def close(self) -> None:
        self._stop.set()

    def wait(self, step: int) -> None:
        """Arrive for `step` and return once every process has arrived; GateError when one is dead or stuck."""
        self.set_state("training")
        self.passed += 1
        self.store.add(f"arrived/{self.rank}", 1)
        total = self.store.add("arrivals", 1)
        want = self.size * self.passed
        if total >= want:
            return
        start = time.monotonic()
        late_since: Dict[int, float] = {}
        nap, next_check = 1e-4, start + self.beat_s
        while self.store.add("arrivals", 0) < want:
            time.sleep(nap)
            nap = min(nap * 2, 0.02)
            now = time.monotonic()
            if now >= next_check:
                next_check = now + self.beat_s
                self._check_peers(step, now, late_since)
        self.waited_s += time.monotonic() - start

    def _check_peers(self, step: int, now: float, late_since: Dict[int, float]) -> None:
        for peer in range(self.size):
            if peer == self.rank or self.store.add(f"arrived/{peer}", 0) >= self.passed:
                continue
            host, pid = self.store.get(f"where/{peer}").decode().rsplit(" ", 1)
            if host == socket.gethostname() and not _process_alive(int(pid)):
                raise GateError(f"rank {peer} stopped answering (its process {pid} has ended)")
            count = self.store.add(f"beat/{peer}", 0)
            last, changed = self._beats.get(peer, (None, now))
            if count != last:
                self._beats[peer] = (count, now)
            elif now - changed > self.dead_after_s:
                raise GateError(f"rank {peer} stopped answering ({now - changed:.0f} s without a heartbeat: its "
                                f"process died or froze)")
            state = self.store.get(f"state/{peer}").decode()
            if state in WAITING_STATES:
                late_since.pop(peer, None)  # a pause or an evaluation restarts the clock
                continue
            since = late_since.setdefault(peer, now)
            if now - since > self.timeout_s:
                raise GateError(f"rank {peer} did not reach step {step} within --machine.timeout-s "
                                f"{self.timeout_s:g} s (it is alive but stuck in its previous step)")


def _process_alive(pid: int) -> bool:
    """Whether process `pid` of this machine runs (a zombie, ended but not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True  # no /proc: os.kill's answer
