"""What an ``.omg4`` file stores, and its mapping onto container sections (omg4 §8).

A :class:`CompressedPayload` holds the explicit per-Gaussian data OMG4 keeps after
attribute compression (paper §4.4): positions ``xyz`` and time centres ``t`` (fp16), for
each sub-vector-quantized attribute its fp16 codebooks and index streams, the fp16
weights of the appearance MLPs, and a JSON-able ``meta`` dict (preset, SH degrees, time
range, normalization, ...).

Three codecs:

* ``"compact"`` (default) — beyond OMG4's coder, at the same quality (container version 5): positions on
  a uniform 15-bit grid over the scene's box in Z-order (the largest 3 % of Gaussians exactly), time centres
  on a grid of 1/1024 of the clip
  (:mod:`omg4.codec.grids`); each SVQ slot's codebook and indices coded without paying for the codewords'
  order (:mod:`omg4.codec.codewords`: unused and duplicate codewords dropped, the smaller of a sorted
  codeword set or first-use order), the codebooks of log-scale attributes (``log_scaled``: scales and
  durations, exp-activated) first rounded to steps of 1/32 in log space (a 3 % size step, so nearby
  codewords merge); rotation quaternions as unit quaternions in 3 × 9 bits (:mod:`omg4.codec.quaternions`)
  where that is smaller than their codebooks; MLP weight matrices in 8 bits per weight, a scale per column
  (:mod:`omg4.codec.weights`); the header deflated. Everything but the codewords' order and the header
  changes values, each by a small amount measured in ``docs/results.md`` (coders). Version-3 and -4 compact files (no exact
  positions, a weight scale per row) and version-2 ones (fp16 positions as Morton codes, fp16 time centres,
  3 × 10-bit quaternions, codebooks as stored) still decode.
* ``"paper"`` — OMG4's ``encode``: fp16 positions, time centres, codebooks and MLP weights,
  Huffman-coded indices, everything LZMA-compressed (OMG4 wraps one pickle in xz; here
  each section is LZMA'd on its own — no pickle). Gaussians keep their order.
* ``"ans"`` — lossless w.r.t. the same fp16 values and indices, smaller:
  Gaussians are stored in Morton (Z-order) order of their fp16 positions (a free
  permutation: Gaussians are unordered), so positions become sorted 48-bit Morton codes
  whose gaps are hybrid-uint coded; indices are ANS-coded; every float section takes the
  smallest of raw fp16, LZMA, or byte planes ANS-coded.

``decode_payload`` validates everything (index < codebook size, consistent counts, finite
floats) and raises :class:`~omg4.errors.CorruptFileError` with one line otherwise.
"""

from __future__ import annotations

import lzma
import math
import os
import re
from dataclasses import astuple, dataclass, field

import numpy as np

from omg4.codec import grids, quaternions, weights
from omg4.codec.codewords import (decode_first_use_indices, decode_sorted_codebook, decode_sorted_codes, deinterleave,
                                  encode_codewords, encode_sorted_codes, interleave, keys_to_fp16, ordered_keys)
from omg4.codec.container import SEQUENCE_VERSION, read_versioned, write_container
from omg4.codec.entropy import MAX_SYMBOLS, decode_indices, encode_indices, pack_varints, unpack_varints
from omg4.codec.rig import check_rig
from omg4.errors import CorruptFileError, OMG4Error

KIND = "omg4-compressed-model"
#: payload codecs, the default first (module docstring)
CODECS = ("compact", "ans", "paper")
MAX_GAUSSIANS = 1 << 27
MAX_SUB_LEN = 64
MAX_MLP_ELEMENTS = 1 << 24
MAX_MLP_DIMS = 4
MAX_MLP_WEIGHTS = 64
MAX_ATTRIBUTES = 32
MAX_SLOTS = 64  # sub-vectors (codebooks) per attribute
#: A header may not declare more Gaussians than the file's section bytes / this, beyond the first
#: GAUSSIANS_ALWAYS_ALLOWED (real files spend 10-25 bytes per Gaussian: positions alone take about
#: 3; a forged one declaring millions in a few kilobytes is refused before anything is decoded).
MIN_BYTES_PER_GAUSSIAN = 4
GAUSSIANS_ALWAYS_ALLOWED = 4096
#: Decoded values (floats, indices, reconstructed attributes) per section byte a header may declare,
#: plus a fixed allowance for tiny files with large, highly compressible codebooks; real files
#: declare about 1 per byte.
MAX_VALUES_PER_BYTE = 64
VALUES_SLACK = 1 << 20
_NAME = re.compile(r"[A-Za-z0-9_]{1,64}")  # SVQ attribute names
_MLP_NAME = re.compile(r"[A-Za-z0-9_.]{1,128}")  # state-dict style weight names
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 6}]
#: allowed bits of each :class:`CompactGrids` field (what the writer accepts)
GRID_BITS_ALLOWED = {"positions": (0, 16), "rotations": (2, 16), "times": (0, 16), "weights": (2, 16),
                     "log_scales": (0, 14), "codebooks": (0, 14), "exact": (0, 100)}


