"""MLP weight matrices in a few bits per weight: symmetric quantization per column or per row (omg4 §8, "compact" codec).

Each column (one input of the layer; ``int<b>-cols``, what the writer uses since container version 5) or each row
(one output unit; ``int<b>-rows``, versions 3 and 4) of a ``[R, C]`` weight matrix gets a scale
``s = max|w| / L`` with ``L = 2^(bits−1) − 1`` (stored as float32, so tiny weights keep their precision) and its
weights the integers ``round(w / s)`` in [−L, L], ANS-coded; the decoded weights are fp16. The section's encoding
names the bits (8 by default; 2-7 under coarser grids, :class:`omg4.codec.coders.CompactGrids`) and the layout.
Per-column scales follow the inputs: an appearance head (paper §4.4) takes 13 shared features and 3 Gaussian
features of different ranges, which per-row scales give one step (the measured effect of both layouts on PSNR:
``docs/results.md``, coders).

A predicted segment of a sequence (beyond the paper; docs/file-format.md §8a) may store a matrix as its change
from the reference segment's decoded one (``delta-int<b>-cols``): integer codes of ``w − reference`` in steps of
its reference column's largest magnitude / :data:`DELTA_LEVELS` (a power of two coarser where the change needs
it), decoding to ``fp16(reference + codes · step)``; nothing of the step is stored but that power, so a weight
that did not move costs the entropy coder's share of a zero code.
"""

from __future__ import annotations

import re

import numpy as np

from omg4.codec.entropy import decode_indices, encode_indices
from omg4.errors import CorruptFileError

BITS = 8
MIN_BITS = 2
F16_MAX = 65504.0
#: a change's step is its reference column's largest magnitude / DELTA_LEVELS (a 5-bit grid where the matrices
#: themselves take 8: the change of a fine-tuned appearance MLP needs no finer one, docs/results.md, predicted
#: segments), times 2^shift (shift at most MAX_SHIFT) for a column whose change is too large for 8-bit codes
DELTA_LEVELS = 15
MAX_SHIFT = 31


def levels(bits: int = BITS) -> int:
    """Largest code magnitude ``L = 2^(bits−1) − 1`` (127 at 8 bits): codes lie in [−L, L]."""
    return (1 << (bits - 1)) - 1


def encoding(bits: int = BITS) -> str:
    """The section encoding's name in a file's header for ``bits`` per weight, per-column scales (the writer's)."""
    return f"int{bits}-cols"


ENCODING_PATTERN = r"int([2-8])-(rows|cols)"
"""A weight matrix's encoding names (bits, per-row or per-column scales), as a regular expression taken whole."""
DELTA_PATTERN = r"delta-int([2-8])-cols"
"""The encoding names of a weight matrix stored as its change from the reference's."""


def parse_encoding(name: str) -> tuple[int, bool] | None:
    """(bits, per-column scales) of a weight encoding name (``int2-rows`` … ``int8-rows``, ``int2-cols`` …
    ``int8-cols``), or None if it is not one."""
    match = re.fullmatch(ENCODING_PATTERN, name)
    return (int(match.group(1)), match.group(2) == "cols") if match else None


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


def encode_columns(w: np.ndarray, bits: int = BITS) -> bytes:
    """Code a 2-D weight matrix ``[R, C]`` with a scale per column: :func:`encode_rows` of its transpose."""
    return encode_rows(np.asarray(w).T, bits)


def decode_matrix(data: bytes, shape: tuple[int, int], name: str) -> np.ndarray:
    """Decode a weight section of encoding ``name`` (:func:`parse_encoding`, checked by the caller) to
    ``float16 [R, C]``."""
    bits, columns = parse_encoding(name)
    rows, cols = shape
    return decode_rows(data, (cols, rows), bits).T.copy() if columns else decode_rows(data, shape, bits)


