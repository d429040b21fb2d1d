"""The lossless rewrite of a file for the browser player (omg4.codec.browser): every value kept, only the
sections the browser cannot decode re-encoded, a file without them returned as it is."""

from __future__ import annotations

import pytest

from omg4.codec.browser import BROWSER_FLOATS, _float_count, browser_decodable
from omg4.codec.container import container_bytes, read_container, write_container
from omg4.codec.payload import CompactGrids, decode_payload
from omg4.codec.sections import decode_f16, encode_f16
from omg4.codec.sequence import read_sequence
from omg4.testing import forge

from tests.codec.test_payload import assert_payload_equal


@pytest.mark.parametrize("codec, count, grids", [
    ("paper", 300, CompactGrids()),
    ("ans", 300, CompactGrids()),
    ("ans", 3000, CompactGrids()),
    ("compact", 300, CompactGrids(weights=16, rotations=16, times=0)),  # fp16 sections LZMA happens to win
])
def test_the_rewrite_keeps_every_value_and_leaves_no_lzma_or_huffman(tmp_path, codec, count, grids):
    path = tmp_path / "m.omg4"
    forge.valid_file(path, count, codec=codec, seed=count, codebook_scale=0.125, precision=grids)
    before, _ = read_container(path)
    assert "f16-lzma" in before["encodings"].values() or codec == "paper"  # a case the rewrite must handle
    data = browser_decodable(path)
    header, sections = read_container(data)
    assert header["codec"] == ("ans" if codec == "paper" else codec)
    assert set(header["encodings"].values()) <= {*BROWSER_FLOATS, "ans", "ranks", "first-use", "sorted", "morton",
                                                 "grid", "grid-morton", "grid-morton-exact", "smallest-three-9",
                                                 "int8-cols"}
    assert_payload_equal(decode_payload(path), decode_payload(data))
    original = read_container(path)[1]
    for name, encoding in before["encodings"].items():  # each LZMA section as the smaller browser encoding
        if encoding == "f16-lzma":
            values = decode_f16(original[name], "f16-lzma", _float_count(before, name))
            assert len(sections[name]) == min(len(encode_f16(values, e)) for e in BROWSER_FLOATS), name
    kept = [name for name, e in before["encodings"].items() if e not in ("f16-lzma", "paper")]
    assert (kept or codec == "paper") and all(sections[name] == original[name] for name in kept)  # byte for byte


def test_a_file_the_browser_decodes_is_returned_as_it_is(tmp_path):
    data = forge.valid_file(tmp_path / "m.omg4", 400, codec="compact", seed=1)
    assert browser_decodable(tmp_path / "m.omg4") == data


def test_a_sequence_is_rewritten_segment_by_segment(tmp_path):
    forge.valid_sequence(tmp_path / "s.omg4", 3, 300, codec="ans", codebook_scale=0.125)
    index, segments = read_sequence(tmp_path / "s.omg4")
    rewritten = tmp_path / "r.omg4"
    rewritten.write_bytes(browser_decodable(tmp_path / "s.omg4"))
    index2, segments2 = read_sequence(rewritten)
    assert [e.time_range for e in index2.segments] == [e.time_range for e in index.segments]
    for a, b in zip(segments, segments2):
        assert "f16-lzma" not in read_container(b)[0]["encodings"].values()
        assert_payload_equal(decode_payload(a), decode_payload(b))


def test_container_bytes_are_the_file_write_container_writes(tmp_path):
    header, sections = {"kind": "x", "n": [1, 2]}, {"a": b"\x00\x01", "b": b"", "c": bytes(range(256))}
    for version in (1, 5):
        write_container(tmp_path / "f.bin", header, sections, version=version)
        assert container_bytes(header, sections, version) == (tmp_path / "f.bin").read_bytes()
        assert read_container(container_bytes(header, sections, version)) == (header, sections)
    write_container(tmp_path / "plain.bin", header, sections)  # both default to version 1, the plain JSON
    assert container_bytes(header, sections) == (tmp_path / "plain.bin").read_bytes()
    assert container_bytes(header, sections)[8:10] == b"\x01\x00"
