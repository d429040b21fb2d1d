"""MLP weight matrices in a few bits per weight: per-row symmetric quantization (omg4 §8, "compact" codec).

Each row (one output unit) of a ``[R, C]`` weight matrix gets a scale ``s = max|w| / L`` with
``L = 2^(bits−1) − 1`` (stored as float32, so rows of tiny weights keep their precision) and its weights the
integers ``round(w / s)`` in [−L, L], ANS-coded; the decoded weights are fp16. The section's encoding
names the bits (``int8-rows`` by default; ``int2-rows`` … ``int7-rows`` under coarser grids,
:class:`omg4.codec.payload.CompactGrids`, which need container version 4). The appearance MLPs of paper
§4.4 tolerate 8 bits: on the demo's OMG4-M it moves PSNR by −0.002 dB and halves the MLPs' share of the
file; on the demo's presets 6 bits cost 0.01-0.05 dB more, 4 bits 0.3-0.7 dB (README, Rate).
"""

from __future__ import annotations

import re

import numpy as np

from omg4.codec.entropy import decode_indices, encode_indices
from omg4.errors import CorruptFileError

BITS = 8
MIN_BITS = 2
F16_MAX = 65504.0


def levels(bits: int = BITS) -> int:
    """Largest code magnitude ``L = 2^(bits−1) − 1`` (127 at 8 bits): codes lie in [−L, L]."""
    return (1 << (bits - 1)) - 1


def encoding(bits: int = BITS) -> str:
    """The section encoding's name in a file's header for ``bits`` per weight."""
    return f"int{bits}-rows"


def bits_of(name: str) -> int | None:
    """The bits per weight an encoding name declares (``int2-rows`` … ``int8-rows``), or None if it is not a weight
    encoding."""
    match = re.fullmatch(r"int([2-8])-rows", name)
    return int(match.group(1)) if match else None


def quantize_rows(w: np.ndarray, bits: int = BITS) -> tuple[np.ndarray, np.ndarray]:
    """(float32 scales ``[R]``, int codes ``[R, C]`` in [−L, L]) of a 2-D weight matrix ``w``."""
    top = levels(bits)
    w = np.asarray(w, np.float32)
    scale = (np.abs(w).max(axis=1, initial=0.0) / top).astype(np.float32)
    safe = np.where(scale > 0, scale, 1.0)[:, None]
    return scale, np.clip(np.rint(w / safe), -top, top).astype(np.int64)


def encode_rows(w: np.ndarray, bits: int = BITS) -> bytes:
    """Code a 2-D weight matrix ``[R, C]``: R float32 scales (little-endian), then the ANS-coded integers."""
    if not MIN_BITS <= bits <= BITS:
        raise ValueError(f"weights in {bits} bits (allowed {MIN_BITS}-{BITS})")
    scale, codes = quantize_rows(w, bits)
    top = levels(bits)
    return scale.astype("<f4").tobytes() + encode_indices((codes + top).ravel(), 2 * top + 1, "ans")


def decode_rows(data: bytes, shape: tuple[int, int], bits: int = BITS) -> np.ndarray:
    """Inverse of :func:`encode_rows`: ``float16 [R, C]``."""
    rows, cols = shape
    top = levels(bits)
    if len(data) < 4 * rows:
        raise CorruptFileError("truncated weight scales")
    with np.errstate(invalid="ignore"):  # a forged signalling NaN is refused below, not warned about
        scale = np.frombuffer(data[:4 * rows], "<f4").astype(np.float64)
    if not (np.isfinite(scale).all() and (scale >= 0).all() and (scale * top <= F16_MAX).all()):
        raise CorruptFileError("invalid weight scales (negative, non-finite or beyond the fp16 range)")
    codes = decode_indices(data[4 * rows:], 2 * top + 1, rows * cols, "ans").reshape(rows, cols) - top
    return (codes * scale[:, None]).astype(np.float16)
