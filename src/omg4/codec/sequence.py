"""A long capture as one ``.omg4`` sequence file: one compressed model per segment, each readable alone.

Layout: an ``.omg4`` container of version :data:`SEQUENCE_VERSION` (``docs/file-format.md`` §8) whose
header is the index — ``{"layout": "sequence", "fps", "segments": [{"frames": [start, stop],
"time_range": [t0, t1]}, ...], "meta"}`` — and whose sections ``segment.000``, ``segment.001``, … each
hold the bytes of a complete single-model ``.omg4`` file. The container's checksummed section table gives
every segment's size and CRC-32, so its byte offset follows from the table: a reader takes the fixed prefix
and the index, then seeks to one segment and reads only its bytes (:func:`read_segment`).

The index is bounded and validated like every header: at most :data:`MAX_SEGMENTS` segments, one section
per segment, frame ranges and time ranges that increase, and neighbours only sharing time — a forged
index (overlapping or reversed ranges, offsets past the end, a billion segments) is a one-line
:class:`~omg4.errors.CorruptFileError`.

:class:`SequenceModel` renders a sequence (or a segmented training run's checkpoints): at a time inside two
segments it is both, blended (:func:`omg4.data.segments.blend_weights`); at most two decoded segments are
held, and the next one is decoded ahead of playback.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Callable

from omg4.codec.container import (PREFIX, SEQUENCE_VERSION, ContainerSource, crc32, has_magic, read_container,
                                  read_prefix_and_table, write_container)
from omg4.errors import CorruptFileError, OMG4Error

MAX_SEGMENTS = 100_000
LAYOUT = "sequence"


@dataclasses.dataclass(frozen=True)
class SegmentEntry:
    """One segment of a sequence: its capture frames ``[start, stop)``, time range ``[t0, t1)``, and where its bytes
    lie (``offset``, ``size``, ``crc``) in the file."""

    index: int
    frames: tuple[int, int]
    time_range: tuple[float, float]
    offset: int
    size: int
    crc: int


@dataclasses.dataclass(frozen=True)
class SequenceIndex:
    """A sequence file's index: its segments, frame rate, metadata and total size."""

    segments: tuple[SegmentEntry, ...]
    fps: float
    meta: dict
    total_bytes: int

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
                   fps: float, meta: dict | None = None) -> int:
    """Write a sequence file: ``segments`` as (frames [start, stop), time range, bytes of its ``.omg4`` file), in
    order. Returns the file size."""
    index = [{"frames": list(frames), "time_range": [float(t) for t in times]} for frames, times, _ in segments]
    header = {"layout": LAYOUT, "fps": float(fps), "segments": index, "meta": meta or {}}
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
                                    crc))
        offset += size
    meta = header.get("meta") if isinstance(header.get("meta"), dict) else {}
    return SequenceIndex(tuple(entries), float(header["fps"]), meta, src.size)


def _check_index(label: str, header: dict, sections: int) -> None:
    segments = header.get("segments")
    if not isinstance(segments, list) or not 1 <= len(segments) <= MAX_SEGMENTS:
        raise CorruptFileError(f"{label}: a sequence holds 1 to {MAX_SEGMENTS} segments")
    if len(segments) != sections:
        raise CorruptFileError(f"{label}: the index lists {len(segments)} segments for {sections} sections")
    fps = header.get("fps")
    if not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and math.isfinite(fps) and fps > 0):
        raise CorruptFileError(f"{label}: the sequence's frame rate must be a positive number")
    previous = None
    for i, seg in enumerate(segments):
        frames, times = (seg.get("frames"), seg.get("time_range")) if isinstance(seg, dict) else (None, None)
        ok = (isinstance(frames, list) and len(frames) == 2 and all(type(f) is int and 0 <= f < 2**40 for f in frames)
              and frames[0] < frames[1] and isinstance(times, list) and len(times) == 2
              and all(isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) for t in times)
              and times[0] < times[1])
        if not ok:
            raise CorruptFileError(f"{label}: segment {i} has an invalid frame or time range")
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


def read_sequence(path: str | os.PathLike) -> tuple[SequenceIndex, list[bytes]]:
    """The index and every segment's bytes (the whole file, verified)."""
    index = read_index(path)
    _, sections = read_container(path)
    return index, [sections[f"segment.{i:03d}"] for i in range(len(index.segments))]


