"""Positions and time centres on uniform grids: the "compact" codec's per-Gaussian floats (omg4 §8, versions 3-5).

The paper stores ``xyz`` and ``t`` as fp16 (OMG4 §4.4), whose step grows with the magnitude: a
position at 8 is stored 16 times more coarsely than one at 0.5. A uniform grid spends its bits
where the scene is instead:

* positions: ``2^bits`` levels per axis over the bounding box's largest side (one step for all
  axes), Gaussians in Z-order of their grid cells, so the positions become sorted 3·bits-bit
  Morton codes whose gaps are hybrid-uint coded. At the default 15 bits a position moves by at most
  half a step, 1/65,534 of the scene's extent.
* exact positions (beyond the paper): a few Gaussians chosen by the writer — the largest, whose appearance
  covers the most pixels — keep their fp16 positions exactly (encoding ``grid-morton-exact``): the appearance MLP
  reads positions through a 16-band frequency encoding (omg4 §6b), whose top band turns a shift of 1/8,000 of
  the scene into a different colour, so a large Gaussian on the grid can change a whole view (``docs/results.md``, coders).
  After the Morton codes come the chosen storage ranks (gaps, hybrid uints) and, per chosen Gaussian and axis,
  the zigzag difference between the ordered fp16 keys of its exact value and of its grid value.
* time centres: a step of ``duration · 2^-bits`` (the clip's time range from the payload's meta,
  else the centres' own range), grid offsets ANS-coded; fp16 is kept where such a grid would not fit
  the coder or fp16.

A section stores its grid (origin and step as float64, so the decoder needs nothing else) before the
codes; the decoder checks every field and the decoded values (finite, within fp16) and raises a
one-line :class:`~omg4.errors.CorruptFileError` otherwise.
"""

from __future__ import annotations

import struct

import numpy as np

from omg4.codec.codewords import (decode_sorted_codes, deinterleave, encode_sorted_codes, interleave, keys_to_fp16,
                                  ordered_keys)
from omg4.codec.entropy import (MAX_SYMBOLS, decode_indices, decode_uints, encode_indices, encode_uints, join_streams,
                                pack_varints, split_streams, unpack_varints)
from omg4.errors import CorruptFileError

POSITION_BITS = 15
TIME_BITS = 10
POSITIONS = "grid-morton"  # section encodings (names in a file's header)
POSITIONS_EXACT = "grid-morton-exact"
TIMES = "grid"
_POSITION_HEAD = struct.Struct("<3ddB")  # origin (x, y, z), step, bits per axis
_TIME_HEAD = struct.Struct("<ddI")  # origin, step, number of levels


def _cells(xyz: np.ndarray, bits: int) -> tuple[np.ndarray, float, np.ndarray]:
    """(origin ``[3]``, step, integer cells ``uint16 [N, 3]``) of positions on the ``bits``-bit grid over their box."""
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    origin = xyz.min(axis=0)
    extent = float((xyz.max(axis=0) - origin).max())
    step = extent / ((1 << bits) - 1) if extent > 0 else 1.0
    cells = np.clip(np.rint((xyz - origin) / step), 0, (1 << bits) - 1).astype(np.uint16)
    return origin, step, cells


def position_order(xyz: np.ndarray, bits: int = POSITION_BITS) -> np.ndarray:
    """The storage order of :func:`encode_positions`: stable Z-order of the grid cells of ``xyz: [N, 3]``."""
    return np.argsort(interleave(_cells(xyz, bits)[2]), kind="stable")


def encode_positions(xyz: np.ndarray, bits: int = POSITION_BITS, exact: np.ndarray | None = None) -> bytes:
    """Code ``xyz: [N, 3]`` (N ≥ 1, finite), already in :func:`position_order`, on the ``bits``-bit grid; with a
    boolean ``exact: [N]`` that marks any Gaussian, those keep their fp16 values (encoding :data:`POSITIONS_EXACT`)."""
    if not 1 <= bits <= 16:
        raise ValueError(f"position grid of {bits} bits (allowed 1-16)")
    origin, step, cells = _cells(xyz, bits)
    codes = interleave(cells)
    if (np.diff(codes.astype(np.int64)) < 0).any():
        raise ValueError("positions must be in position_order")
    grid = _POSITION_HEAD.pack(*origin, step, bits) + encode_sorted_codes(codes)
    if exact is None:
        return grid
    exact = np.asarray(exact)
    if exact.dtype != bool or exact.shape != (len(cells),):
        raise ValueError(f"exact must be a boolean mask of {len(cells)} Gaussians, got {exact.dtype} {exact.shape}")
    if not exact.any():
        return grid
    ranks = np.flatnonzero(exact)
    on_grid = ordered_keys(_grid_values(origin, step, cells[ranks])).astype(np.int64)
    diff = (ordered_keys(np.asarray(xyz, np.float16).reshape(-1, 3)[ranks]).astype(np.int64) - on_grid).ravel()
    zigzag = np.where(diff < 0, -2 * diff - 1, 2 * diff).astype(np.uint64)
    return join_streams(grid, pack_varints(np.array([ranks.size])) +
                        join_streams(encode_sorted_codes(ranks.astype(np.uint64)), encode_uints(zigzag)))


