"""Unit quaternions in ~3 × 9 bits: "smallest three" coding (omg4 §8, "compact" codec).

A rotation quaternion is normalized at use and ``q`` and ``−q`` give the same rotation (for
Real-Time4DGS's pair of isoclinic quaternions too: negating one negates the 4D rotation, not
the covariance), so a Gaussian's rotation has three degrees of freedom, not the four fp16
numbers (or two 2-d sub-vector codewords) it is stored as. This coder normalizes, flips the
sign so the largest-magnitude component is positive, stores which component that is (2 bits,
ANS-coded) and the other three on a uniform grid of ``2^bits − 1`` levels over [−1/√2, 1/√2]
(odd, so 0 is a level and the identity is exact; ANS-coded); the decoder recovers the largest
as √(1 − Σ others²). The grid's bits are part of the section's encoding name
(``smallest-three-9``; version-2 files hold ``smallest-three-10``). At 9 bits a component is off by
at most 1.4·10⁻³ (the rotation by ~0.3°; its measured cost in PSNR: ``docs/results.md``, coders).
"""

from __future__ import annotations

import re

import numpy as np

from omg4.codec.entropy import decode_indices, encode_indices, join_streams, split_streams

BITS = 9
_PREFIX = "smallest-three-"
ENCODING_PATTERN = _PREFIX + r"([2-9]|1[0-5])"
"""The encoding names, bits 2-15 (ASCII digits, no leading zero), as a regular expression taken whole."""
_LIMIT = 1 / np.sqrt(2)


def encoding(bits: int = BITS) -> str:
    """The section encoding's name in a file's header for a grid of ``bits``."""
    return f"{_PREFIX}{bits}"


def bits_of(name: str) -> int | None:
    """The grid bits an encoding name declares (2-15, ASCII digits without a leading zero), or None if it is not
    a quaternion encoding."""
    match = re.fullmatch(ENCODING_PATTERN, name)
    return int(match.group(1)) if match else None


def levels(bits: int) -> int:
    """Grid levels per component: ``2^bits − 1`` (odd: 0 is a level)."""
    return (1 << bits) - 1


def _step(bits: int) -> float:
    return 2 * _LIMIT / (levels(bits) - 1)


def quantize_quaternions(q: np.ndarray, bits: int = BITS) -> tuple[np.ndarray, np.ndarray]:
    """(index of the largest component ``int64 [N]``, grid codes of the other three ``int64 [N, 3]``) of
    ``q: [N, 4]`` (any non-zero norm; a zero quaternion becomes the identity's first component)."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))
    largest = np.abs(q).argmax(axis=1)
    rows = np.arange(q.shape[0])
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = q[~(np.arange(4)[None, :] == largest[:, None])].reshape(-1, 3)
    codes = np.clip(np.rint((others + _LIMIT) / _step(bits)), 0, levels(bits) - 1).astype(np.int64)
    return largest.astype(np.int64), codes


def dequantize_quaternions(largest: np.ndarray, codes: np.ndarray, bits: int = BITS) -> np.ndarray:
    """Unit quaternions ``float64 [N, 4]`` from :func:`quantize_quaternions`' output."""
    others = codes.astype(np.float64) * _step(bits) - _LIMIT
    w = np.sqrt(np.maximum(0.0, 1.0 - (others ** 2).sum(axis=1)))
    q = np.empty((largest.size, 4))
    mask = np.arange(4)[None, :] == largest[:, None]
    q[mask] = w
    q[~mask] = others.ravel()
    return q


def encode_quaternions(q: np.ndarray, bits: int = BITS) -> bytes:
    """Code ``q: [N, 4]`` (N ≥ 1): varint size of the largest-component stream, that stream, the grid codes."""
    largest, codes = quantize_quaternions(q, bits)
    head = encode_indices(largest, 4, "ans")
    return join_streams(head, encode_indices(codes.ravel(), levels(bits), "ans"))


def decode_quaternions(data: bytes, count: int, bits: int = BITS) -> np.ndarray:
    """Inverse of :func:`encode_quaternions`: unit quaternions rounded to ``float16 [count, 4]``."""
    head, tail = split_streams(data, "quaternion stream")
    largest = decode_indices(head, 4, count, "ans")
    codes = decode_indices(tail, levels(bits), 3 * count, "ans").reshape(count, 3)
    return dequantize_quaternions(largest, codes, bits).astype(np.float16)
