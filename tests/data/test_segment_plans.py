"""Cutting a capture into segments, blending neighbours, telling boundary frames (omg4.data.segments)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omg4.data.segments import blend_weights, near_boundary, plan_segments
from omg4.errors import OMG4Error


def frames_of(segments):
    return [(s.start, s.stop) for s in segments]


@pytest.mark.parametrize("n,f,k,expected", [
    (60, 50, 10, [(0, 50), (40, 60)]),                      # basketball: segments of 50 sharing 10
    (240, 60, 10, [(0, 60), (50, 110), (100, 160), (150, 210), (200, 240)]),
    (120, 60, 0, [(0, 60), (60, 120)]),                     # F divides the length, no overlap
    (100, 60, 0, [(0, 60), (60, 100)]),                     # it does not: a shorter last segment
    (61, 60, 10, [(0, 60), (50, 61)]),                      # the last adds one frame beyond the shared ones
    (45, 60, 10, [(0, 45)]),                                # a capture shorter than F is one segment
    (60, 60, 5, [(0, 60)]),
    (7, 3, 2, [(0, 3), (1, 4), (2, 5), (3, 6), (4, 7)]),
])
def test_segment_plans(n, f, k, expected):
    segments = plan_segments(n, f, k)
    assert frames_of(segments) == expected
    assert [s.index for s in segments] == list(range(len(segments)))
    assert all(b.start == a.stop - k for a, b in zip(segments, segments[1:]))  # neighbours share exactly K frames
    assert segments[0].start == 0 and segments[-1].stop == n


def test_bad_plans_are_one_line_errors():
    assert frames_of(plan_segments(30, None)) == [(0, 30)]
    for args in ((0, 10, 0), (30, 1, 0), (30, 10, 10), (30, 10, -1)):
        with pytest.raises(OMG4Error):
            plan_segments(*args)


def test_blend_weights_crossfade_across_the_shared_frames():
    ranges = [(0.0, 2.0), (1.5, 3.5), (3.0, 5.0)]
    assert blend_weights(1.0, ranges) == [(0, 1.0)]
    assert blend_weights(1.5, ranges) == [(0, 1.0)]  # the shared range starts with the earlier segment alone
    assert blend_weights(1.625, ranges) == [(0, 0.75), (1, 0.25)]
    assert blend_weights(1.875, ranges) == [(0, 0.25), (1, 0.75)]
    assert blend_weights(2.0, ranges) == [(1, 1.0)]
    assert blend_weights(3.25, ranges) == [(1, 0.5), (2, 0.5)]
    assert blend_weights(-1.0, ranges) == [(0, 1.0)] and blend_weights(9.0, ranges) == [(2, 1.0)]
    touching = [(0.0, 2.0), (2.0, 4.0)]  # no overlap: a frame at 2.0 is the second segment's first
    assert blend_weights(2.0, touching) == [(1, 1.0)] and blend_weights(1.99, touching) == [(0, 1.0)]
    for t in np.linspace(-1, 6, 71):
        assert math.isclose(sum(w for _, w in blend_weights(float(t), ranges)), 1.0)


def test_boundary_frames_are_those_within_half_the_shared_span():
    fps = 10.0
    ranges = [(0.0, 5.0), (4.0, 9.0)]  # 10 shared frames, 40-49
    assert [f for f in range(90) if near_boundary(f / fps, ranges, fps)] == list(range(40, 50))
    # no shared frame: the last frame of one segment and the first of the next
    assert [f for f in range(40) if near_boundary(f / fps, [(0.0, 2.0), (2.0, 4.0)], fps)] == [19, 20]


# ------------------------------------------------------------------------------ the sequence file

@pytest.fixture(scope="module")
def long_scene(synthetic_scene):
    return synthetic_scene("long", num_cameras=3, num_frames=16, width=64, height=48, num_points=300)


def test_a_segment_keeps_only_its_own_frames_in_the_frame_cache(long_scene, tmp_path):
    from omg4.data import load_scene

    load_scene(long_scene, frames=range(8, 16), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    (window,) = tmp_path.glob("cam01-*.npy")
    assert np.load(window, mmap_mode="r").shape[0] == 8  # frames 8-15, not a prefix of 16
    whole = load_scene(long_scene, frames=range(0, 16), cameras=["cam01"], cache_dir=tmp_path / "p", progress=False)
    part = load_scene(long_scene, frames=range(8, 16), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    np.testing.assert_array_equal(part.train_views[3].image(), whole.train_views[11].image())


def test_boundary_frames_are_the_shared_ones():
    """Segments of 60 frames sharing 10 at 30 fps: frames 50–59 and 100–109 are boundary frames, no others;
    segments that only touch make the last frame of one and the first of the next boundary frames."""
    from omg4.data.segments import near_boundary

    shared = [(0.0, 2.0), (50 / 30, 110 / 30), (100 / 30, 160 / 30)]
    assert [f for f in range(160) if near_boundary(f / 30, shared, 30.0)] == [*range(50, 60), *range(100, 110)]
    touching = [(0.0, 2.0), (2.0, 4.0)]
    assert [f for f in range(120) if near_boundary(f / 30, touching, 30.0)] == [59, 60]


def test_a_run_plan_is_read_back_and_a_damaged_one_refused(tmp_path):
    import json

    from omg4.data.segments import is_segmented_run, read_run_plan

    plan = {"fps": 30.0, "segment_frames": 6, "overlap": 2, "segments": [
        {"index": 0, "frames": [0, 6], "time_range": [0.0, 0.2], "folder": "segment_000"}]}
    assert not is_segmented_run(tmp_path)
    (tmp_path / "segments.json").write_text(json.dumps(plan))
    assert is_segmented_run(tmp_path) and read_run_plan(tmp_path) == plan
    plan["segments"][0]["time_range"] = [0.0, 0.1, 0.2]
    (tmp_path / "segments.json").write_text(json.dumps(plan))
    with pytest.raises(OMG4Error):
        read_run_plan(tmp_path)
