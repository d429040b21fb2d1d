"""Long captures end to end: a segmented run, blending at a boundary, resuming between segments, a sequence
file and its evaluation."""

from __future__ import annotations

import json

import pytest
import torch

from omg4.app.cli import main
from omg4.codec import sequence
from omg4.data.segments import blend_weights


@pytest.fixture(scope="module")
def long_scene(synthetic_scene):
    return synthetic_scene("long", num_cameras=5, num_frames=16, width=64, height=48, num_points=600)


TRAIN = ["--preset", "cpu-small", "--iterations", "12", "--batch-size", "2", "--backend", "cpu",
         "--checkpoint-interval", "0", "--test-interval", "0"]


@pytest.fixture(scope="module")
def segmented_run(long_scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("segrun") / "run"
    assert main(["train", str(long_scene), "--out", str(run), *TRAIN, "--segment-frames", "8", "--overlap", "2"]) == 0
    return run


def test_a_segmented_run_has_one_model_per_segment_and_its_plan(segmented_run):
    plan = json.loads((segmented_run / "segments.json").read_text())
    assert [s["frames"] for s in plan["segments"]] == [[0, 8], [6, 14], [12, 16]]
    assert plan["fps"] == pytest.approx(30.0)
    assert [s["time_range"] for s in plan["segments"]][1] == pytest.approx([6 / 30, 14 / 30])
    for s in plan["segments"]:
        assert (segmented_run / s["folder"] / "model.safetensors").is_file()


def test_render_at_a_boundary_is_the_stated_blend_of_the_two_segments(segmented_run, long_scene):
    from omg4.data import load_scene
    from omg4.models import load_model
    from omg4.render.view import render_view

    model = load_model(segmented_run)
    camera = load_scene(long_scene, progress=False).test_views[0].camera
    t = 6.5 / 30  # a quarter into the shared span of frames 6-7: weights 0.75 and 0.25
    assert blend_weights(t, model.ranges) == [(0, pytest.approx(0.75)), (1, pytest.approx(0.25))]
    with torch.no_grad():
        blended = render_view(model, camera, t, backend="cpu")[0].image
        a = render_view(model.segment(0), camera, t, backend="cpu")[0].image
        b = render_view(model.segment(1), camera, t, backend="cpu")[0].image
    torch.testing.assert_close(blended, 0.75 * a + 0.25 * b, atol=1e-6, rtol=0)
    assert float((a - b).abs().max()) > 1e-3  # the two segments do differ there


def test_a_run_stopped_between_segments_resumes_with_the_missing_ones(segmented_run, long_scene, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(segmented_run, run)
    shutil.rmtree(run / "segment_002")  # stopped before the last segment
    done = {p: p.stat().st_mtime_ns for p in run.glob("segment_00[01]/model.safetensors")}
    assert main(["train", str(long_scene), "--out", str(run), *TRAIN, "--segment-frames", "8", "--overlap", "2"]) == 2
    assert main(["train", str(long_scene), "--out", str(run), *TRAIN, "--segment-frames", "8", "--overlap", "2",
                 "--resume"]) == 0
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in done.items())  # finished segments untouched
    from omg4.gaussians.checkpoint import load_gaussians

    again, _ = load_gaussians(run / "segment_002" / "model.safetensors")
    first, _ = load_gaussians(segmented_run / "segment_002" / "model.safetensors")
    assert all(torch.equal(again.params[k], first.params[k]) for k in first.params)  # as the uninterrupted run
    assert main(["train", str(long_scene), "--out", str(run), *TRAIN, "--segment-frames", "6", "--overlap", "2",
                 "--resume"]) == 2  # another plan in the same folder is refused


def test_compress_writes_one_sequence_and_eval_of_it_weights_the_segments_by_frames(long_scene, tmp_path):
    """Segments sharing no frame: the sequence's metrics are the per-segment metrics weighted by their frames."""
    run = tmp_path / "run"
    assert main(["train", str(long_scene), "--out", str(run), *TRAIN, "--segment-frames", "8", "--overlap", "0"]) == 0
    out = tmp_path / "seq.omg4"
    assert main(["compress", str(long_scene), "--model", str(run), "--out", str(out), "--schedule", "tiny",
                 "--batch-size", "2", "--backend", "cpu", "--key-interval", "1"]) == 0  # each segment readable alone
    index = sequence.read_index(out)
    assert [e.frames for e in index.segments] == [(0, 8), (8, 16)]
    assert main(["eval", str(long_scene), "--model", str(out), "--backend", "cpu", "--lpips", "",
                 "--json", str(tmp_path / "seq.json")]) == 0
    whole = json.loads((tmp_path / "seq.json").read_text())
    parts = []
    for k, (start, stop) in enumerate(e.frames for e in index.segments):
        part = tmp_path / f"part{k}.omg4"
        part.write_bytes(sequence.read_segment(out, index.segments[k]))
        assert main(["eval", str(long_scene), "--model", str(part), "--backend", "cpu", "--lpips", "", "--frames",
                     f"{start}:{stop}", "--json", str(tmp_path / f"part{k}.json")]) == 0
        parts.append((stop - start, json.loads((tmp_path / f"part{k}.json").read_text())))
    total = sum(n for n, _ in parts)
    for key in ("psnr", "ssim"):
        assert whole[key] == pytest.approx(sum(n * r[key] for n, r in parts) / total, rel=1e-9)
    assert whole["num_segments"] == 2 and whole["boundary"]["num_views"] == 2  # frames 7 and 8
    assert whole["bitrate_mbps"] == pytest.approx(8 * out.stat().st_size / (16 / 30) / 1e6)


def test_info_shows_the_chain_of_a_sequence_with_predicted_segments(segmented_run, long_scene, tmp_path, capsys):
    """Key interval 2 over three segments: 0 key, 1 predicted from 0, 2 key; info says so in its text and its JSON,
    with each segment's bytes (the predicted one's MLPs stored as their change, in fewer) and how many Gaussians it
    carries from the one before (a loose --carry, so some are); --key-interval on one model is refused in one line."""
    out = tmp_path / "seq.omg4"
    assert main(["compress", str(long_scene), "--model", str(segmented_run), "--out", str(out), "--schedule", "tiny",
                 "--batch-size", "2", "--backend", "cpu", "--key-interval", "2", "--carry", "4"]) == 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "3 segments (2 key, 1 predicted; key interval 2)" in text and "predicted from 0" in text
    assert main(["info", str(out), "--json", str(tmp_path / "info.json")]) == 0
    info = json.loads((tmp_path / "info.json").read_text())
    index = sequence.read_index(out)
    assert info["key_interval"] == 2 and [s["reference"] for s in info["segments"]] == [None, 0, None]
    assert [s["total_bytes"] for s in info["segments"]] == [e.size for e in index.segments]
    assert 0 < info["segments"][1]["groups"]["MLPs"] < info["segments"][0]["groups"]["MLPs"]  # their change
    carried = [s["carried"] for s in info["segments"]]
    assert carried[0] == carried[2] == 0 and 0 < carried[1] < info["segments"][1]["num_gaussians"]
    assert f"predicted from 0, {carried[1]} of them carried)" in text
    capsys.readouterr()
    assert main(["compress", str(long_scene), "--model", str(segmented_run / "segment_000"), "--out",
                 str(tmp_path / "one.omg4"), "--schedule", "tiny", "--key-interval", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--key-interval applies to a segmented training run" in err and "\n" not in err


def test_the_library_calls_train_and_compress_a_long_capture_as_the_commands_do(long_scene, tmp_path):
    import omg4
    from omg4.codec.sequence import read_index
    from omg4.compress.schedule import SCHEDULES
    from omg4.models import SequenceModel, load_model

    cfg = omg4.train_config("cpu-small", iterations=12, batch_size=2, backend="cpu", checkpoint_interval=0,
                            test_interval=0)
    run = tmp_path / "run"
    summaries = omg4.train_segments(long_scene, run, 8, cfg, overlap=2)
    plan = json.loads((run / "segments.json").read_text())
    assert [s["frames"] for s in plan["segments"]] == [[0, 8], [6, 14], [12, 16]]  # 8 frames, 2 shared
    assert [s["index"] for s in summaries] == [s["index"] for s in plan["segments"]]
    assert all((run / s["folder"] / "model.safetensors").is_file() for s in plan["segments"])
    again = omg4.train_segments(long_scene, run, 8, cfg, overlap=2)  # every segment done: nothing retrained
    assert [s["num_gaussians"] for s in again] == [s["num_gaussians"] for s in summaries]
    out = tmp_path / "seq.omg4"
    report = omg4.compress_segments(run, long_scene, out, omg4.CompressConfig(lengths=SCHEDULES["tiny"],
                                                                               batch_size=2, backend="cpu"))
    index = read_index(out)
    assert [list(e.frames) for e in index.segments] == [s["frames"] for s in plan["segments"]]
    assert report["file_bytes"] == out.stat().st_size and len(report["segments"]) == len(plan["segments"])
    assert isinstance(load_model(out), SequenceModel)
