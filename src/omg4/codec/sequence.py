"""A long capture as one ``.omg4`` sequence file: one compressed model per segment, seekable by key segments.

Layout: an ``.omg4`` container of version :data:`SEQUENCE_VERSION` (``docs/file-format.md`` §8) whose
header is the index — ``{"layout": "sequence", "fps", "key_interval", "segments": [{"frames": [start, stop],
"time_range": [t0, t1], "reference": k or null}, ...], "meta"}`` — and whose sections ``segment.000``,
``segment.001``, … each hold the bytes of a single-model ``.omg4`` file. The container's checksummed section table
gives every segment's size and CRC-32, so its byte offset follows from the table: a reader takes the fixed prefix
and the index, then seeks to one segment and reads only its bytes (:func:`read_segment`).

A key segment (``reference`` null) is a complete model. A predicted segment (``reference`` = the index of the
segment just before it, beyond the paper) takes its appearance MLPs and codebooks from that segment's decoded
values (:func:`omg4.codec.payload.reference_sections`), so it decodes only after it
(:class:`SegmentDecoder`). At most ``key_interval - 1`` predicted segments follow a key segment, so a reader
seeking to any time decodes at most ``key_interval`` segments. A file without these fields (written before
predicted segments) is all key segments.

The index is bounded and validated like every header: at most :data:`MAX_SEGMENTS` segments, one section
per segment, frame ranges and time ranges that increase, and neighbours only sharing time — a forged
index (overlapping or reversed ranges, offsets past the end, a billion segments) is a one-line
:class:`~omg4.errors.CorruptFileError`.

Bytes only: :class:`omg4.models.SequenceModel` renders a sequence.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
from collections import OrderedDict
from pathlib import Path

from omg4.codec.container import (PREFIX, SEQUENCE_VERSION, ContainerSource, crc32, has_magic, read_container,
                                  read_prefix_and_table, write_container)
from omg4.codec.payload import CompressedPayload, decode_payload
from omg4.codec.references import reference_sections
from omg4.errors import CorruptFileError, OMG4Error

MAX_SEGMENTS = 100_000
LAYOUT = "sequence"
MAX_KEY_INTERVAL = 1024
"""The longest chain a reader decodes for one seek (a key interval beyond it is a forged index)."""
DEFAULT_KEY_INTERVAL = 8
"""Segments from one key segment to the next unless told (``omg4 compress --key-interval``): a seek decodes at most
this many; docs/results.md, "Predicted segments", measures the choice."""


@dataclasses.dataclass(frozen=True)
class SegmentEntry:
    """One segment of a sequence: its capture frames ``[start, stop)``, time range ``[t0, t1)``, where its bytes
    lie (``offset``, ``size``, ``crc``) in the file, and the segment it is predicted from (None: a key segment)."""

    index: int
    frames: tuple[int, int]
    time_range: tuple[float, float]
    offset: int
    size: int
    crc: int
    reference: int | None = None


@dataclasses.dataclass(frozen=True)
class SequenceIndex:
    """A sequence file's index: its segments, frame rate, metadata, total size and key interval (the most segments
    a reader decodes to show any one)."""

    segments: tuple[SegmentEntry, ...]
    fps: float
    meta: dict
    total_bytes: int
    key_interval: int = 1

    def chain(self, k: int) -> list[int]:
        """The segments to decode, in order, to decode segment ``k``: its key segment, then each predicted one up to
        ``k``."""
        chain = [k]
        while self.segments[chain[-1]].reference is not None:
            chain.append(self.segments[chain[-1]].reference)
        return chain[::-1]

    @property
    def time_range(self) -> tuple[float, float]:
        return self.segments[0].time_range[0], self.segments[-1].time_range[1]

    @property
    def duration_s(self) -> float:
        t0, t1 = self.time_range
        return t1 - t0

    @property
    def bitrate_mbps(self) -> float:
        """Megabits of file per second of capture."""
        return 8 * self.total_bytes / self.duration_s / 1e6


def write_sequence(path: str | os.PathLike, segments: list[tuple[tuple[int, int], tuple[float, float], bytes]], *,
                   fps: float, meta: dict | None = None, references: list[int | None] | None = None,
                   key_interval: int = 1) -> int:
    """Write a sequence file: ``segments`` as (frames [start, stop), time range, bytes of its ``.omg4`` file), in
    order; ``references``: each segment's reference (None: a key segment; default all), at most ``key_interval - 1``
    predicted in a row. Returns the file size."""
    references = references or [None] * len(segments)
    if len(references) != len(segments):
        raise OMG4Error(f"{len(references)} references for {len(segments)} segments")
    index = [{"frames": list(frames), "time_range": [float(t) for t in times], "reference": ref}
             for (frames, times, _), ref in zip(segments, references)]
    header = {"layout": LAYOUT, "fps": float(fps), "key_interval": key_interval, "segments": index, "meta": meta or {}}
    _check_index(str(path), header, len(segments))
    return write_container(path, header, {f"segment.{i:03d}": data for i, (_, _, data) in enumerate(segments)},
                           version=SEQUENCE_VERSION)


def is_sequence(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an ``.omg4`` sequence file (by its version field; a single model is not)."""
    path = Path(path)
    if not path.is_file() or not has_magic(path):
        return False
    with open(path, "rb") as f:
        head = f.read(PREFIX.size)
    return len(head) == PREFIX.size and PREFIX.unpack(head)[1] == SEQUENCE_VERSION