class SequenceModel:
    """A render-only model of a sequence of segments: each segment a model loaded on demand by ``load(k)``.

    ``parts_at(t)`` gives the models to render at ``t`` with their blend weights (one, or two across a
    boundary); :func:`omg4.render.view.render_view` renders and blends them. At most ``keep`` decoded segments
    are held (two across a boundary plus the one decoded ahead).
    """

    def __init__(self, ranges: list[tuple[float, float]], load: Callable[[int], object], *, meta: dict | None = None,
                 num_gaussians: list[int] | None = None, storage_bytes: int | None = None, keep: int = 3):
        self.ranges = [tuple(r) for r in ranges]
        self._load = load
        self._cache: OrderedDict[int, object] = OrderedDict()
        self._ahead: dict[int, Future] = {}
        self._lock = threading.Lock()
        self._executor = ThreadPoolExecutor(max_workers=1)
        self.keep = keep
        self.storage_bytes = storage_bytes
        self.segment_gaussians = list(num_gaussians or [None] * len(ranges))
        first = self.segment(0)
        self.meta = {**getattr(first, "meta", {}), **(meta or {})}  # the scene's normalization, the frame rate
        self.config = dataclasses.replace(first.config, time_range=(self.ranges[0][0], self.ranges[-1][1]))
        self.active_sh_degree, self.active_sh_degree_t = first.active_sh_degree, first.active_sh_degree_t

    @property
    def num_segments(self) -> int:
        return len(self.ranges)

    @property
    def num_gaussians(self) -> int:
        """Gaussians of every segment (what the sequence stores; a frame shows one or two segments')."""
        return sum(n for n in self.segment_gaussians if n is not None)

    def segment(self, k: int):
        """Segment ``k``'s model (decoded once, kept while among the last :attr:`keep` used)."""
        with self._lock:
            if k in self._cache:
                self._cache.move_to_end(k)
                return self._cache[k]
            ahead = self._ahead.pop(k, None)
        model = ahead.result() if ahead is not None else self._load(k)
        with self._lock:
            self._cache[k] = model
            self._cache.move_to_end(k)
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        self.segment_gaussians[k] = model.num_gaussians
        return model

    def parts_at(self, time: float) -> list[tuple[object, float]]:
        """(segment model, weight) pairs to render and blend at ``time``; starts decoding the next segment."""
        from omg4.data.segments import blend_weights

        weights = blend_weights(float(time), self.ranges)
        parts = [(self.segment(k), w) for k, w in weights]
        self._decode_ahead(weights[-1][0] + 1)
        return parts

    def segment_at(self, time: float):
        """The model of the segment weighing most at ``time`` (what one time slice of the sequence exports)."""
        from omg4.data.segments import blend_weights

        return self.segment(max(blend_weights(float(time), self.ranges), key=lambda kw: kw[1])[0])

    @property
    def values(self) -> dict:
        """The first segment's per-Gaussian values (for the bounds a viewer frames its first camera by)."""
        return self.segment(0).values

    def _decode_ahead(self, k: int) -> None:
        with self._lock:
            if k >= len(self.ranges) or k in self._cache or k in self._ahead:
                return
            self._ahead = {k: self._executor.submit(self._load, k)}  # forget older look-aheads

    def to(self, device) -> "SequenceModel":
        raise OMG4Error("a sequence model is loaded on its device by load_model(path, device)")


def load_sequence(path: str | os.PathLike, device="cpu") -> SequenceModel:
    """A :class:`SequenceModel` of a sequence file on ``device``: its index now, each segment when first shown."""
    from omg4.codec.decoder import CompactModel
    from omg4.codec.payload import decode_payload

    index = read_index(path)

    def load(k: int):
        return CompactModel(decode_payload(read_segment(path, index.segments[k])), device)

    return SequenceModel([e.time_range for e in index.segments], load, meta={**index.meta, "fps": index.fps},
                         storage_bytes=index.total_bytes)


__all__ = ["SEQUENCE_VERSION", "MAX_SEGMENTS", "SegmentEntry", "SequenceIndex", "SequenceModel", "write_sequence",
           "is_sequence", "read_index", "read_segment", "read_sequence", "load_sequence"]
