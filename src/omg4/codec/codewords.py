"""Codebook + index coding that spends no bits on the order of the codewords (omg4 §8, "compact" codec).

A sub-vector-quantized slot stores a codebook ``[K, s]`` and one index per Gaussian; any
permutation of the codebook's rows (with the indices relabelled) is the same attribute, so
a coder that stores one fixed order wastes up to log2(K!) bits. Both modes here remove
that freedom, after dropping unused codewords and merging rows whose fp16 values are equal
(both exact: the reconstruction ``codebook[indices]`` is unchanged bit for bit):

* ``"sorted"`` — the distinct codewords as a set: their fp16 values become one integer
  each (the sub-vector's order-preserving 16-bit keys interleaved bit by bit, as the
  positions' Morton codes), sorted, and the gaps coded as hybrid uints; the indices are
  ranks in that order, ANS-coded with the stream's histogram. Best when K ≪ N.
* ``"first-use"`` — codewords in order of first use by the (Morton-ordered) Gaussians, stored
  as fp16; each index is then either the next new codeword (a flag, ANS-coded) or a repeat
  of an earlier one (its label, ANS-coded). When every Gaussian has its own codeword
  (K ≈ N: the paper's 2^13 rotation codebooks on a model of a few thousand Gaussians) the
  indices cost almost nothing.

:func:`encode_codewords` tries both and keeps the smaller; :func:`decode_codewords` validates
everything (strictly increasing codes within range, labels that refer to an earlier first
use, counts) and raises a one-line :class:`~omg4.errors.CorruptFileError`.
"""

from __future__ import annotations

import numpy as np

from omg4.codec.entropy import decode_indices, decode_uints, encode_indices, encode_uints, join_streams, split_streams
from omg4.errors import CorruptFileError

MAX_SORTED_SUB_LEN = 4  # 16 bits per element: the interleaved code fits 64 bits


def ordered_keys(h: np.ndarray) -> np.ndarray:
    """fp16 → uint16 whose unsigned order is the float order (sign flip trick)."""
    bits = np.ascontiguousarray(h, dtype=np.float16).view(np.uint16)
    return np.where(bits & 0x8000, ~bits, bits | 0x8000).astype(np.uint16)


def keys_to_fp16(key: np.ndarray) -> np.ndarray:
    """Inverse of :func:`ordered_keys`."""
    bits = np.where(key & 0x8000, key ^ 0x8000, ~key).astype(np.uint16)
    return bits.view(np.float16)


def interleave(keys: np.ndarray) -> np.ndarray:
    """Bit-interleave ``keys: uint16 [M, s]`` (s ≤ 4) into one uint64 per row: bit b of column a lands at b·s + a."""
    m, s = keys.shape
    bits = (keys.astype(np.uint64)[:, None, :] >> np.arange(16, dtype=np.uint64)[None, :, None]) & np.uint64(1)
    return np.bitwise_or.reduce(bits.reshape(m, 16 * s) << np.arange(16 * s, dtype=np.uint64), axis=1)


def encode_sorted_codes(codes: np.ndarray) -> bytes:
    """Non-decreasing ``uint64`` codes as their gaps (the first from 0), hybrid-uint coded: sorted Morton codes
    of positions and the "sorted" codebooks."""
    return encode_uints(np.diff(np.asarray(codes, np.uint64), prepend=np.uint64(0)))


def decode_sorted_codes(data: bytes, count: int, bits: int, strict: bool, damaged: str) -> np.ndarray:
    """Inverse of :func:`encode_sorted_codes`: ``uint64 [count]`` codes below ``2^bits``, non-decreasing (strictly
    increasing with ``strict``); otherwise a :class:`CorruptFileError` "damaged ``damaged``"."""
    codes = np.cumsum(decode_uints(data, count, max_bits=bits), dtype=np.uint64)
    later, earlier = codes[1:], codes[:-1]  # a sum that wrapped past 2^64 shows as a decrease
    if count and (int(codes[-1]) >> bits or (later <= earlier if strict else later < earlier).any()):
        raise CorruptFileError(f"damaged {damaged}")
    return codes


_DEINTERLEAVE_BLOCK = 1 << 16  # codes per block: the [block, 16·s] bit arrays stay a few tens of MB


def deinterleave(codes: np.ndarray, s: int) -> np.ndarray:
    """Inverse of :func:`interleave`: uint16 [M, s] (in blocks, so a decoder's memory stays bounded whatever M)."""
    codes = np.asarray(codes, np.uint64).reshape(-1)
    keys = np.empty((codes.size, s), np.uint16)
    shifts, weights = np.arange(16 * s, dtype=np.uint64), np.arange(16, dtype=np.uint64)[None, :, None]
    for start in range(0, codes.size, _DEINTERLEAVE_BLOCK):
        block = codes[start:start + _DEINTERLEAVE_BLOCK]
        bits = ((block[:, None] >> shifts) & np.uint64(1)).reshape(-1, 16, s)
        keys[start:start + block.size] = np.bitwise_or.reduce(bits << weights, axis=1)
    return keys


