"""Compressing a segmented run into one sequence file (omg4.compress.api.compress_segments)."""

from __future__ import annotations

import pytest

from omg4.codec.sequence import read_index, read_segment
from omg4.compress.api import compress_segments, compress_to_file
from omg4.compress.pipeline import CompressConfig
from omg4.compress.schedule import StageLengths
from omg4.data import load_scene
from omg4.data.segments import plan_segments
from omg4.gaussians.checkpoint import load_gaussians
from omg4.train import make_config
from omg4.train.init import initial_points
from omg4.train.segmented import segment_plan, train_segments, write_plan

LENGTHS = StageLengths(sample=2, prune=2, merge=2, appearance=4, svq3d=2, svq4d=2)


def trained_segments(root, frames: int):
    """A synthetic capture of ``frames`` frames in ``root``, trained (6 steps a segment) as segments of 6 sharing 2
    in ``root/run``; its plan and its scenes (``scenes(start, stop)``)."""
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    write_synthetic_scene(root / "scene", SynthConfig(num_cameras=4, num_frames=frames, width=48, height=32,
                                                      num_points=300), progress=False)
    cfg = make_config("cpu-small", iterations=6, batch_size=1, checkpoint_interval=0, backend="cpu",
                      num_random_points=300)
    plan = segment_plan(plan_segments(frames, 6, 2), fps=30.0, first_frame=0, segment_frames=6, overlap=2)
    write_plan(root / "run", plan)

    def scenes(a, b):
        return load_scene(root / "scene", frames=range(a, b), progress=False)

    train_segments(root / "run", plan, cfg, scenes, lambda scene: initial_points(scene, "random", cfg),
                   log=lambda *_: None)
    return plan, scenes


@pytest.fixture(scope="module")
def segmented(tmp_path_factory):
    root = tmp_path_factory.mktemp("segmented")
    plan, _ = trained_segments(root, 10)
    return root, plan


@pytest.mark.parametrize("teach", [False, True])
def test_each_segment_is_the_file_compress_to_file_writes_for_it(segmented, tmp_path, teach):
    """Independent segments: each the file of its own scene; taught ones: segment 1's scene shows, for the shared
    frames 4 and 5, the crossfade from the renders of segment 0, as decoded from the sequence, into the video."""
    from omg4.codec.payload import decode_payload
    from omg4.models.compact import CompactModel
    from omg4.optimize.teaching import taught_by

    root, plan = segmented
    cfg = CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu")
    out = tmp_path / "new" / "seq.omg4"  # into a folder that does not exist yet
    report = compress_segments(root / "run", lambda a, b: load_scene(root / "scene", frames=range(a, b),
                                                                      progress=False), cfg, out, progress=False,
                               log=lambda *_: None, teach=teach, key_interval=1)
    index = read_index(out)
    assert [e.frames for e in index.segments] == [(0, 6), (4, 10)]
    assert [e.time_range for e in index.segments] == [pytest.approx((0.0, 0.2)), pytest.approx((4 / 30, 10 / 30))]
    assert report["file_bytes"] == out.stat().st_size and len(report["segments"]) == 2
    assert report["bitrate_mbps"] == pytest.approx(8 * out.stat().st_size / (10 / 30) / 1e6)
    assert not list(out.parent.glob(".*"))  # the segments' working files are gone
    for k, seg in enumerate(plan["segments"]):
        baseline, _ = load_gaussians(root / "run" / seg["folder"] / "model.safetensors")
        scene = load_scene(root / "scene", frames=range(*seg["frames"]), progress=False)
        if teach and k:
            before = CompactModel(decode_payload(read_segment(out, index.segments[k - 1])), "cpu")
            scene = taught_by(scene, before, (4, 6), backend="cpu")
        alone = tmp_path / f"alone{k}.omg4"
        compress_to_file(baseline, scene, cfg, alone, progress=False, log=lambda *_: None)
        assert read_segment(out, index.segments[k]) == alone.read_bytes()
    if teach:  # and the teaching changed what segment 1 learnt
        plain = tmp_path / "plain1.omg4"
        compress_to_file(baseline, load_scene(root / "scene", frames=range(4, 10), progress=False), cfg, plain,
                         progress=False, log=lambda *_: None)
        assert read_segment(out, index.segments[1]) != plain.read_bytes()


def test_leftovers_of_an_interrupted_compression_do_not_block_the_next(segmented, tmp_path):
    root, _ = segmented
    out = tmp_path / "seq.omg4"
    leftover = tmp_path / ".seq.omg4.segments"
    leftover.mkdir()
    (leftover / "segment_000.omg4").write_bytes(b"partial")
    cfg = CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu")
    compress_segments(root / "run", lambda a, b: load_scene(root / "scene", frames=range(a, b), progress=False), cfg,
                      out, progress=False, log=lambda *_: None)
    assert len(read_index(out).segments) == 2 and not leftover.exists()


