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
from omg4.train.segmented import plan_capture, segment_plan, train_segments, write_plan


@pytest.fixture(scope="module")
def capture(synthetic_scene):
    return synthetic_scene("capture", num_cameras=4, num_frames=12, width=48, height=32, num_points=300)


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


def test_a_capture_is_planned_from_its_frames_and_refused_without_a_frame_sequence(capture):
    scene = load_scene(capture, decode=False, progress=False)  # 12 frames at 30 fps
    plan = plan_capture(scene, 6)
    assert plan["overlap"] == 1 and plan["fps"] == pytest.approx(30.0)  # a sixth of a segment by default
    assert [s["frames"] for s in plan["segments"]] == [[0, 6], [5, 11], [10, 12]]
    assert plan_capture(scene, 6, overlap=2)["overlap"] == 2
    gaps = load_scene(capture, frames=[0, 1, 2, 5, 6], decode=False, progress=False)
    with pytest.raises(OMG4Error, match="needs a contiguous range of frames"):
        plan_capture(gaps, 2)
    scene.format = "blender"
    with pytest.raises(OMG4Error, match="a blender scene has no frame sequence to cut"):
        plan_capture(scene, 6)


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


def test_a_segment_learns_its_shared_frames_as_the_crossfade_from_the_segment_before_into_the_video(capture, tmp_path):
    """The training views of the frames 4 and 5 a segment shares with the one before show (1 − w)·that segment's
    render + w·video, w the weight playback gives the new segment there (0 at frame 4, ½ at frame 5: linear over
    the two shared frames); the others, and every test view, show the video."""
    import numpy as np
    import torch

    from omg4.models import load_model
    from omg4.render.view import render_view
    from omg4.optimize.teaching import taught_by

    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    _run(capture, tmp_path / "run", plan)
    teacher = load_model(tmp_path / "run" / "segment_000" / "model.safetensors")
    scene = load_scene(capture, frames=range(4, 10), progress=False)
    taught = taught_by(scene, teacher, (4, 6))
    assert sum(v.frame_index < 6 for v in taught.train_views) == 2 * 3  # frames 4 and 5 of the 3 training cameras
    for v, original in zip(taught.train_views, scene.train_views):
        if v.frame_index >= 6:
            np.testing.assert_array_equal(v.image(), original.image())
            continue
        w = {4: 0.0, 5: 0.5}[v.frame_index]
        with torch.no_grad():
            render = render_view(teacher, v.camera, v.timestamp)[0].image.clamp(0, 1).double().numpy()
        np.testing.assert_allclose(v.image(), (1 - w) * render + w * original.image(), atol=1e-6)
        assert v.frame_index == 5 or not np.allclose(v.image(), original.image(), atol=1e-2)  # frame 4: the render
    assert all(
        np.array_equal(a.image(), b.image()) for a, b in zip(taught.test_views, scene.test_views))


