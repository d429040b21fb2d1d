"""The numba runtime every CPU kernel shares (the rasterizer's and the Gaussians' SH and conditioning kernels):
where numba caches compiled code, the fast-math flags, handing tensors to kernels, and keeping torch's thread
count while numba's OpenMP pool runs; and which kernels do the per-Gaussian work (:func:`kernel_mode`: the
numba ones, the pure-torch reference, or that reference compiled by ``torch.compile``, :func:`torch_form`).

numba's on-disk cache goes to ``NUMBA_CACHE_DIR`` when set, else beside each kernel's module, or to
``~/.cache/omg4/numba`` when the package directory is read-only; importing this module decides it, before any
kernel is defined (numba binds the cache location at decoration time).
"""

from __future__ import annotations

import contextlib
import functools
import os
import warnings
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numba
import numpy as np
import torch

FAST_MATH = {"contract", "afn", "arcp", "reassoc", "nsz"}
"""LLVM fast-math flags of the compositing kernels: fused multiply-adds, fast ``exp``, reassociated
sums (about 15 % faster here, within the dense-reference tolerances); NaN and infinity keep their
IEEE semantics (no ``nnan``/``ninf``)."""


def resolve_cache_dir(environ: Mapping[str, str], package_dir: str | os.PathLike,
                      writable: Callable[[str | os.PathLike], bool]) -> str | None:
    """Folder to force as numba's cache, or None to keep numba's own choice.

    ``NUMBA_CACHE_DIR`` in ``environ`` wins (numba reads it itself); a writable
    ``package_dir`` keeps numba's default ``__pycache__``; otherwise ``~/.cache/omg4/numba``.
    """
    if environ.get("NUMBA_CACHE_DIR"):
        return None
    if writable(package_dir):
        return None
    return str(Path.home() / ".cache" / "omg4" / "numba")


def configure_numba_cache() -> None:
    """Point numba's on-disk cache where it can write (see the module docstring). Runs when this module is
    imported, before its kernels are defined; another module's kernels need it to have run before theirs."""
    folder = resolve_cache_dir(os.environ, Path(__file__).parent, lambda p: os.access(p, os.W_OK))
    if folder is not None:
        os.makedirs(folder, exist_ok=True)
        os.environ["NUMBA_CACHE_DIR"] = folder  # survives numba's config reloads
        numba.config.CACHE_DIR = folder


configure_numba_cache()


def as_numpy(t: torch.Tensor) -> np.ndarray:
    """The numpy view of a CPU tensor for a numba kernel (detached; copied only when not contiguous). A contiguous
    tensor that needs no gradient is viewed as it is, dispatching no operation."""
    if t.is_contiguous():
        return t.numpy(force=t.requires_grad)  # force: one detach where the tensor needs a gradient
    return t.detach().contiguous().numpy()


KERNEL_MODES = ("fused", "reference", "compiled")
"""``fused``: the per-Gaussian numba kernels run where they can, the torch forms elsewhere (the default);
``reference``: the pure-torch forms everywhere (the reference the kernels are tested against); ``compiled``: the
torch forms compiled by ``torch.compile`` (:func:`torch_form`: inductor's Triton kernels on CUDA, its C++ kernels on
the CPU, which need a C++ compiler). The rasterizer's kernels run in all three."""

_chosen_mode: str | None = None


def kernel_mode() -> str:
    """The kernels in use: :func:`set_kernel_mode`'s choice, else ``$OMG4_KERNELS``, else ``fused``."""
    mode = _chosen_mode or os.environ.get("OMG4_KERNELS") or KERNEL_MODES[0]
    if mode not in KERNEL_MODES:
        raise ValueError(f"unknown kernels '{mode}' (OMG4_KERNELS): choose from {', '.join(KERNEL_MODES)}")
    return mode