def _distinct_used(codebook: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct fp16 rows actually used ``[K', s]``, indices into them ``[N]``), rows in ascending bit order."""
    bits = np.ascontiguousarray(codebook, dtype=np.float16).view(np.uint16)
    rows, inverse = np.unique(bits[np.asarray(indices, np.int64)], axis=0, return_inverse=True)
    return rows.view(np.float16), inverse.reshape(-1).astype(np.int64)


def _sorted(rows: np.ndarray, labels: np.ndarray) -> tuple[bytes, bytes]:
    codes = interleave(ordered_keys(rows))
    order = np.argsort(codes, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    codebook = encode_sorted_codes(codes[order])
    return codebook, encode_indices(rank[labels], rows.shape[0], "ans")


def _first_use(rows: np.ndarray, labels: np.ndarray, encode_floats) -> tuple[str, bytes, bytes]:
    first = np.full(rows.shape[0], labels.size, np.int64)
    np.minimum.at(first, labels, np.arange(labels.size))
    order = np.argsort(first, kind="stable")  # codewords by first use
    relabel = np.empty_like(order)
    relabel[order] = np.arange(order.size)
    new_labels = relabel[labels]
    is_new = np.zeros(labels.size, np.int64)
    is_new[np.sort(first)] = 1
    flags = encode_indices(is_new, 2, "ans")
    repeats = encode_indices(new_labels[is_new == 0], rows.shape[0], "ans")
    encoding, floats = encode_floats(rows[order])
    return encoding, floats, join_streams(flags, repeats)


def encode_codewords(codebook: np.ndarray, indices: np.ndarray, encode_floats) -> tuple[str, bytes, str, bytes, int]:
    """Code one SVQ slot: ``codebook: fp16 [K, s]``, ``indices: int [N]`` (N ≥ 1).

    ``encode_floats(values) -> (encoding, bytes)`` stores the fp16 rows of the first-use mode.
    Returns ``(codebook encoding, codebook bytes, index encoding, index bytes, K')`` with K' the
    number of distinct used codewords (the decoded codebook's length).
    """
    rows, labels = _distinct_used(codebook, indices)
    k = rows.shape[0]
    options = []
    if rows.shape[1] <= MAX_SORTED_SUB_LEN:
        options.append(("sorted", *_sorted(rows, labels)))
    float_encoding, floats, index = _first_use(rows, labels, encode_floats)
    options.append((float_encoding, floats, index))
    cb_encoding, cb_bytes, ix_bytes = min(options, key=lambda o: len(o[1]) + len(o[2]))
    ix_encoding = "ranks" if cb_encoding == "sorted" else "first-use"
    return cb_encoding, cb_bytes, ix_encoding, ix_bytes, k


def decode_sorted_codebook(data: bytes, num_rows: int, sub_len: int) -> np.ndarray:
    """The ``[K', s]`` fp16 codebook of the "sorted" mode (strictly increasing codes within 16·s bits)."""
    if not 1 <= sub_len <= MAX_SORTED_SUB_LEN:
        raise CorruptFileError(f"sorted codebook with sub-vectors of {sub_len} values (limit {MAX_SORTED_SUB_LEN})")
    codes = decode_sorted_codes(data, num_rows, 16 * sub_len, strict=True,
                                damaged="sorted codebook (codes not strictly increasing or out of range)")
    rows = keys_to_fp16(deinterleave(codes, sub_len))
    if not np.isfinite(rows).all():
        raise CorruptFileError("non-finite codebook values")
    return rows


def decode_first_use_indices(data: bytes, num_rows: int, count: int) -> np.ndarray:
    """The ``int64 [count]`` indices of the "first-use" mode into a codebook of ``num_rows`` rows."""
    if num_rows < 1:
        raise CorruptFileError("first-use indices into an empty codebook")
    flags, repeat_stream = split_streams(data, "first-use flags")
    is_new = decode_indices(flags, 2, count, "ans").astype(bool)
    if int(is_new.sum()) != num_rows or (count and not is_new[0]):
        raise CorruptFileError("damaged first-use flags (new codewords do not match the codebook)")
    seen = np.cumsum(is_new)  # codewords introduced up to and including each Gaussian
    repeats = decode_indices(repeat_stream, num_rows, count - num_rows, "ans")
    if (repeats >= seen[~is_new]).any():
        raise CorruptFileError("damaged first-use indices (a repeat refers to a codeword not yet used)")
    labels = np.empty(count, np.int64)
    labels[is_new] = np.arange(num_rows)
    labels[~is_new] = repeats
    return labels
