"""The .omg4 sequence file (omg4.codec.sequence): round trip, seeking to one segment, forged indexes."""

from __future__ import annotations

import pytest

from omg4.codec import sequence
from omg4.codec.container import read_container, write_container
from omg4.errors import CorruptFileError, OMG4Error
from omg4.models.sequence import SequenceModel, load_sequence
from omg4.testing import forge


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
    original_read = container.ContainerSource.read
    def counted(self, n, what):  # reads from the file (a segment's bytes are then decoded from memory)
        if self.file is not None:
            read.append(n)
        return original_read(self, n, what)

    monkeypatch.setattr(container.ContainerSource, "read", counted)
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
    model = load_sequence(path)  # the index, then segment 0 for the model's settings
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
    lambda h: h["segments"][1].update(frames=[0, 18]),             # starting with its neighbour, not after it
    lambda h: h["segments"][1].update(time_range=[0.0, 1.8]),      # the same in time
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
    from omg4.models import load_model

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


def test_late_frames_and_the_whole_time_range(tmp_path):
    """Frame numbers far into a capture are valid (below 2⁴⁰); a sequence spans its first segment's start to its
    last one's end."""
    parts = [((f0 + 1_000_000, f1 + 1_000_000), (t0 + 100_000.0, t1 + 100_000.0), data)
             for (f0, f1), (t0, t1), data in _segments(tmp_path)]
    path = tmp_path / "late.omg4"
    sequence.write_sequence(path, parts, fps=10.0)
    index = sequence.read_index(path)
    assert [e.frames for e in index.segments] == [(1_000_000, 1_000_010), (1_000_008, 1_000_018),
                                                  (1_000_016, 1_000_026)]
    model = load_sequence(path)
    assert model.config.time_range == pytest.approx((100_000.0, 100_002.6))


def test_showing_a_segment_decodes_the_next_one_ahead_and_only_that(tmp_path):
    """``parts_at(t)`` returns the segments to blend at t and starts decoding the segment after the last of them
    in the background, so playback finds it decoded; the last segment starts nothing."""
    import dataclasses
    import threading

    @dataclasses.dataclass
    class Config:
        time_range: tuple

    class Segment:
        def __init__(self, k):
            self.k, self.config, self.meta, self.num_gaussians = k, Config((k, k + 1)), {}, 10 + k
            self.active_sh_degree = self.active_sh_degree_t = 0

    loads, loaded = [], threading.Condition()

    def load(k):
        with loaded:
            loads.append(k)
            loaded.notify_all()
        return Segment(k)

    model = SequenceModel([(0.0, 1.0), (1.0, 2.0), (2.0, 3.0), (3.0, 4.0)], load)
    assert loads == [0]
    parts = model.parts_at(0.5)
    assert [(seg.k, w) for seg, w in parts] == [(0, 1.0)]
    with loaded:
        assert loaded.wait_for(lambda: len(loads) == 2, timeout=10)
    assert loads == [0, 1]
    assert model.segment(1).k == 1 and loads == [0, 1]  # taken from the look-ahead, not decoded again
    model.parts_at(3.5)
    with loaded:
        assert loaded.wait_for(lambda: len(loads) == 3, timeout=10)
    assert loads == [0, 1, 3]  # segment 3 on demand; nothing after the last


# ---------------------------------------------------------------- predicted segments


def _predicted(tmp_path, segments=3, key_interval=3):
    path = tmp_path / "pred.omg4"
    forge.valid_sequence(path, segments, 300, codec="compact", codebook_scale=1 / 32, key_interval=key_interval)
    return path


def _reforged(tmp_path, path, header_edit=None, segment_edit=None):
    """``path`` written again with its index edited, or with one segment's file replaced by
    ``segment_edit(segment header, [(section, bytes)]) -> (index, bytes)``."""
    header, sections = read_container(path)
    if header_edit:
        header_edit(header)
    if segment_edit:
        k, data = segment_edit(*forge.split_container(sections[f"segment.{segment_edit.k:03d}"]))
        sections[f"segment.{k:03d}"] = data
    forged = tmp_path / "forged.omg4"
    write_container(forged, header, sections, version=sequence.SEQUENCE_VERSION)
    return forged


