"""Synchronizing the cameras of a capture: the frames of each video to skip so that all start at one instant,
and the span every camera covers from there.

``--sync audio`` finds each video's delay against the first by cross-correlating their audio tracks
(:func:`audio_delays`): a sound heard ``d`` seconds later in video *i* than in the reference means video *i*
started ``d`` seconds earlier, so *i* skips ``d`` seconds more. ``--sync FILE`` gives the frames to skip by
hand; ``--sync none`` takes the videos as synchronized; ``auto`` is audio when every video has sound, else none.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omg4.errors import OMG4Error
from omg4.prepare.sources import AUDIO_RATE, Source

SYNC_MODES = ("auto", "audio", "none")
"""``--sync`` values besides a file of offsets."""

MAX_AUDIO_SECONDS = 120.0
"""Seconds of each audio track cross-correlated."""

MIN_CONFIDENCE = 3.0
"""Below this peak-to-runner-up ratio an audio offset is reported as unsure."""


@dataclass
class Offsets:
    """Where each camera's common span starts.

    Attributes:
        frames: frames of each source skipped to reach the common start.
        confidence: per source, how sure the audio estimate is (the correlation peak over the best peak more than
            a frame away; ≥ :data:`MIN_CONFIDENCE` is clear), or None where no audio decided it.
        method: ``"audio"``, ``"file"`` or ``"none"``.
    """

    frames: list[int]
    confidence: list[float | None]
    method: str


def audio_delays(tracks: list[np.ndarray], rate: int = AUDIO_RATE, resolution: float | None = None
                 ) -> tuple[list[float], list[float]]:
    """``(delays, confidences)``: per track, the seconds by which its sounds come later than the first track's
    (0 for the first), from the peak of their full cross-correlation (FFT), and the peak over the best other
    peak at least ``resolution`` seconds away (default: a 30th of a second)."""
    if len(tracks) < 2:
        raise OMG4Error("audio synchronization needs two or more tracks")
    resolution = 1.0 / 30.0 if resolution is None else resolution
    reference = _normalized(tracks[0])
    delays, confidences = [0.0], [float("inf")]
    for track in tracks[1:]:
        other = _normalized(track)
        if not reference.any() or not other.any():
            raise OMG4Error("an audio track is silent: synchronize by --sync FILE or none")
        size = 1 << int(np.ceil(np.log2(len(reference) + len(other))))
        correlation = np.fft.irfft(np.fft.rfft(other, size) * np.conj(np.fft.rfft(reference, size)), size)
        # lag k ≥ 0: other[n + k] matches reference[n]; negative lags wrap to the end of the array
        lags = np.concatenate([np.arange(0, len(other)), np.arange(-len(reference) + 1, 0)])
        values = np.concatenate([correlation[:len(other)], correlation[size - len(reference) + 1:]])
        best = int(np.argmax(values))
        away = np.abs(lags - lags[best]) > resolution * rate
        runner_up = float(values[away].max()) if away.any() else 0.0
        delays.append(float(lags[best]) / rate)
        confidences.append(float(values[best]) / runner_up if runner_up > 0 else float("inf"))
    return delays, confidences


def _normalized(track: np.ndarray) -> np.ndarray:
    x = np.asarray(track, dtype=np.float64).reshape(-1)
    x = x - x.mean() if len(x) else x
    peak = np.abs(x).max() if len(x) else 0.0
    return x / peak if peak > 0 else x


def skipped_frames(delays: list[float], fps: float) -> list[int]:
    """Frames each video skips so all start together: its delay over the smallest, in frames."""
    base = min(delays)
    return [int(round((d - base) * fps)) for d in delays]


def offsets_from_file(path: str | Path, sources: list[Source]) -> list[int]:
    """Frames to skip per source from ``path``: JSON ``{"name": frames, ...}`` (a file name or its stem), or lines
    ``name frames``; every source must be named once, with a whole number ≥ 0."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise OMG4Error(f"cannot read the offsets file {path} ({exc.strerror or exc})") from None
    try:
        given = json.loads(text)
    except ValueError:
        given = {}
        for number, line in enumerate(text.splitlines(), 1):
            if line.strip() and not line.lstrip().startswith("#"):
                parts = line.split()
                if len(parts) != 2:
                    raise OMG4Error(f"{path}:{number}: expected 'name frames', got '{line.strip()}'") from None
                given[parts[0]] = parts[1]
    if not isinstance(given, dict):
        raise OMG4Error(f"{path}: expected a JSON object of name → frames to skip")
    out = []
    for s in sources:
        value = given.get(s.name, given.get(s.stem))
        try:
            frames = int(value)
        except (TypeError, ValueError):
            raise OMG4Error(f"{path} gives no whole number of frames for {s.name}") from None
        if frames < 0 or str(value).strip() not in (str(frames), f"{frames}.0"):
            raise OMG4Error(f"{path}: {s.name}: frames to skip must be a whole number ≥ 0, got {value!r}")
        out.append(frames)
    unknown = sorted(set(given) - {s.name for s in sources} - {s.stem for s in sources})
    if unknown:
        raise OMG4Error(f"{path} names {unknown[0]}, which is not one of the cameras")
    return out


def synchronize(sources: list[Source], mode: str = "auto") -> Offsets:
    """The frames each source skips (see the module docstring for ``mode``: a :data:`SYNC_MODES` value or a
    file of offsets)."""
    if mode not in SYNC_MODES:
        return Offsets(offsets_from_file(mode, sources), [None] * len(sources), "file")
    with_audio = all(s.has_audio for s in sources)
    if mode == "audio" and not with_audio:
        silent = next(s for s in sources if not s.has_audio)
        raise OMG4Error(f"--sync audio: {silent.name} has no audio track")
    if mode == "none" or not with_audio:
        return Offsets([0] * len(sources), [None] * len(sources), "none")
    tracks = [s.audio(MAX_AUDIO_SECONDS) for s in sources]
    delays, confidence = audio_delays(tracks)
    return Offsets(skipped_frames(delays, sources[0].fps), [None, *confidence[1:]], "audio")


def common_span(sources: list[Source], skipped: list[int]) -> int:
    """Frames every source has from its common start on; none is a one-line error naming the shortest."""
    remaining = [s.num_frames - k for s, k in zip(sources, skipped)]
    length = min(remaining)
    if length <= 0:
        short = sources[int(np.argmin(remaining))]
        raise OMG4Error(f"the cameras share no span: {short.name} ends before the others start (check --sync)")
    return length


__all__ = ["MIN_CONFIDENCE", "Offsets", "SYNC_MODES", "audio_delays", "common_span", "offsets_from_file",
           "skipped_frames", "synchronize"]
