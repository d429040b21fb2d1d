"""The codecs of an ``.omg4`` file, one class each, in one table (:data:`CODERS`; docs/file-format.md §4).

A coder decides how :func:`omg4.codec.payload.encode_payload` writes a payload: the Gaussians' storage order, the
sections of the positions, time centres, sub-vector-quantized attributes and MLP weights, extra header fields
and the container version. Reading follows each section's recorded encoding
(:func:`omg4.codec.payload.decode_payload`); a coder states which of those encodings its files may hold, so a
header that names one codec and encodings of another is refused. A new codec is a :class:`Coder` subclass and one
entry of :data:`CODERS` (:func:`register_coder`); its class's docstring describes it, and its settings are a class
of their own (:class:`CompactGrids` for ``compact``).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import astuple, dataclass

import numpy as np

from omg4.codec import grids, quaternions, weights
from omg4.codec.codewords import encode_codewords
from omg4.codec.encodings import ENCODINGS
from omg4.codec.entropy import MAX_SYMBOLS, encode_indices
from omg4.codec.sections import canonical_order, encode_f16, encode_xyz_morton, smallest_f16
from omg4.errors import OMG4Error

Section = tuple[str, bytes]
"""(encoding, bytes) of one section."""


class Coder:
    """The writing choices of one codec; the defaults store every float as the smallest fp16 section and the
    Gaussians in Morton order.

    Attributes: ``name`` (the header's ``codec``), ``order`` (the header's ``order``), ``takes_grids`` (whether
    :class:`CompactGrids` other than the default apply), and what its files may hold when
    read: ``index_encodings``, ``morton_positions``, ``grid_encodings`` (grid positions and times, sorted
    codebooks, quantized weights) and ``quaternion_sections`` (the header's ``quaternions`` list) — the rules the
    browser's reader takes too (:func:`browser_module`); ``browser_codec``: the codec a file becomes when its
    sections are rewritten for the browser (:mod:`omg4.codec.browser`), itself unless that changes its index
    encodings.
    """

    name = ""
    order = "morton"
    takes_grids = False
    index_encodings: tuple[str, ...] = ()
    morton_positions = True
    grid_encodings = False
    quaternion_sections = False

    @property
    def browser_codec(self) -> str:
        return self.name

    def float_section(self, values: np.ndarray) -> Section:
        return smallest_f16(values)

    def arrange(self, q, precision):
        """The payload ``q`` in the order its Gaussians are stored."""
        return q.permuted(canonical_order(q.xyz))

    def positions(self, q, precision) -> Section:
        return "morton", encode_xyz_morton(q.xyz)

    def times(self, q, precision) -> Section:
        return self.float_section(q.t)

    def attribute(self, name: str, qa, q, precision) -> tuple[list[list[int]] | None, dict[str, Section]]:
        """The codebook shapes of attribute ``name`` (None: stored as unit quaternions) and its sections, in order:
        every codebook, then every index stream."""
        sections = {f"svq.{name}.codebook{j}": self.float_section(cb) for j, cb in enumerate(qa.codebooks)}
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            sections[f"svq.{name}.index{j}"] = self.index_section(ix, cb.shape[0])
        return [list(cb.shape) for cb in qa.codebooks], sections

    def referenced_attribute(self, name: str, qa, encoding: str) -> tuple[list[list[int]], dict[str, Section]]:
        """Attribute ``name`` of a predicted segment whose codebooks are its reference's: the codebook sections as
        ``encoding`` (no bytes), the indices into those codebooks as they are."""
        sections = {f"svq.{name}.codebook{j}": (encoding, b"") for j in range(len(qa.codebooks))}
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            sections[f"svq.{name}.index{j}"] = self.index_section(ix, cb.shape[0])
        return [list(cb.shape) for cb in qa.codebooks], sections

    def index_section(self, indices: np.ndarray, num_symbols: int) -> Section:
        """An index stream into a codebook of ``num_symbols`` rows, coded as they are by the codec's first index
        encoding (an entropy method of :func:`omg4.codec.entropy.encode_indices`)."""
        encoding = self.index_encodings[0]
        return encoding, encode_indices(indices, num_symbols, encoding)

    def mlp_weight(self, w: np.ndarray, precision) -> Section:
        return self.float_section(w)

    def mlp_change(self, w: np.ndarray, reference: np.ndarray, precision) -> Section | None:
        """A predicted segment's MLP weight ``w`` as its change from the reference's decoded ``reference`` (same
        shape), or None where this codec stores weights as they are."""
        return None

    def any_length_rotation(self, qa, name: str, rotations: tuple[str, ...], precision) -> bool:
        """Whether attribute ``name`` may have codebooks longer than an index can address (stored another way)."""
        return False

    def version(self, encodings: object) -> int:
        """The container version of a file whose sections have ``encodings`` (1: every reader reads it)."""
        return 1


class AnsCoder(Coder):
    """``ans``: lossless w.r.t. the paper coder's fp16 values and indices, smaller. Gaussians are stored in Morton
    (Z-order) order of their fp16 positions (a free permutation: Gaussians are unordered), so positions become
    sorted 48-bit Morton codes whose gaps are hybrid-uint coded; indices are ANS-coded; every float section takes
    the smallest of raw fp16, LZMA, or byte planes ANS-coded."""

    name = "ans"
    index_encodings = ("ans",)


class PaperCoder(Coder):
    """``paper``: OMG4's ``encode`` — fp16 positions, time centres, codebooks and MLP weights, Huffman-coded
    indices, every section LZMA-compressed on its own (OMG4 wraps one pickle in xz; no pickle here); the Gaussians
    keep their order."""

    name = "paper"
    order = "original"
    index_encodings = ("paper",)
    morton_positions = False

    @property
    def browser_codec(self) -> str:
        return AnsCoder.name  # its Huffman index streams become ANS streams

    def float_section(self, values: np.ndarray) -> Section:
        return "f16-lzma", encode_f16(values, "f16-lzma")

    def arrange(self, q, precision):
        return q

    def positions(self, q, precision) -> Section:
        return self.float_section(q.xyz)


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


class CompactCoder(Coder):
    """``compact`` (the default) — beyond OMG4's coder, at the same quality (container version 5), its grids set by
    :class:`CompactGrids` (``settings``): positions on a uniform 15-bit grid over the scene's box in Z-order (the
    largest 3 % of Gaussians exactly), time centres on a grid of 1/1024 of the clip (:mod:`omg4.codec.grids`); each
    SVQ slot's codebook and indices coded without paying for the codewords' order (:mod:`omg4.codec.codewords`:
    unused and duplicate codewords dropped, the smaller of a sorted codeword set or first-use order), the codebooks
    of log-scale attributes (``log_scaled``: scales and durations, exp-activated) first rounded to steps of 1/32 in
    log space (a 3 % size step, so nearby codewords merge); rotation quaternions as unit quaternions in 3 × 9 bits
    (:mod:`omg4.codec.quaternions`) where that is smaller than their codebooks; MLP weight matrices in 8 bits per
    weight, a scale per column (:mod:`omg4.codec.weights`); the header deflated. Everything but the codewords'
    order and the header changes values, each by a small amount measured in ``docs/results.md`` (coders).
    Version-3 and -4 compact files (no exact positions, a weight scale per row) and version-2 ones (fp16 positions
    as Morton codes, fp16 time centres, 3 × 10-bit quaternions, codebooks as stored) still decode."""

    settings = CompactGrids

    name = "compact"
    takes_grids = True
    index_encodings = ("ranks", "first-use")
    grid_encodings = True
    quaternion_sections = True

    def arrange(self, q, precision):
        if not precision.positions:
            return super().arrange(q, precision)
        return q.permuted(grids.position_order(q.xyz, precision.positions))

    def positions(self, q, precision) -> Section:
        if not precision.positions:
            return super().positions(q, precision)
        exact = largest_footprints(q, precision.exact)
        return (grids.POSITIONS_EXACT if exact.any() else grids.POSITIONS,
                grids.encode_positions(q.xyz, precision.positions, exact))

    def times(self, q, precision) -> Section:
        """Time centres on their grid, or fp16 where the grid is off or the centres too spread for it."""
        coded = (grids.encode_times(q.t, grids.time_step(q.t, q.meta.get("time_range"), precision.times))
                 if precision.times else None)
        return super().times(q, precision) if coded is None else (grids.TIMES, coded)

    def attribute(self, name: str, qa, q, precision) -> tuple[list[list[int]] | None, dict[str, Section]]:
        """Each slot's codebook and indices by :func:`~omg4.codec.codewords.encode_codewords` (log-scale codebooks
        rounded to their grid first), or the attribute as unit quaternions where that is smaller (or its codebooks
        too long for indices)."""
        round_bits = (precision.log_scales if name in q.log_scaled
                      else 0 if name in q.rotations else precision.codebooks)
        as_quaternion = self.any_length_rotation(qa, name, q.rotations, precision)
        quat = quaternions.encode_quaternions(qa.reconstruct(), precision.rotations) if as_quaternion else None
        slots, shapes = {}, []
        if max(cb.shape[0] for cb in qa.codebooks) <= MAX_SYMBOLS:
            for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
                cb = round_codebook(cb, round_bits) if round_bits else cb
                cb_enc, cb_bytes, ix_enc, ix_bytes, k = encode_codewords(cb, ix, smallest_f16)
                slots[f"svq.{name}.codebook{j}"], slots[f"svq.{name}.index{j}"] = (cb_enc, cb_bytes), (ix_enc, ix_bytes)
                shapes.append([k, int(cb.shape[1])])
        if quat is not None and (not slots or len(quat) < sum(len(b) for _, b in slots.values())):
            return None, {f"quat.{name}": (quaternions.encoding(precision.rotations), quat)}
        return shapes, slots

    def index_section(self, indices: np.ndarray, num_symbols: int) -> Section:
        """Indices as they are: the "ranks" encoding (an ANS stream) of codewords in the order given."""
        return "ranks", encode_indices(indices, num_symbols, "ans")

    def mlp_weight(self, w: np.ndarray, precision) -> Section:
        if w.ndim == 2 and w.size and precision.weights <= weights.BITS:
            return weights.encoding(precision.weights), weights.encode_columns(w, precision.weights)
        return super().mlp_weight(w, precision)

    def mlp_change(self, w: np.ndarray, reference: np.ndarray, precision) -> Section | None:
        """A matrix whose weights are quantized (``precision.weights`` < 16) as :func:`omg4.codec.weights.encode_delta`
        of it, when that decodes within the fp16 range."""
        if w.ndim != 2 or not w.size or precision.weights > weights.BITS:
            return None
        return weights.encode_delta(w, reference)

    def any_length_rotation(self, qa, name: str, rotations: tuple[str, ...], precision) -> bool:
        """A rotation, 4 wide, is stored as unit quaternions unless the grids keep rotation codebooks
        (``precision.rotations`` 16)."""
        return (precision.rotations < 16 and name in rotations
                and sum(int(np.shape(cb)[1]) for cb in qa.codebooks) == 4)

    def version(self, encodings: object) -> int:
        """3 (deflated JSON, grid-coded sections), 4 with an MLP weight in fewer than 8 bits per row, 5 with exact
        positions or column-scaled weights, so files of the older codecs and grids stay readable by older builds."""
        names = [e for e in (encodings.values() if isinstance(encodings, dict) else ()) if isinstance(e, str)]
        weight_encodings = [parsed for e in names if (parsed := weights.parse_encoding(e))]
        if grids.POSITIONS_EXACT in names or any(columns for _, columns in weight_encodings):
            return 5
        return 4 if any(bits < weights.BITS for bits, _ in weight_encodings) else 3


def round_codebook(codebook: np.ndarray, bits: int) -> np.ndarray:
    """A codebook rounded to steps of 2^-bits, then to fp16 (for the log-scale codebooks at the default 5 bits fp16
    holds every such value below 64 exactly, so rounding twice changes nothing)."""
    step = 2.0 ** -bits
    return (np.rint(np.asarray(codebook, np.float64) / step) * step).astype(np.float16)


def largest_footprints(p, percent: int) -> np.ndarray:
    """bool ``[N]``: the ⌈percent · N / 100⌉ Gaussians of the payload ``p`` with the largest footprint — the product
    of their two largest scales, from the 3-wide log-scale attribute ``scale`` of both backbones, as ``p`` holds it
    (the writer passes its fp16 payload in storage order, before log-scale rounding) — whose positions the compact
    codec stores exactly (``CompactGrids.exact``); none without such an attribute. Ties: the earlier row."""
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


CODERS: dict[str, Coder] = {c.name: c for c in (CompactCoder(), AnsCoder(), PaperCoder())}
"""Every codec by name, the default first."""


def register_coder(coder: Coder) -> None:
    """Make ``coder`` known to the writer, the reader and the commands' ``--codec`` (its name must be new)."""
    if not coder.name or coder.name in CODERS:
        raise OMG4Error(f"a coder needs a new name, got {coder.name!r}")
    CODERS[coder.name] = coder


