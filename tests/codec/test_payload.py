"""The compressed-model payload ↔ .omg4 file: exact round trips, storage accounting, validation."""

from __future__ import annotations

import json
import subprocess
import sys
import zlib

import numpy as np
import pytest

from omg4.codec.container import describe_container, read_container, write_container
from omg4.codec.entropy import encode_indices
from omg4.codec.payload import CompressedPayload, QuantizedAttribute, decode_payload, encode_payload
from omg4.codec.sections import canonical_order, morton_codes, morton_to_xyz
from omg4.errors import CorruptFileError, OMG4Error

# attribute → (D, sub-vector length, codebook size): the M preset (omg4 §7)
LAYOUT = {"scale": (3, 1, 512), "rotation": (4, 2, 8192), "app": (6, 2, 1024), "scale_t": (1, 1, 512),
          "rotation_r": (4, 2, 8192)}


def make_payload(n: int = 3000, seed: int = 0) -> CompressedPayload:
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(20, 3))
    xyz = centres[rng.integers(0, 20, n)] + 0.05 * rng.normal(size=(n, 3))  # clustered, like a scene
    attrs = {}
    for name, (d, s, k) in LAYOUT.items():
        attrs[name] = QuantizedAttribute([rng.normal(size=(k, s)) for _ in range(d // s)],
                                         [np.minimum(rng.geometric(4.0 / k, n) - 1, k - 1) for _ in range(d // s)])
    mlp = {"cont.0": 0.1 * rng.normal(size=(64, 128)), "cont.1": 0.1 * rng.normal(size=(13, 64)),
           "opacity.0": 0.1 * rng.normal(size=(64, 16)), "empty": np.zeros((0, 4))}
    meta = {"preset": "M", "sh_degree": 3, "sh_degree_t": 2, "time_range": [0.0, 10.0],
            "normalization": {"scale": 0.25, "R": np.eye(3).tolist(), "t": [0.0, 0.0, 0.0]}}
    return CompressedPayload(xyz, rng.uniform(0, 10, n), attrs, mlp, meta)


def assert_payload_equal(a: CompressedPayload, b: CompressedPayload) -> None:
    """Bit-exact equality: fp16 bit patterns and integer indices."""
    def bits(x):
        return np.asarray(x, np.float16).view(np.uint16)
    np.testing.assert_array_equal(bits(a.xyz), bits(b.xyz))
    np.testing.assert_array_equal(bits(a.t), bits(b.t))
    assert list(a.attributes) == list(b.attributes)
    for name in a.attributes:
        qa, qb = a.attributes[name], b.attributes[name]
        assert len(qa.codebooks) == len(qb.codebooks)
        for ca, cb in zip(qa.codebooks, qb.codebooks):
            np.testing.assert_array_equal(bits(ca), bits(cb))
        for ia, ib in zip(qa.indices, qb.indices):
            assert ia.dtype == ib.dtype == np.int64
            np.testing.assert_array_equal(ia, ib)
    assert list(a.mlp) == list(b.mlp)
    for name in a.mlp:
        assert a.mlp[name].shape == b.mlp[name].shape
        np.testing.assert_array_equal(bits(a.mlp[name]), bits(b.mlp[name]))
    assert a.meta == b.meta


def test_paper_codec_round_trip_keeps_order(tmp_path):
    p = make_payload()
    encode_payload(p, tmp_path / "m.omg4", codec="paper")
    q = decode_payload(tmp_path / "m.omg4")
    assert q.xyz.dtype == q.t.dtype == np.float16
    assert_payload_equal(q, p.to_fp16())


def test_ans_codec_round_trip_in_morton_order(tmp_path):
    p = make_payload()
    encode_payload(p, tmp_path / "m.omg4", codec="ans")
    q = decode_payload(tmp_path / "m.omg4")
    assert_payload_equal(q, p.permuted(canonical_order(p.xyz)).to_fp16())
    # the permutation is free: every Gaussian keeps its own attributes
    before = {tuple(r) for r in np.column_stack([p.to_fp16().xyz.view(np.uint16), p.attributes["rotation"].indices[1]])}
    after = {tuple(r) for r in np.column_stack([q.xyz.view(np.uint16), q.attributes["rotation"].indices[1]])}
    assert before == after


def test_decoded_reconstruction_equals_fp16_codebook_lookup(tmp_path):
    p = make_payload(500)
    encode_payload(p, tmp_path / "m.omg4", codec="paper")
    q = decode_payload(tmp_path / "m.omg4")
    rot = p.attributes["rotation"]
    expected = np.concatenate([cb.astype(np.float16).astype(np.float64)[ix]
                               for cb, ix in zip(rot.codebooks, rot.indices)], 1)
    np.testing.assert_array_equal(q.attributes["rotation"].reconstruct(), expected.astype(np.float32))


@pytest.mark.parametrize("codec", ["compact", "ans", "paper"])
def test_storage_accounting_equals_file_size(tmp_path, codec):
    path = tmp_path / "m.omg4"
    sizes = encode_payload(make_payload(), path, codec=codec)
    total = path.stat().st_size
    assert sum(sizes.values()) == total
    info = describe_container(path)
    assert info["total_bytes"] == total
    assert info["header_bytes"] == sizes["header"]
    assert info["sections"] == {k: v for k, v in sizes.items() if k != "header"}
    expected_sections = {"xyz", "t", "mlp.cont.0", "mlp.cont.1", "mlp.opacity.0", "mlp.empty"}
    for name, (d, s, _) in LAYOUT.items():
        expected_sections |= {f"svq.{name}.{kind}{j}" for kind in ("codebook", "index") for j in range(d // s)}
    assert set(info["sections"]) == expected_sections


def test_ans_is_smaller_than_paper(tmp_path):
    p = make_payload(20_000)
    paper = encode_payload(p, tmp_path / "p.omg4", codec="paper")
    ans = encode_payload(p, tmp_path / "a.omg4", codec="ans")
    assert sum(ans.values()) < sum(paper.values())
    assert ans["xyz"] < 0.8 * paper["xyz"]  # sorted Morton gaps beat LZMA on raw fp16 positions


def test_header_carries_meta_counts_and_shapes(tmp_path):
    p = make_payload(100)
    encode_payload(p, tmp_path / "m.omg4", codec="ans")
    header, _ = read_container(tmp_path / "m.omg4")
    assert header["num_gaussians"] == 100 and header["codec"] == "ans"
    assert header["meta"]["normalization"]["scale"] == 0.25
    assert header["attributes"]["rotation"] == [[8192, 2], [8192, 2]]
    assert header["mlp"]["cont.0"] == [64, 128]


def _bit_interleave_reference(keys: np.ndarray) -> int:
    code = 0
    for bit in range(16):
        for axis in range(3):
            code |= ((int(keys[axis]) >> bit) & 1) << (3 * bit + axis)
    return code


def test_morton_codes_against_bitwise_reference():
    rng = np.random.default_rng(1)
    xyz = rng.normal(scale=3, size=(200, 3)).astype(np.float16)
    xyz[0] = [0.0, -0.0, 65504.0]
    codes = morton_codes(xyz)
    bits = xyz.view(np.uint16)
    keys = np.where(bits & 0x8000, ~bits, bits | 0x8000).astype(np.uint16)  # float order as unsigned order
    for i in range(len(xyz)):
        assert int(codes[i]) == _bit_interleave_reference(keys[i])
    np.testing.assert_array_equal(morton_to_xyz(codes).view(np.uint16), xyz.view(np.uint16))


def test_morton_key_preserves_float_order():
    values = np.unique(np.random.default_rng(2).normal(scale=100, size=5000).astype(np.float16))
    xyz = np.stack([values, np.zeros_like(values), np.zeros_like(values)], 1)
    codes = morton_codes(xyz)
    assert np.all(np.diff(codes.astype(np.float64)) > 0)  # sorted floats give increasing codes


def test_canonical_order_is_idempotent():
    p = make_payload(1000)
    once = p.permuted(canonical_order(p.xyz))
    np.testing.assert_array_equal(canonical_order(once.xyz), np.arange(1000))


@pytest.mark.parametrize("mutate,match", [
    (lambda p: p.xyz.__setitem__((3, 1), np.nan), "xyz"),
    (lambda p: p.t.__setitem__(0, 1e6), "t has"),
    (lambda p: p.attributes["scale"].indices[0].__setitem__(5, 512), "index array 0"),
    (lambda p: p.attributes["scale"].indices[2].__setitem__(5, -1), "index array 2"),
    (lambda p: p.attributes["app"].codebooks[1].__setitem__((0, 0), np.inf), "codebook 1"),
    (lambda p: p.attributes.__setitem__("bad.name", p.attributes["scale"]), "attribute name"),
    (lambda p: p.attributes["rotation"].indices.pop(), "one index array per codebook"),
    (lambda p: p.mlp.__setitem__("w", np.array([np.nan])), "w has"),
    (lambda p: p.meta.__setitem__("x", object()), "JSON"),
])
def test_encode_rejects_invalid_payloads(tmp_path, mutate, match):
    p = make_payload(50)
    mutate(p)
    with pytest.raises(OMG4Error, match=match):
        encode_payload(p, tmp_path / "m.omg4")
    assert not (tmp_path / "m.omg4").exists()


def test_encode_rejects_empty_payload_and_unknown_codec(tmp_path):
    with pytest.raises(OMG4Error, match="N >= 1"):
        encode_payload(CompressedPayload(np.zeros((0, 3)), np.zeros(0)), tmp_path / "m.omg4")
    with pytest.raises(OMG4Error, match="codec"):
        encode_payload(make_payload(10), tmp_path / "m.omg4", codec="zip")


@pytest.mark.parametrize("codec", ["compact", "ans", "paper"])
def test_random_bit_flips_and_truncations_raise(tmp_path, codec):
    path = tmp_path / "m.omg4"
    encode_payload(make_payload(300), path, codec=codec)
    data = path.read_bytes()
    rng = np.random.default_rng(3)
    for bit in rng.choice(8 * len(data), size=300, replace=False):
        damaged = bytearray(data)
        damaged[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(CorruptFileError):
            decode_payload(bytes(damaged))
    for length in rng.choice(len(data), size=100, replace=False):
        with pytest.raises(CorruptFileError):
            decode_payload(data[:length])


def _rewrite(path, edit_header=None, edit_sections=None):
    """Re-wrap a valid file with a modified header/sections and fresh checksums (damage a CRC cannot see)."""
    header, sections = read_container(path)
    if edit_header:
        edit_header(header)
    if edit_sections:
        edit_sections(sections)
    write_container(path, header, sections)


@pytest.mark.parametrize("edit_header,edit_sections,match", [
    (lambda h: h.__setitem__("kind", "something-else"), None, "not an OMG4 compressed model"),
    (lambda h: h.__setitem__("num_gaussians", 0), None, "not an OMG4"),
    (lambda h: h.__setitem__("num_gaussians", 10**12), None, "not an OMG4"),
    (lambda h: h.__setitem__("num_gaussians", 10**8), None, "more than the file"),
    (lambda h: h.__setitem__("num_gaussians", 301), None, "section"),
    (lambda h: h.__setitem__("num_gaussians", "300"), None, "not an OMG4"),
    (lambda h: h["attributes"]["scale"][0].__setitem__(0, 100), None, "svq.scale"),
    (lambda h: h["attributes"]["scale"][0].__setitem__(0, 2**20), None, "codebook shapes"),
    (lambda h: h["attributes"].__setitem__("scale", []), None, "codebook shapes"),
    (lambda h: h["mlp"].__setitem__("cont.0", [64, 129]), None, "mlp.cont.0"),
    (lambda h: h["mlp"].__setitem__("cont.0", [2**20, 2**20]), None, "MLP weight"),
    (lambda h: h["encodings"].__setitem__("t", "f32"), None, "section t: unknown encoding"),
    (None, lambda s: s.pop("svq.app.index2"), "section list"),
    (None, lambda s: s.__setitem__("extra", b""), "section list"),
    (None, lambda s: s.__setitem__("t", s["t"][:-1]), "section t"),
    (lambda h: h.__setitem__("rotations", ["no_such_attribute"]), None, "rotation attributes"),
    (lambda h: h["mlp"].update({f"extra.{i}": [1, 1] for i in range(65 - len(h["mlp"]))}), None,
     "65 MLP weights"),
])
def test_decode_validates_content_behind_valid_checksums(tmp_path, edit_header, edit_sections, match):
    path = tmp_path / "m.omg4"
    encode_payload(make_payload(300), path, codec="paper")
    _rewrite(path, edit_header, edit_sections)
    with pytest.raises(CorruptFileError, match=match) as err:
        decode_payload(path)
    assert "\n" not in str(err.value) and "m.omg4" in str(err.value)


def test_decode_rejects_out_of_range_indices_and_nan_floats(tmp_path):
    path = tmp_path / "m.omg4"
    p = make_payload(300)
    encode_payload(p, path, codec="ans")

    def bad_index(sections):  # a valid ANS stream for a bigger alphabet, declared as K = 512
        sections["svq.scale.index0"] = encode_indices(np.full(300, 600), 1024, "ans")

    _rewrite(path, edit_sections=bad_index)
    with pytest.raises(CorruptFileError, match="svq.scale.index0"):
        decode_payload(path)

    encode_payload(p, path, codec="paper")

    def raw_nan(sections):
        sections["svq.app.codebook0"] = np.full(1024 * 2, np.nan, "<f2").tobytes()

    _rewrite(path, lambda h: h["encodings"].__setitem__("svq.app.codebook0", "f16"), raw_nan)
    with pytest.raises(CorruptFileError, match="svq.app.codebook0: non-finite"):
        decode_payload(path)


def test_codec_decoder_does_not_import_training_or_torch():
    code = ("import sys, omg4.codec; "
            "bad = [m for m in sys.modules if m.startswith(('torch', 'omg4.compress', 'omg4.train', 'omg4.render'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("codec, version", [("compact", 5), ("ans", 1), ("paper", 1)])
def test_file_is_not_a_pickle(tmp_path, codec, version):
    path = tmp_path / "m.omg4"
    encode_payload(make_payload(20), path, codec=codec)
    data = path.read_bytes()
    assert data[:8] == b"\x89OMG4\r\n\x1a" and int.from_bytes(data[8:10], "little") == version
    n = int.from_bytes(data[12:16], "little")
    assert zlib.crc32(data[20:20 + n]) == int.from_bytes(data[16:20], "little")
    text = zlib.decompress(data[20:20 + n], -15) if version >= 2 else data[20:20 + n]
    assert json.loads(text)["header"]["kind"] == "omg4-compressed-model"


def test_up_to_64_mlp_weights_pass_the_header_limit(tmp_path):
    """MAX_MLP_WEIGHTS is 64 (docs/file-format.md §5): a header listing 64 passes that check (and fails a later
    one, its sections being missing)."""
    path = tmp_path / "m.omg4"
    encode_payload(make_payload(300), path, codec="paper")
    _rewrite(path, lambda h: h["mlp"].update({f"extra.{i}": [1, 1] for i in range(64 - len(h["mlp"]))}))
    with pytest.raises(CorruptFileError) as err:
        decode_payload(path)
    assert "MLP weights (limits" not in str(err.value)


def test_up_to_32_rotation_names_pass_the_header_check(tmp_path):
    """``rotations`` lists at most 32 names of stored attributes (docs/file-format.md §5): 32 pass, 33 do not."""
    path = tmp_path / "m.omg4"
    encode_payload(make_payload(300), path, codec="paper")
    _rewrite(path, lambda h: h.__setitem__("rotations", [next(iter(h["attributes"]))] * 32))
    decode_payload(path)
    _rewrite(path, lambda h: h.__setitem__("rotations", [next(iter(h["attributes"]))] * 33))
    with pytest.raises(CorruptFileError, match="rotation attributes"):
        decode_payload(path)
