"""The versioned ``.omg4`` binary container (no pickle: docs/file-format.md; omg4 §8).

Layout (all integers little-endian)::

    offset  size  field
    0       8     magic  b"\\x89OMG4\\r\\n\\x1a"  (PNG-style: catches text-mode mangling)
    8       2     format version (uint16)
    10      2     flags (uint16, must be 0)
    12      4     JSON length L (uint32, at most MAX_JSON_BYTES)
    16      4     CRC-32 of the JSON bytes
    20      L     JSON object {"header": <caller's dict>, "sections": [[name, size, crc32], ...]}
                  (version 1: UTF-8 text; versions 2 to 7: that text raw-DEFLATE-compressed)
    20+L    ...   the sections' bytes, concatenated in table order

The file must end exactly after the last section. The section table lives inside the
checksummed JSON, so every length and checksum is itself protected; each section has its
own CRC-32. Reading validates lengths against the real file size before allocating
anything, so a damaged file never causes a large allocation, a hang or a deep traceback:
every problem is a one-line :class:`~omg4.errors.CorruptFileError`.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path
from typing import BinaryIO

from omg4.atomic import atomic_path
from omg4.errors import CorruptFileError, OMG4Error

MAGIC = b"\x89OMG4\r\n\x1a"
FORMAT_VERSION = 7
#: versions this build reads: 1 (plain JSON; the "ans" and "paper" codecs still write it, so older omg4
#: builds read those files), 2 (deflated JSON; the first "compact" codec) and 3 (deflated JSON; the "compact"
#: codec with grid-coded positions and time centres, which builds reading only 1-2 cannot decode) and 4 (version 3
#: whose MLP weights may be coded in fewer than 8 bits, which builds reading only 1-3 cannot decode) and 5
#: (version 4 whose grid positions may carry exact corrections, which builds reading only 1-4 cannot decode); 6 is
#: a sequence of segments, each section a whole single-model file (:mod:`omg4.codec.sequence`); 7 is a predicted
#: segment of a sequence: a single model some of whose sections are its reference segment's
#: (:data:`omg4.codec.payload.REFERENCE`), which builds reading only 1-6 cannot decode
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7)
SEQUENCE_VERSION = 6
PREDICTED_VERSION = 7
DEFLATED_VERSIONS = (2, 3, 4, 5, 6, 7)
MAX_JSON_BYTES = 16 * 1024 * 1024
MAX_SECTION_NAME = 200
PREFIX = struct.Struct("<8sHHII")  # magic, version, flags, json length, json crc32


def crc32(data: bytes | memoryview) -> int:
    """The CRC-32 the container stores for the JSON and for each section (unsigned)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def _reject_constant(name: str):
    raise ValueError(f"non-finite number {name}")


