"""Carried Gaussians of a predicted segment (beyond the paper; docs/file-format.md §8b).

A segment predicted from the one before may take some of that segment's decoded Gaussians as they are — their
positions, time centres, codebook indices and rotations — instead of coding Gaussians of its own in their place.
Its file names them by one bit per Gaussian of the reference (the ``carry`` section, an ANS-coded stream of 0 and
1, so a carried Gaussian costs about a bit and one that is not far less where most are), and its header declares
how many (``carried``). Everything the Gaussians' appearance goes through — the segment's MLPs — is its own.

The reference's per-Gaussian arrays travel with its :func:`omg4.codec.payload.reference_sections` under the names
this module gives them (:func:`gaussian_sections`); :func:`carried_gaussians` reads them back as a payload, and a
decoder puts the carried rows first, in the reference's order, then the segment's own (:func:`with_carried`).
"""

from __future__ import annotations

import itertools

import numpy as np

from omg4.codec.entropy import decode_indices, encode_indices
from omg4.codec.types import REFERENCE, CompressedPayload, QuantizedAttribute
from omg4.errors import CorruptFileError, OMG4Error

SECTION = "carry"
"""The section that names the carried Gaussians."""
ENCODING = "mask"
"""Its encoding: one symbol per Gaussian of the reference, 1 where it is carried, ANS-coded."""
_PREFIX = "gaussians."


def gaussian_sections(p) -> dict[str, np.ndarray]:
    """The per-Gaussian arrays of the decoded payload ``p`` a segment predicted from it may carry: positions, time
    centres, each non-rotation attribute's indices (into codebooks the segment must take as they are) and each
    rotation's values, one quaternion per Gaussian (fp16)."""
    out = {f"{_PREFIX}xyz": np.asarray(p.xyz), f"{_PREFIX}t": np.asarray(p.t)}
    for attr, qa in p.attributes.items():
        if attr in p.rotations:
            out[f"{_PREFIX}rotation.{attr}"] = qa.reconstruct().astype(np.float16)
        else:
            out.update({f"{_PREFIX}svq.{attr}.index{j}": np.asarray(ix) for j, ix in enumerate(qa.indices)})
    return out


def reference_count(reference: dict[str, np.ndarray] | None) -> int:
    """How many Gaussians the reference segment holds (CorruptFileError without one)."""
    if reference is None or f"{_PREFIX}xyz" not in reference:
        raise CorruptFileError("a segment that carries Gaussians takes them from the segment before: decode it "
                               "through its sequence file")
    return int(reference[f"{_PREFIX}xyz"].shape[0])


def encode_mask(rows: np.ndarray, count: int) -> bytes:
    """The ``carry`` section of the reference rows ``rows`` (distinct, in [0, count))."""
    mask = np.zeros(count, np.int64)
    mask[rows] = 1
    return encode_indices(mask, 2, "ans")


def decode_mask(data: bytes, encoding: object, count: int, declared: int) -> np.ndarray:
    """The carried reference rows, ascending, from a ``carry`` section over ``count`` reference Gaussians; the
    header ``declared`` so many (one-line CorruptFileError otherwise)."""
    if encoding != ENCODING:
        raise CorruptFileError(f"section {SECTION}: encoding {encoding!r} is not {ENCODING!r}")
    try:
        rows = np.flatnonzero(decode_indices(data, 2, count, "ans"))
    except CorruptFileError as exc:
        raise CorruptFileError(f"section {SECTION}: {exc}") from None
    if rows.size != declared:
        raise CorruptFileError(f"section {SECTION} marks {rows.size} carried Gaussians, the header declares {declared}")
    return rows


def taken(reference: dict[str, np.ndarray], what: str, rows: np.ndarray, columns: int | None = None) -> np.ndarray:
    """The carried ``rows`` of the reference's per-Gaussian array ``what`` (``xyz``, ``t``, ``rotation.ATTR``,
    ``svq.ATTR.indexJ``), checked to be ``columns`` wide where given."""
    array = reference.get(_PREFIX + what)
    if array is None:
        raise CorruptFileError(f"the reference segment has no {what} to carry")
    if columns is not None and (array.ndim != 2 or array.shape[1] != columns):
        raise CorruptFileError(f"the reference's {what} is {array.shape[1:] or 'one'} wide, not {columns}")
    return array[rows]