@dataclass(frozen=True)
class CompactGrids:
    """The grids of the "compact" codec's lossy values (beyond the paper; ``docs/results.md``, coders), a rate–distortion knob the
    decoder needs no setting for (each section records its grid, or holds fp16 values).

    positions: bits per axis over the scene box's largest side (:func:`omg4.codec.grids.encode_positions`), or 0:
    the fp16 positions as the paper, losslessly (sorted Morton codes, as the "ans" codec);
    rotations: bits per "smallest three" quaternion component (:mod:`omg4.codec.quaternions`), or 16: the rotation
    codebooks and indices as the pipeline made them, losslessly;
    times: time centres on steps of the clip's duration · 2^-times (:func:`omg4.codec.grids.time_step`), or 0: fp16
    as the paper;
    weights: MLP weight matrices in 2-8 bits per weight, a scale per column (:mod:`omg4.codec.weights`; a file with
    such a matrix is container version 5), or 16 (fp16, as the paper);
    log_scales: codebooks of log-scale attributes rounded to steps of 2^-log_scales in log space, or 0: as they are;
    codebooks: the other codebooks (appearance features, FreeTimeGS velocities; not rotations) rounded to steps of
    2^-codebooks, or 0 (the
    default): as they are — near-equal codewords then merge, so indices shrink too;
    exact: the percentage of Gaussians, the largest (:func:`largest_footprints`), whose grid positions are
    corrected to their fp16 values exactly (:func:`omg4.codec.grids.encode_positions`; a file with any is
    container version 5), or 0: none. The default 3 % costs a few hundredths of a byte per Gaussian and keeps one
    large Gaussian's
    appearance from changing a whole view (``docs/results.md``, coders).
    ``CompactGrids(0, 16, 0, 16, 0)`` stores the paper coder's values exactly (a lossless compact file).
    """

    positions: int = grids.POSITION_BITS
    rotations: int = quaternions.BITS
    times: int = grids.TIME_BITS
    weights: int = 8
    log_scales: int = 5
    codebooks: int = 0
    exact: int = 3

    def __post_init__(self):
        for name, (lo, hi) in GRID_BITS_ALLOWED.items():
            bits = getattr(self, name)
            if isinstance(bits, bool) or not isinstance(bits, int) or not lo <= bits <= hi:
                what = "percentage" if name == "exact" else "bits"
                raise OMG4Error(f"compact grid: {name} {what} must be an integer in [{lo}, {hi}], got {bits!r}")
        if 8 < self.weights < 16:
            raise OMG4Error(f"compact grid: weights take 2-8 bits, or 16 (fp16), got {self.weights}")

    @classmethod
    def parse(cls, text: str) -> "CompactGrids":
        """From ``"POSITIONS,ROTATIONS,TIMES[,WEIGHTS,LOG_SCALES[,CODEBOOKS[,EXACT]]]"``, e.g. ``"15,9,10"``,
        ``"16,12,12,16,10"``, ``"15,8,8,8,5,6"`` or ``"12,7,7,8,5,0,1"``, or a name: ``"default"`` (15,9,10,8,5,0,3)
        or ``"lossless"`` (0,16,0,16,0,0,3: the paper coder's values; exact positions are moot without a grid)."""
        named = {"default": cls(), "lossless": cls(0, 16, 0, 16, 0)}
        if text.strip().lower() in named:
            return named[text.strip().lower()]
        parts = [p.strip() for p in text.split(",")]
        if len(parts) not in _GRID_LENGTHS or not all(re.fullmatch(r"[0-9]{1,3}", p) for p in parts):
            raise OMG4Error(f"compact grid {text!r}: give three integers POSITIONS,ROTATIONS,TIMES such as 15,9,10, "
                            "five to seven with WEIGHTS,LOG_SCALES[,CODEBOOKS[,EXACT]] such as 16,12,12,16,10, "
                            "15,8,8,8,5,6 or 12,7,7,8,5,0,2, or default or lossless")
        return cls(*(int(p) for p in parts))

    @property
    def label(self) -> str:
        """``"15/9/10"`` (positions/rotations/times bits), then as many of ``/weights/log_scales``, ``/codebooks``
        and ``/exact`` as the last field that is not the default needs (the forms :meth:`parse` reads)."""
        fields = astuple(self)
        defaults = astuple(CompactGrids())
        length = next(n for n in _GRID_LENGTHS if fields[n:] == defaults[n:])
        return "/".join(map(str, fields[:length]))