def _encode_json(header: dict, table: list[list]) -> bytes:
    if not isinstance(header, dict):
        raise OMG4Error(f"container header must be a dict, got {type(header).__name__}")
    try:
        return json.dumps({"header": header, "sections": table}, allow_nan=False,
                          separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise OMG4Error(f"container header is not JSON-serializable: {exc}") from None


def deflate_raw(data: bytes) -> bytes:
    """Raw DEFLATE (zlib level 9, no zlib header): the deflated JSON and the ANS model tables."""
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return packer.compress(data) + packer.flush()


def stored_json(blob: bytes, version: int) -> bytes:
    """The container's start for the JSON text ``blob``: the prefix, then the JSON as ``version`` stores it
    (versions 2 to 7 deflate it)."""
    stored = deflate_raw(blob) if version in DEFLATED_VERSIONS else blob
    return PREFIX.pack(MAGIC, version, 0, len(stored), crc32(stored)) + stored


def has_magic(path) -> bool:
    """Whether the file at ``path`` starts with the ``.omg4`` container's magic bytes; an unreadable file is a
    one-line :class:`OMG4Error`."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError as e:
        raise OMG4Error(f"cannot read {path} ({e.strerror or e})") from None


def write_container(path: str | os.PathLike, header: dict, sections: dict[str, bytes], version: int = 1) -> int:
    """Write ``header`` (a JSON-able dict) and named binary ``sections`` to ``path`` atomically.

    Section order is the dict's order; versions 2 to 7 deflate the JSON. Returns the file size in bytes.
    """
    head = _head(header, sections, version)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head)
        for data in sections.values():
            f.write(data)
        size = f.tell()
    return size


def container_bytes(header: dict, sections: dict[str, bytes], version: int = 1) -> bytes:
    """The bytes :func:`write_container` writes (for a file held in memory, such as a segment of a sequence)."""
    return _head(header, sections, version) + b"".join(sections.values())


def _head(header: dict, sections: dict[str, bytes], version: int) -> bytes:
    """The prefix and stored JSON of a container of ``header`` and ``sections`` (checked as :func:`write_container`
    documents)."""
    if version not in READABLE_VERSIONS:
        raise OMG4Error(f"unknown container version {version}")
    table = []
    for name, data in sections.items():
        if not isinstance(name, str) or not name or len(name) > MAX_SECTION_NAME:
            raise OMG4Error(f"invalid container section name {name!r}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise OMG4Error(f"container section {name!r} must be bytes, got {type(data).__name__}")
        table.append([name, len(data), crc32(data)])
    blob = _encode_json(header, table)
    if len(blob) > MAX_JSON_BYTES:
        raise OMG4Error(f"container header is {len(blob)} bytes (limit {MAX_JSON_BYTES})")
    head = stored_json(blob, version)
    if version in DEFLATED_VERSIONS and len(blob) > max_inflated_json(len(head) - PREFIX.size):
        raise OMG4Error(f"container header compresses {len(blob)} → {len(head) - PREFIX.size} bytes, beyond what a "
                        "reader accepts; write it with version 1")
    return head


class ContainerSource:
    """Bounded reads from a file or an in-memory buffer; knows the total size up front."""

    def __init__(self, source: str | os.PathLike | bytes | bytearray | memoryview):
        self.file: BinaryIO | None = None
        if isinstance(source, (bytes, bytearray, memoryview)):
            self.buffer, self.label, self.size, self.pos = memoryview(source), "data", len(source), 0
            return
        path = Path(source)
        try:
            self.file = open(path, "rb")
            self.size = os.fstat(self.file.fileno()).st_size
        except FileNotFoundError:
            raise OMG4Error(f"{path}: no such file") from None
        except IsADirectoryError:
            raise OMG4Error(f"{path}: is a folder, not an .omg4 file") from None
        except OSError as exc:
            raise OMG4Error(f"{path}: cannot read ({exc.strerror})") from None
        self.label = str(path)

    def read(self, n: int, what: str) -> bytes:
        """Exactly ``n`` bytes; ``n`` has been checked against the remaining size by the caller."""
        if self.file is not None:
            data = self.file.read(n)
        else:
            data = bytes(self.buffer[self.pos:self.pos + n])
            self.pos += n
        if len(data) != n:
            raise CorruptFileError(f"{self.label}: truncated while reading {what}")
        return data

    def close(self) -> None:
        if self.file is not None:
            self.file.close()


def _parse_table(label: str, doc: object) -> tuple[dict, list[tuple[str, int, int]]]:
    if not (isinstance(doc, dict) and isinstance(doc.get("header"), dict) and isinstance(doc.get("sections"), list)):
        raise CorruptFileError(f"{label}: container header is not an object with 'header' and 'sections'")
    table, seen = [], set()
    for entry in doc["sections"]:
        ok = (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], str)
              and 0 < len(entry[0]) <= MAX_SECTION_NAME
              and all(type(v) is int and 0 <= v for v in entry[1:]) and entry[2] <= 0xFFFFFFFF)
        if not ok:
            raise CorruptFileError(f"{label}: malformed section table entry")
        if entry[0] in seen:
            raise CorruptFileError(f"{label}: duplicate section {entry[0]!r}")
        seen.add(entry[0])
        table.append((entry[0], entry[1], entry[2]))
    return doc["header"], table


def max_inflated_json(compressed: int) -> int:
    """Most JSON bytes a deflated header of ``compressed`` bytes may inflate to: real headers shrink 3-4×, so
    a header far more compressible than that (a bomb of repeated brackets) is refused before it is parsed."""
    return min(MAX_JSON_BYTES, 65536 + 32 * compressed)


def _inflate_json(label: str, blob: bytes) -> bytes:
    """The JSON text of a deflated header (at most :func:`max_inflated_json` of its size)."""
    limit = max_inflated_json(len(blob))
    d = zlib.decompressobj(-15)
    try:
        text = d.decompress(blob, limit)
    except zlib.error:
        raise CorruptFileError(f"{label}: damaged compressed header") from None
    if not d.eof or d.unconsumed_tail or d.unused_data:
        raise CorruptFileError(f"{label}: damaged compressed header (wrong length or over {limit} bytes inflated)")
    return text


def read_prefix_and_table(src: ContainerSource) -> tuple[int, dict, list[tuple[str, int, int]]]:
    """Validate magic, version and the checksummed JSON; returns (version, header, section table)."""
    label = src.label
    if src.size < PREFIX.size:
        start = src.read(min(src.size, len(MAGIC)), "the magic bytes")
        if not MAGIC.startswith(start):
            raise CorruptFileError(f"{label}: not an .omg4 file (wrong magic bytes)")
        raise CorruptFileError(f"{label}: truncated ({src.size} bytes, shorter than the fixed header)")
    magic, version, flags, json_len, json_crc = PREFIX.unpack(src.read(PREFIX.size, "the fixed header"))
    if magic != MAGIC:
        raise CorruptFileError(f"{label}: not an .omg4 file (wrong magic bytes)")
    if version not in READABLE_VERSIONS:
        newer = "a newer" if version > FORMAT_VERSION else "an unknown"
        raise CorruptFileError(f"{label}: .omg4 format version {version} is from {newer} omg4 "
                               f"(this build reads versions {', '.join(map(str, READABLE_VERSIONS))})")
    if flags != 0:
        raise CorruptFileError(f"{label}: unknown container flags {flags:#06x}")
    if json_len > MAX_JSON_BYTES or json_len > src.size - PREFIX.size:
        raise CorruptFileError(f"{label}: header length {json_len} exceeds the file size or limit "
                               "(truncated or damaged)")
    blob = src.read(json_len, "the JSON header")
    if crc32(blob) != json_crc:
        raise CorruptFileError(f"{label}: header checksum mismatch (file is damaged)")
    if version in DEFLATED_VERSIONS:
        blob = _inflate_json(label, blob)
    try:
        doc = json.loads(blob.decode("utf-8"), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise CorruptFileError(f"{label}: header is not valid JSON ({type(exc).__name__})") from None
    header, table = _parse_table(label, doc)
    expected = PREFIX.size + json_len + sum(size for _, size, _ in table)
    if expected != src.size:
        state = "truncated" if expected > src.size else "has trailing bytes"
        raise CorruptFileError(f"{label}: file {state} ({src.size} bytes, the section table needs {expected})")
    return version, header, table


def read_container(source: str | os.PathLike | bytes | bytearray | memoryview) -> tuple[dict, dict[str, bytes]]:
    """Read and verify a container from a path or from bytes; returns ``(header, sections)``.

    Raises :class:`CorruptFileError` (one line) on any damage and :class:`OMG4Error` when
    the file is missing.
    """
    return read_versioned(source)[1:]


def read_versioned(source) -> tuple[int, dict, dict[str, bytes]]:
    """:func:`read_container` plus the file's format version."""
    src = ContainerSource(source)
    try:
        version, header, table = read_prefix_and_table(src)
        sections = {}
        for name, size, crc in table:
            data = src.read(size, f"section {name!r}")
            if crc32(data) != crc:
                raise CorruptFileError(f"{src.label}: checksum mismatch in section {name!r} (file is damaged)")
            sections[name] = data
    finally:
        src.close()
    return version, header, sections


def describe_container(source: str | os.PathLike | bytes | bytearray | memoryview) -> dict:
    """Storage breakdown for ``omg4 info``; verifies every checksum.

    Returns ``{"version", "total_bytes", "header_bytes", "sections": {name: bytes}, "header"}``
    where ``header_bytes`` counts the fixed prefix plus the JSON, so
    ``header_bytes + sum(sections.values()) == total_bytes``.
    """
    version, header, sections = read_versioned(source)
    sizes = {name: len(data) for name, data in sections.items()}
    total = Path(source).stat().st_size if not isinstance(source, (bytes, bytearray, memoryview)) else len(source)
    return {"version": version, "total_bytes": total, "header_bytes": total - sum(sizes.values()),
            "sections": sizes, "header": header}
