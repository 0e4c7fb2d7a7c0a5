"""The step gate (geer_ns/distributed/gate.py) on a real TCPStore, its processes played by threads: a paused or
evaluating process is waited for past the timeout, a stuck or dead one is named within it."""

from __future__ import annotations

import os
import socket
import time
from datetime import timedelta

import pytest
import torch.distributed as dist

from conftest import start_in_thread
from geer_ns.distributed.gate import GateError, StepGate


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def stores():
    """Two clients of one store, as two processes of a run have (rank 0 hosts it)."""
    port = _free_port()
    host = dist.TCPStore("127.0.0.1", port, 2, is_master=True, timeout=timedelta(seconds=20), wait_for_workers=False)
    client = dist.TCPStore("127.0.0.1", port, 2, is_master=False, timeout=timedelta(seconds=20))
    yield host, client


def _gates(stores, timeout_s=0.6, beat_s=0.1, dead_after_s=0.6):
    return [StepGate(store, rank, 2, timeout_s, beat_s=beat_s, dead_after_s=dead_after_s)
            for rank, store in enumerate(stores)]


def _in_thread(fn):
    return start_in_thread(fn, daemon=True)


def test_processes_meet_at_each_step(stores):
    gates = _gates(stores)
    for step in range(5):
        thread, result = _in_thread(lambda: gates[1].wait(step))
        gates[0].wait(step)
        thread.join(5)
        assert not thread.is_alive() and "error" not in result
    assert gates[0].passed == gates[1].passed == 5
    for g in gates:
        g.close()


@pytest.mark.parametrize("state", ["paused", "evaluating", "saving"])
def test_a_paused_or_busy_process_is_waited_for_past_the_timeout(stores, state):
    gates = _gates(stores)
    gates[0].set_state(state)  # rank 0: paused in the viewer (or evaluating, saving), beating meanwhile
    started = time.monotonic()
    thread, result = _in_thread(lambda: gates[1].wait(0))
    time.sleep(3 * gates[1].timeout_s)
    assert thread.is_alive(), result  # still waiting, no error
    gates[0].wait(0)
    thread.join(5)
    assert "error" not in result and time.monotonic() - started >= 3 * gates[1].timeout_s
    assert gates[1].waited_s >= 3 * gates[1].timeout_s
    for g in gates:
        g.close()


def test_a_process_stuck_in_its_step_is_named_within_the_timeout(stores):
    gates = _gates(stores)
    started = time.monotonic()
    with pytest.raises(GateError, match=r"rank 1 did not reach step 7 within --machine.timeout-s 0.6 s"):
        gates[0].wait(7)  # rank 1 beats and says it is training, but never arrives
    assert time.monotonic() - started < gates[0].timeout_s + 3 * gates[0].beat_s + 1.0
    for g in gates:
        g.close()


def test_a_dead_process_is_named_even_while_it_said_it_was_paused(stores):
    gates = _gates(stores)
    gates[1].set_state("paused")
    gates[1].close()  # its heartbeat stops: the process died
    with pytest.raises(GateError, match=r"rank 1 stopped answering .* its process died or froze"):
        gates[0].wait(0)
    gates[0].close()


def test_geers_nccl_processes_raise_a_timed_out_collective_instead_of_the_watchdog_tearing_them_down(monkeypatch):
    """distributed_worker on a CUDA launch sets the two NCCL variables (the user's own settings win) before the
    process group starts, and hosts the store the gate uses. No GPU here: the process group start is replaced
    by a recorder and the worker stops at its first use of CUDA."""
    import torch
    import torch.distributed as dist

    from geer_ns.distributed import gate, launch

    seen = {}

    def record(**kwargs):
        seen.update(env={k: os.environ.get(k) for k in ("TORCH_NCCL_BLOCKING_WAIT", "TORCH_NCCL_ASYNC_ERROR_HANDLING")},
                    **kwargs)
        raise RuntimeError("recorded")

    environ = {k: v for k, v in os.environ.items() if k != "TORCH_NCCL_BLOCKING_WAIT"}
    environ["TORCH_NCCL_ASYNC_ERROR_HANDLING"] = "3"  # the user's choice
    monkeypatch.setattr(os, "environ", environ)  # the worker's settings stay in this test
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "set_device", lambda index: None)
    monkeypatch.setattr(dist, "init_process_group", record)

    class Config:
        class machine:
            timeout_s = 5.0

    with pytest.raises(SystemExit):
        launch.distributed_worker(0, None, 1, 1, 0, f"tcp://127.0.0.1:{_free_port()}", Config, timedelta(seconds=5),
                                  device_type="cuda")
    assert seen["env"] == {"TORCH_NCCL_BLOCKING_WAIT": "1", "TORCH_NCCL_ASYNC_ERROR_HANDLING": "3"}
    assert seen["backend"] == "nccl" and isinstance(seen["store"], dist.PrefixStore)
    gate.use_store(None)


def test_a_process_of_this_machine_that_ended_is_named_at_once(stores):
    import subprocess
    import sys

    gates = _gates(stores, timeout_s=30.0, dead_after_s=30.0)
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()
    gates[1].store.set("where/1", f"{socket.gethostname()} {ended.pid}")  # rank 1 was that process
    started = time.monotonic()
    with pytest.raises(GateError, match=rf"rank 1 stopped answering \(its process {ended.pid} has ended\)"):
        gates[0].wait(0)
    assert time.monotonic() - started < 5.0
    for g in gates:
        g.close()


def test_the_gate_needs_a_tcp_rendezvous():
    """rendezvous_store makes the gate's store for tcp://host:port only; other URLs get none (the trainer then
    says that the run has no gate)."""
    from geer_ns.distributed.launch import rendezvous_store

    for url in ("file:///tmp/geer-rendezvous", "env://"):
        assert rendezvous_store(url, 1, 0, timedelta(seconds=5)) is None
    store = rendezvous_store(f"tcp://127.0.0.1:{_free_port()}", 1, 0, timedelta(seconds=5))
    assert isinstance(store, dist.TCPStore)
    store.set("k", "v")
    assert store.get("k") == b"v"