def set_kernel_mode(mode: str | None) -> None:
    """Use the ``mode`` kernels from now on (None: back to ``$OMG4_KERNELS`` or the default)."""
    global _chosen_mode
    if mode is not None and mode not in KERNEL_MODES:
        raise ValueError(f"unknown kernels '{mode}': choose from {', '.join(KERNEL_MODES)}")
    _chosen_mode = mode


@contextlib.contextmanager
def using_kernels(mode: str) -> Iterator[None]:
    """Run the body with the ``mode`` kernels (:data:`KERNEL_MODES`)."""
    before = _chosen_mode
    set_kernel_mode(mode)
    try:
        yield
    finally:
        set_kernel_mode(before)


def runs_cpu_kernels(*tensors: torch.Tensor) -> bool:
    """Whether the numba kernels take ``tensors``: the fused kernels in use, all on the CPU, all float32 or all
    float64 (else the torch forms run)."""
    dtype = tensors[0].dtype
    return kernel_mode() == "fused" and dtype in (torch.float32, torch.float64) and all(
        t.device.type == "cpu" and t.dtype == dtype for t in tensors)


def torch_form(fn: Callable) -> Callable:
    """``fn``, a per-Gaussian function of torch operations, as the kernels in use run it: itself, or with the
    ``compiled`` kernels its ``torch.compile`` form (shapes dynamic; compiled on first use per dtype and device, a
    few seconds to tens of seconds, then cached by torch on disk). A call with an empty tensor, or whose first
    tensor (the Gaussians or rows) has one row, runs ``fn`` itself: the compiler specializes sizes 0 and 1, and
    such edge cases would each compile anew."""
    if kernel_mode() != "compiled":
        return fn
    compiled = _compiled(fn)

    def run(*args, **kwargs):
        tensors = [a for a in args if isinstance(a, torch.Tensor)]
        if tensors[0].shape[0] < 2 or any(t.numel() == 0 for t in tensors):
            return fn(*args, **kwargs)
        with warnings.catch_warnings():  # the forms' constant tables come from lru_cache'd builders, traced as such
            warnings.filterwarnings("ignore", message="Dynamo detected a call to a `functools.lru_cache`")
            return compiled(*args, **kwargs)

    return run


@functools.lru_cache(maxsize=None)
def _compiled(fn: Callable) -> Callable:
    """``torch.compile(fn)`` with dynamic shapes, made once per function."""
    return torch.compile(fn, dynamic=True)


def compile_failure(exc: BaseException) -> str | None:
    """The one-line message for ``exc`` when it is ``torch.compile`` failing to compile the ``compiled`` kernels (in
    their forward or, later, inside ``backward()``), else None. Seen on an H200 with torch 2.11: inductor's Triton
    code generation asserted on the backward graph of a 200,000-Gaussian training step."""
    from torch._dynamo.exc import BackendCompilerFailed  # torch._dynamo only once a command has failed

    if not isinstance(exc, BackendCompilerFailed):
        return None
    inner = getattr(exc, "inner_exception", None) or exc
    detail = str(inner).strip().splitlines()
    cause = type(inner).__name__ + (f": {detail[0][:160]}" if detail else "")
    return (f"torch.compile could not compile the per-Gaussian kernels (torch {torch.__version__}, {cause}); "
            f"run without --kernels compiled (the default kernels compute the same)")


@contextlib.contextmanager
def keeping_torch_threads() -> Iterator[None]:
    """Run numba parallel kernels inside: numba's OpenMP pool shares the OpenMP runtime with torch and
    resets its thread count on first use; torch's intra-op thread setting is restored afterwards."""
    torch_threads = torch.get_num_threads()
    try:
        yield
    finally:
        if torch.get_num_threads() != torch_threads:
            torch.set_num_threads(torch_threads)


__all__ = ["FAST_MATH", "KERNEL_MODES", "as_numpy", "compile_failure", "configure_numba_cache", "keeping_torch_threads", "kernel_mode",
           "resolve_cache_dir", "runs_cpu_kernels", "set_kernel_mode", "torch_form", "using_kernels"]
