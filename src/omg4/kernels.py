"""The numba runtime every CPU kernel shares (the rasterizer's and the Gaussians' SH and conditioning kernels):
where numba caches compiled code, the fast-math flags, handing tensors to kernels, and keeping torch's thread
count while numba's OpenMP pool runs; and which kernels do the per-Gaussian work (:func:`kernel_mode`: the
numba ones or the pure-torch reference).

numba's on-disk cache goes to ``NUMBA_CACHE_DIR`` when set, else beside each kernel's module, or to
``~/.cache/omg4/numba`` when the package directory is read-only; importing this module decides it, before any
kernel is defined (numba binds the cache location at decoration time).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import weakref
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
    """The numpy view of a CPU tensor for a numba kernel (detached; copied, by numpy, only when not contiguous).
    A tensor that needs no gradient is viewed as it is, and a parameter (a leaf that needs one) through the view kept
    from its first hand-off (:func:`_parameter_view`): neither dispatches an operation. Any other tensor that needs a
    gradient costs one ``detach``."""
    if t.requires_grad and t.is_leaf and t.is_contiguous():
        return _parameter_view(t)
    array = t.numpy(force=t.requires_grad)
    return array if t.is_contiguous() else np.ascontiguousarray(array)


_PARAMETER_VIEWS: dict[int, tuple[weakref.ref, int, np.ndarray]] = {}
"""id(parameter) → (a weak reference to it, its data pointer, its numpy view). The view's base is a detached alias,
so it does not keep the parameter alive; the entry goes with the parameter."""


def _parameter_view(t: torch.Tensor) -> np.ndarray:
    """The numpy view of parameter ``t``, the same from step to step while ``t`` keeps its memory (optimizers update it
    in place; a parameter replaced or resized has a new pointer or shape, and gets a new view)."""
    key = id(t)
    kept = _PARAMETER_VIEWS.get(key)
    if kept is not None and kept[0]() is t and kept[1] == t.data_ptr() and kept[2].shape == tuple(t.shape):
        return kept[2]
    view = t.numpy(force=True)
    _PARAMETER_VIEWS[key] = (weakref.ref(t, lambda _, key=key: _PARAMETER_VIEWS.pop(key, None)), t.data_ptr(), view)
    return view


KERNEL_MODES = ("fused", "reference")
"""``fused``: the per-Gaussian numba kernels run where they can, the torch forms elsewhere (the default);
``reference``: the pure-torch forms everywhere (the reference the kernels are tested against). The rasterizer's
kernels run in both."""

KERNELS_HELP = ("per-Gaussian work on the CPU: fused (the numba kernels) or reference (the pure-torch forms they are "
                "tested against); unset: $OMG4_KERNELS, else fused")
"""The help of the configs' ``kernels`` field (:class:`~omg4.train.config.TrainConfig`,
:class:`~omg4.compress.pipeline.CompressConfig`)."""

_chosen_mode: contextvars.ContextVar[str | None] = contextvars.ContextVar("omg4_kernels", default=None)
"""The kernels :func:`using_kernels` chose for the code it runs: a run's config's ``kernels`` (the trainer, the
compression pipeline), a command's ``--kernels``."""


def kernel_mode() -> str:
    """The kernels in use: :func:`using_kernels`'s choice, else ``$OMG4_KERNELS``, else ``fused``; the one place that
    decides (every operation with a kernel asks :func:`runs_cpu_kernels`, a model's frame :func:`fused_kernels`)."""
    mode = _chosen_mode.get() or os.environ.get("OMG4_KERNELS") or KERNEL_MODES[0]
    if mode not in KERNEL_MODES:
        raise ValueError(f"unknown kernels '{mode}' (OMG4_KERNELS): choose from {', '.join(KERNEL_MODES)}")
    return mode


@contextlib.contextmanager
def using_kernels(mode: str | None) -> Iterator[None]:
    """Run the body with the ``mode`` kernels (:data:`KERNEL_MODES`; None: those already in use); the choice before
    holds again after it. The choice is the body's context's (a thread or task started inside keeps the choice it
    started with)."""
    check_kernels(mode)
    token = _chosen_mode.set(mode or _chosen_mode.get())
    try:
        yield
    finally:
        _chosen_mode.reset(token)


def check_kernels(mode: str | None) -> None:
    """A ``ValueError`` naming the choices unless ``mode`` is one of :data:`KERNEL_MODES` or None."""
    if mode is not None and mode not in KERNEL_MODES:
        raise ValueError(f"unknown kernels '{mode}': choose from {', '.join(KERNEL_MODES)}")


def fused_kernels() -> bool:
    """Whether the fused kernels are in use (else the pure-torch reference)."""
    return kernel_mode() == "fused"


def runs_cpu_kernels(*tensors: torch.Tensor) -> bool:
    """Whether the numba kernels take ``tensors``: the fused kernels in use, all on the CPU, all float32 or all
    float64 (else the torch forms run)."""
    dtype = tensors[0].dtype
    return fused_kernels() and dtype in (torch.float32, torch.float64) and all(
        t.device.type == "cpu" and t.dtype == dtype for t in tensors)


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


__all__ = ["FAST_MATH", "KERNEL_MODES", "KERNELS_HELP", "as_numpy", "check_kernels", "configure_numba_cache",
           "keeping_torch_threads", "kernel_mode", "fused_kernels", "resolve_cache_dir", "runs_cpu_kernels",
           "using_kernels"]
