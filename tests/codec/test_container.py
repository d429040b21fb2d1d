"""The .omg4 container: round trip, storage accounting, and every kind of damage → CorruptFileError."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

from omg4.codec.container import FORMAT_VERSION, MAGIC, describe_container, read_container, write_container
from omg4.errors import CorruptFileError, OMG4Error

HEADER = {"kind": "test", "preset": "M", "time_range": [0.0, 10.0], "note": "ünïcode ✓", "nested": {"a": [1, 2]}}
SECTIONS = {"xyz": bytes(range(40)), "empty": b"", "svq.scale.index0": b"\x00\xff" * 17, "mlp.cont": b"abc"}


def _crafted(doc_bytes: bytes, body: bytes = b"", version: int = 1, flags: int = 0,
             json_len: int | None = None, crc: int | None = None) -> bytes:
    """A container built by hand (independent of write_container) with arbitrary JSON and fields."""
    n = len(doc_bytes) if json_len is None else json_len
    c = zlib.crc32(doc_bytes) if crc is None else crc
    return struct.pack("<8sHHII", MAGIC, version, flags, n, c) + doc_bytes + body


@pytest.fixture
def written(tmp_path):
    path = tmp_path / "model.omg4"
    size = write_container(path, HEADER, SECTIONS)
    return path, size


def test_round_trip_path_and_bytes(written):
    path, size = written
    assert size == path.stat().st_size
    for source in (path, str(path), path.read_bytes()):
        header, sections = read_container(source)
        assert header == HEADER
        assert sections == SECTIONS
        assert list(sections) == list(SECTIONS)  # order kept


def test_layout_matches_spec(written):
    """Independent parse of the documented layout: prefix, checksummed JSON, sections in order."""
    data = written[0].read_bytes()
    magic, version, flags, n, crc = struct.unpack("<8sHHII", data[:20])
    assert (magic, version, flags) == (MAGIC, 1, 0)
    blob = data[20:20 + n]
    assert zlib.crc32(blob) == crc
    doc = json.loads(blob)
    assert doc["header"] == HEADER
    pos = 20 + n
    for name, length, section_crc in doc["sections"]:
        assert data[pos:pos + length] == SECTIONS[name]
        assert zlib.crc32(SECTIONS[name]) == section_crc
        pos += length
    assert pos == len(data)


def test_version_2_deflates_the_json_and_reads_like_version_1(tmp_path):
    """Independent parse of version 2: the checksummed JSON is raw DEFLATE; sections as in version 1."""
    path = tmp_path / "v2.omg4"
    size = write_container(path, HEADER, SECTIONS, version=2)
    data = path.read_bytes()
    magic, version, flags, n, crc = struct.unpack("<8sHHII", data[:20])
    assert (magic, version, flags) == (MAGIC, 2, 0) and zlib.crc32(data[20:20 + n]) == crc
    doc = json.loads(zlib.decompress(data[20:20 + n], -15))
    assert doc["header"] == HEADER and [s[0] for s in doc["sections"]] == list(SECTIONS)
    assert read_container(path) == (HEADER, SECTIONS)
    assert describe_container(path)["version"] == 2 and size == len(data)
    assert size < write_container(tmp_path / "v1.omg4", HEADER, SECTIONS)  # the JSON shrank


def test_damaged_version_2_header_is_one_line_error():
    doc = json.dumps({"header": {}, "sections": []}).encode()
    with pytest.raises(CorruptFileError, match="damaged compressed header"):
        read_container(_crafted(doc, version=2))  # text where DEFLATE data belongs
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    bomb = packer.compress(b" " * (17 * 1024 * 1024)) + packer.flush()  # inflates past MAX_JSON_BYTES
    with pytest.raises(CorruptFileError, match="compressed header"):
        read_container(_crafted(bomb, version=2))


def test_describe_accounts_for_every_byte(written):
    path, size = written
    info = describe_container(path)
    assert info["total_bytes"] == size == path.stat().st_size
    assert info["header_bytes"] + sum(info["sections"].values()) == size
    assert info["sections"] == {k: len(v) for k, v in SECTIONS.items()}
    assert info["header"] == HEADER


def test_no_sections_and_empty_header(tmp_path):
    path = tmp_path / "e.omg4"
    write_container(path, {}, {})
    assert read_container(path) == ({}, {})


def test_every_truncation_is_detected(written):
    data = written[0].read_bytes()
    for length in range(len(data)):
        with pytest.raises(CorruptFileError):
            read_container(data[:length])


def test_trailing_bytes_are_detected(written):
    with pytest.raises(CorruptFileError, match="trailing"):
        read_container(written[0].read_bytes() + b"\x00")


def test_every_single_bit_flip_is_detected(written):
    data = written[0].read_bytes()
    for bit in range(8 * len(data)):
        damaged = bytearray(data)
        damaged[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(CorruptFileError):
            read_container(bytes(damaged))


def test_random_multi_byte_damage_is_detected(written):
    data = written[0].read_bytes()
    rng = np.random.default_rng(0)
    for _ in range(300):
        damaged = bytearray(data)
        for pos in rng.choice(len(data), size=rng.integers(1, 6), replace=False):
            damaged[pos] = (damaged[pos] + int(rng.integers(1, 256))) % 256
        with pytest.raises(CorruptFileError):
            read_container(bytes(damaged))


def test_wrong_magic(tmp_path):
    path = tmp_path / "x.omg4"
    path.write_bytes(b"PK\x03\x04" + bytes(100))
    with pytest.raises(CorruptFileError, match="magic"):
        read_container(path)
    with pytest.raises(CorruptFileError, match="magic"):
        read_container(b"\x80")  # shorter than the prefix, but not a prefix of the magic


def test_future_version_and_unknown_flags():
    from omg4.codec.container import READABLE_VERSIONS

    doc = json.dumps({"header": {}, "sections": []}).encode()
    newest = max(READABLE_VERSIONS)  # 7: a predicted segment of a sequence
    assert newest == FORMAT_VERSION
    with pytest.raises(CorruptFileError, match=f"version {newest + 1} is from a newer"):
        read_container(_crafted(doc, version=newest + 1))
    with pytest.raises(CorruptFileError, match="version 0"):
        read_container(_crafted(doc, version=0))
    with pytest.raises(CorruptFileError, match="flags"):
        read_container(_crafted(doc, flags=1))


@pytest.mark.parametrize("json_len", [2**32 - 1, 2**31, 10**9, 17 * 2**20])
def test_absurd_json_length(json_len):
    doc = json.dumps({"header": {}, "sections": []}).encode()
    with pytest.raises(CorruptFileError, match="header length"):
        read_container(_crafted(doc, json_len=json_len))


@pytest.mark.parametrize("size", [2**63, 10**15, 2**32 + 4])
def test_absurd_section_length_is_rejected_before_reading(size):
    doc = json.dumps({"header": {}, "sections": [["a", size, 0]]}).encode()
    with pytest.raises(CorruptFileError, match="truncated"):
        read_container(_crafted(doc, b"abcd"))


@pytest.mark.parametrize("doc", [
    b"[1, 2, 3]", b'"a string"', b"42", b"null", b'{"header": [], "sections": []}', b'{"header": {}}',
    b'{"header": {}, "sections": [["a", -1, 0]]}', b'{"header": {}, "sections": [["a", 1.5, 0]]}',
    b'{"header": {}, "sections": [["a", 1, 4294967296]]}', b'{"header": {}, "sections": [["", 0, 0]]}',
    b'{"header": {}, "sections": [["a", true, 0]]}', b'{"header": {}, "sections": [["a", 0, 0], ["a", 0, 0]]}',
    b'{"header": {"x": NaN}, "sections": []}', b'{"header": {"x": Infinity}, "sections": []}',
    b"\xff\xfe not utf-8", b"{not json", b"[" * 200_000 + b"]" * 200_000,
])
def test_malformed_json_headers(doc):
    with pytest.raises(CorruptFileError):
        read_container(_crafted(doc))


def test_section_checksum_mismatch_names_the_section():
    doc = json.dumps({"header": {}, "sections": [["xyz", 4, zlib.crc32(b"abcd")]]}).encode()
    assert read_container(_crafted(doc, b"abcd")) == ({}, {"xyz": b"abcd"})
    with pytest.raises(CorruptFileError, match="'xyz'"):
        read_container(_crafted(doc, b"abce"))


def test_messages_are_one_line_and_name_the_file(tmp_path):
    path = tmp_path / "bad.omg4"
    path.write_bytes(MAGIC + b"\x01")
    with pytest.raises(CorruptFileError) as err:
        read_container(path)
    assert "\n" not in str(err.value) and "bad.omg4" in str(err.value)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(OMG4Error, match="no such file"):
        read_container(tmp_path / "nope.omg4")
    with pytest.raises(OMG4Error, match="folder"):
        read_container(tmp_path)


def test_failed_write_keeps_the_old_file(written):
    path, _ = written
    before = path.read_bytes()
    with pytest.raises(OMG4Error, match="JSON"):
        write_container(path, {"bad": object()}, {"a": b"x"})
    with pytest.raises(OMG4Error, match="JSON"):
        write_container(path, {"nan": float("nan")}, {})
    with pytest.raises(OMG4Error, match="bytes"):
        write_container(path, {}, {"a": "not bytes"})
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_section_names_up_to_the_limit_are_written_and_read(tmp_path):
    """A section name of MAX_SECTION_NAME characters is valid for the writer and the reader; one more is refused
    before anything is written."""
    from omg4.codec.container import MAX_SECTION_NAME

    longest = "s" * MAX_SECTION_NAME
    write_container(tmp_path / "ok.bin", {}, {longest: b"abc"})
    assert read_container(tmp_path / "ok.bin")[1] == {longest: b"abc"}
    with pytest.raises(OMG4Error):
        write_container(tmp_path / "long.bin", {}, {longest + "s": b"abc"})
    assert not (tmp_path / "long.bin").exists()


def test_the_writer_refuses_exactly_the_headers_a_reader_would_not_inflate(tmp_path):
    """A deflated header may inflate to at most 65,536 + 32 × its stored size (docs/file-format.md §1): a header
    one to a few hundred bytes past that bound is refused by the writer, one just inside it is written and read."""
    def sizes(text):
        blob = json.dumps({"header": {"pad": text}, "sections": []}, separators=(",", ":")).encode()
        packer = zlib.compressobj(9, zlib.DEFLATED, -15)
        stored = len(packer.compress(blob) + packer.flush())
        return len(blob), 65536 + 32 * stored

    lo, hi = 1000, 400_000  # the smallest run of one letter whose header passes the bound
    while hi - lo > 1:
        mid = (lo + hi) // 2
        length, limit = sizes("a" * mid)
        lo, hi = (mid, hi) if length <= limit else (lo, mid)
    inside, outside = "a" * lo, "a" * hi
    assert sizes(inside)[0] <= sizes(inside)[1] and 0 < sizes(outside)[0] - sizes(outside)[1] <= 64
    write_container(tmp_path / "in.omg4", {"pad": inside}, {}, version=FORMAT_VERSION)
    assert read_container(tmp_path / "in.omg4")[0] == {"pad": inside}
    with pytest.raises(OMG4Error, match="compresses"):
        write_container(tmp_path / "out.omg4", {"pad": outside}, {}, version=FORMAT_VERSION)
    assert not (tmp_path / "out.omg4").exists()