def read_index(path: str | os.PathLike) -> SequenceIndex:
    """The index of a sequence file, reading only its prefix and header (one-line errors on anything forged)."""
    src = ContainerSource(path)
    try:
        version, header, table = read_prefix_and_table(src)
        json_end = src.size - sum(size for _, size, _ in table)
    finally:
        src.close()
    label = str(path)
    if version != SEQUENCE_VERSION or not isinstance(header, dict) or header.get("layout") != LAYOUT:
        raise CorruptFileError(f"{label}: not an .omg4 sequence file")
    _check_index(label, header, len(table))
    names = [name for name, _, _ in table]
    if names != [f"segment.{i:03d}" for i in range(len(table))]:
        raise CorruptFileError(f"{label}: the sequence's sections are not its segments in order")
    entries, offset = [], json_end
    for i, ((name, size, crc), seg) in enumerate(zip(table, header["segments"])):
        entries.append(SegmentEntry(i, tuple(seg["frames"]), tuple(float(t) for t in seg["time_range"]), offset, size,
                                    crc, seg.get("reference")))
        offset += size
    meta = header.get("meta") if isinstance(header.get("meta"), dict) else {}
    return SequenceIndex(tuple(entries), float(header["fps"]), meta, src.size, header.get("key_interval", 1))


def valid_key_interval(value: object) -> bool:
    """Whether ``value`` is a key interval a sequence may declare: an integer from 1 to :data:`MAX_KEY_INTERVAL`."""
    return type(value) is int and 1 <= value <= MAX_KEY_INTERVAL


def _check_index(label: str, header: dict, sections: int) -> None:
    segments = header.get("segments")
    if not isinstance(segments, list) or not 1 <= len(segments) <= MAX_SEGMENTS:
        raise CorruptFileError(f"{label}: a sequence holds 1 to {MAX_SEGMENTS} segments")
    if len(segments) != sections:
        raise CorruptFileError(f"{label}: the index lists {len(segments)} segments for {sections} sections")
    fps = header.get("fps")
    if not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and math.isfinite(fps) and fps > 0):
        raise CorruptFileError(f"{label}: the sequence's frame rate must be a positive number")
    key_interval = header.get("key_interval", 1)
    if not valid_key_interval(key_interval):
        raise CorruptFileError(f"{label}: the key interval must be an integer from 1 to {MAX_KEY_INTERVAL}")
    previous, predicted_in_a_row = None, 0
    for i, seg in enumerate(segments):
        frames, times = (seg.get("frames"), seg.get("time_range")) if isinstance(seg, dict) else (None, None)
        ok = (isinstance(frames, list) and len(frames) == 2 and all(type(f) is int and 0 <= f < 2**40 for f in frames)
              and frames[0] < frames[1] and isinstance(times, list) and len(times) == 2
              and all(isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) for t in times)
              and times[0] < times[1])
        if not ok:
            raise CorruptFileError(f"{label}: segment {i} has an invalid frame or time range")
        reference = seg.get("reference")
        if reference is not None and not (type(reference) is int and i >= 1 and reference == i - 1):
            raise CorruptFileError(f"{label}: segment {i} is predicted from segment {reference!r}; a segment may only be "
                                   "predicted from the one just before it")
        predicted_in_a_row = 0 if reference is None else predicted_in_a_row + 1
        if predicted_in_a_row >= key_interval:
            raise CorruptFileError(f"{label}: segment {i} makes {predicted_in_a_row} predicted segments in a row, more "
                                   f"than the key interval {key_interval} allows")
        if previous is not None:
            (f0, f1), (t0, t1) = previous
            if not (frames[0] > f0 and frames[1] > f1 and frames[0] <= f1 and times[0] > t0 and times[1] > t1
                    and times[0] <= t1):
                raise CorruptFileError(f"{label}: segment {i} does not follow segment {i - 1} (ranges must increase "
                                       "and neighbours may only share their ends)")
            if i >= 2 and frames[0] < segments[i - 2]["frames"][1]:
                raise CorruptFileError(f"{label}: segment {i} overlaps segment {i - 2}")
        previous = (frames, times)