def browser_module() -> str:
    """The ES module ``web/decoder/codecs.js``: each registered codec's reading rules (:class:`Coder`'s
    ``index_encodings``, ``morton_positions``, ``grid_encodings``, ``quaternion_sections``) and each section
    encoding's (:data:`omg4.codec.encodings.ENCODINGS`: pattern, section kinds, the capability it needs), which the
    browser's reader looks up as :func:`omg4.codec.payload.decode_payload` does. ``omg4 export --format web`` writes it from the
    table as it is, so a codec added with :func:`register_coder` from the encodings the browser decodes plays too;
    the copy in the source tree is the built-in codecs' (a test keeps it equal)."""
    table = {name: {"name": name, "index_encodings": list(c.index_encodings), "morton_positions": c.morton_positions,
                    "grid_encodings": c.grid_encodings, "quaternion_sections": c.quaternion_sections}
             for name, c in CODERS.items()}
    rules = {family: {"pattern": e.pattern, "sections": list(e.sections), "needs": e.needs}
             for family, e in ENCODINGS.items()}
    return ("// The codecs' and the section encodings' reading rules, written by omg4.codec.coders.browser_module from\n"
            "// their tables (CODERS, omg4.codec.encodings.ENCODINGS): regenerate, do not edit.\n"
            f"export const CODERS = {json.dumps(table, indent=2)};\n\n"
            f"export const ENCODINGS = {json.dumps(rules, indent=2)};\n")


__all__ = ["CODERS", "AnsCoder", "Coder", "CompactCoder", "CompactGrids", "PaperCoder", "browser_module",
           "largest_footprints", "register_coder", "round_codebook"]
