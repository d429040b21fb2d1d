"""How plain arrays become section bytes, whatever the codec: fp16 values (as they are, LZMA-compressed or as
ANS-coded byte planes) and fp16 positions as sorted Morton codes (docs/file-format.md, "Float encodings")."""

from __future__ import annotations

import lzma

import numpy as np

from omg4.codec.codewords import decode_sorted_codes, deinterleave, encode_sorted_codes, interleave, keys_to_fp16, \
    ordered_keys
from omg4.codec.entropy import decode_indices, encode_indices, pack_varints, unpack_varints
from omg4.errors import CorruptFileError

LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 6}]
"""The raw LZMA2 stream of ``f16-lzma`` sections (no container, so no magic bytes to forge)."""

F16_ENCODINGS = ("f16", "f16-lzma", "f16-planes")


# ----------------------------------------------------------------------- Morton order
def morton_codes(xyz16: np.ndarray) -> np.ndarray:
    """48-bit Z-order codes of fp16 positions ``xyz16: float16 [N, 3]`` → uint64 [N] (x in the lowest bit)."""
    return interleave(ordered_keys(np.asarray(xyz16, np.float16).reshape(-1, 3)))


def morton_to_xyz(codes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`morton_codes`: float16 [N, 3]."""
    return keys_to_fp16(deinterleave(codes, 3))


def canonical_order(xyz: np.ndarray) -> np.ndarray:
    """Stable Morton order of the fp16-rounded positions ``xyz: [N, 3]``: the storage order of the "ans" codec."""
    return np.argsort(morton_codes(np.asarray(xyz, np.float16)), kind="stable")


def encode_xyz_morton(xyz16: np.ndarray) -> bytes:
    """fp16 positions [N, 3] (in Morton order) as their sorted Morton codes (the ``morton`` encoding)."""
    return encode_sorted_codes(morton_codes(xyz16))


def decode_xyz_morton(data: bytes, count: int) -> np.ndarray:
    """``count`` fp16 positions [count, 3] of a ``morton`` section; checks finiteness."""
    codes = decode_sorted_codes(data, count, 48, strict=False, damaged="Morton codes")
    xyz = morton_to_xyz(codes)
    if not np.isfinite(xyz).all():
        raise CorruptFileError("non-finite positions")
    return xyz


# ------------------------------------------------------------------ float sections
def _f16_planes(values: np.ndarray) -> bytes:
    bits = values.view(np.uint16).ravel()
    hi = encode_indices(bits >> 8, 256, "ans")
    return pack_varints(np.array([len(hi)])) + hi + encode_indices(bits & 0xFF, 256, "ans")


def encode_f16(values: np.ndarray, encoding: str) -> bytes:
    """The bytes of a float section: fp16 values as they are (``f16``), LZMA-compressed (``f16-lzma``) or split
    into byte planes (``f16-planes``)."""
    raw = np.ascontiguousarray(values, dtype="<f2")
    if encoding == "f16":
        return raw.tobytes()
    if encoding == "f16-lzma":
        return lzma.compress(raw.tobytes(), format=lzma.FORMAT_RAW, filters=LZMA_FILTERS)
    return _f16_planes(raw)


def smallest_f16(values: np.ndarray) -> tuple[str, bytes]:
    """(encoding, bytes) of the smallest of the :data:`F16_ENCODINGS` for ``values`` (the first among equals)."""
    options = [(enc, encode_f16(values, enc)) for enc in F16_ENCODINGS]
    return min(options, key=lambda o: len(o[1]))


def decode_f16(data: bytes, encoding: str, count: int) -> np.ndarray:
    """``count`` fp16 values of a float section; checks length and finiteness."""
    if encoding == "f16":
        raw = data
    elif encoding == "f16-lzma":
        d = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=LZMA_FILTERS)
        try:
            raw = d.decompress(data, max_length=2 * count)
        except lzma.LZMAError:
            raise CorruptFileError("damaged LZMA data") from None
        if not d.eof or d.unused_data:
            raise CorruptFileError("damaged LZMA data (wrong length)")
    elif encoding == "f16-planes":
        (size,), used = unpack_varints(data, 1, "plane sizes")
        if size > len(data) - used:
            raise CorruptFileError("truncated byte planes")
        hi = decode_indices(data[used:used + int(size)], 256, count, "ans")
        lo = decode_indices(data[used + int(size):], 256, count, "ans")
        raw = ((hi << 8) | lo).astype("<u2").tobytes()
    else:
        raise CorruptFileError(f"unknown encoding {encoding!r}")
    if len(raw) != 2 * count:
        raise CorruptFileError(f"{len(raw)} bytes of fp16 data, expected {2 * count}")
    values = np.frombuffer(raw, "<f2").astype(np.float16)
    if not np.isfinite(values).all():
        raise CorruptFileError("non-finite values")
    return values


__all__ = ["F16_ENCODINGS", "LZMA_FILTERS", "canonical_order", "decode_f16", "decode_xyz_morton", "encode_f16",
           "encode_xyz_morton", "morton_codes", "morton_to_xyz", "smallest_f16"]
