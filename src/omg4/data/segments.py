"""Long captures as a sequence of segments, like a video codec's groups of pictures.

A capture of any length is cut into segments of ``F`` frames, neighbours sharing ``K`` frames: segment i
starts at frame i·(F − K); the last one ends at the capture's end (it is shorter when ``F − K`` does not
divide the rest, and always adds at least one frame to the ones it shares). A capture of at most ``F`` frames is one segment: the behaviour without segments. Each
segment is trained and compressed as its own model; at a time inside two segments' shared frames a
frame is the blend of both renders (:func:`blend_weights`), so playback crosses a boundary without a seam.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from omg4.errors import OMG4Error

PLAN_FILE = "segments.json"
"""A segmented training run's plan, in its folder: the segments' frames, time ranges and folders."""


@dataclass(frozen=True)
class Segment:
    """Frames ``[start, stop)`` of the capture (``index``: its position in the sequence)."""

    index: int
    start: int
    stop: int

    @property
    def num_frames(self) -> int:
        return self.stop - self.start

    @property
    def frames(self) -> range:
        return range(self.start, self.stop)


def plan_segments(num_frames: int, segment_frames: int | None, overlap: int = 0) -> list[Segment]:
    """The segments of a capture of ``num_frames`` frames (see the module docstring); ``segment_frames`` None:
    one segment, the whole capture."""
    if num_frames < 1:
        raise OMG4Error(f"a capture needs at least one frame, got {num_frames}")
    if segment_frames is None or segment_frames >= num_frames:
        return [Segment(0, 0, num_frames)]
    if segment_frames < 2:
        raise OMG4Error(f"--segment-frames must be at least 2, got {segment_frames}")
    if not 0 <= overlap < segment_frames:
        raise OMG4Error(f"--overlap must be in [0, {segment_frames - 1}] for segments of {segment_frames} frames, "
                        f"got {overlap}")
    step = segment_frames - overlap
    return [Segment(i, s, min(s + segment_frames, num_frames))
            for i, s in enumerate(range(0, num_frames - overlap, step))]


def crossfade_weight(position: float, shared_start: float, shared_stop: float) -> float:
    """The later segment's weight at ``position`` (a time, or a frame) in the span ``[shared_start, shared_stop)`` two
    neighbouring segments share: rising linearly from 0 at its start towards 1 at its end."""
    return (position - shared_start) / (shared_stop - shared_start)


def blend_weights(time: float, ranges: list[tuple[float, float]]) -> list[tuple[int, float]]:
    """(segment, weight) pairs, weights summing to 1, for a frame at ``time``, given each segment's time range
    ``[t0, t1)`` in order (a frame at ``f / fps`` belongs to the segment holding frame ``f``).

    In the shared range of segments a and a + 1, ``[t0(a+1), t1(a))``, both, the later one's weight rising
    linearly from 0 at its start to 1 at its end (a crossfade); elsewhere the one segment holding ``time``;
    before the first range or after the last, the nearest segment."""
    if not ranges:
        raise OMG4Error("a sequence without segments")
    for a in range(len(ranges) - 1):
        shared_start, shared_stop = ranges[a + 1][0], ranges[a][1]
        if shared_start <= time < shared_stop:
            w = crossfade_weight(time, shared_start, shared_stop)
            return [(a, 1.0 - w), (a + 1, w)] if w > 0.0 else [(a, 1.0)]
    holding = [a for a, (t0, t1) in enumerate(ranges) if t0 <= time < t1]
    if holding:
        return [(holding[-1], 1.0)]
    return [(0, 1.0)] if time < ranges[0][0] else [(max(a for a, (t0, _) in enumerate(ranges) if t0 <= time), 1.0)]


def near_boundary(time: float, ranges: list[tuple[float, float]], fps: float) -> bool:
    """Whether the frame shown at ``time`` (lasting until the next, ``1 / fps`` later) is a boundary frame: its middle
    lies within half the shared span of two neighbouring segments, measured from that span's middle — the shared
    frames, or with no shared frame the last of one segment and the first of the next. Evaluation reports these
    apart from the interior frames."""
    middle = time + 0.5 / fps
    for a in range(len(ranges) - 1):
        shared_start, shared_stop = ranges[a + 1][0], ranges[a][1]
        half = max(shared_stop - shared_start, 1.0 / fps) / 2.0
        if abs(middle - 0.5 * (shared_start + shared_stop)) <= half + 1e-9:
            return True
    return False


def shared_frames(before: dict | None, seg: dict) -> tuple[int, int] | None:
    """The frames ``[start, stop)`` that the plan's segment ``seg`` shares with ``before`` (the plan's entry of the
    segment before it, None for the first), or None when they share none."""
    if before is None or before["frames"][1] <= seg["frames"][0]:
        return None
    return seg["frames"][0], before["frames"][1]


def segment_folder(index: int) -> str:
    """A segment's run folder inside a segmented run: ``segment_000``, ``segment_001``, …"""
    return f"segment_{index:03d}"


def is_segmented_run(path: Path) -> bool:
    """Whether ``path`` is a segmented training run's folder (it holds :data:`PLAN_FILE`)."""
    return Path(path).is_dir() and (Path(path) / PLAN_FILE).is_file()


def read_run_plan(run_dir: Path) -> dict:
    """A segmented run's plan (:data:`PLAN_FILE`): ``{"fps", "segment_frames", "overlap", "segments": [{"index",
    "frames": [start, stop], "time_range": [t0, t1], "folder"}]}``; a damaged plan is a one-line error."""
    path = Path(run_dir) / PLAN_FILE
    try:
        plan = json.loads(path.read_text())
        segments = plan["segments"]
        ok = (isinstance(segments, list) and segments and all(
            isinstance(s, dict) and isinstance(s.get("folder"), str) and "/" not in s["folder"]
            and len(s.get("time_range", ())) == 2 and len(s.get("frames", ())) == 2 for s in segments))
    except (OSError, ValueError, KeyError, TypeError):
        ok = False
    if not ok:
        raise OMG4Error(f"{path} is not a segment plan omg4 wrote")
    return plan


HOLD_LASTING_REMOVED = ("removed: a segment holding the one before's lasting Gaussians in training did not pay once "
                        "compressed (docs/results.md, 'Options removed, and why'; "
                        "benchmarks/results/segments_prediction_basketball24.json)")
"""Why runs and files of segments trained with ``--hold-lasting`` are refused (it was removed)."""

__all__ = ["HOLD_LASTING_REMOVED", "PLAN_FILE", "Segment", "plan_segments", "crossfade_weight", "blend_weights",
           "near_boundary", "shared_frames", "segment_folder", "is_segmented_run", "read_run_plan"]