def carried_gaussians(reference: dict[str, np.ndarray] | None, rows: np.ndarray | None = None) -> CompressedPayload:
    """The reference segment's decoded Gaussians ``rows`` (default all) as a payload of their positions, time centres
    and attributes — each non-rotation attribute indexing the reference's codebooks, each rotation one quaternion per
    Gaussian — with no MLPs (one-line CorruptFileError where the reference lacks them)."""
    count = reference_count(reference)
    rows = np.arange(count) if rows is None else rows
    attributes, rotations = {}, []
    for name in reference:
        if name.startswith(f"{_PREFIX}rotation."):
            attr = name[len(f"{_PREFIX}rotation."):]
            attributes[attr] = QuantizedAttribute([taken(reference, f"rotation.{attr}", rows, 4)],
                                                  [np.arange(rows.size)])
            rotations.append(attr)
        elif name.startswith("svq.") and name.endswith(".codebook0"):
            attr = name[len("svq."):-len(".codebook0")]
            slots = list(itertools.takewhile(lambda j: f"svq.{attr}.codebook{j}" in reference, itertools.count()))
            attributes[attr] = QuantizedAttribute([reference[f"svq.{attr}.codebook{j}"] for j in slots],
                                                  [taken(reference, f"svq.{attr}.index{j}", rows) for j in slots])
    return CompressedPayload(taken(reference, "xyz", rows, 3), taken(reference, "t", rows), attributes,
                             rotations=tuple(rotations))


def with_carried(own: CompressedPayload, header: dict, data: bytes, reference: dict[str, np.ndarray] | None
                 ) -> CompressedPayload:
    """A predicted segment's Gaussians: the reference's carried ones (:func:`carried_gaussians`), as they decoded
    there, then its own ``own`` (decoded from the sections of ``header``); rotations become one quaternion per Gaussian.
    ``data``: the ``carry`` section."""
    rows = decode_mask(data, header["encodings"][SECTION], reference_count(reference), header["carried"])
    carried = carried_gaussians(reference, rows)
    n = rows.size + own.num_gaussians
    attributes = {}
    for attr, qa in own.attributes.items():
        if (attr not in carried.attributes or (attr in own.rotations) != (attr in carried.rotations)
                or (attr not in own.rotations and len(carried.attributes[attr].indices) != len(qa.indices))):
            raise CorruptFileError(f"the reference segment has no {attr} like this segment's to carry")
        if attr in own.rotations:
            values = np.concatenate([carried.attributes[attr].codebooks[0], qa.reconstruct().astype(np.float16)])
            attributes[attr] = QuantizedAttribute([values], [np.arange(n)])
        elif any(header["encodings"][f"svq.{attr}.codebook{j}"] != REFERENCE for j in range(len(qa.codebooks))):
            raise CorruptFileError(f"carried Gaussians index the reference's codebooks, and {attr} has its own")
        else:
            attributes[attr] = QuantizedAttribute(qa.codebooks, [np.concatenate([c, ix]) for c, ix in zip(
                carried.attributes[attr].indices, qa.indices)])
    return CompressedPayload(np.concatenate([carried.xyz, own.xyz]).astype(np.float16),
                             np.concatenate([carried.t, own.t]).astype(np.float16), attributes, own.mlp, own.meta,
                             own.rotations, own.log_scaled)


def carried_section(q: CompressedPayload, reference: dict[str, np.ndarray], taken: set[str]):
    """The ``carry`` section of ``q.carried`` (OMG4Error where the reference lacks them or an attribute of ``q`` that is
    not a rotation has codebooks of its own, not among those ``taken`` from the reference: carried Gaussians index the
    reference's)."""
    try:
        count = reference_count(reference or None)
    except CorruptFileError as exc:
        raise OMG4Error(f"carried Gaussians: {exc}") from None
    rows = np.asarray(q.carried)
    if (rows.ndim != 1 or not rows.size or not np.issubdtype(rows.dtype, np.integer) or rows.min() < 0
            or rows.max() >= count or np.unique(rows).size != rows.size):
        raise OMG4Error(f"carried Gaussians must be 1 or more distinct rows of the reference's {count}")
    own = [a for a in q.attributes if a not in q.rotations and a not in taken]
    if own:
        raise OMG4Error(f"carried Gaussians index the reference's codebooks, and {', '.join(own)} has its own")
    return ENCODING, encode_mask(rows, count)


__all__ = ["ENCODING", "SECTION", "carried_gaussians", "carried_section", "decode_mask", "encode_mask", "gaussian_sections", "reference_count",
           "taken", "with_carried"]