_GRID_LENGTHS = (3, 5, 6, 7)  # how many CompactGrids fields a grid string may give


@dataclass
class QuantizedAttribute:
    """One sub-vector-quantized attribute (paper §4.4; omg4 §7).

    ``codebooks[j]: [K_j, s_j]`` (fp16) holds the centroids of sub-vector slot j and
    ``indices[j]: [N]`` (int) picks a row per Gaussian; the attribute is the concatenation
    of ``codebooks[j][indices[j]]`` over slots, ``[N, Σ s_j]``.
    """

    codebooks: list[np.ndarray]
    indices: list[np.ndarray]

    def reconstruct(self) -> np.ndarray:
        """The quantized attribute values, float32 ``[N, D]``."""
        return np.concatenate([cb.astype(np.float32)[ix] for cb, ix in zip(self.codebooks, self.indices)], axis=1)


@dataclass
class CompressedPayload:
    """Everything an ``.omg4`` file stores (omg4 §8).

    xyz: [N, 3] positions; t: [N] time centres; attributes: SVQ attribute name (scale,
    rotation, app, scale_t, rotation_r) → :class:`QuantizedAttribute`; mlp: weight name →
    array (any shape); meta: JSON-able settings; rotations: the attributes that are one rotation
    quaternion each, normalized at use (the backbone's ``quaternion_groups``; the "compact" codec
    may store them as unit quaternions). Floats are stored in fp16.
    """

    xyz: np.ndarray
    t: np.ndarray
    attributes: dict[str, QuantizedAttribute] = field(default_factory=dict)
    mlp: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    rotations: tuple[str, ...] = ()
    log_scaled: tuple[str, ...] = ()

    @property
    def num_gaussians(self) -> int:
        return int(self.xyz.shape[0])

    def permuted(self, order: np.ndarray) -> "CompressedPayload":
        """The same payload with Gaussians reordered: row i of the result is row ``order[i]``."""
        attrs = {a: QuantizedAttribute(list(q.codebooks), [ix[order] for ix in q.indices])
                 for a, q in self.attributes.items()}
        return CompressedPayload(self.xyz[order], self.t[order], attrs, dict(self.mlp), dict(self.meta), self.rotations,
                                 self.log_scaled)

    def to_fp16(self) -> "CompressedPayload":
        """What a decoder returns: floats rounded to fp16 (float16 arrays), indices as int64."""
        attrs = {a: QuantizedAttribute([np.asarray(cb, np.float16) for cb in q.codebooks],
                                       [np.asarray(ix).astype(np.int64) for ix in q.indices])
                 for a, q in self.attributes.items()}
        return CompressedPayload(np.asarray(self.xyz, np.float16).reshape(-1, 3),
                                 np.asarray(self.t, np.float16).reshape(-1), attrs,
                                 {k: np.asarray(v, np.float16) for k, v in self.mlp.items()}, dict(self.meta),
                                 tuple(self.rotations), tuple(self.log_scaled))


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


# ------------------------------------------------------------------ float sections
def _f16_planes(values: np.ndarray) -> bytes:
    bits = values.view(np.uint16).ravel()
    hi = encode_indices(bits >> 8, 256, "ans")
    return pack_varints(np.array([len(hi)])) + hi + encode_indices(bits & 0xFF, 256, "ans")


def encode_f16(values: np.ndarray, encoding: str) -> bytes:
    """The bytes of a float section: fp16 values as they are (``f16``), LZMA-compressed (``f16-lzma``) or split
    into byte planes (docs/file-format.md, "Float encodings")."""
    raw = np.ascontiguousarray(values, dtype="<f2")
    if encoding == "f16":
        return raw.tobytes()
    if encoding == "f16-lzma":
        return lzma.compress(raw.tobytes(), format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
    return _f16_planes(raw)


def decode_f16(data: bytes, encoding: str, count: int) -> np.ndarray:
    """``count`` fp16 values of a float section; checks length and finiteness."""
    if encoding == "f16":
        raw = data
    elif encoding == "f16-lzma":
        d = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS)
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


def _smallest_f16(values: np.ndarray) -> tuple[str, bytes]:
    options = [(enc, encode_f16(values, enc)) for enc in ("f16", "f16-lzma", "f16-planes")]
    return min(options, key=lambda o: len(o[1]))


def _encode_xyz_morton(xyz16: np.ndarray) -> bytes:
    return encode_sorted_codes(morton_codes(xyz16))


