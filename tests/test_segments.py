"""Long captures as segments: planning, the sequence file (round trip, seeking, forged indexes), blending at a
boundary, resuming between segments, and evaluation over a sequence."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

import forge
from omg4.cli import main
from omg4.codec import sequence
from omg4.codec.container import read_container, write_container
from omg4.data.segments import blend_weights, near_boundary, plan_segments
from omg4.errors import CorruptFileError, OMG4Error


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
def _segments(tmp_path, count=3):
    """``count`` small valid single-model files as consecutive segments of 10 frames sharing 2, at 10 fps."""
    parts = []
    for i in range(count):
        path = tmp_path / f"s{i}.omg4"
        forge.valid_file(path, 200 + 50 * i, codec="compact", seed=i, codebook_scale=1 / 32)
        start = 8 * i
        parts.append(((start, start + 10), (start / 10, (start + 10) / 10), path.read_bytes()))
    return parts


def test_sequence_round_trip_and_index(tmp_path):
    parts = _segments(tmp_path)
    path = tmp_path / "seq.omg4"
    size = sequence.write_sequence(path, parts, fps=10.0, meta={"overlap": 2})
    index = sequence.read_index(path)
    assert size == path.stat().st_size == index.total_bytes
    assert [e.frames for e in index.segments] == [p[0] for p in parts]
    assert index.time_range == (0.0, 2.6) and index.bitrate_mbps == pytest.approx(8 * size / 2.6 / 1e6)
    for entry, (_, _, data) in zip(index.segments, parts):
        assert sequence.read_segment(path, entry) == data
    _, datas = sequence.read_sequence(path)
    assert datas == [p[2] for p in parts]
    assert sequence.is_sequence(path) and not sequence.is_sequence(tmp_path / "s0.omg4")
    with pytest.raises(OMG4Error, match="sequence of 3 segments"):
        from omg4.codec.payload import decode_payload
        decode_payload(path)


def test_one_segment_is_read_by_seeking_to_it(tmp_path, monkeypatch):
    """The index costs its own bytes; decoding segment k then reads segment k's bytes and nothing else."""
    from omg4.codec import container

    parts = _segments(tmp_path, 4)
    path = tmp_path / "seq.omg4"
    sequence.write_sequence(path, parts, fps=10.0)
    read = []
    original_read = container._Source.read
    def counted(self, n, what):  # reads from the file (a segment's bytes are then decoded from memory)
        if self.file is not None:
            read.append(n)
        return original_read(self, n, what)

    monkeypatch.setattr(container._Source, "read", counted)
    real_open = open

    class Counting:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def seek(self, offset):
            return self.f.seek(offset)

        def read(self, n):
            read.append(n)
            return self.f.read(n)

    monkeypatch.setattr(sequence, "open", lambda p, mode="r": Counting(real_open(p, mode)), raising=False)
    entries = sequence.read_index(path).segments
    assert sum(read) == entries[0].offset  # the prefix and the index: everything before the first segment
    model = sequence.load_sequence(path)  # the index, then segment 0 for the model's settings
    read.clear()
    model.segment(2)
    assert read == [entries[2].size]


def _forged(tmp_path, header_edit=None, sections_edit=None):
    parts = _segments(tmp_path)
    path = tmp_path / "seq.omg4"
    sequence.write_sequence(path, parts, fps=10.0)
    header, sections = read_container(path)
    if header_edit:
        header_edit(header)
    if sections_edit:
        sections = sections_edit(sections)
    forged = tmp_path / "forged.omg4"
    write_container(forged, header, sections, version=sequence.SEQUENCE_VERSION)
    return forged