def test_a_segment_starts_from_the_gaussians_of_the_segment_before_that_can_be_drawn_in_its_time(capture):
    """Carried: opacity × exp(−½ gap² / σ_t²) ≥ 1/255, the gap from the time centre to the segment's range (σ_t:
    exp of ``scaling_t`` with identity rotations); then fresh Gaussians up to the cap; over the cap, the most
    opaque carried."""
    import math

    import torch

    from omg4.gaussians.model import GaussianConfig, Gaussians4D
    from omg4.models.windowed import WindowedModel
    from omg4.train.segmented import warm_start

    scene = load_scene(capture, frames=range(4, 10), progress=False)  # times [4/30, 10/30)
    t0, t1 = scene.time_range
    centres = [t0 - 0.5, t0 - 0.32, t0 + 0.05, t1 + 0.2, t1 + 0.31, t0 - 2.9, t0 - 3.6]
    sigmas = [0.1, 0.1, 0.1, 0.1, 0.1, 1.0, 1.0]
    logits = [3.0, 5.0, -1.0, -4.0, 0.0, 1.0, 0.0]

    def peak(t, s, o):
        gap = max(t0 - t, t - t1, 0.0)
        return math.exp(-0.5 * (gap / s) ** 2) / (1.0 + math.exp(-o))

    alive = [i for i, args in enumerate(zip(centres, sigmas, logits)) if peak(*args) >= 1 / 255]
    assert alive == [1, 2, 4, 5]  # 1 and 4 beyond three σ but opaque enough; 3 within two σ but too faint
    before = Gaussians4D.from_points(torch.rand(7, 3), torch.rand(7, 3),
                                     GaussianConfig(time_range=(0.0, 0.2), backbone="rt4dgs"),
                                     generator=torch.Generator().manual_seed(0))
    before.params["t"] = torch.tensor(centres).reshape(-1, 1)
    before.params["scaling_t"] = torch.tensor([math.log(s) for s in sigmas]).reshape(-1, 1)
    before.params["opacity"] = torch.tensor(logits).reshape(-1, 1)
    teacher = WindowedModel(before.params, before.config, 3, 1)
    points = initial_points(scene, "random", CFG)

    start = warm_start(teacher, scene, CFG.with_strategy(max_gaussians=0), points)
    assert start.config.time_range == pytest.approx((t0, t1))
    assert start.num_gaussians == len(alive) + len(points.xyz)
    for k, v in start.params.items():
        torch.testing.assert_close(v[: len(alive)], before.params[k][alive], rtol=0, atol=0)
    torch.testing.assert_close(start.params["xyz"][len(alive):], torch.as_tensor(points.xyz, dtype=torch.float32))

    capped = warm_start(teacher, scene, CFG.with_strategy(max_gaussians=6), points)
    assert capped.num_gaussians == 6  # the four carried and two fresh
    full = warm_start(teacher, scene, CFG.with_strategy(max_gaussians=2), points)
    torch.testing.assert_close(full.params["t"], before.params["t"][[1, 5]])  # logits 5.0 and 1.0, in order


def test_a_warm_started_segment_holds_at_most_the_first_segments_gaussians():
    from omg4.train.segmented import segment_budget

    assert segment_budget(CFG.with_strategy(max_gaussians=0), 150).strategy.max_gaussians == 150
    assert segment_budget(CFG.with_strategy(max_gaussians=100), 150).strategy.max_gaussians == 100
    assert segment_budget(CFG.with_strategy(max_gaussians=1000), 150).strategy.max_gaussians == 150


def test_a_taught_segment_starts_from_the_one_before(capture, tmp_path, monkeypatch):
    """With teaching, segments 1 and 2 start from the model of the segment before (its trained file), in their own
    time range; independent segments start afresh."""
    from omg4.train import segmented

    plan = segment_plan(plan_segments(12, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    calls = []
    original = segmented.warm_start

    def spy(teacher, scene, cfg, points=None):
        calls.append((teacher.num_gaussians, tuple(scene.time_range), cfg.strategy.max_gaussians))
        return original(teacher, scene, cfg, points)

    monkeypatch.setattr(segmented, "warm_start", spy)
    _run(capture, tmp_path / "run", plan)
    trained = [load_gaussians(tmp_path / "run" / s["folder"] / "model.safetensors")[0].num_gaussians
               for s in plan["segments"]]
    assert [n for n, _, _ in calls] == trained[:2]
    assert [r for _, r, _ in calls] == [pytest.approx((4 / 30, 10 / 30)), pytest.approx((8 / 30, 12 / 30))]
    assert [cap for _, _, cap in calls] == [trained[0]] * 2  # the first segment's count, below CFG's cap
    assert trained[0] < CFG.strategy.max_gaussians and max(trained[1:]) <= trained[0]
    calls.clear()
    independent = tmp_path / "independent"
    write_plan(independent, plan)
    train_segments(independent, plan, CFG, lambda a, b: load_scene(capture, frames=range(a, b), progress=False),
                   lambda scene: initial_points(scene, "random", CFG), teach=False, log=lambda *_: None)
    assert calls == []


def test_the_frames_a_segment_shares_with_the_one_before():
    from omg4.data.segments import shared_frames

    assert shared_frames(None, {"frames": [0, 6]}) is None
    assert shared_frames({"frames": [0, 6]}, {"frames": [4, 10]}) == (4, 6)
    assert shared_frames({"frames": [0, 6]}, {"frames": [6, 12]}) is None  # touching, nothing shared