@pytest.mark.parametrize("edit, message", [
    (lambda h: h["segments"][1].update(reference=2), "predicted from segment 2"),      # a later segment
    (lambda h: h["segments"][1].update(reference=1), "predicted from segment 1"),      # itself
    (lambda h: h["segments"][0].update(reference=-1), "predicted from segment -1"),    # a missing one
    (lambda h: h["segments"][2].update(reference=0), "predicted from segment 0"),      # not the one before
    (lambda h: h["segments"][1].update(reference="0"), "predicted from segment '0'"),
    (lambda h: h["segments"][1].update(reference=True), "predicted from segment True"),
    (lambda h: h.update(key_interval=2), "segment 2 makes 2 predicted segments in a row, more than the key interval 2"),
    (lambda h: h.update(key_interval=0), "key interval must be an integer"),
    (lambda h: h.update(key_interval=2.5), "key interval must be an integer"),
    (lambda h: h.update(key_interval=10**9), "key interval must be an integer"),
    (lambda h: h.update(key_interval=1025), "key interval must be an integer from 1 to 1024"),  # a seek's bound
])
def test_a_forged_chain_is_a_one_line_error_before_any_segment_is_read(tmp_path, edit, message, monkeypatch):
    forged = _reforged(tmp_path, _predicted(tmp_path), header_edit=edit)
    monkeypatch.setattr(sequence, "read_segment", lambda *a: pytest.fail("a segment was read"))
    with pytest.raises(CorruptFileError, match=message) as err:
        sequence.read_index(forged)
    assert "\n" not in str(err.value)


def _edited_segment(k, edit):
    def segment_edit(header, sections):
        header, sections = edit(json_copy(header), dict(sections))
        return k, forge.assemble_container(header, list(sections.items()))
    segment_edit.k = k
    return segment_edit


def json_copy(value):
    import json

    return json.loads(json.dumps(value))


def _weight_the_reference_lacks(header, sections):
    header["mlp"]["extra.weight"] = [2, 2]
    header["encodings"]["mlp.extra.weight"] = "reference"
    sections["mlp.extra.weight"] = b""
    return header, sections


def _with_bytes(header, sections):
    name = next(n for n, e in header["encodings"].items() if e == "reference")
    sections[name] = b"\x00" * 16
    return header, sections


def _wrong_shape(header, sections):
    name = next(n for n, e in header["encodings"].items() if e == "reference" and n.startswith("mlp."))
    shape = header["mlp"][name[len("mlp."):]]
    header["mlp"][name[len("mlp."):]] = [shape[0] + 1, *shape[1:]]
    return header, sections


def _truncated_change(header, sections):
    name = next(n for n, e in header["encodings"].items() if e.startswith("delta-"))
    sections[name] = sections[name][:3]
    return header, sections


def _change_of_a_weight_the_reference_lacks(header, sections):
    header["mlp"]["extra.weight"] = [2, 2]
    header["encodings"]["mlp.extra.weight"] = "delta-int8-cols"
    sections["mlp.extra.weight"] = b"\x00" * 12
    return header, sections


@pytest.mark.parametrize("k, edit, message", [
    (1, _truncated_change, "truncated change of a weight matrix"),
    (2, _change_of_a_weight_the_reference_lacks, "the reference segment has no such section"),
    (1, _with_bytes, "holds 16 bytes of its own"),
    (1, _wrong_shape, "the reference's section has shape"),
    (2, _weight_the_reference_lacks, "the reference segment has no such section"),
])
def test_a_forged_predicted_segment_is_a_one_line_error(tmp_path, k, edit, message):
    from omg4.models import load_model
    from omg4.models.summary import describe_sequence

    forged = _reforged(tmp_path, _predicted(tmp_path), segment_edit=_edited_segment(k, edit))
    with pytest.raises(CorruptFileError, match=message) as err:
        describe_sequence(forged)
    assert "\n" not in str(err.value) and f"segment {k}" in str(err.value)
    with pytest.raises(CorruptFileError, match=message):
        load_model(forged).segment(k)


