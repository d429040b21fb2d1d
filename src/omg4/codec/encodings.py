"""Every section encoding of an ``.omg4`` file in one table (docs/file-format.md §3–§4): its name (a fixed name or
a pattern with parameters), the section kinds it may stand for, the codec capability it needs, and its decoder.

The Python reader (:func:`omg4.codec.payload.decode_payload`) looks each section's encoding up here; the browser's
reader reads the same rules (``web/decoder/codecs.js``, written by :func:`omg4.codec.coders.browser_module`) and
holds a decoder per encoding of its own. A section kind is ``xyz``, ``t``, ``codebook``, ``index``, ``quat``,
``mlp`` (a weight of any shape) or ``matrix`` (a 2-D weight, which is an ``mlp`` too). ``needs`` names the
:class:`~omg4.codec.coders.Coder` attribute that must allow it: ``grid_encodings``, ``morton_positions``, or
``index_encodings`` (the name must be one of the codec's); None: any codec.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable

import numpy as np

from omg4.codec import grids, quaternions, weights
from omg4.codec.codewords import decode_first_use_indices, decode_sorted_codebook
from omg4.codec.entropy import decode_indices
from omg4.codec.references import reference_array, referenced
from omg4.codec.sections import decode_f16, decode_xyz_morton
from omg4.codec.types import REFERENCE
from omg4.errors import CorruptFileError


@dataclass(frozen=True)
class Section:
    """What a decoder needs of one section: its bytes, encoding, value count, declared shape (codebooks and MLP
    weights), alphabet size (index streams), name, and a predicted segment's reference arrays."""

    data: bytes
    encoding: str
    count: int
    shape: tuple[int, ...] | None
    num_symbols: int
    name: str
    reference: dict[str, np.ndarray] | None


@dataclass(frozen=True)
class Encoding:
    """One encoding (or a family of them: ``pattern`` is a regular expression both readers take whole)."""

    pattern: str
    sections: tuple[str, ...]
    needs: str | None
    decode: Callable[[Section], np.ndarray]

    def matches(self, name: str) -> bool:
        return re.fullmatch(self.pattern, name) is not None


FLOAT_KINDS = ("xyz", "t", "codebook", "mlp", "matrix")
ENCODINGS: dict[str, Encoding] = {
    "reference": Encoding(REFERENCE, ("codebook", "mlp", "matrix"), None,
                          lambda s: referenced(s.name, s.data, s.shape, s.reference)),
    "delta-weights": Encoding(weights.DELTA_PATTERN, ("matrix",), "grid_encodings",
                              lambda s: weights.decode_delta(s.data, reference_array(s.name, s.shape, s.reference),
                                                             s.encoding)),
    "ans": Encoding("ans", ("index",), "index_encodings",
                    lambda s: decode_indices(s.data, s.num_symbols, s.count, "ans")),
    "ranks": Encoding("ranks", ("index",), "index_encodings",
                      lambda s: decode_indices(s.data, s.num_symbols, s.count, "ans")),
    "first-use": Encoding("first-use", ("index",), "index_encodings",
                          lambda s: decode_first_use_indices(s.data, s.num_symbols, s.count)),
    "paper": Encoding("paper", ("index",), "index_encodings",
                      lambda s: decode_indices(s.data, s.num_symbols, s.count, "paper")),
    "quaternions": Encoding(quaternions.ENCODING_PATTERN, ("quat",), None,
                            lambda s: quaternions.decode_quaternions(s.data, s.count,
                                                                     quaternions.bits_of(s.encoding))),
    "sorted": Encoding("sorted", ("codebook",), "grid_encodings", lambda s: decode_sorted_codebook(s.data, *s.shape)),
    "weights": Encoding(weights.ENCODING_PATTERN, ("matrix",), "grid_encodings",
                        lambda s: weights.decode_matrix(s.data, s.shape, s.encoding)),
    "morton": Encoding("morton", ("xyz",), "morton_positions", lambda s: decode_xyz_morton(s.data, s.count)),
    "grid-positions": Encoding(f"{grids.POSITIONS}|{grids.POSITIONS_EXACT}", ("xyz",), "grid_encodings",
                               lambda s: grids.decode_positions(s.data, s.count,
                                                                exact=s.encoding == grids.POSITIONS_EXACT)),
    "grid-times": Encoding(grids.TIMES, ("t",), "grid_encodings", lambda s: grids.decode_times(s.data, s.count)),
    "f16": Encoding("f16|f16-lzma|f16-planes", FLOAT_KINDS, None, lambda s: decode_f16(s.data, s.encoding, s.count)),
}
"""Every encoding a reader decodes, by family name (the browser's decoders use the same names)."""


def section_kind(name: str, shape: tuple[int, ...] | None, num_symbols: int) -> str:
    """The kind of section ``name`` (see the module docstring)."""
    if num_symbols:
        return "index"
    head = name.split(".")[0]
    if head == "mlp":
        return "matrix" if shape is not None and len(shape) == 2 else "mlp"
    return {"svq": "codebook", "quat": "quat"}.get(head, head)


def allowed(encoding: Encoding, coder, name: str) -> bool:
    """Whether ``coder`` (a :class:`~omg4.codec.coders.Coder`) may hold the encoding named ``name``."""
    if encoding.needs is None:
        return True
    if encoding.needs == "index_encodings":
        return name in coder.index_encodings
    return bool(getattr(coder, encoding.needs))


def decode_section(section: Section, coder) -> np.ndarray:
    """The values of ``section`` in a file of ``coder``'s codec: the table's decoder for its encoding, accepted only
    for the section kinds it was made for and the codecs allowed it (one-line :class:`CorruptFileError` else)."""
    kind = section_kind(section.name, section.shape, section.num_symbols)
    name = section.encoding
    for encoding in ENCODINGS.values():
        if kind in encoding.sections and encoding.matches(name) and allowed(encoding, coder, name):
            return encoding.decode(section)
    if kind == "index":
        raise CorruptFileError(f"encoding {name!r} is not an index encoding of the codec {coder.name!r}")
    if kind == "quat":
        raise CorruptFileError(f"encoding {name!r} is not a quaternion encoding")
    raise CorruptFileError(f"unknown encoding {name!r}")


__all__ = ["ENCODINGS", "Encoding", "Section", "allowed", "decode_section", "section_kind"]