def _decode_xyz_morton(data: bytes, count: int) -> np.ndarray:
    codes = decode_sorted_codes(data, count, 48, strict=False, damaged="Morton codes")
    xyz = morton_to_xyz(codes)
    if not np.isfinite(xyz).all():
        raise CorruptFileError("non-finite positions")
    return xyz


# ------------------------------------------------------------------------ encoding
def container_version(codec: object, encodings: object = None) -> int:
    """The container version of a file of ``codec`` whose sections have ``encodings`` (``{section: name}``): 3 for
    "compact" (deflated JSON, grid-coded sections), 4 for "compact" with an MLP weight in fewer than 8 bits per row and
    5 for "compact" with exact positions or column-scaled weights (encodings builds reading 1-3, or 1-4, do not
    know), 1 otherwise, so files
    of the older codecs stay readable by builds that predate versions 2 to 5. Any ``encodings`` value is accepted
    (a forged header's too)."""
    if codec != "compact":
        return 1
    names = [e for e in (encodings.values() if isinstance(encodings, dict) else ()) if isinstance(e, str)]
    weight_encodings = [parsed for e in names if (parsed := weights.parse_encoding(e))]
    if grids.POSITIONS_EXACT in names or any(columns for _, columns in weight_encodings):
        return 5
    return 4 if any(bits < weights.BITS for bits, _ in weight_encodings) else 3


def largest_footprints(p: CompressedPayload, percent: int) -> np.ndarray:
    """bool ``[N]``: the ⌈percent · N / 100⌉ Gaussians of ``p`` with the largest footprint — the product of their two
    largest scales, from the 3-wide log-scale attribute ``scale`` of both backbones, as ``p`` holds it (the writer
    passes its fp16 payload in storage order, before log-scale rounding) — whose positions the compact codec stores
    exactly (:class:`CompactGrids` ``exact``); none without such an attribute. Ties: the earlier row."""
    chosen = np.zeros(p.num_gaussians, bool)
    scale = p.attributes.get("scale")
    if not percent or scale is None or "scale" not in p.log_scaled:
        return chosen
    log_scales = scale.reconstruct().astype(np.float64)
    if log_scales.shape[1] != 3:
        return chosen
    footprint = np.sort(log_scales, axis=1)[:, 1:].sum(axis=1)  # log of the two largest scales' product
    chosen[np.argsort(-footprint, kind="stable")[:math.ceil(percent * p.num_gaussians / 100)]] = True
    return chosen


def _quaternion_stored(q: QuantizedAttribute, name: str, rotations: tuple[str, ...], precision: CompactGrids) -> bool:
    """Whether the compact codec may store attribute ``name`` as unit quaternions (a rotation, 4 wide, unless the
    grids keep rotation codebooks: ``precision.rotations`` 16)."""
    return (precision.rotations < 16 and name in rotations
            and sum(int(np.shape(cb)[1]) for cb in q.codebooks) == 4)


def _check_payload(p: CompressedPayload, codec: str, precision: CompactGrids) -> CompressedPayload:
    """The fp16/int64 form of ``p`` after checking shapes, names, ranges and finiteness (OMG4Error).

    A rotation the compact codec stores as unit quaternions (``precision.rotations`` < 16) may have codebooks of
    any length (a decoded compact file holds one row per Gaussian); every other codebook has at most MAX_SYMBOLS
    rows."""
    n = int(np.asarray(p.xyz).shape[0]) if np.asarray(p.xyz).ndim == 2 else -1
    if n < 1 or np.asarray(p.xyz).shape != (n, 3) or np.asarray(p.t).size != n:
        raise OMG4Error(f"payload needs xyz [N, 3] and t [N] with N >= 1, got {np.shape(p.xyz)} and {np.shape(p.t)}")
    if n > MAX_GAUSSIANS:
        raise OMG4Error(f"payload has {n} Gaussians (limit {MAX_GAUSSIANS})")
    for attr, qa in p.attributes.items():
        if not all(np.issubdtype(np.asarray(ix).dtype, np.integer) for ix in qa.indices):
            raise OMG4Error(f"attribute {attr}: index arrays must be integers")
    with np.errstate(over="ignore"):
        q = p.to_fp16()
    for name in q.attributes:
        if not _NAME.fullmatch(name):
            raise OMG4Error(f"invalid attribute name {name!r} (letters, digits, underscore)")
    for name in q.mlp:
        if not _MLP_NAME.fullmatch(name):
            raise OMG4Error(f"invalid MLP weight name {name!r} (letters, digits, underscore, dot)")
    for name, arr in [("xyz", q.xyz), ("t", q.t), *q.mlp.items()]:
        if not np.isfinite(arr).all():
            raise OMG4Error(f"{name} has NaN/Inf or values beyond the fp16 range")
    for attr, qa in q.attributes.items():
        if not qa.codebooks or len(qa.codebooks) != len(qa.indices):
            raise OMG4Error(f"attribute {attr}: needs one index array per codebook")
        any_length = codec == "compact" and _quaternion_stored(qa, attr, q.rotations, precision)
        max_rows = max(n, MAX_SYMBOLS) if any_length else MAX_SYMBOLS
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            if cb.ndim != 2 or not 1 <= cb.shape[0] <= max_rows or not 1 <= cb.shape[1] <= MAX_SUB_LEN:
                raise OMG4Error(f"attribute {attr}: codebook {j} has shape {cb.shape} (at most {MAX_SYMBOLS} rows of "
                                f"at most {MAX_SUB_LEN}; more rotations than that only the compact codec stores, as unit "
                                "quaternions)")
            if not np.isfinite(cb).all():
                raise OMG4Error(f"attribute {attr}: codebook {j} has NaN/Inf or values beyond the fp16 range")
            if ix.shape != (n,) or ix.min() < 0 or ix.max() >= cb.shape[0]:
                raise OMG4Error(f"attribute {attr}: index array {j} must be [N] with values in [0, {cb.shape[0]})")
    return q


