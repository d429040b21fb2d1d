"""Synchronization: audio delays from cross-correlation (exact, with the sign convention), offsets from a file,
the shared span."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.errors import OMG4Error
from omg4.prepare.sources import Source
from omg4.prepare.sync import audio_delays, common_span, offsets_from_file, skipped_frames

RATE = 16_000


def noise(seconds: float, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=int(seconds * RATE))


def test_audio_delays_are_exact_and_a_later_sound_is_a_positive_delay():
    """Track 1 started 0.2 s before the reference (the same sounds come 0.2 s later in it); track 2 0.1 s after it
    (they come earlier). Every delay lands on the planted sample."""
    base = noise(6.0)
    reference = base[RATE:5 * RATE]
    earlier = base[RATE - RATE // 5:4 * RATE]
    later = base[RATE + RATE // 10:6 * RATE]
    delays, confidence = audio_delays([reference, earlier, later], RATE)
    assert delays == [0.0, 0.2, -0.1]
    assert confidence[1] > 10 and confidence[2] > 10  # noise: one clear peak
    # to start together, the video that started first skips the most: 0.3 s of the earliest, 0.1 s of the reference
    assert skipped_frames(delays, fps=30.0) == [3, 9, 0]


def test_unrelated_tracks_are_unsure_and_silence_is_refused():
    delays, confidence = audio_delays([noise(3.0, 1), noise(3.0, 2)], RATE)
    assert confidence[1] < 2.0
    with pytest.raises(OMG4Error, match="silent"):
        audio_delays([noise(1.0), np.zeros(RATE)], RATE)


def source(name: str, frames: int) -> Source:
    return Source(path=None, name=name, num_frames=frames, width=64, height=48, fps=30.0)


def test_offsets_from_a_file_by_name_or_stem(tmp_path):
    sources = [source("left.mp4", 100), source("right.mov", 90)]
    (tmp_path / "o.json").write_text('{"left.mp4": 12, "right": 0}')
    assert offsets_from_file(tmp_path / "o.json", sources) == [12, 0]
    (tmp_path / "o.txt").write_text("# frames to skip\nleft 0\nright.mov 7\n")
    assert offsets_from_file(tmp_path / "o.txt", sources) == [0, 7]
    for text, message in (('{"left": 1}', "no whole number of frames for right.mov"),
                          ('{"left": 1, "right": -2}', "whole number"),
                          ('{"left": 1, "right": 2, "centre": 3}', "names centre"),
                          ("left 1 2\n", "expected 'name frames'")):
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(OMG4Error, match=message):
            offsets_from_file(tmp_path / "bad.txt", sources)


def test_the_shared_span_is_trimmed_to_the_shortest_remainder():
    sources = [source("a", 100), source("b", 80), source("c", 95)]
    assert common_span(sources, [10, 0, 20]) == 75  # a: 90 left, b: 80, c: 75
    with pytest.raises(OMG4Error, match="b ends before the others start"):
        common_span(sources, [0, 80, 0])