def delta_encoding(bits: int) -> str:
    """The section encoding's name of a matrix stored as its change from the reference's, codes of ``bits``."""
    return f"delta-int{bits}-cols"


def parse_delta_encoding(name: object) -> int | None:
    """The code bits of a change's encoding name (``delta-int2-cols`` … ``delta-int8-cols``), or None."""
    match = re.fullmatch(DELTA_PATTERN, name) if isinstance(name, str) else None
    return int(match.group(1)) if match else None


def _steps(ref: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """float64 ``[C]``: column j's step, the largest magnitude of the reference's column (float64 ``ref``; at
    least 2^-14) / :data:`DELTA_LEVELS` · 2^shifts[j], as the browser computes it too."""
    largest = np.abs(ref).max(axis=0, initial=0.0)
    return np.maximum(largest, 2.0 ** -14) / DELTA_LEVELS * np.exp2(np.asarray(shifts, np.float64))


def _changed(reference: np.ndarray, codes: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """``fp16(reference + codes · step)`` (:func:`_steps`), float16 ``[R, C]``; a weight beyond the fp16 range comes
    out infinite."""
    ref = np.asarray(reference, np.float16).astype(np.float64)
    with np.errstate(over="ignore"):
        return (ref + codes * _steps(ref, shifts)).astype(np.float16)


def encode_delta(w: np.ndarray, reference: np.ndarray) -> tuple[str, bytes] | None:
    """(encoding, bytes) of the 2-D matrix ``w`` as its change from ``reference`` (same shape, the decoded fp16
    values a reader holds), or None where the change would decode beyond the fp16 range: per column the smallest
    shift (:func:`_steps`) that keeps its codes within 8 bits, then the integer codes in the fewest bits that hold
    them, both ANS-coded (a uint32 gives the shifts' bytes). :func:`decode_delta` gives ``_changed``."""
    ref = np.asarray(reference, np.float16).astype(np.float64)
    change = np.asarray(w, np.float16).astype(np.float64) - ref
    ratio = np.abs(change).max(axis=0, initial=0.0) / (levels(BITS) * _steps(ref, np.zeros(ref.shape[1])))
    shifts = np.clip(np.ceil(np.log2(np.maximum(ratio, 1.0))), 0, MAX_SHIFT).astype(np.int64)
    codes = np.clip(np.rint(change / _steps(ref, shifts)), -levels(BITS), levels(BITS)).astype(np.int64)
    if not np.isfinite(_changed(ref, codes, shifts)).all():
        return None
    widest = int(np.abs(codes).max(initial=0))
    code_bits = next(b for b in range(MIN_BITS, BITS + 1) if levels(b) >= widest)
    top = levels(code_bits)
    head = encode_indices(shifts, MAX_SHIFT + 1, "ans")
    data = len(head).to_bytes(4, "little") + head + encode_indices((codes.T + top).ravel(), 2 * top + 1, "ans")
    return delta_encoding(code_bits), data


def decode_delta(data: bytes, reference: np.ndarray, name: str) -> np.ndarray:
    """Inverse of :func:`encode_delta` for an encoding ``name`` (:func:`parse_delta_encoding`, checked by the
    caller) over the reference's decoded matrix: ``float16 [R, C]``; a change that leaves the fp16 range is a
    CorruptFileError."""
    rows, cols = reference.shape
    top = levels(parse_delta_encoding(name))
    head = int.from_bytes(data[:4], "little")
    if len(data) < 4 or head > len(data) - 4:
        raise CorruptFileError("truncated change of a weight matrix")
    shifts = decode_indices(data[4:4 + head], MAX_SHIFT + 1, cols, "ans")
    codes = decode_indices(data[4 + head:], 2 * top + 1, rows * cols, "ans").reshape(cols, rows).T - top
    out = _changed(reference, codes, shifts)
    if not np.isfinite(out).all():
        raise CorruptFileError("the change takes weights beyond the fp16 range")
    return out