def round_codebook(codebook: np.ndarray, bits: int) -> np.ndarray:
    """A codebook rounded to steps of 2^-bits, then to fp16 (for the log-scale codebooks at the default 5 bits fp16
    holds every such value below 64 exactly, so rounding twice changes nothing)."""
    step = 2.0 ** -bits
    return (np.rint(np.asarray(codebook, np.float64) / step) * step).astype(np.float16)


def _encode_compact_attribute(name: str, qa: QuantizedAttribute, as_quaternion: bool, round_bits: int,
                              precision: CompactGrids, sections: dict[str, bytes], encodings: dict[str, str]
                              ) -> list[list[int]] | None:
    """Add the sections of one SVQ attribute in the "compact" codec at ``precision``, its codebooks rounded to steps of
    2^-round_bits (0: as they are); returns its codebook shapes, or None when it was stored as unit quaternions
    (smaller than its codebooks and indices, or too many rows for them)."""
    quat = quaternions.encode_quaternions(qa.reconstruct(), precision.rotations) if as_quaternion else None
    slots, shapes = {}, []
    if max(cb.shape[0] for cb in qa.codebooks) <= MAX_SYMBOLS:
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            cb = round_codebook(cb, round_bits) if round_bits else cb
            cb_enc, cb_bytes, ix_enc, ix_bytes, k = encode_codewords(cb, ix, _smallest_f16)
            slots[f"svq.{name}.codebook{j}"], slots[f"svq.{name}.index{j}"] = (cb_enc, cb_bytes), (ix_enc, ix_bytes)
            shapes.append([k, int(cb.shape[1])])
    if quat is not None and (not slots or len(quat) < sum(len(b) for _, b in slots.values())):
        sections[f"quat.{name}"], encodings[f"quat.{name}"] = quat, quaternions.encoding(precision.rotations)
        return None
    for section, (enc, data) in slots.items():
        sections[section], encodings[section] = data, enc
    return shapes


def check_codec(codec: str, precision: CompactGrids = CompactGrids()) -> None:
    """Raise :class:`~omg4.errors.OMG4Error` unless ``codec`` is one of :data:`CODECS` and ``precision`` is the
    default or ``codec`` is "compact" (the only codec with grids)."""
    if codec not in CODECS:
        raise OMG4Error(f"unknown codec {codec!r} (choose from {', '.join(CODECS)})")
    if codec != "compact" and precision != CompactGrids():
        raise OMG4Error(f"grids {precision.label} apply to the compact codec only, not {codec!r}")


