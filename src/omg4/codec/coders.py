"""The codecs of an ``.omg4`` file, one class each, in one table (:data:`CODERS`; docs/file-format.md §4).

A coder decides how :func:`omg4.codec.payload.encode_payload` writes a payload: the Gaussians' storage order, the
sections of the positions, time centres, sub-vector-quantized attributes and MLP weights, extra header fields
and the container version. Reading follows each section's recorded encoding
(:func:`omg4.codec.payload.decode_payload`); a coder states which of those encodings its files may hold, so a
header that names one codec and encodings of another is refused. A new codec is a :class:`Coder` subclass and one
entry of :data:`CODERS` (:func:`register_coder`). The codecs themselves are described in
:mod:`omg4.codec.payload`.
"""

from __future__ import annotations

import math

import numpy as np

from omg4.codec import grids, quaternions, weights
from omg4.codec.codewords import encode_codewords
from omg4.codec.entropy import MAX_SYMBOLS, encode_indices
from omg4.codec.sections import canonical_order, encode_f16, encode_xyz_morton, smallest_f16
from omg4.errors import OMG4Error

Section = tuple[str, bytes]
"""(encoding, bytes) of one section."""


class Coder:
    """The writing choices of one codec; the defaults store every float as the smallest fp16 section and the
    Gaussians in Morton order.

    Attributes: ``name`` (the header's ``codec``), ``order`` (the header's ``order``), ``takes_grids`` (whether
    :class:`~omg4.codec.payload.CompactGrids` other than the default apply), and what its files may hold when
    read: ``index_encodings``, ``morton_positions``, ``grid_encodings`` (grid positions and times, sorted
    codebooks, quantized weights) and ``quaternion_sections`` (the header's ``quaternions`` list).
    """

    name = ""
    order = "morton"
    takes_grids = False
    index_encodings: tuple[str, ...] = ()
    morton_positions = True
    grid_encodings = False
    quaternion_sections = False

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
        """An index stream into a codebook of ``num_symbols`` rows, coded as they are."""
        return self.name, encode_indices(indices, num_symbols, self.name)

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
    """``ans``: lossless w.r.t. the fp16 values; Morton order, ANS-coded indices, the smallest float sections."""

    name = "ans"
    index_encodings = ("ans",)


class PaperCoder(Coder):
    """``paper``: OMG4's coder — fp16 everywhere, LZMA per section, Huffman-coded indices, the Gaussians' order
    kept."""

    name = "paper"
    order = "original"
    index_encodings = ("paper",)
    morton_positions = False

    def float_section(self, values: np.ndarray) -> Section:
        return "f16-lzma", encode_f16(values, "f16-lzma")

    def arrange(self, q, precision):
        return q

    def positions(self, q, precision) -> Section:
        return self.float_section(q.xyz)


class CompactCoder(Coder):
    """``compact`` (the default): positions and time centres on grids, codewords without their order, unit
    quaternions, quantized MLP weights (:class:`~omg4.codec.payload.CompactGrids`)."""

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


__all__ = ["CODERS", "AnsCoder", "Coder", "CompactCoder", "PaperCoder", "largest_footprints", "register_coder",
           "round_codebook"]