def test_a_key_segment_that_takes_sections_is_refused(tmp_path):
    """Segment 1's file under an index that calls it a key segment: it has no reference to take from."""
    forged = _reforged(tmp_path, _predicted(tmp_path, key_interval=2), header_edit=lambda h: h["segments"][1].update(
        reference=None))
    with pytest.raises(CorruptFileError, match="segment 1: .*decode it through its sequence"):
        sequence.SegmentDecoder(forged).payload(1)


def test_a_file_without_chain_fields_is_all_key_segments(tmp_path):
    """Files written before predicted segments: no ``reference`` and no ``key_interval`` in the index."""
    path = tmp_path / "old.omg4"
    sequence.write_sequence(path, _segments(tmp_path), fps=10.0)

    def strip(h):
        h.pop("key_interval")
        for seg in h["segments"]:
            seg.pop("reference")

    old = _reforged(tmp_path, path, header_edit=strip)
    index = sequence.read_index(old)
    assert index.key_interval == 1 and [e.reference for e in index.segments] == [None, None, None]
    assert forge.exercise(old) == "ok"


@pytest.mark.parametrize("key_interval", [1, 3])
def test_forged_predicted_sequences_end_as_one_line_errors_or_decode(tmp_path, key_interval):
    """The fuzz harness's forged-file classes on a sequence of predicted segments: each case decodes, or is one
    CorruptFileError, in every reader."""
    path = _predicted(tmp_path, key_interval=key_interval)
    refused = 0
    for i, (kind, data) in enumerate(forge.forged_files(path.read_bytes(), 24, seed=5)):
        case = tmp_path / f"case{i}.omg4"
        case.write_bytes(data)
        try:
            forge.exercise(case)
        except CorruptFileError as exc:
            assert "\n" not in str(exc)
            refused += 1
    assert refused > 10


@pytest.mark.parametrize("codec", ["ans", "paper"])
def test_a_predicted_segment_decodes_to_the_values_it_was_written_with(tmp_path, codec):
    """Lossless codecs: a segment whose MLPs and non-rotation codebooks are its reference's decoded ones decodes,
    with that reference, to exactly the payload written (in the codec's order); the taken sections cost no bytes,
    and the file is smaller than the same payload coded alone by at least their bytes."""
    import numpy as np

    from omg4.codec.payload import decode_payload, encode_payload
    from omg4.codec.references import reference_sections
    from omg4.codec.sections import canonical_order

    from tests.codec.test_payload import assert_payload_equal

    encode_payload(forge.valid_payload(300, seed=0, codebook_scale=1 / 32), tmp_path / "key.omg4", codec=codec)
    reference = reference_sections(decode_payload(tmp_path / "key.omg4"))
    p = forge.valid_payload(250, seed=1, codebook_scale=1 / 32)
    rng = np.random.default_rng(1)
    p.mlp = {name: reference[f"mlp.{name}"] for name in p.mlp}
    for attr, qa in p.attributes.items():
        if attr not in p.rotations:
            qa.codebooks = [reference[f"svq.{attr}.codebook{j}"] for j in range(len(qa.codebooks))]
            qa.indices = [rng.integers(0, len(cb), 250) for cb in qa.codebooks]
    predicted = encode_payload(p, tmp_path / "p.omg4", codec=codec, reference=reference)
    alone = encode_payload(p, tmp_path / "alone.omg4", codec=codec)
    expected = p.permuted(canonical_order(p.xyz)) if codec == "ans" else p
    assert_payload_equal(decode_payload(tmp_path / "p.omg4", reference), expected.to_fp16())
    taken = [name for name in reference if name in predicted]
    assert taken and all(predicted[name] == 0 for name in taken)
    assert sum(predicted.values()) <= sum(alone.values()) - sum(alone[name] for name in taken) + 64


def test_an_attribute_stored_as_quaternions_must_be_a_rotation(tmp_path):
    """Else a reader would offer its per-Gaussian quaternions as a codebook a predicted segment could take."""
    from omg4.codec.payload import decode_payload

    header, sections = forge.split_container(forge.valid_file(tmp_path / "m.omg4", 300, codec="compact", seed=2,
                                                              codebook_scale=1 / 32))
    assert header["quaternions"]
    forged = forge.assemble_container({**header, "rotations": []}, sections)
    with pytest.raises(CorruptFileError, match="invalid list of rotation attributes"):
        decode_payload(forged)