def encode_payload(p: CompressedPayload, path: str | os.PathLike, codec: str = CODECS[0],
                   precision: CompactGrids = CompactGrids()) -> dict[str, int]:
    """Write ``p`` to ``path`` (atomically) with ``codec`` from :data:`CODECS`; ``precision``: the "compact" codec's
    grids (any other is refused with another codec).

    With "ans" the Gaussians are stored in :func:`canonical_order`, so the decoded payload
    equals ``p.permuted(canonical_order(p.xyz)).to_fp16()``; with "paper" it equals
    ``p.to_fp16()``. With "compact" the order is :func:`omg4.codec.grids.position_order` (:func:`canonical_order`
    with ``precision.positions`` 0),
    positions (but the largest ``precision.exact`` %) and time centres are on their grids, and every SVQ
    attribute reconstructs to the same fp16
    values (codebooks relabelled, unused and duplicate codewords dropped), except the log-scale codebooks
    rounded to steps of 2^-5 in log space, the quaternion attributes stored on the unit-quaternion grid and the
    MLP weight matrices stored in 8 bits (other grids: ``precision``). Returns the byte size of every section
    plus ``"header"``; the values sum to the file size.
    """
    check_codec(codec, precision)
    q = _check_payload(p, codec, precision)
    fp16_positions = codec == "ans" or (codec == "compact" and not precision.positions)
    if codec == "compact" and not fp16_positions:
        q = q.permuted(grids.position_order(q.xyz, precision.positions))
    elif fp16_positions:
        q = q.permuted(canonical_order(q.xyz))
    sections: dict[str, bytes] = {}
    encodings: dict[str, str] = {}

    def put_float(name: str, values: np.ndarray, fixed: str | None = None) -> None:
        enc, data = (fixed, encode_f16(values, fixed)) if fixed else _smallest_f16(values)
        sections[name], encodings[name] = data, enc

    float_encoding = "f16-lzma" if codec == "paper" else None
    if codec == "paper":
        put_float("xyz", q.xyz, float_encoding)
    elif fp16_positions:
        sections["xyz"], encodings["xyz"] = _encode_xyz_morton(q.xyz), "morton"
    else:
        exact = largest_footprints(q, precision.exact)
        sections["xyz"] = grids.encode_positions(q.xyz, precision.positions, exact)
        encodings["xyz"] = grids.POSITIONS_EXACT if exact.any() else grids.POSITIONS
    times = (grids.encode_times(q.t, grids.time_step(q.t, q.meta.get("time_range"), precision.times))
             if codec == "compact" and precision.times else None)
    if times is None:
        put_float("t", q.t, float_encoding)
    else:
        sections["t"], encodings["t"] = times, grids.TIMES
    shapes: dict[str, list[list[int]]] = {}
    stored_as_quaternions: list[str] = []
    if codec == "compact":
        for attr, qa in q.attributes.items():
            as_quaternion = _quaternion_stored(qa, attr, q.rotations, precision)
            round_bits = (precision.log_scales if attr in q.log_scaled
                          else 0 if attr in q.rotations else precision.codebooks)
            attr_shapes = _encode_compact_attribute(attr, qa, as_quaternion, round_bits, precision, sections,
                                                    encodings)
            if attr_shapes is None:
                stored_as_quaternions.append(attr)
            else:
                shapes[attr] = attr_shapes
    else:
        for attr, qa in q.attributes.items():
            for j, cb in enumerate(qa.codebooks):
                put_float(f"svq.{attr}.codebook{j}", cb, float_encoding)
            for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
                name = f"svq.{attr}.index{j}"
                sections[name], encodings[name] = encode_indices(ix, cb.shape[0], codec), codec
            shapes[attr] = [list(cb.shape) for cb in qa.codebooks]
    for name, w in q.mlp.items():
        if codec == "compact" and w.ndim == 2 and w.size and precision.weights <= weights.BITS:
            sections[f"mlp.{name}"] = weights.encode_columns(w, precision.weights)
            encodings[f"mlp.{name}"] = weights.encoding(precision.weights)
        else:
            put_float(f"mlp.{name}", w, float_encoding)
    header = {
        "kind": KIND, "codec": codec, "order": "original" if codec == "paper" else "morton",
        "num_gaussians": q.num_gaussians, "meta": q.meta,
        "attributes": shapes,
        "mlp": {k: list(w.shape) for k, w in q.mlp.items()},
        "encodings": encodings,
        "rotations": [a for a in q.rotations if a in q.attributes],
        "log_scaled": [a for a in q.log_scaled if a in shapes],  # not those stored as unit quaternions
    }
    if codec == "compact":
        header["quaternions"] = stored_as_quaternions
    sizes = {name: len(data) for name, data in sections.items()}
    try:  # the decoder's limits hold for every file written, so no written file is refused on reading
        check_sections(header, sizes)
    except CorruptFileError as exc:
        raise OMG4Error(f"this model cannot be stored: {exc}") from None
    total = write_container(path, header, sections, version=container_version(codec, encodings))
    sizes["header"] = total - sum(sizes.values())
    return sizes


# ------------------------------------------------------------------------ decoding
def _is_int(v: object, lo: int, hi: int) -> bool:
    return type(v) is int and lo <= v <= hi


