"""NCCL's device rule on a machine without a GPU: the world says NCCL, and a collective refuses any tensor that is
not a CUDA tensor, as NCCL does ("No backend type associated with device type cpu"). gloo, which accepts CPU
tensors, still moves the bytes.

CUDA tensors are emulated: `EmulatedCuda` is a CPU tensor that reports device cuda:0 (a torch wrapper subclass);
every op on it runs on its CPU data and returns emulated CUDA tensors, `.to("cuda")` / `device="cuda"` make one
(while `nccl_rule()` is active), `.cpu()` gives the plain tensor back, and an op mixing it with a CPU tensor of
more than 0 dimensions raises as CUDA would. Used by distributed_harness.nccl_rule_main.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import torch
import torch.distributed as dist
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

CUDA = torch.device("cuda", 0)
# The torch.distributed collectives geer calls (directly or through torch.distributed.nn).
COLLECTIVES = ("all_reduce", "broadcast", "all_to_all_single", "all_gather", "all_gather_into_tensor", "gather",
               "reduce_scatter_tensor", "reduce")
_COPIES = (torch.ops.aten.copy_.default, torch.ops.aten._to_copy.default)


class NcclRefused(RuntimeError):
    """A collective got a tensor NCCL would not take."""


class EmulatedCuda(torch.Tensor):
    """A CPU tensor (`inner`) that says it lives on cuda:0."""

    @staticmethod
    def __new__(cls, inner: torch.Tensor, requires_grad: bool = False):
        return torch.Tensor._make_wrapper_subclass(cls, inner.shape, strides=inner.stride(), dtype=inner.dtype,
                                                   storage_offset=inner.storage_offset(), device=CUDA,
                                                   requires_grad=requires_grad)

    def __init__(self, inner: torch.Tensor, requires_grad: bool = False) -> None:
        self.inner = inner

    def __repr__(self) -> str:
        return f"EmulatedCuda({self.inner!r})"

    __torch_function__ = torch._C._disabled_torch_function_impl

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return _run(func, args, kwargs or {})


def _is_cuda_device(value) -> bool:
    return value is not None and torch.device(value).type == "cuda"


def _run(func, args, kwargs):
    flat, _ = tree_flatten((args, kwargs))
    emulated = any(isinstance(t, EmulatedCuda) for t in flat)
    to_cuda = _is_cuda_device(kwargs.get("device"))
    if func is torch.ops.aten._to_copy.default and emulated and not to_cuda and kwargs.get("device") is not None:
        return func(args[0].inner, *args[1:], **kwargs)  # .cpu(): the plain tensor
    if emulated and func not in _COPIES:
        for t in flat:
            if isinstance(t, torch.Tensor) and not isinstance(t, EmulatedCuda) and t.ndim > 0:
                raise RuntimeError(f"emulated CUDA: {func} got a CPU tensor {tuple(t.shape)} among cuda:0 tensors "
                                   "(Expected all tensors to be on the same device)")
    if func is torch.ops.aten.copy_.default and not isinstance(args[0], EmulatedCuda):
        return args[0].copy_(_unwrap(args[1]))  # into a CPU tensor
    unwrapped_args, unwrapped_kwargs = tree_map(_unwrap, (args, kwargs))
    if to_cuda:
        unwrapped_kwargs["device"] = torch.device("cpu")
    out = func(*unwrapped_args, **unwrapped_kwargs)
    if not (emulated or to_cuda):
        return out
    originals = {id(_unwrap(t)): t for t in flat if isinstance(t, EmulatedCuda)}

    def wrap(value):
        if not isinstance(value, torch.Tensor):
            return value
        original = originals.get(id(value))  # an in-place op returns its argument
        return original if original is not None else EmulatedCuda(value)

    return tree_map(wrap, out)


def _unwrap(value):
    return value.inner if isinstance(value, EmulatedCuda) else value


class _CudaFactories(TorchDispatchMode):
    """`.to("cuda")`, `torch.zeros(..., device="cuda")`: emulated CUDA tensors instead of a missing driver
    (torch's factories initialise CUDA through torch.cuda._lazy_init, a no-op while the mode is on)."""

    def __enter__(self):
        self._lazy_init, torch.cuda._lazy_init = torch.cuda._lazy_init, lambda: None
        torch._C._ensureCUDADeviceGuardSet()  # no GPU: a no-op device guard (as FakeTensorMode does)
        self._lift = torch._C._only_lift_cpu_tensors()
        torch._C._set_only_lift_cpu_tensors(True)  # torch.tensor(..., device="cuda"): made on the CPU, then moved
        return super().__enter__()

    def __exit__(self, *exc):
        torch.cuda._lazy_init = self._lazy_init
        torch._C._set_only_lift_cpu_tensors(self._lift)
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        flat, _ = tree_flatten((args, kwargs))
        if _is_cuda_device(kwargs.get("device")) or any(isinstance(t, EmulatedCuda) for t in flat):
            return _run(func, args, kwargs)
        return func(*args, **kwargs)


def cuda(t: torch.Tensor) -> EmulatedCuda:
    """An emulated CUDA copy of CPU tensor t (requires_grad carried over)."""
    return EmulatedCuda(t.detach().clone(), requires_grad=t.requires_grad)


def _refusing(name: str, original):
    def collective(*args, **kwargs):
        flat, _ = tree_flatten((args, kwargs))
        for t in flat:
            if isinstance(t, torch.Tensor) and not isinstance(t, EmulatedCuda):
                raise NcclRefused(f"emulated NCCL: dist.{name} got a tensor on {t.device} {tuple(t.shape)}: "
                                  "No backend type associated with device type cpu")
        return original(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))

    return collective


@contextlib.contextmanager
def nccl_rule() -> Iterator[None]:
    """Inside: dist.get_backend() says "nccl", the collectives refuse non-CUDA tensors (NcclRefused) and run
    gloo on the emulated CUDA tensors' data; `device="cuda"` makes emulated CUDA tensors."""
    saved = {name: getattr(dist, name) for name in (*COLLECTIVES, "get_backend")}
    for name in COLLECTIVES:
        setattr(dist, name, _refusing(name, saved[name]))
    dist.get_backend = lambda group=None: "nccl"
    try:
        with _CudaFactories():
            yield
    finally:
        for name, fn in saved.items():
            setattr(dist, name, fn)
