"""MLP weight matrices in 8 bits per weight: per-row symmetric quantization (omg4 §8, "compact" codec).

Each row (one output unit) of a ``[R, C]`` weight matrix gets a scale ``s = max|w| / 127``
(stored as float32, so rows of tiny weights keep their precision) and its weights the integers
``round(w / s)`` in [−127, 127], ANS-coded; the decoded weights are fp16.
The appearance MLPs of paper §4.4 tolerate this: on the demo's OMG4-M it moves PSNR by
−0.002 dB and halves the MLPs' share of the file (README, rate table).
"""

from __future__ import annotations

import numpy as np

from omg4.codec.entropy import decode_indices, encode_indices
from omg4.errors import CorruptFileError

LEVELS = 127
F16_MAX = 65504.0


def quantize_rows(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(float32 scales ``[R]``, int codes ``[R, C]`` in [−127, 127]) of a 2-D weight matrix ``w``."""
    w = np.asarray(w, np.float32)
    scale = (np.abs(w).max(axis=1, initial=0.0) / LEVELS).astype(np.float32)
    safe = np.where(scale > 0, scale, 1.0)[:, None]
    return scale, np.clip(np.rint(w / safe), -LEVELS, LEVELS).astype(np.int64)


def encode_rows(w: np.ndarray) -> bytes:
    """Code a 2-D weight matrix ``[R, C]``: R float32 scales (little-endian), then the ANS-coded integers."""
    scale, codes = quantize_rows(w)
    return scale.astype("<f4").tobytes() + encode_indices((codes + LEVELS).ravel(), 2 * LEVELS + 1, "ans")


def decode_rows(data: bytes, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`encode_rows`: ``float16 [R, C]``."""
    rows, cols = shape
    if len(data) < 4 * rows:
        raise CorruptFileError("truncated weight scales")
    scale = np.frombuffer(data[:4 * rows], "<f4").astype(np.float64)
    if not (np.isfinite(scale).all() and (scale >= 0).all() and (scale * LEVELS <= F16_MAX).all()):
        raise CorruptFileError("invalid weight scales (negative, non-finite or beyond the fp16 range)")
    codes = decode_indices(data[4 * rows:], 2 * LEVELS + 1, rows * cols, "ans").reshape(rows, cols) - LEVELS
    return (codes * scale[:, None]).astype(np.float16)
