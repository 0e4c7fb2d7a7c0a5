"""nerfstudio's `--machine.*` launcher made to work for geer runs: one process per device, CPU machines too.

nerfstudio's worker (`_distributed_worker`, nerfstudio/scripts/train.py) asserts torch.cuda.is_available() and
num_devices <= torch.cuda.device_count(), so N gloo processes on a CPU machine fail; it never selects each
process's GPU (every NCCL process would use GPU 0); its timeout is a fixed 30 minutes; and a failed process ends
the run in pages of tracebacks. `install_launch_router` routes nerfstudio's spawn of that worker, for geer
configs only (those with `machine.timeout_s`), to `distributed_worker`: nerfstudio's set-up without the
CUDA-only asserts, gloo on CPU (each process with its share of the cores), NCCL on CUDA (each process on its
own GPU), the config's timeout, and a launch that ends with one line naming the process that failed.
Installed by GeerTrainerConfig before ns-train launches a geer run; other methods keep nerfstudio's launcher.
"""

from __future__ import annotations

import os

import torch

from geer_ns.distributed import gate


def install_launch_router() -> None:
    """Route nerfstudio's `mp.spawn(_distributed_worker, ...)` for geer configs to `distributed_worker`."""
    import torch.multiprocessing as mp

    if getattr(mp.spawn, "_geer_launch_fix", False):
        return
    original = mp.spawn

    def spawn(fn, args=(), nprocs=1, join=True, daemon=False, start_method="spawn"):
        nerfstudio_worker = getattr(fn, "__module__", "") == "nerfstudio.scripts.train" and \
            getattr(fn, "__name__", "") == "_distributed_worker"
        config = args[5] if nerfstudio_worker and len(args) > 5 else None
        timeout_s = getattr(getattr(config, "machine", None), "timeout_s", None)
        if timeout_s is None:
            return original(fn, args, nprocs, join, daemon, start_method)
        context = original(distributed_worker, args, nprocs, join=False, daemon=daemon, start_method=start_method)
        reporting = ReportingContext(context, machine_rank=int(args[3]), grace_s=float(timeout_s) + 10.0)
        return reporting.join() if join else reporting

    spawn._geer_launch_fix = True  # type: ignore[attr-defined]
    mp.spawn = spawn


def distributed_worker(local_rank, main_func, world_size, num_devices_per_machine, machine_rank, dist_url, config,
                       timeout, device_type="cuda"):
    """nerfstudio's _distributed_worker (same arguments) without its CUDA-only asserts: see above."""
    import sys
    from datetime import timedelta

    import torch.distributed as dist
    from nerfstudio.utils import comms

    global_rank = machine_rank * num_devices_per_machine + local_rank
    if device_type == "cuda":
        found = torch.cuda.device_count()
        if num_devices_per_machine > found:
            print(f"geer: --machine.num-devices {num_devices_per_machine} but this machine has {found} CUDA "
                  "device(s); use --machine.device-type cpu for processes on the CPU", file=sys.stderr, flush=True)
            raise SystemExit(2)
        torch.cuda.set_device(local_rank)
    else:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        torch.set_num_threads(max(1, cores // num_devices_per_machine))
    timeout = timedelta(seconds=float(getattr(config.machine, "timeout_s", timeout.total_seconds())))
    if device_type == "cuda":
        # A timed-out NCCL collective raises in the waiting thread (one line, trainer._stop) instead of NCCL's
        # watchdog tearing the process down; the user's own settings win.
        os.environ.setdefault("TORCH_NCCL_BLOCKING_WAIT", "1")
        os.environ.setdefault("TORCH_NCCL_ASYNC_ERROR_HANDLING", "2")
    try:
        store = rendezvous_store(dist_url, world_size, global_rank, timeout)
        rendezvous = {"init_method": dist_url} if store is None else {"store": dist.PrefixStore("geer-pg/", store)}
        dist.init_process_group(backend="nccl" if device_type == "cuda" else "gloo", world_size=world_size,
                                rank=global_rank, timeout=timeout, **rendezvous)
    except Exception as error:  # noqa: BLE001 - one line: which rank could not join, where, why
        print(f"geer: rank {global_rank} of {world_size} could not join the others at {dist_url} within "
              f"{timeout.total_seconds():g} s: {str(error).strip().splitlines()[0]}", file=sys.stderr, flush=True)
        raise SystemExit(1)
    gate.use_store(store)
    for machine in range(world_size // num_devices_per_machine):  # nerfstudio's per-machine groups
        ranks = list(range(machine * num_devices_per_machine, (machine + 1) * num_devices_per_machine))
        group = dist.new_group(ranks)
        if machine == machine_rank:
            comms.LOCAL_PROCESS_GROUP = group
    try:
        # No barrier at the end (nerfstudio has one): rank 0 may stay to serve the viewer after training.
        return main_func(local_rank, world_size, config, global_rank)
    finally:
        dist.destroy_process_group()


def rendezvous_store(dist_url: str, world_size: int, rank: int, timeout):
    """The run's TCPStore at `dist_url` (tcp://host:port; rank 0 hosts it), shared by the process group and
    the step gate (gate.py); None for other URL schemes (the process group then makes its own, no gate)."""
    from urllib.parse import urlparse

    import torch.distributed as dist

    url = urlparse(dist_url)
    if url.scheme != "tcp" or url.hostname is None or url.port is None:
        return None
    return dist.TCPStore(url.hostname, url.port, world_size, is_master=rank == 0, timeout=timeout)


class ReportingContext:
    """torch's spawn context whose join waits for every process and ends a failed launch with one line."""

    def __init__(self, context, machine_rank: int, grace_s: float):
        self.context, self.machine_rank, self.grace_s = context, machine_rank, grace_s
        self.processes = context.processes

    def join(self, timeout=None) -> bool:
        import sys

        from torch.multiprocessing import ProcessExitedException, ProcessRaisedException

        n = len(self.processes)
        try:
            while not self.context.join(timeout, grace_period=self.grace_s):
                if timeout is not None:
                    return False
        except ProcessRaisedException as error:
            print(error.msg, file=sys.stderr)  # the process's traceback (nerfstudio would have printed it)
            lines = [line for line in error.msg.strip().splitlines() if line.strip()]
            self._stopped(error.error_index, f"raised {lines[-1].strip() if lines else 'an exception'}", n)
        except ProcessExitedException as error:
            what = (f"was killed by signal {error.signal_name}" if error.signal_name else
                    f"exited with status {error.exit_code} (its message is above)")
            self._stopped(error.error_index, what, n)
        return True

    def _stopped(self, index: int, what: str, n: int) -> None:
        import sys

        rank = self.machine_rank * n + index
        print(f"geer: training stopped: rank {rank} (pid {self.processes[index].pid}) {what}; the other "
              f"{n - 1} process(es) of this machine were stopped", file=sys.stderr, flush=True)
        raise SystemExit(1)
