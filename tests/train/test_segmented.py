"""Training a capture segment by segment (omg4.train.segmented): the plan, one run per segment, resuming."""

from __future__ import annotations

import json

import pytest

from omg4.data import load_scene
from omg4.data.segments import plan_segments
from omg4.errors import OMG4Error
from omg4.gaussians.checkpoint import load_gaussians
from omg4.train import make_config
from omg4.train.init import initial_points
from omg4.train.segmented import segment_plan, train_segments, write_plan


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    out = tmp_path_factory.mktemp("capture") / "scene"
    write_synthetic_scene(out, SynthConfig(num_cameras=4, num_frames=12, width=48, height=32, num_points=300),
                          progress=False)
    return out


CFG = make_config("cpu-small", iterations=6, batch_size=1, checkpoint_interval=0, backend="cpu",
                  num_random_points=200)


def _run(capture, run_dir, plan, calls=None):
    def load(start, stop):
        if calls is not None:
            calls.append((start, stop))
        return load_scene(capture, frames=range(start, stop), progress=False)

    write_plan(run_dir, plan)
    return train_segments(run_dir, plan, CFG, load, lambda scene: initial_points(scene, "random", CFG),
                          log=lambda *_: None)


def test_the_plan_names_frames_times_and_folders():
    plan = segment_plan(plan_segments(12, 5, 1), fps=10.0, first_frame=20, segment_frames=5, overlap=1)
    assert [s["frames"] for s in plan["segments"]] == [[20, 25], [24, 29], [28, 32]]
    assert [s["time_range"] for s in plan["segments"]] == [[2.0, 2.5], [2.4, 2.9], [2.8, 3.2]]
    assert [s["folder"] for s in plan["segments"]] == ["segment_000", "segment_001", "segment_002"]


def test_each_segment_trains_on_its_own_frames_and_done_ones_are_skipped(capture, tmp_path):
    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    calls = []
    summaries = _run(capture, tmp_path / "run", plan, calls)
    assert calls == [(0, 6), (4, 10), (8, 12)]
    assert [s["frames"] for s in summaries] == [[0, 6], [4, 10], [8, 12]]
    assert json.loads((tmp_path / "run" / "segments.json").read_text()) == json.loads(json.dumps(plan))
    for seg in plan["segments"]:
        model, meta = load_gaussians(tmp_path / "run" / seg["folder"] / "model.safetensors")
        assert tuple(meta["time_range"]) == pytest.approx(tuple(seg["time_range"]))  # its own frames' times
    done = {p: p.stat().st_mtime_ns for p in (tmp_path / "run").glob("segment_*/model.safetensors")}
    (tmp_path / "run" / "segment_001" / "model.safetensors").unlink()
    calls.clear()
    _run(capture, tmp_path / "run", plan, calls)
    assert calls == [(4, 10)]  # only the missing segment
    again, _ = load_gaussians(tmp_path / "run" / "segment_001" / "model.safetensors")
    for p, stamp in done.items():
        if "segment_001" not in str(p):
            assert p.stat().st_mtime_ns == stamp


def test_a_folder_holding_another_plan_is_refused_and_modes_are_checked(capture, tmp_path):
    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    write_plan(tmp_path / "run", plan)
    other = segment_plan(plan_segments(12, 4, 1), fps=30.0, first_frame=0, segment_frames=4, overlap=1)
    with pytest.raises(OMG4Error, match="other segments"):
        write_plan(tmp_path / "run", other)
    with pytest.raises(OMG4Error, match="--parallel"):
        train_segments(tmp_path / "run", plan, CFG, None, None, parallel="frames")


def test_a_segment_learns_its_shared_frames_from_the_segment_before(capture, tmp_path):
    """The training views of the frames a segment shares with the one before show that segment's renders; the
    others, and every test view, show the video."""
    import numpy as np
    import torch

    from omg4.evaluate import load_model
    from omg4.render.view import render_view
    from omg4.train.segmented import taught_by

    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    _run(capture, tmp_path / "run", plan)
    teacher = load_model(tmp_path / "run" / "segment_000" / "model.safetensors")
    scene = load_scene(capture, frames=range(4, 10), progress=False)
    taught = taught_by(scene, teacher, (4, 6), torch.zeros(3))
    shared = [v for v in taught.train_views if v.frame_index < 6]
    assert len(shared) == 2 * 3  # frames 4 and 5 of the 3 training cameras
    for v in shared:
        with torch.no_grad():
            expected = render_view(teacher, v.camera, v.timestamp)[0].image.clamp(0, 1).numpy()
        np.testing.assert_array_equal(v.image(), expected)
    for plain, original in zip(taught.train_views, scene.train_views):
        if plain.frame_index >= 6:
            np.testing.assert_array_equal(plain.image(), original.image())
    assert all(
        np.array_equal(a.image(), b.image()) for a, b in zip(taught.test_views, scene.test_views))