@pytest.fixture(scope="module")
def three_segments(tmp_path_factory):
    """A segmented run of 14 frames as three segments of 6 sharing 2, and its scenes."""
    root = tmp_path_factory.mktemp("three")
    return root, trained_segments(root, 14)[1]


def _sequence(three_segments, tmp_path, key_interval: int, predicted_mlp: str = "tune", carry: float | str = 0.0):
    root, scenes = three_segments
    out = tmp_path / f"seq{key_interval}{predicted_mlp}{carry}.omg4"
    compress_segments(root / "run", scenes, CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu",
                                                           predicted_mlp=predicted_mlp, carry=carry), out,
                      progress=False, log=lambda *_: None, key_interval=key_interval)
    return out


def test_predicted_segments_take_the_mlps_and_codebooks_of_the_one_before(three_segments, tmp_path):
    """With a key interval of 3 segments 1 and 2 are predicted, keeping the MLPs (``predicted_mlp="keep"``): each
    stores none of its MLP weights, none of its non-rotation codebooks (which decode to the segment before's decoded
    values bit for bit) and no camera rig, and each is smaller than the same segment coded alone; alone a predicted
    segment does not decode."""
    import numpy as np

    from omg4.codec.container import read_versioned
    from omg4.codec.payload import decode_payload
    from omg4.codec.sequence import SegmentDecoder
    from omg4.errors import CorruptFileError

    predicted, alone = _sequence(three_segments, tmp_path, 3, "keep"), _sequence(three_segments, tmp_path, 1)
    index = read_index(predicted)
    assert index.key_interval == 3 and [e.reference for e in index.segments] == [None, 0, 1]
    assert [e.reference for e in read_index(alone).segments] == [None, None, None]
    decoded = [SegmentDecoder(predicted).payload(k) for k in range(3)]
    for k in (1, 2):
        version, header, _ = read_versioned(read_segment(predicted, index.segments[k]))
        assert version == 7
        taken = sorted(name for name, e in header["encodings"].items() if e == "reference")
        mlp = sorted(f"mlp.{name}" for name in header["mlp"])
        codebooks = sorted(f"svq.{a}.codebook{j}" for a, shapes in header["attributes"].items()
                           if a not in header["rotations"] for j in range(len(shapes)))
        assert mlp and codebooks and taken == sorted(mlp + codebooks)
        for name, w in decoded[k].mlp.items():
            assert np.array_equal(w, decoded[k - 1].mlp[name]) and w.dtype == np.float16
        for attr, qa in decoded[k].attributes.items():
            if attr not in header["rotations"]:
                assert all(np.array_equal(a, b) for a, b in zip(qa.codebooks, decoded[k - 1].attributes[attr].codebooks))
        assert index.segments[k].size < read_index(alone).segments[k].size
        assert "rig" not in decoded[k].meta and "rig" in decoded[0].meta  # the sequence's cameras: segment 0's
        with pytest.raises(CorruptFileError, match="decode it through its sequence"):
            decode_payload(read_segment(predicted, index.segments[k]))
    assert read_segment(predicted, index.segments[0]) == read_segment(alone, read_index(alone).segments[0])


def test_predicted_segments_fine_tune_the_mlps_of_the_one_before_and_store_the_change(three_segments, tmp_path):
    """By default (``predicted_mlp="tune"``) a predicted segment starts from the segment before's decoded MLPs and
    trains them: its file stores each weight matrix as its change from that segment's (``delta-int<b>-cols``), the
    decoded weights differ from the segment before's, and the changes cost fewer bytes than the same segment's
    weights coded alone; its codebooks are still taken."""
    import numpy as np

    from omg4.codec.container import read_versioned
    from omg4.codec.sequence import SegmentDecoder
    from omg4.codec.weights import parse_delta_encoding

    predicted, alone = _sequence(three_segments, tmp_path, 3), _sequence(three_segments, tmp_path, 1)
    decoded = [SegmentDecoder(predicted).payload(k) for k in range(3)]
    for k in (1, 2):
        _, header, sections = read_versioned(read_segment(predicted, read_index(predicted).segments[k]))
        _, _, alone_sections = read_versioned(read_segment(alone, read_index(alone).segments[k]))
        mlp = [f"mlp.{name}" for name in header["mlp"]]
        assert all(parse_delta_encoding(header["encodings"][n]) for n in mlp)
        assert sum(len(sections[n]) for n in mlp) < sum(len(alone_sections[n]) for n in mlp)
        assert any(not np.array_equal(w, decoded[k - 1].mlp[name]) for name, w in decoded[k].mlp.items())
        assert all(e == "reference" for n, e in header["encodings"].items() if ".codebook" in n
                   and n.split(".")[1] not in header["rotations"])