def _check_header(h: dict, section_bytes: int) -> None:
    """Structural validation of a payload header against hard limits and the file's own size.

    Every count and shape is an exact Python integer; a count above :data:`GAUSSIANS_ALWAYS_ALLOWED`
    may not exceed the section bytes / :data:`MIN_BYTES_PER_GAUSSIAN`, and the values the sections decode to
    (floats, indices, reconstructed attributes) may not exceed :data:`MAX_VALUES_PER_BYTE` per
    section byte plus :data:`VALUES_SLACK`, so a forged header cannot make the decoder
    allocate or inflate more than a bounded multiple of the file. Raises CorruptFileError.
    """
    n = h.get("num_gaussians")
    ok = (h.get("kind") == KIND and h.get("codec") in CODECS and isinstance(h.get("meta"), dict)
          and isinstance(h.get("attributes"), dict) and isinstance(h.get("mlp"), dict)
          and isinstance(h.get("encodings"), dict) and _is_int(n, 1, MAX_GAUSSIANS))
    if not ok:
        raise CorruptFileError("not an OMG4 compressed model (header fields missing or invalid)")
    if "rig" in h["meta"]:
        check_rig(h["meta"]["rig"])
    rotations = h.get("quaternions", [])
    if (("quaternions" in h) != (h["codec"] == "compact") or not isinstance(rotations, list)
            or len(rotations) > MAX_ATTRIBUTES or len(set(map(str, rotations))) != len(rotations)
            or not all(isinstance(a, str) and _NAME.fullmatch(a) and a not in h["attributes"] for a in rotations)):
        raise CorruptFileError("invalid list of quaternion attributes")
    named = h.get("rotations", [])
    if not (isinstance(named, list) and len(named) <= MAX_ATTRIBUTES
            and all(isinstance(a, str) and (a in h["attributes"] or a in rotations) for a in named)):
        raise CorruptFileError("invalid list of rotation attributes")
    if n > GAUSSIANS_ALWAYS_ALLOWED and n * MIN_BYTES_PER_GAUSSIAN > section_bytes:
        raise CorruptFileError(f"header claims {n} Gaussians, more than the file's {section_bytes} data bytes can hold")
    if len(h["attributes"]) > MAX_ATTRIBUTES or len(h["mlp"]) > MAX_MLP_WEIGHTS:
        raise CorruptFileError(f"header lists {len(h['attributes'])} attributes and {len(h['mlp'])} MLP weights "
                               f"(limits {MAX_ATTRIBUTES} and {MAX_MLP_WEIGHTS})")
    values = 8 * n + 8 * n * len(rotations)  # xyz, t and exact-position corrections; per rotation 4 codes and 4 values
    for attr, shapes in h["attributes"].items():
        if not (_NAME.fullmatch(attr) and isinstance(shapes, list) and 1 <= len(shapes) <= MAX_SLOTS and all(
                isinstance(s, list) and len(s) == 2 and _is_int(s[0], 1, MAX_SYMBOLS) and _is_int(s[1], 1, MAX_SUB_LEN)
                for s in shapes)):
            raise CorruptFileError(f"invalid codebook shapes for attribute {attr!r}")
        # codebooks, one index per Gaussian and slot, and the reconstructed [N, D] attribute
        values += sum(k * d for k, d in shapes) + n * len(shapes) + n * sum(d for _, d in shapes)
    logs = h.get("log_scaled", [])
    if not (isinstance(logs, list) and len(logs) <= MAX_ATTRIBUTES
            and all(isinstance(a, str) and a in h["attributes"] for a in logs)):
        raise CorruptFileError("invalid list of log-scale attributes")
    for name, shape in h["mlp"].items():
        ok = (_MLP_NAME.fullmatch(name) and isinstance(shape, list) and len(shape) <= MAX_MLP_DIMS
              and all(_is_int(s, 0, MAX_MLP_ELEMENTS) for s in shape) and math.prod(shape) <= MAX_MLP_ELEMENTS)
        if not ok:
            raise CorruptFileError(f"invalid shape for MLP weight {name!r}")
        values += math.prod(shape)
    if values > MAX_VALUES_PER_BYTE * section_bytes + VALUES_SLACK:
        raise CorruptFileError(f"header declares {values} values, more than {section_bytes} data bytes can encode")


def check_sections(header: dict, section_sizes: dict[str, int]) -> None:
    """Validate a payload header (:func:`_check_header`) and that the sections present (name → byte size) are
    exactly those it names; raises :class:`CorruptFileError`. Used by the decoder and by ``omg4 info``."""
    _check_header(header, sum(section_sizes.values()))
    expected = ["xyz", "t"]
    expected += [f"svq.{a}.{kind}{j}" for a, shapes in header["attributes"].items()
                 for kind in ("codebook", "index") for j in range(len(shapes))]
    expected += [f"mlp.{name}" for name in header["mlp"]]
    expected += [f"quat.{attr}" for attr in header.get("quaternions", [])]
    encodings = header["encodings"]
    if (sorted(expected) != sorted(section_sizes) or sorted(expected) != sorted(encodings)
            or not all(isinstance(e, str) for e in encodings.values())):
        raise CorruptFileError("section list does not match the header")