def read_segment(path: str | os.PathLike, entry: SegmentEntry) -> bytes:
    """The bytes of one segment's ``.omg4`` file, read by seeking to it (its CRC-32 checked)."""
    try:
        with open(path, "rb") as f:
            f.seek(entry.offset)
            data = f.read(entry.size)
    except OSError as exc:
        raise OMG4Error(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) != entry.size:
        raise CorruptFileError(f"{path}: truncated in segment {entry.index}")
    if crc32(data) != entry.crc:
        raise CorruptFileError(f"{path}: checksum mismatch in segment {entry.index} (file is damaged)")
    return data


class SegmentDecoder:
    """Decodes the segments of a sequence file, each predicted one after the segments of its chain
    (:meth:`SequenceIndex.chain`); the last ``keep`` decoded payloads are held, so playing forward decodes every
    segment once and a seek decodes at most the key interval. ``bytes_read`` counts the segment bytes read.
    Thread-safe (a player decodes ahead on another thread)."""

    def __init__(self, path: str | os.PathLike, index: SequenceIndex | None = None, keep: int = 3):
        self.path = path
        self.index = index or read_index(path)
        self.keep = keep
        self.bytes_read = 0
        self._decoded: OrderedDict[int, CompressedPayload] = OrderedDict()
        self._lock = threading.Lock()

    def payload(self, k: int) -> CompressedPayload:
        """Segment ``k``'s decoded payload."""
        with self._lock:
            chain = self.index.chain(k)
            start = max((j for j, s in enumerate(chain) if s in self._decoded), default=0)
            payload = None
            for s in chain[start:]:
                payload = self._decoded.get(s) or self._decode(s, payload)
                self._decoded[s] = payload
                self._decoded.move_to_end(s)
                while len(self._decoded) > self.keep:
                    self._decoded.popitem(last=False)
            return payload

    def _decode(self, k: int, reference: CompressedPayload | None) -> CompressedPayload:
        entry = self.index.segments[k]
        data = read_segment(self.path, entry)
        self.bytes_read += len(data)
        try:
            return decode_payload(data, None if reference is None else reference_sections(reference))
        except CorruptFileError as exc:
            raise CorruptFileError(f"{self.path}: segment {k}: {str(exc).removeprefix('data: ')}") from None


def read_sequence(path: str | os.PathLike) -> tuple[SequenceIndex, list[bytes]]:
    """The index and every segment's bytes (the whole file, verified)."""
    index = read_index(path)
    _, sections = read_container(path)
    return index, [sections[f"segment.{i:03d}"] for i in range(len(index.segments))]


__all__ = ["SEQUENCE_VERSION", "MAX_SEGMENTS", "MAX_KEY_INTERVAL", "DEFAULT_KEY_INTERVAL", "SegmentDecoder", "SegmentEntry", "SequenceIndex", "write_sequence",
           "is_sequence", "read_index", "read_segment", "read_sequence"]