@pytest.mark.parametrize("edit", [
    lambda h: h["segments"][1].update(frames=[4, 30]),            # beyond its neighbour's range
    lambda h: h["segments"][2].update(frames=[1, 9]),              # going back
    lambda h: h["segments"][1].update(time_range=[1.0, 0.5]),      # a reversed time range
    lambda h: h["segments"][2].update(frames=[7, 26]),             # overlapping the segment before its neighbour
    lambda h: h.update(segments=h["segments"][:2]),                # fewer index entries than sections
    lambda h: h.update(segments=h["segments"] * 2),                # more
    lambda h: h.update(fps=0),
    lambda h: h["segments"][0].update(time_range=[0, "x"]),
    lambda h: h.update(layout="other"),
])
def test_a_forged_index_is_a_one_line_error(tmp_path, edit):
    forged = _forged(tmp_path, header_edit=edit)
    with pytest.raises(CorruptFileError) as err:
        sequence.read_index(forged)
    assert "\n" not in str(err.value)


def test_a_billion_segments_and_bytes_past_the_end_are_refused(tmp_path):
    header = {"layout": "sequence", "fps": 10.0,
              "segments": [{"frames": [i, i + 1], "time_range": [i, i + 1]} for i in range(sequence.MAX_SEGMENTS + 1)]}
    with pytest.raises(CorruptFileError, match="1 to 100000 segments"):
        sequence._check_index("x", header, sequence.MAX_SEGMENTS + 1)
    # an index of 10^9 entries would be gigabytes of JSON: the container refuses headers beyond its limit unread
    from omg4.codec.container import MAX_JSON_BYTES

    assert MAX_JSON_BYTES < 10**9 * len('{"frames":[0,1],"time_range":[0,1]},')
    parts = _segments(tmp_path)
    path = tmp_path / "seq.omg4"
    sequence.write_sequence(path, parts, fps=10.0)
    (tmp_path / "cut.omg4").write_bytes(path.read_bytes()[:-100])  # the last segment would end past the file
    with pytest.raises(CorruptFileError, match="truncated"):
        sequence.read_index(tmp_path / "cut.omg4")


def test_forged_sequence_files_end_as_one_line_errors_or_decode(tmp_path):
    """The fuzz harness's forged-file classes on a sequence: every case decodes or is one CorruptFileError."""
    from omg4.evaluate import load_model

    parts = _segments(tmp_path)
    path = tmp_path / "seq.omg4"
    sequence.write_sequence(path, parts, fps=10.0)
    outcomes = {"ok": 0, "refused": 0}
    for i, (kind, data) in enumerate(forge.forged_files(path.read_bytes(), 60, seed=3)):
        case = tmp_path / f"case{i}.omg4"
        case.write_bytes(data)
        try:
            model = load_model(case)
            for k in range(getattr(model, "num_segments", 1)):
                model.segment(k) if hasattr(model, "segment") else None
            outcomes["ok"] += 1
        except CorruptFileError as exc:
            assert "\n" not in str(exc)
            outcomes["refused"] += 1
    assert outcomes["refused"] > 30


# ---------------------------------------------------------------- rendering, training, evaluation
@pytest.fixture(scope="module")
def long_scene(tmp_path_factory):
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    out = tmp_path_factory.mktemp("long") / "scene"
    write_synthetic_scene(out, SynthConfig(num_cameras=5, num_frames=16, width=64, height=48, num_points=600),
                          progress=False)
    return out


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
    from omg4.evaluate import load_model
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
                 "--batch-size", "2", "--backend", "cpu"]) == 0
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


def test_a_segment_keeps_only_its_own_frames_in_the_frame_cache(long_scene, tmp_path):
    from omg4.data import load_scene

    load_scene(long_scene, frames=range(8, 16), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    (window,) = tmp_path.glob("cam01-*.npy")
    assert np.load(window, mmap_mode="r").shape[0] == 8  # frames 8-15, not a prefix of 16
    whole = load_scene(long_scene, frames=range(0, 16), cameras=["cam01"], cache_dir=tmp_path / "p", progress=False)
    part = load_scene(long_scene, frames=range(8, 16), cameras=["cam01"], cache_dir=tmp_path, progress=False)
    np.testing.assert_array_equal(part.train_views[3].image(), whole.train_views[11].image())
