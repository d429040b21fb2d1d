"""What an ``.omg4`` file stores, and its mapping onto container sections (omg4 §8).

A :class:`CompressedPayload` holds the explicit per-Gaussian data OMG4 keeps after
attribute compression (paper §4.4): positions ``xyz`` and time centres ``t`` (fp16), for
each sub-vector-quantized attribute its fp16 codebooks and index streams, the fp16
weights of the appearance MLPs, and a JSON-able ``meta`` dict (preset, SH degrees, time
range, normalization, ...).

``decode_payload`` validates everything (index < codebook size, consistent counts, finite
floats) and raises :class:`~omg4.errors.CorruptFileError` with one line otherwise.

Each codec — what it writes, its settings, the encodings its files may hold — is its class in
:data:`omg4.codec.coders.CODERS` (``compact``, the default, beyond OMG4's coder; ``paper``, OMG4's; ``ans``,
lossless and smaller); array-to-bytes helpers shared by all are in :mod:`omg4.codec.sections`. This module keeps
what every codec shares — the file's limits, the header checks and the section reader — in one place, because
together they are the boundary a hostile file meets (docs/file-format.md §5).
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from omg4.codec import carry, grids, weights
from omg4.codec.coders import CODERS, Coder, CompactGrids
from omg4.codec.container import PREDICTED_VERSION, SEQUENCE_VERSION, read_versioned, write_container
from omg4.codec.encodings import Section, decode_section
from omg4.codec.entropy import MAX_SYMBOLS
from omg4.codec.references import takes_codebooks
from omg4.codec.rig import check_rig
from omg4.codec.types import REFERENCE, CompressedPayload, QuantizedAttribute
from omg4.errors import CorruptFileError, OMG4Error

KIND = "omg4-compressed-model"
#: the encoding of a section a predicted segment takes from its reference segment: no bytes, the reference's decoded
#: array (:func:`reference_sections`; docs/file-format.md §8a)
#: the built-in payload codecs, the default first (module docstring; every known one: :data:`omg4.codec.coders.CODERS`)
CODECS = tuple(CODERS)
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
#: allowed bits of each :class:`CompactGrids` field (what the writer accepts)


# ------------------------------------------------------------------------ encoding
def container_version(codec: object, encodings: object = None) -> int:
    """The container version of a file of ``codec`` whose sections have ``encodings`` (``{section: name}``):
    :data:`~omg4.codec.container.PREDICTED_VERSION` for a predicted segment (a section encoded as
    :data:`REFERENCE` or as a change from it, :func:`omg4.codec.weights.parse_delta_encoding`, or one that carries
    Gaussians, :mod:`omg4.codec.carry`), else
    :meth:`omg4.codec.coders.Coder.version` of its coder, 1 for an unknown one. Any ``encodings`` value is accepted
    (a forged header's too)."""
    if isinstance(encodings, dict) and (carry.SECTION in encodings or any(
            e == REFERENCE or weights.parse_delta_encoding(e) for e in encodings.values())):
        return PREDICTED_VERSION
    coder = CODERS.get(codec) if isinstance(codec, str) else None
    return coder.version(encodings) if coder is not None else 1


def _check_payload(p: CompressedPayload, coder: Coder, precision: CompactGrids) -> CompressedPayload:
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
        any_length = coder.any_length_rotation(qa, attr, q.rotations, precision)
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


def check_codec(codec: str, precision: CompactGrids = CompactGrids()) -> None:
    """Raise :class:`~omg4.errors.OMG4Error` unless ``codec`` is one of :data:`CODECS` and ``precision`` is the
    default or ``codec`` is "compact" (the only codec with grids)."""
    if codec not in CODERS:
        raise OMG4Error(f"unknown codec {codec!r} (choose from {', '.join(CODERS)})")
    if not CODERS[codec].takes_grids and precision != CompactGrids():
        raise OMG4Error(f"grids {precision.label} apply to the compact codec only, not {codec!r}")


def encode_payload(p: CompressedPayload, path: str | os.PathLike, codec: str = CODECS[0],
                   precision: CompactGrids = CompactGrids(),
                   reference: dict[str, np.ndarray] | None = None) -> dict[str, int]:
    """Write ``p`` to ``path`` (atomically) with ``codec`` from :data:`CODECS`; ``precision``: the "compact" codec's
    grids (any other is refused with another codec). ``reference``: the :func:`reference_sections` of the segment
    this one is predicted from; every MLP weight and every attribute's codebooks equal to the reference's are
    stored as :data:`REFERENCE` (no bytes; the attribute's indices then index the reference's codebooks), and an
    MLP weight that differs as its change from the reference's where the codec codes changes and that is smaller
    (:func:`_mlp_section`), which makes the file a predicted segment that decodes only with that reference.
    ``p.carried``: the rows of the reference's Gaussians the segment also holds as they are, named in a ``carry``
    section (:mod:`omg4.codec.carry`; its attributes' codebooks must then be the reference's).

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
    coder = CODERS[codec]
    q = coder.arrange(_check_payload(p, coder, precision), precision)
    reference = reference or {}
    taken = {attr for attr, qa in q.attributes.items()
             if attr not in q.rotations and takes_codebooks(qa, attr, reference)}
    carried = None if q.carried is None else carry.carried_section(q, reference, taken)  # refused before any coding
    written: dict[str, tuple[str, bytes]] = {"xyz": coder.positions(q, precision), "t": coder.times(q, precision)}
    shapes: dict[str, list[list[int]]] = {}
    stored_as_quaternions: list[str] = []
    for attr, qa in q.attributes.items():
        if attr in taken:
            attr_shapes, attr_sections = coder.referenced_attribute(attr, qa, REFERENCE)
        else:
            attr_shapes, attr_sections = coder.attribute(attr, qa, q, precision)
        written.update(attr_sections)
        if attr_shapes is None:
            stored_as_quaternions.append(attr)
        else:
            shapes[attr] = attr_shapes
    for name, w in q.mlp.items():
        written[f"mlp.{name}"] = _mlp_section(coder, w, reference.get(f"mlp.{name}"), precision)
    if carried is not None:
        written[carry.SECTION] = carried
    sections = {name: data for name, (_, data) in written.items()}
    encodings = {name: enc for name, (enc, _) in written.items()}
    header = {
        "kind": KIND, "codec": codec, "order": coder.order,
        "num_gaussians": q.num_gaussians, "meta": q.meta,
        "attributes": shapes,
        "mlp": {k: list(w.shape) for k, w in q.mlp.items()},
        "encodings": encodings,
        "rotations": [a for a in q.rotations if a in q.attributes],
        "log_scaled": [a for a in q.log_scaled if a in shapes],  # not those stored as unit quaternions
    }
    if coder.quaternion_sections:
        header["quaternions"] = stored_as_quaternions
    if q.carried is not None:
        header["carried"] = int(len(q.carried))
    sizes = {name: len(data) for name, data in sections.items()}
    try:  # the decoder's limits hold for every file written, so no written file is refused on reading
        check_sections(header, sizes)
    except CorruptFileError as exc:
        raise OMG4Error(f"this model cannot be stored: {exc}") from None
    total = write_container(path, header, sections, version=container_version(codec, encodings))
    sizes["header"] = total - sum(sizes.values())
    return sizes


def _mlp_section(coder: Coder, w: np.ndarray, same: np.ndarray | None, precision: CompactGrids):
    """MLP weight ``w``'s section: :data:`REFERENCE` where it equals the reference's ``same`` (None: no such
    weight), else the smaller of its change from ``same`` (:meth:`omg4.codec.coders.Coder.mlp_change`, lossy in
    its own way) and the weight itself."""
    if same is None or same.shape != w.shape:
        return coder.mlp_weight(w, precision)
    if np.array_equal(same, w):
        return REFERENCE, b""
    whole, change = coder.mlp_weight(w, precision), coder.mlp_change(w, same, precision)
    return change if change is not None and len(change[1]) < len(whole[1]) else whole


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
    ok = (h.get("kind") == KIND and isinstance(h.get("codec"), str) and h["codec"] in CODERS
          and isinstance(h.get("meta"), dict)
          and isinstance(h.get("attributes"), dict) and isinstance(h.get("mlp"), dict)
          and isinstance(h.get("encodings"), dict) and _is_int(n, 1, MAX_GAUSSIANS))
    if not ok:
        raise CorruptFileError("not an OMG4 compressed model (header fields missing or invalid)")
    if "rig" in h["meta"]:
        check_rig(h["meta"]["rig"])
    rotations = h.get("quaternions", [])
    if (("quaternions" in h) != CODERS[h["codec"]].quaternion_sections or not isinstance(rotations, list)
            or len(rotations) > MAX_ATTRIBUTES or len(set(map(str, rotations))) != len(rotations)
            or not all(isinstance(a, str) and _NAME.fullmatch(a) and a not in h["attributes"] for a in rotations)):
        raise CorruptFileError("invalid list of quaternion attributes")
    named = h.get("rotations", [])
    if not (isinstance(named, list) and len(named) <= MAX_ATTRIBUTES
            and all(isinstance(a, str) and (a in h["attributes"] or a in rotations) for a in named)
            and all(a in named for a in rotations)):  # an attribute stored as quaternions is a rotation
        raise CorruptFileError("invalid list of rotation attributes")
    if "carried" in h and not _is_int(h["carried"], 1, MAX_GAUSSIANS):
        raise CorruptFileError("invalid count of carried Gaussians")
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
    expected += [carry.SECTION] if "carried" in header else []
    encodings = header["encodings"]
    if (sorted(expected) != sorted(section_sizes) or sorted(expected) != sorted(encodings)
            or not all(isinstance(e, str) for e in encodings.values())):
        raise CorruptFileError("section list does not match the header")


def decode_payload(source: str | os.PathLike | bytes,
                   reference: dict[str, np.ndarray] | None = None) -> CompressedPayload:
    """Read an ``.omg4`` file (path or bytes) written by :func:`encode_payload`; fp16 floats, int64 indices.
    ``reference``: a predicted segment's reference, the :func:`reference_sections` of its decoded payload.

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
        return _decode_sections(header, sections, reference)
    except CorruptFileError as exc:
        raise CorruptFileError(f"{label}: {exc}") from None


def _decode_sections(header: dict, sections: dict[str, bytes],
                     reference: dict[str, np.ndarray] | None = None) -> CompressedPayload:
    check_sections(header, {name: len(data) for name, data in sections.items()})
    n, codec, enc = header["num_gaussians"], header["codec"], header["encodings"]
    coder = CODERS[codec]

    def decode(name: str, count: int, num_symbols: int = 0, shape: tuple[int, ...] | None = None) -> np.ndarray:
        """Decode section ``name`` by its encoding's entry of the table (:mod:`omg4.codec.encodings`)."""
        try:
            return decode_section(Section(sections[name], enc[name], count, shape, num_symbols, name, reference), coder)
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
    own = CompressedPayload(xyz, t, attributes, mlp, header["meta"], tuple(header.get("rotations", [])),
                            tuple(header.get("log_scaled", [])))
    return own if "carried" not in header else carry.with_carried(own, header, sections[carry.SECTION], reference)