def decode_payload(source: str | os.PathLike | bytes) -> CompressedPayload:
    """Read an ``.omg4`` file (path or bytes) written by :func:`encode_payload`; fp16 floats, int64 indices.

    Any damage raises a one-line :class:`CorruptFileError` naming the file and section.
    """
    version, header, sections = read_versioned(source)
    label = "data" if isinstance(source, (bytes, bytearray, memoryview)) else str(source)
    if version == SEQUENCE_VERSION or header.get("layout") is not None:
        if version == SEQUENCE_VERSION and header.get("layout") == "sequence":
            raise OMG4Error(f"{label} is a sequence of {len(sections)} segments, not one model: open it with "
                            "omg4.load_model (or any omg4 command)")
        raise CorruptFileError(f"{label}: a single-model header and a sequence's version or layout")
    try:
        return _decode_sections(header, sections)
    except CorruptFileError as exc:
        raise CorruptFileError(f"{label}: {exc}") from None


def _decode_sections(header: dict, sections: dict[str, bytes]) -> CompressedPayload:
    check_sections(header, {name: len(data) for name, data in sections.items()})
    n, codec, enc = header["num_gaussians"], header["codec"], header["encodings"]
    compact = codec == "compact"
    index_encodings = ("ranks", "first-use") if compact else (codec,)

    def decode(name: str, count: int, num_symbols: int = 0, shape: tuple[int, ...] | None = None) -> np.ndarray:
        """Decode section ``name``; each encoding is accepted only for the section kind it was made for."""
        try:
            data, encoding = sections[name], enc[name]
            if num_symbols:
                if encoding not in index_encodings:
                    raise CorruptFileError(f"encoding {encoding!r} is not an index encoding of the codec {codec!r}")
                if encoding == "first-use":
                    return decode_first_use_indices(data, num_symbols, count)
                return decode_indices(data, num_symbols, count, "ans" if encoding == "ranks" else codec)
            kind = name.split(".")[0]
            if kind == "quat":
                bits = quaternions.bits_of(encoding)
                if bits is None:
                    raise CorruptFileError(f"encoding {encoding!r} is not a quaternion encoding")
                return quaternions.decode_quaternions(data, count, bits)
            if compact and encoding == "sorted" and kind == "svq":
                return decode_sorted_codebook(data, *shape)
            if compact and weights.parse_encoding(encoding) and kind == "mlp" and len(shape) == 2:
                return weights.decode_matrix(data, shape, encoding)
            if encoding == "morton" and name == "xyz" and codec != "paper":
                return _decode_xyz_morton(data, count)
            if compact and encoding in (grids.POSITIONS, grids.POSITIONS_EXACT) and name == "xyz":
                return grids.decode_positions(data, count, exact=encoding == grids.POSITIONS_EXACT)
            if compact and encoding == grids.TIMES and name == "t":
                return grids.decode_times(data, count)
            return decode_f16(data, encoding, count)
        except CorruptFileError as exc:
            raise CorruptFileError(f"section {name}: {exc}") from None

    xyz = decode("xyz", n if enc["xyz"] in ("morton", grids.POSITIONS, grids.POSITIONS_EXACT) else 3 * n).reshape(n, 3)
    t = decode("t", n)
    attributes = {}
    for attr, shapes in header["attributes"].items():
        codebooks = [decode(f"svq.{attr}.codebook{j}", k * s, shape=(k, s)).reshape(k, s)
                     for j, (k, s) in enumerate(shapes)]
        indices = [decode(f"svq.{attr}.index{j}", n, k) for j, (k, _) in enumerate(shapes)]
        attributes[attr] = QuantizedAttribute(codebooks, indices)
    for attr in header.get("quaternions", []):  # one unit quaternion per Gaussian: an identity lookup
        attributes[attr] = QuantizedAttribute([decode(f"quat.{attr}", n).reshape(n, 4)], [np.arange(n)])
    mlp = {name: decode(f"mlp.{name}", math.prod(shape), shape=tuple(shape)).reshape(shape)
           for name, shape in header["mlp"].items()}
    return CompressedPayload(xyz, t, attributes, mlp, header["meta"], tuple(header.get("rotations", [])),
                             tuple(header.get("log_scaled", [])))
