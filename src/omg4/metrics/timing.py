"""Render-only frame-rate measurement.

Protocol of rt4dgs §6 (FPS recommendation) and omg4 §10 (``test.py``), with the missing
synchronization added: untimed warm-up calls, then each call timed on its own between two
device synchronizations, with gradients off; no I/O happens inside the timed region
(inputs are prepared by the caller; outputs are freed after the clock stops). The reported FPS is
``1 / median`` per-frame time (robust to a stray slow frame on a shared machine); the
official-style ``frames / total time`` is ``fps_mean``.
"""

from __future__ import annotations

import statistics
import time
from typing import Any, Callable, Sequence

import torch

from omg4.errors import OMG4Error


def _synchronizer(device: torch.device | str | None) -> Callable[[], None]:
    """A function that waits for queued CUDA work; a no-op on CPU.

    ``device=None`` synchronizes whenever CUDA is initialized in this process (any CUDA
    rendering initializes it), so callers need not say where ``render_fn`` runs.
    """
    if device is None:
        use_cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
        return torch.cuda.synchronize if use_cuda else (lambda: None)
    device = torch.device(device)
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def measure_fps(render_fn: Callable[[Any], Any], inputs: Sequence[Any], warmup: int = 3, repeats: int = 1,
                device: torch.device | str | None = None) -> dict[str, float | int]:
    """Time ``render_fn(x)`` for every ``x`` in ``inputs`` (``repeats`` passes) after ``warmup`` calls.

    Args:
        render_fn: renders one input (e.g. ``lambda v: render_view(model, v.camera, v.timestamp)``).
        inputs: the prepared per-frame inputs (cameras/times), at least one.
        warmup: untimed calls before timing, cycling through ``inputs``.
        repeats: timed passes over ``inputs``.
        device: where ``render_fn`` computes; CUDA is synchronized before and after each
            timed call (None: whenever CUDA is initialized).

    Returns a dict with ``frames`` (timed calls), ``warmup``, ``median_ms``, ``mean_ms``,
    ``min_ms``, ``max_ms``, ``fps`` (= 1000 / median_ms) and ``fps_mean`` (= 1000 / mean_ms).
    """
    return measure_fps_together([render_fn], inputs, warmup=warmup, repeats=repeats, device=device)[0]


def measure_fps_together(render_fns: Sequence[Callable[[Any], Any]], inputs: Sequence[Any], warmup: int = 3,
                         repeats: int = 1, device: torch.device | str | None = None) -> list[dict[str, float | int]]:
    """:func:`measure_fps` of several renderers whose frames take turns: for each input every renderer renders
    it once, the one to start rotating from input to input and pass to pass, so a slow spell of a shared
    machine falls on all of them alike (their FPS ratio is then comparable). One result per renderer."""
    if len(inputs) == 0:
        raise OMG4Error("no views to time: the FPS measurement needs at least one input")
    if warmup < 0 or repeats < 1:
        raise ValueError(f"need warmup >= 0 and repeats >= 1, got warmup={warmup}, repeats={repeats}")
    sync = _synchronizer(device)
    times: list[list[float]] = [[] for _ in render_fns]
    with torch.no_grad():
        for render_fn in render_fns:
            for i in range(warmup):
                render_fn(inputs[i % len(inputs)])
        turn = 0
        for _ in range(repeats):
            for x in inputs:
                for k in range(len(render_fns)):
                    which = (turn + k) % len(render_fns)
                    sync()
                    start = time.perf_counter()
                    out = render_fns[which](x)
                    sync()
                    times[which].append(time.perf_counter() - start)
                    del out  # freed outside the timed region
                turn += 1
    return [_summary(t, warmup) for t in times]


def _summary(times: list[float], warmup: int) -> dict[str, float | int]:
    median_ms = 1e3 * statistics.median(times)
    mean_ms = 1e3 * statistics.fmean(times)
    return {
        "frames": len(times),
        "warmup": warmup,
        "median_ms": median_ms,
        "mean_ms": mean_ms,
        "min_ms": 1e3 * min(times),
        "max_ms": 1e3 * max(times),
        "fps": 1e3 / median_ms if median_ms > 0 else float("inf"),
        "fps_mean": 1e3 / mean_ms if mean_ms > 0 else float("inf"),
    }