def test_a_seek_decodes_only_the_chain_back_to_its_key_segment(three_segments, tmp_path):
    """Key interval 2 over three segments: 0 key, 1 predicted from 0, 2 key. Decoding segment 2 reads its bytes
    alone; segment 1 reads segment 0's and its own; playing 0, 1, 2 in order reads each segment once."""
    from omg4.codec.sequence import SegmentDecoder

    out = _sequence(three_segments, tmp_path, 2)
    index = read_index(out)
    sizes = [e.size for e in index.segments]
    assert [e.reference for e in index.segments] == [None, 0, None]
    seek = SegmentDecoder(out)
    seek.payload(2)
    assert seek.bytes_read == sizes[2]
    seek = SegmentDecoder(out)
    seek.payload(1)
    assert seek.bytes_read == sizes[0] + sizes[1]
    play = SegmentDecoder(out)
    for k in range(3):
        play.payload(k)
    assert play.bytes_read == sum(sizes)


def test_a_predicted_segment_carries_the_segment_befores_gaussians_as_they_decoded(three_segments, tmp_path):
    """Segment 1 compressed against segment 0's decoded file with a loose carry tolerance: some of its Gaussians are
    segment 0's, fixed at their decoded values through the fine-tuning; its file names them, and decoding it gives
    those values first, bit for bit, then its own; with no tolerance nothing is carried."""
    import numpy as np
    import torch

    from omg4.codec.container import read_versioned
    from omg4.codec.payload import decode_payload, encode_payload
    from omg4.codec.references import reference_sections
    from omg4.compress.api import build_payload
    from omg4.compress.pipeline import CompressionPipeline
    from omg4.compress.stream import SegmentBefore
    from omg4.models.compact import payload_values

    root, scenes = three_segments
    cfg = CompressConfig(lengths=LENGTHS, batch_size=1, backend="cpu")
    key, _ = load_gaussians(root / "run" / "segment_000" / "model.safetensors")
    compress_to_file(key, scenes(0, 6), cfg, tmp_path / "key.omg4", progress=False, log=lambda *_: None)
    reference = reference_sections(decode_payload(tmp_path / "key.omg4"))
    baseline, _ = load_gaussians(root / "run" / "segment_001" / "model.safetensors")
    for tolerance in (0.0, 4.0):
        pipeline = CompressionPipeline(baseline, scenes(4, 10), CompressConfig(lengths=LENGTHS, batch_size=1,
                                       backend="cpu", carry=tolerance), progress=False, log=lambda *_: None,
                                       before=SegmentBefore(reference))
        model = pipeline.run()
        encode_payload(build_payload(model, {"time_range": [4 / 30, 10 / 30]}), tmp_path / "p.omg4",
                       reference=reference)
        _, header, _ = read_versioned(tmp_path / "p.omg4")
        if not tolerance:
            assert model.num_carried == 0 and "carried" not in header
            continue
        carried = model.num_carried
        assert 0 < carried < reference["gaussians.xyz"].shape[0] and header["carried"] == carried
        rows = model.carried_rows
        assert np.array_equal(rows, np.sort(rows))
        decoded = payload_values(decode_payload(tmp_path / "p.omg4", reference), model.config.schema)
        for name, values in model.carried.items():
            expected = torch.from_numpy(np.asarray(reference[f"gaussians.{name}"], np.float32)) if name in (
                "xyz", "t") else None
            if expected is not None:
                assert torch.equal(values.reshape(expected[rows].shape), expected[rows]), name
            assert torch.equal(decoded[name][:carried], values), name
        assert decoded["xyz"].shape[0] == carried + model.num_gaussians


def test_auto_decides_each_predicted_segments_carry_from_what_it_covers_and_info_shows_it(three_segments, tmp_path,
                                                                                          capsys):
    """``carry="auto"``: each predicted segment records the share of its Gaussians the segment before's lasting ones
    cover and whether it carried them; it carries them exactly where that share is at least the threshold, and then
    as many as it records; ``omg4 info`` prints the decision."""
    from omg4.app.cli import main
    from omg4.codec.container import read_versioned
    from omg4.compress.stream import AUTO_MIN_COVERED

    out = _sequence(three_segments, tmp_path, 3, carry="auto")
    index = read_index(out)
    decisions = []
    for k in (1, 2):
        _, header, _ = read_versioned(read_segment(out, index.segments[k]))
        decision = header["meta"]["carry"]
        share = decision["covered_share"]
        assert decision["setting"] == "auto" and 0 <= share <= 1
        if abs(share - AUTO_MIN_COVERED) > 1e-4:  # the record rounds the share to 4 places
            assert decision["carried"] == ("lasting" if share >= AUTO_MIN_COVERED else "none")
        assert header.get("carried", 0) == (decision["gaussians"] if decision["carried"] == "lasting" else 0)
        decisions.append((share, decision["carried"]))
    _, key_header, _ = read_versioned(read_segment(out, index.segments[0]))
    assert "carry" not in key_header["meta"]  # a key segment decides nothing
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    for share, kind in decisions:
        assert f"carry auto: {100 * share:.1f} % covered by lasting Gaussians, " + (
            "the lasting ones carried" if kind == "lasting" else "none carried") in text