def _grid_values(origin, step: float, cells: np.ndarray) -> np.ndarray:
    """fp16 positions of grid ``cells: [M, 3]``, the encoder's and the decoder's (which checks them for finiteness)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return (np.asarray(origin) + cells.astype(np.float64) * step).astype(np.float16)


def _fp16(values: np.ndarray) -> np.ndarray | None:
    """``values`` rounded to fp16, or None when one is not finite there (beyond ±65504 after rounding)."""
    with np.errstate(over="ignore", invalid="ignore"):
        rounded = values.astype(np.float16)
    return rounded if np.isfinite(rounded).all() else None


def _finite_in_fp16(values: np.ndarray, what: str) -> np.ndarray:
    rounded = _fp16(values)
    if rounded is None:
        raise CorruptFileError(f"{what} beyond the fp16 range")
    return rounded


def decode_positions(data: bytes, count: int, exact: bool = False) -> np.ndarray:
    """Inverse of :func:`encode_positions`: ``float16 [count, 3]``; ``exact``: the section is :data:`POSITIONS_EXACT`."""
    grid, tail = split_streams(data, "position grid") if exact else (data, b"")
    if len(grid) < _POSITION_HEAD.size:
        raise CorruptFileError("truncated position grid")
    *origin, step, bits = _POSITION_HEAD.unpack_from(grid)
    if not (1 <= bits <= 16 and np.isfinite([*origin, step]).all() and step > 0):
        raise CorruptFileError("invalid position grid")
    codes = decode_sorted_codes(grid[_POSITION_HEAD.size:], count, 3 * bits, strict=False, damaged="Morton codes")
    xyz = _grid_values(origin, step, deinterleave(codes, 3))
    if not np.isfinite(xyz).all():
        raise CorruptFileError("positions beyond the fp16 range")
    return _exact_positions(xyz, tail) if exact else xyz


def _exact_positions(xyz: np.ndarray, tail: bytes) -> np.ndarray:
    """``xyz`` (grid values, fp16) with the exact fp16 values the section's ``tail`` restores."""
    (num,), used = unpack_varints(tail, 1, "exact-position count")
    if not 1 <= num <= len(xyz):
        raise CorruptFileError(f"{num} exact positions for {len(xyz)} Gaussians")
    ranks_data, diffs_data = split_streams(tail[used:], "exact-position ranks")
    rank_bits = max(1, (len(xyz) - 1).bit_length())
    ranks = decode_sorted_codes(ranks_data, int(num), rank_bits, strict=True,
                                damaged="exact-position ranks").astype(np.int64)
    if ranks[-1] >= len(xyz):
        raise CorruptFileError("damaged exact-position ranks")
    zigzag = decode_uints(diffs_data, 3 * int(num), max_bits=17).astype(np.int64)
    diff = np.where(zigzag & 1, -(zigzag + 1) // 2, zigzag // 2).reshape(-1, 3)
    keys = ordered_keys(xyz[ranks]).astype(np.int64) + diff
    if keys.min() < 0 or keys.max() > 0xFFFF:
        raise CorruptFileError("damaged exact positions")
    out = xyz.copy()
    out[ranks] = _finite_in_fp16(keys_to_fp16(keys.astype(np.uint16)), "exact positions")
    return out


def time_step(t: np.ndarray, time_range: object, bits: int = TIME_BITS) -> float:
    """The grid step of time centres ``t``: ``duration · 2^-bits``, the duration from ``time_range`` (a [lo, hi]
    pair with hi > lo) when valid, else the centres' own range (1 if they are all equal)."""
    try:
        lo, hi = (float(v) for v in (time_range if isinstance(time_range, (list, tuple)) else ()))
    except (TypeError, ValueError, OverflowError):
        lo = hi = 0.0
    duration = hi - lo
    if not (np.isfinite(duration) and duration > 0):
        duration = float(np.ptp(np.asarray(t, np.float64))) or 1.0
    return duration / (1 << bits)


def encode_times(t: np.ndarray, step: float) -> bytes | None:
    """Code time centres ``t: [N]`` (N ≥ 1, finite) on a grid of ``step`` from their minimum; None (the caller
    keeps fp16) when the step is not a positive finite number, the grid would need more than the entropy coder's
    symbols, or a value on it would leave the fp16 range."""
    t = np.asarray(t, np.float64).ravel()
    origin = float(t.min())
    if not (np.isfinite(step) and step > 0):
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        scaled = np.rint((t - origin) / step)
    if not (np.isfinite(scaled).all() and scaled.max() < MAX_SYMBOLS):
        return None
    codes = scaled.astype(np.int64)
    if _fp16(origin + codes * step) is None:
        return None
    levels = int(codes.max()) + 1
    return _TIME_HEAD.pack(origin, step, levels) + encode_indices(codes, levels, "ans")


def decode_times(data: bytes, count: int) -> np.ndarray:
    """Inverse of :func:`encode_times`: ``float16 [count]``."""
    if len(data) < _TIME_HEAD.size:
        raise CorruptFileError("truncated time grid")
    origin, step, levels = _TIME_HEAD.unpack_from(data)
    if not (np.isfinite([origin, step]).all() and step > 0 and 1 <= levels <= MAX_SYMBOLS):
        raise CorruptFileError("invalid time grid")
    codes = decode_indices(data[_TIME_HEAD.size:], levels, count, "ans")
    return _finite_in_fp16(origin + codes.astype(np.float64) * step, "time centres")
