"""The "compact" codec: codeword coding without the codewords' order, unit quaternions, 8-bit MLP weights,
the version gate — each against an independent computation."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.codec import codewords, quaternions, weights
from omg4.codec.container import describe_container, read_container
from omg4.codec.grids import position_order
from omg4.codec.payload import CompactGrids, CompressedPayload, QuantizedAttribute, decode_payload, encode_payload
from omg4.codec.sections import canonical_order, smallest_f16
from omg4.errors import CorruptFileError, OMG4Error

from tests.codec.test_payload import make_payload


def _entropy_bits(symbols: np.ndarray) -> float:
    counts = np.bincount(symbols)
    p = counts[counts > 0] / symbols.size
    return float(-(counts[counts > 0] * np.log2(p)).sum())


def _decode_slot(cb_enc, cb_bytes, ix_enc, ix_bytes, k, s, n):
    if cb_enc == "sorted":
        rows = codewords.decode_sorted_codebook(cb_bytes, k, s)
    else:
        from omg4.codec.sections import decode_f16
        rows = decode_f16(cb_bytes, cb_enc, k * s).reshape(k, s)
    if ix_enc == "first-use":
        labels = codewords.decode_first_use_indices(ix_bytes, k, n)
    else:
        from omg4.codec.entropy import decode_indices
        labels = decode_indices(ix_bytes, k, n, "ans")
    return rows, labels


def _streams():
    rng = np.random.default_rng(3)
    yield "skewed", rng.normal(size=(512, 1)), np.minimum(rng.geometric(0.01, 5000) - 1, 511)
    yield "one codeword per Gaussian", rng.normal(size=(3000, 2)), rng.permutation(3000)
    yield "constant", rng.normal(size=(7, 3)), np.full(100, 4)
    yield "single Gaussian", rng.normal(size=(9, 4)), np.array([8])
    dup = rng.normal(size=(64, 2))
    dup[32:] = dup[:32]  # every row twice; half the codebook unused
    yield "duplicates and unused rows", dup, rng.integers(0, 48, 2000)
    yield "sub-vectors of 5 (no sorted mode)", rng.normal(size=(40, 5)), rng.integers(0, 40, 900)
    special = np.array([[0.0], [-0.0], [65504.0], [-65504.0], [6e-8], [-6e-8], [1.0]])
    yield "extreme fp16 values", special, rng.integers(0, 7, 300)


@pytest.mark.parametrize("name, codebook, indices", list(_streams()), ids=[s[0] for s in _streams()])
def test_codewords_reconstruct_every_value_exactly(name, codebook, indices):
    cb16 = np.asarray(codebook, np.float16)
    result = codewords.encode_codewords(cb16, indices, smallest_f16)
    rows, labels = _decode_slot(*result, cb16.shape[1], indices.size)
    expected = cb16[indices].view(np.uint16)
    np.testing.assert_array_equal(rows[labels].view(np.uint16), expected)
    # no unused and no duplicate codeword survives
    assert rows.shape[0] == len({r.tobytes() for r in expected}) == result[4]
    assert np.unique(labels).size == rows.shape[0]


def test_first_use_makes_one_codeword_per_gaussian_nearly_free():
    rng = np.random.default_rng(0)
    n = 4000
    cb = rng.normal(size=(n, 2)).astype(np.float16)
    cb_enc, cb_bytes, ix_enc, ix_bytes, k = codewords.encode_codewords(cb, rng.permutation(n), smallest_f16)
    assert ix_enc == "first-use" and k == n
    assert len(ix_bytes) < 32  # every index is "the next new codeword": a constant flag stream
    assert len(ix_bytes) < 0.01 * n * np.log2(n) / 8


def test_sorted_set_saves_the_order_of_a_small_codebook():
    """K ≪ N: the codebook as a sorted set beats the same rows in first-use order, the ranks stay at entropy."""
    rng = np.random.default_rng(1)
    cb = np.sort(rng.normal(size=(512, 1)), axis=0).astype(np.float16)
    ix = np.minimum(rng.geometric(0.01, 20000) - 1, 511)
    cb_enc, cb_bytes, ix_enc, ix_bytes, k = codewords.encode_codewords(cb, ix, smallest_f16)
    assert cb_enc == "sorted" and ix_enc == "ranks"
    assert len(cb_bytes) < len(smallest_f16(cb[np.unique(ix)])[1])
    rows, labels = _decode_slot(cb_enc, cb_bytes, ix_enc, ix_bytes, k, 1, ix.size)
    assert 8 * len(ix_bytes) <= 1.01 * _entropy_bits(labels) + 8 * 600  # within 1 % plus the model table


def test_interleave_matches_a_bitwise_reference():
    rng = np.random.default_rng(2)
    for s in (1, 2, 3, 4):
        keys = rng.integers(0, 1 << 16, size=(50, s)).astype(np.uint16)
        codes = codewords.interleave(keys)
        for row, code in zip(keys, codes):
            ref = sum(((int(row[a]) >> b) & 1) << (b * s + a) for b in range(16) for a in range(s))
            assert int(code) == ref
        np.testing.assert_array_equal(codewords.deinterleave(codes, s), keys)
    many = rng.integers(0, 1 << 16, size=(2 * codewords._DEINTERLEAVE_BLOCK + 3, 3)).astype(np.uint16)
    np.testing.assert_array_equal(codewords.deinterleave(codewords.interleave(many), 3), many)  # across blocks


def test_damaged_codeword_streams_are_corrupt_file_errors():
    rng = np.random.default_rng(4)
    cb = rng.normal(size=(100, 2)).astype(np.float16)
    _, cb_bytes, _, ix_bytes, k = codewords.encode_codewords(cb, rng.permutation(100), smallest_f16)
    with pytest.raises(CorruptFileError):
        codewords.decode_first_use_indices(ix_bytes, k + 1, 100)  # more codewords than new flags
    codes = np.array([5, 5], np.uint64)  # not strictly increasing
    from omg4.codec.entropy import encode_uints
    with pytest.raises(CorruptFileError, match="strictly increasing"):
        codewords.decode_sorted_codebook(encode_uints(np.diff(codes, prepend=np.uint64(0))), 2, 1)
    with pytest.raises(CorruptFileError, match="longer than 16 bits"):  # refused before the raw bits are read
        codewords.decode_sorted_codebook(encode_uints(np.array([1 << 20], np.uint64)), 1, 1)
    with pytest.raises(CorruptFileError, match="out of range"):  # two gaps summing past 16 bits
        codewords.decode_sorted_codebook(encode_uints(np.array([1 << 15, 1 << 15], np.uint64)), 2, 1)
    # a repeat that names a codeword before its first use: flags say [new, repeat, new], repeat label 1
    from omg4.codec.entropy import encode_indices, pack_varints
    flags = encode_indices(np.array([1, 0, 1]), 2, "ans")
    forged = pack_varints(np.array([len(flags)])) + flags + encode_indices(np.array([1]), 2, "ans")
    with pytest.raises(CorruptFileError, match="not yet used"):
        codewords.decode_first_use_indices(forged, 2, 3)


def _rotation_matrix(q: np.ndarray) -> np.ndarray:
    """3×3 rotation of unit-normalized quaternions (w, x, y, z), float64 (independent textbook formula)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1).reshape(-1, 3, 3)


def test_unit_quaternions_keep_the_rotation_within_the_grid_step():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(5000, 4)) * rng.uniform(0.1, 3, size=(5000, 1))  # any norm, any sign
    q[:4] = [[1, 0, 0, 0], [0, 0, 0, -2], [0.5, 0.5, 0.5, 0.5], [1e-3, 0, 0, 0]]
    decoded = quaternions.decode_quaternions(quaternions.encode_quaternions(q), q.shape[0]).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(decoded, axis=1), 1.0, atol=2e-3)
    err = np.abs(_rotation_matrix(decoded) - _rotation_matrix(q)).max()
    step = np.sqrt(2) / (2 ** quaternions.BITS - 1)
    assert quaternions.BITS == 9
    assert err < 4 * step  # each of 3 components off by ≤ step/2, fp16 rounding on top
    same = quaternions.encode_quaternions(-q)  # q and −q are the same rotation: the same bytes
    assert same == quaternions.encode_quaternions(q)


def test_unit_quaternions_cost_about_their_entropy():
    rng = np.random.default_rng(6)
    q = np.abs(rng.normal(size=(20000, 4))) * [4, 1, 1, 1]  # concentrated near the identity
    data = quaternions.encode_quaternions(q)
    largest, codes = quaternions.quantize_quaternions(q)
    bound = _entropy_bits(largest) + _entropy_bits(codes.ravel())
    assert 8 * len(data) <= 1.01 * bound + 8 * 1200  # within 1 % plus the model tables
    assert 8 * len(data) < 0.6 * 4 * 16 * q.shape[0]  # well under four fp16 numbers per rotation


@pytest.mark.parametrize("bits", [8, 6, 4, 2])
def test_weights_in_few_bits_match_an_independent_rounding(bits):
    rng = np.random.default_rng(7)
    w = (0.2 * rng.normal(size=(64, 37))).astype(np.float16)
    w[3] = 0.0  # an all-zero row
    w[5] *= 1e-4  # a row of tiny weights keeps its relative precision (float32 scales)
    data = weights.encode_rows(w, bits)
    decoded = weights.decode_rows(data, w.shape, bits).astype(np.float64)
    top = 2 ** (bits - 1) - 1  # 127 at 8 bits
    w64 = w.astype(np.float64)
    scale = np.abs(w64).max(axis=1, keepdims=True) / top
    ref = np.clip(np.rint(np.divide(w64, scale, out=np.zeros_like(w64), where=scale > 0)), -top, top) * scale
    ref16 = ref.astype(np.float16).astype(np.float64)  # the payload's weights are fp16
    np.testing.assert_allclose(decoded, ref16, rtol=1e-3, atol=6e-8)  # 6e-8: fp16's subnormal step
    assert (decoded[3] == 0).all()
    assert (np.abs(decoded - w64) <= scale / 2 + 1e-3 * np.abs(w64) + 6e-8).all()
    assert len(np.unique(decoded[0])) <= 2 * top + 1
    assert weights.parse_encoding(weights.encoding(bits)) == (bits, True) and weights.encoding(8) == "int8-cols"
    assert weights.parse_encoding(f"int{bits}-rows") == (bits, False) and weights.parse_encoding(f"int{bits}-cols") == \
        (bits, True)
    for name in ("int1-rows", "int9-rows", "int08-rows", "int8-rowsx", "smallest-three-8", "int9-cols", "int8-col"):
        assert weights.parse_encoding(name) is None
    # per column: the same rounding with one scale per column, decoded through the column encoding's name
    by_column = weights.decode_matrix(weights.encode_columns(w.T, bits), w.T.shape, weights.encoding(bits))
    np.testing.assert_array_equal(by_column.view(np.uint16), decoded.astype(np.float16).T.view(np.uint16))


def _with_row_scaled_weights(path, bits: int) -> bytes:
    """The file at ``path`` as the writer of versions 3 and 4 made it: every MLP matrix re-coded with a scale per row
    (``int<bits>-rows``, the old writer path ``weights.encode_rows``), the version the container then needs."""
    from omg4.testing import forge
    header, sections = forge.split_container(path.read_bytes())
    sections = dict(sections)
    decoded = decode_payload(path)
    for name, shape in header["mlp"].items():
        w = decoded.mlp[name]
        if len(shape) == 2 and w.size:
            sections[f"mlp.{name}"] = weights.encode_rows(w.astype(np.float32), bits)
            header["encodings"][f"mlp.{name}"] = f"int{bits}-rows"
    return forge.assemble_container(header, list(sections.items()))


def test_weights_are_column_scaled_in_version_5_and_older_row_scaled_files_still_decode(tmp_path):
    """The writer scales MLP weights per column (``int<b>-cols``, version 5, refused by older builds by its
    version); files of versions 3 (8 bits) and 4 (fewer), whose weights have a scale per row, still decode to a
    per-row rounding computed here."""
    p = make_payload(500)  # no log-scale attribute, so no exact positions: only the weights need version 5
    encode_payload(p, tmp_path / "w6.omg4", precision=CompactGrids(weights=6))
    encode_payload(p, tmp_path / "w16.omg4", precision=CompactGrids(weights=16))
    assert describe_container(tmp_path / "w6.omg4")["version"] == 5
    assert describe_container(tmp_path / "w16.omg4")["version"] == 3
    assert read_container(tmp_path / "w6.omg4")[0]["encodings"]["mlp.cont.0"] == "int6-cols"
    ref = p.to_fp16()
    d = decode_payload(tmp_path / "w6.omg4")
    for name, w in ref.mlp.items():
        if w.size:
            assert len(np.unique(d.mlp[name][:, 0])) <= 63
            step = np.abs(w.astype(np.float64)).max(axis=0, keepdims=True) / 31
            assert (np.abs(d.mlp[name].astype(np.float64) - w) <= step / 2 + 1e-3 * np.abs(w) + 1e-7).all()
    for bits, version in ((6, 4), (8, 3)):
        (tmp_path / "old.omg4").write_bytes(_with_row_scaled_weights(tmp_path / "w16.omg4", bits))
        assert describe_container(tmp_path / "old.omg4")["version"] == version
        d = decode_payload(tmp_path / "old.omg4")
        top = 2 ** (bits - 1) - 1
        for name, w in ref.mlp.items():
            if w.size:
                w32 = w.astype(np.float32)  # the writer's float32 arithmetic, so ties round alike
                scale = np.abs(w32).max(axis=1, keepdims=True) / np.float32(top)
                codes = np.clip(np.rint(w32 / np.where(scale > 0, scale, np.float32(1))), -top, top)
                rounded = codes.astype(np.float64) * scale.astype(np.float64)
                np.testing.assert_array_equal(d.mlp[name], rounded.astype(np.float16))  # (−0 equals +0)
    sizes = {bits: sum(encode_payload(p, tmp_path / "x.omg4", precision=CompactGrids(weights=bits)).values())
             for bits in (8, 6, 4)}
    assert sizes[8] > sizes[6] > sizes[4]
    from omg4.app.commands.info import omg4_summary
    from omg4.testing import forge
    model = tmp_path / "model_w6.omg4"  # a whole model, which omg4 info decodes before describing
    encode_payload(forge.valid_payload(300), model, precision=CompactGrids(weights=6))
    summary, text = omg4_summary(model)  # omg4 info names the version and the encodings
    assert summary["version"] == 5 and "(container version 5)" in text.splitlines()[0]
    mlp = {k: v for k, v in summary["encodings"].items() if k.startswith("mlp.")}
    assert mlp and all(v == "int6-cols" for v in mlp.values() if v.startswith("int"))
    assert sum(summary["groups"].values()) == model.stat().st_size


def test_a_weight_change_decodes_to_an_independent_rounding_and_an_unmoved_weight_costs_almost_nothing():
    """A matrix stored as its change from the reference's decoded one: each weight is the reference plus its change
    rounded to steps of the reference column's largest magnitude / 15 (computed here), a column whose change is
    too large for 8-bit codes in a coarser power-of-two step; a change of one weight in 8,192 costs a few bytes."""
    rng = np.random.default_rng(3)
    ref = (0.2 * rng.normal(size=(64, 128))).astype(np.float16)
    ref[:, 7] = 0.0  # an all-zero column: the smallest step, 2^-14 / 15
    change = 0.01 * rng.normal(size=ref.shape)
    change[:, 9] *= 1000  # too large for 127 steps of this column
    change[:, 7] = 0.0
    w = (ref.astype(np.float64) + change).astype(np.float16)
    encoding, data = weights.encode_delta(w, ref)
    assert weights.parse_delta_encoding(encoding) is not None
    decoded = weights.decode_delta(data, ref, encoding).astype(np.float64)
    step = np.maximum(np.abs(ref.astype(np.float64)).max(axis=0), 2.0 ** -14) / 15
    r64, w64 = ref.astype(np.float64), w.astype(np.float64)
    expected = (r64 + np.rint((w64 - r64) / step) * step).astype(np.float16).astype(np.float64)
    fine = [j for j in range(128) if j not in (7, 9)]
    np.testing.assert_array_equal(decoded[:, fine], expected[:, fine])
    assert (decoded[:, 7] == 0).all()
    coarse = step[9] * 2.0 ** np.ceil(np.log2(np.abs(w64[:, 9] - r64[:, 9]).max() / (127 * step[9])))
    np.testing.assert_array_equal(decoded[:, 9], (r64[:, 9] + np.rint((w64[:, 9] - r64[:, 9]) / coarse) * coarse
                                                  ).astype(np.float16).astype(np.float64))
    moved = ref.copy()
    moved[3, 5] += np.float16(0.05)
    encoding, data = weights.encode_delta(moved, ref)
    assert len(data) <= 40 and weights.parse_delta_encoding(encoding) <= 4  # 0.05: a few steps of the column's
    assert np.count_nonzero(weights.decode_delta(data, ref, encoding) != ref) == 1
    for name in ("delta-int1-cols", "delta-int9-cols", "delta-int8-rows", "int8-cols", None, 8):
        assert weights.parse_delta_encoding(name) is None


def test_a_forged_weight_change_is_a_corrupt_file_error():
    from omg4.codec.entropy import encode_indices
    ref = np.full((2, 2), 60000.0, np.float16)
    encoding, data = weights.encode_delta(ref, ref)
    for truncated in (data[:3], (10**6).to_bytes(4, "little") + data[4:]):
        with pytest.raises(CorruptFileError, match="truncated change"):
            weights.decode_delta(truncated, ref, encoding)
    head = encode_indices(np.full(2, 31), 32, "ans")
    overflow = len(head).to_bytes(4, "little") + head + encode_indices(np.full(4, 254), 255, "ans")
    with pytest.raises(CorruptFileError, match="beyond the fp16 range"):
        weights.decode_delta(overflow, ref, "delta-int8-cols")


def test_weight_scales_beyond_fp16_are_corrupt_file_errors():
    from omg4.codec.entropy import encode_indices
    forged = np.array([1e4, 1.0], "<f4").tobytes() + encode_indices(np.full(4, 254), 255, "ans")
    with pytest.raises(CorruptFileError, match="fp16 range"):
        weights.decode_rows(forged, (2, 2))  # 1e4 · 127 overflows fp16


def test_weight_scales_are_checked_against_their_own_bits():
    """The fp16 limit applies to scale × L of the section's bits: a 4-bit row reaching 10,000 is valid (7 · scale =
    10,000), one whose scale × 7 overflows fp16 is refused."""
    from omg4.codec.entropy import encode_indices
    w = np.zeros((2, 3), np.float16)
    w[0] = [10000.0, -5000.0, 2.0]
    decoded = weights.decode_rows(weights.encode_rows(w, 4), w.shape, 4)
    np.testing.assert_allclose(decoded[0], [10000.0, -10000.0 * 4 / 7, 0.0], rtol=1e-3)
    forged = np.array([1e4, 1.0], "<f4").tobytes() + encode_indices(np.full(4, 14), 15, "ans")
    with pytest.raises(CorruptFileError, match="fp16 range"):
        weights.decode_rows(forged, (2, 2), 4)  # 1e4 · 7 overflows fp16


def test_a_valid_weight_stream_on_a_codebook_section_is_refused(tmp_path):
    """A well-formed ``int5-rows`` stream of the codebook's own shape: refused for its section kind, not its bytes."""
    def edit(header, sections):
        k, s = header["attributes"]["scale"][0]
        header["encodings"]["svq.scale.codebook0"] = "int5-rows"
        sections["svq.scale.codebook0"] = weights.encode_rows(np.ones((k, s)), 5)
    with pytest.raises(CorruptFileError, match="svq\\.scale\\.codebook0"):
        decode_payload(_forged_compact(tmp_path, edit))


def test_forged_files_keep_the_version_their_encodings_need(tmp_path):
    from omg4.testing import forge
    encode_payload(make_payload(60), tmp_path / "w6.omg4", precision=CompactGrids(weights=6))
    assert describe_container(forge.assemble_container(*forge.split_container((tmp_path / "w6.omg4").read_bytes())))["version"] == 5
    encode_payload(make_payload(60), tmp_path / "w16.omg4", precision=CompactGrids(weights=16))
    assert describe_container(forge.assemble_container(*forge.split_container((tmp_path / "w16.omg4").read_bytes())))["version"] == 3
    assert describe_container(_with_row_scaled_weights(tmp_path / "w16.omg4", 6))["version"] == 4


def test_identity_rotation_is_exact():
    q = np.array([[1.0, 0, 0, 0], [0, 0, 0, 3.0], [-2.0, 0, 0, 0]])
    decoded = quaternions.decode_quaternions(quaternions.encode_quaternions(q), 3)
    np.testing.assert_array_equal(decoded, [[1, 0, 0, 0], [0, 0, 0, 1], [1, 0, 0, 0]])


def test_uint_values_longer_than_allowed_are_refused_before_unpacking():
    from omg4.codec.entropy import decode_uints, encode_uints
    data = encode_uints(np.array([3, 1 << 40], np.uint64))
    np.testing.assert_array_equal(decode_uints(data, 2), [3, 1 << 40])
    with pytest.raises(CorruptFileError, match="longer than 32 bits"):
        decode_uints(data, 2, max_bits=32)


def _forged_compact(tmp_path, edit):
    """A valid compact file with ``edit(header, sections)`` applied and every checksum recomputed."""
    from omg4.testing import forge
    p = make_payload(60)
    p.rotations = ("rotation",)
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    header, sections = forge.split_container((tmp_path / "m.omg4").read_bytes())
    sections = dict(sections)
    edit(header, sections)
    return forge.assemble_container(header, list(sections.items()))


@pytest.mark.parametrize("section, encoding, data", [
    ("quat.rotation", "f16", np.zeros(60, "<f2").tobytes()),  # a float encoding on a quaternion section
    ("mlp.cont.1", "sorted", b"\x00"),  # a codebook encoding on an MLP weight
    ("svq.scale.codebook0", "int8-rows", b"\x00" * 8),  # a weight encoding on a codebook
    ("mlp.empty", "int8-rows", b""),  # not a 2-D matrix with rows
    ("svq.scale.codebook0", "int5-rows", b"\x00" * 8),  # a few-bit weight encoding on a codebook
    ("mlp.cont.1", "int9-rows", b"\x00" * 60),  # no such weight encoding
    ("mlp.cont.1", "int5-rows", b"\x00" * 52 + b"\x07"),  # scales, then a damaged code stream
])
def test_encodings_outside_their_section_kind_are_refused(tmp_path, section, encoding, data):
    def edit(header, sections):
        header["encodings"][section] = encoding
        sections[section] = data
    with pytest.raises(CorruptFileError, match=section.replace(".", "\\.")):
        decode_payload(_forged_compact(tmp_path, edit))


def test_a_header_that_inflates_far_beyond_real_ones_is_refused(tmp_path):
    import zlib

    from omg4.codec.container import max_inflated_json

    def edit(header, sections):
        header["meta"]["padding"] = [[]] * 200_000  # 600 kB of brackets that deflate to about 1 kB
    data = _forged_compact(tmp_path, edit)
    n = int.from_bytes(data[12:16], "little")
    assert len(zlib.decompress(data[20:20 + n], -15)) > max_inflated_json(n)
    with pytest.raises(CorruptFileError, match="compressed header"):
        decode_payload(data)


def test_more_rotations_than_a_codebook_holds_are_stored_by_the_compact_codec_only(tmp_path):
    """A decoded compact file holds one rotation row per Gaussian; beyond 65,536 of them only compact re-encodes it."""
    rng = np.random.default_rng(9)
    n = 70_000
    q = rng.normal(size=(n, 4))
    p = CompressedPayload(rng.normal(size=(n, 3)), rng.uniform(size=n),
                          {"rotation": QuantizedAttribute([q], [np.arange(n)])}, {}, {}, ("rotation",))
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    d = decode_payload(tmp_path / "m.omg4")
    assert d.attributes["rotation"].codebooks[0].shape == (n, 4)
    encode_payload(d, tmp_path / "again.omg4", codec="compact")  # a decoded file re-encodes
    from omg4.errors import OMG4Error
    with pytest.raises(OMG4Error, match="only the compact codec"):
        encode_payload(d, tmp_path / "ans.omg4", codec="ans")


def _z_order(xyz: np.ndarray, bits: int) -> np.ndarray:
    """Stable Z-order of the ``bits``-bit grid cells of ``xyz`` over its box, from bit strings (x in the lowest
    bit): the compact codec's storage order, computed independently."""
    step = (xyz.max(axis=0) - xyz.min(axis=0)).max() / (2 ** bits - 1)
    cells = np.rint((xyz - xyz.min(axis=0)) / step).astype(np.int64)
    keys = [int("".join(f"{c[2]:0{bits}b}"[i] + f"{c[1]:0{bits}b}"[i] + f"{c[0]:0{bits}b}"[i] for i in range(bits)), 2)
            for c in cells]
    return np.argsort(keys, kind="stable")


def test_compact_payload_round_trip(tmp_path):
    """Positions and time centres on their grids (at most half a step off, in the grid's Z-order); log-scale
    codebooks on steps of 1/32; every other SVQ attribute bit-exact (codebooks relabelled); rotations on the unit
    grid; MLP matrices in 8 bits; vectors and empty arrays kept."""
    p = make_payload(3000)
    p.rotations, p.log_scaled = ("rotation",), ("scale",)
    sizes = encode_payload(p, tmp_path / "m.omg4", codec="compact")
    assert sum(sizes.values()) == (tmp_path / "m.omg4").stat().st_size
    d = decode_payload(tmp_path / "m.omg4")
    ref = p.to_fp16()
    xyz = ref.xyz.astype(np.float64)
    step = (xyz.max(axis=0) - xyz.min(axis=0)).max() / (2 ** 15 - 1)
    ref = ref.permuted(_z_order(xyz, 15))
    fp16_ulp = 2.0 ** -10
    assert (np.abs(d.xyz - ref.xyz.astype(np.float64)) <= step / 2 + fp16_ulp * np.abs(ref.xyz)).all()
    t_step = 10.0 / 1024  # the meta's time range [0, 10] in 1024 steps
    assert (np.abs(d.t - ref.t.astype(np.float64)) <= t_step / 2 + fp16_ulp * np.abs(ref.t)).all()
    assert set(d.attributes) == set(ref.attributes) and d.rotations == ("rotation",) and d.log_scaled == ("scale",)
    for name in ref.attributes:
        a, b = d.attributes[name].reconstruct(), ref.attributes[name].reconstruct()
        if name == "rotation":
            np.testing.assert_allclose(_rotation_matrix(a.astype(np.float64)), _rotation_matrix(b.astype(np.float64)),
                                       atol=4 * np.sqrt(2) / (2 ** 9 - 1))
        elif name == "scale":
            assert (np.abs(a - b.astype(np.float64)) <= 1 / 64 + fp16_ulp * np.abs(b)).all()
            np.testing.assert_array_equal(a * 32, np.rint(a * 32))  # on the 1/32 grid
        else:
            np.testing.assert_array_equal(a.view(np.uint16), b.view(np.uint16))
    for name, w in ref.mlp.items():
        assert d.mlp[name].shape == w.shape
        if w.size:  # a scale per column (input)
            step = np.abs(w.astype(np.float64)).max(axis=0, keepdims=True) / 127
            assert (np.abs(d.mlp[name].astype(np.float64) - w) <= step / 2 + 1e-3 * np.abs(w) + 1e-7).all()
    header, _ = read_container(tmp_path / "m.omg4")
    assert header["codec"] == "compact" and header["quaternions"] == ["rotation"]
    assert header["encodings"]["mlp.cont.0"] == "int8-cols"


@pytest.mark.parametrize("positions, rotations, times, weights, log_scales",
                         [(12, 7, 7, 8, 5), (16, 12, 12, 16, 10), (1, 2, 1, 8, 1), (0, 13, 0, 16, 14)])
def test_compact_grids_hold_each_value_within_half_their_step(tmp_path, positions, rotations, times, weights,
                                                              log_scales):
    """Other grids (``--grid-bits``): every position within half a step of the ``positions``-bit grid over the box,
    every time centre within half of duration · 2^-times (0: both in fp16, exactly as the paper stores them), every
    rotation within the ``rotations``-bit quaternion grid,
    log-scale codebooks on steps of 2^-log_scales, MLP weights in fp16 exactly at 16 bits; the sections name their
    grids, so the decoder needs no setting; coarser grids take fewer bytes."""
    p = make_payload(3000)
    p.rotations, p.log_scaled = ("rotation",), ("scale",)
    grids = CompactGrids(positions, rotations, times, weights, log_scales)
    sizes = encode_payload(p, tmp_path / "g.omg4", codec="compact", precision=grids)
    default = encode_payload(p, tmp_path / "d.omg4", codec="compact")
    ref, d = p.to_fp16(), decode_payload(tmp_path / "g.omg4")
    fp16_ulp = 2.0 ** -10
    if positions == 0:  # fp16 as the paper, Gaussians in the Morton order of those values
        ref = ref.permuted(canonical_order(ref.xyz))
        np.testing.assert_array_equal(d.xyz.view(np.uint16), ref.xyz.view(np.uint16))
    else:
        ref = ref.permuted(_z_order(ref.xyz.astype(np.float64), positions))
        xyz = ref.xyz.astype(np.float64)
        step = (xyz.max(axis=0) - xyz.min(axis=0)).max() / (2 ** positions - 1)
        assert (np.abs(d.xyz - xyz) <= step / 2 + fp16_ulp * np.abs(xyz)).all()
    t = ref.t.astype(np.float64)
    if times == 0:
        np.testing.assert_array_equal(d.t.view(np.uint16), ref.t.view(np.uint16))
    else:
        assert (np.abs(d.t - t) <= 10.0 / 2 ** times / 2 + fp16_ulp * np.abs(t)).all()
    # rotations: the three smaller components of the unit quaternion (largest made positive) within half a grid step
    q_step = np.sqrt(2) / (2 ** rotations - 2)  # 2^bits − 1 levels over [−1/√2, 1/√2]
    q = ref.attributes["rotation"].reconstruct().astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows, largest = np.arange(len(q)), np.abs(q).argmax(axis=1)
    q *= np.sign(q[rows, largest])[:, None]
    dq = d.attributes["rotation"].reconstruct().astype(np.float64)
    dq *= np.where(dq[rows, largest] < 0, -1.0, 1.0)[:, None]  # (at 2 bits the largest may decode as 0)
    others = np.arange(4)[None, :] != largest[:, None]
    assert (np.abs(dq[others] - q[others]) <= q_step / 2 + 2.0 ** -11 + 1e-9).all()  # decoded in fp16
    if rotations >= 7:  # and the rotation within a few steps
        np.testing.assert_allclose(_rotation_matrix(dq), _rotation_matrix(q), atol=4 * q_step + 4 * 2.0 ** -11)
    scale, scale_ref = d.attributes["scale"].reconstruct(), ref.attributes["scale"].reconstruct().astype(np.float64)
    assert (np.abs(scale - scale_ref) <= 2.0 ** -log_scales / 2 + fp16_ulp * np.abs(scale_ref)).all()
    for name, w in ref.mlp.items():
        if weights == 16:  # the paper's fp16 weights, bit for bit
            np.testing.assert_array_equal(d.mlp[name].view(np.uint16), w.view(np.uint16))
        elif w.size:
            assert not np.array_equal(d.mlp[name].view(np.uint16), w.view(np.uint16))
    header, _ = read_container(tmp_path / "g.omg4")
    assert header["encodings"]["quat.rotation"] == f"smallest-three-{rotations}"
    finer = {"xyz": positions > 15, "t": times > 10 or times == 0, "quat.rotation": rotations > 9}
    for section in ("xyz", "t", "quat.rotation") if positions else ("t", "quat.rotation"):  # fp16: depends on the box
        assert (sizes[section] > default[section]) if finer[section] else (sizes[section] < default[section])
    assert header["encodings"]["xyz"] == ("morton" if positions == 0 else "grid-morton-exact")  # the default 3 %


def test_lossless_grids_store_the_paper_coders_values_exactly_and_smaller(tmp_path):
    """``--grid-bits 0,16,0,16,0``: fp16 positions and time centres, the rotation codebooks, fp16 MLP weights and
    unrounded log-scale codebooks — the payload's values bit for bit (Gaussians in Morton order, as "ans"), in fewer
    bytes than both lossless coders; a rotation codebook longer than an index alphabet is then refused."""
    p = make_payload(3000)
    p.rotations, p.log_scaled = ("rotation",), ("scale",)
    lossless = CompactGrids(0, 16, 0, 16, 0)
    size = sum(encode_payload(p, tmp_path / "c.omg4", precision=lossless).values())
    d, ref = decode_payload(tmp_path / "c.omg4"), p.permuted(canonical_order(p.xyz)).to_fp16()
    for a, b in [(d.xyz, ref.xyz), (d.t, ref.t), *((d.mlp[k], ref.mlp[k]) for k in ref.mlp),
                 *((d.attributes[k].reconstruct(), ref.attributes[k].reconstruct()) for k in ref.attributes)]:
        np.testing.assert_array_equal(np.asarray(a, np.float16).view(np.uint16), np.asarray(b, np.float16).view(np.uint16))
    assert set(d.attributes) == set(ref.attributes) and d.meta == ref.meta
    assert size < sum(encode_payload(p, tmp_path / "a.omg4", codec="ans").values())
    assert size < sum(encode_payload(p, tmp_path / "p.omg4", codec="paper").values())
    big = make_payload(70000)
    big.rotations = ("rotation",)
    big.attributes["rotation"] = QuantizedAttribute([np.random.default_rng(1).normal(size=(70000, 4))],
                                                    [np.arange(70000)])
    encode_payload(big, tmp_path / "q.omg4")  # as unit quaternions: any number of rows
    with pytest.raises(OMG4Error, match="at most 65536 rows"):
        encode_payload(big, tmp_path / "b.omg4", precision=lossless)


def test_codebook_grid_rounds_the_other_codebooks_and_merges_their_codewords(tmp_path):
    """``codebooks`` 6: the appearance codebooks on steps of 1/64 (their duplicates merged, so fewer codewords), the
    log-scale ones on their own 1/32 steps, rotation codebooks (stored as such with rotations 16) untouched."""
    p = make_payload(3000)
    p.rotations, p.log_scaled = ("rotation", "rotation_r"), ("scale", "scale_t")
    p.attributes["app"] = QuantizedAttribute([np.round(cb * 20) / 20 + 1e-3 * np.random.default_rng(j).normal(size=cb.shape)
                                              for j, cb in enumerate(p.attributes["app"].codebooks)],
                                             p.attributes["app"].indices)  # codewords 0.001 apart around a 0.05 grid
    grids = CompactGrids(15, 16, 10, 8, 5, 6)
    encode_payload(p, tmp_path / "c.omg4", precision=grids)
    encode_payload(p, tmp_path / "d.omg4", precision=CompactGrids(15, 16, 10))
    d, plain, ref = decode_payload(tmp_path / "c.omg4"), decode_payload(tmp_path / "d.omg4"), p.to_fp16()
    app, app_ref = d.attributes["app"].reconstruct(), ref.attributes["app"].reconstruct().astype(np.float64)
    np.testing.assert_array_equal(app * 64, np.rint(app * 64))
    np.testing.assert_array_equal(np.sort(app, axis=0),  # the same Gaussians, in another order: compare as sets
                                  np.sort(np.rint(app_ref * 64) / 64, axis=0).astype(np.float16))
    header, plain_header = read_container(tmp_path / "c.omg4")[0], read_container(tmp_path / "d.omg4")[0]
    assert all(k < k0 for (k, _), (k0, _) in zip(header["attributes"]["app"], plain_header["attributes"]["app"]))
    np.testing.assert_array_equal(d.attributes["rotation"].reconstruct(), plain.attributes["rotation"].reconstruct())
    np.testing.assert_array_equal(d.attributes["scale"].reconstruct(), plain.attributes["scale"].reconstruct())
    np.testing.assert_array_equal(d.attributes["scale_t"].reconstruct(), plain.attributes["scale_t"].reconstruct())


def test_grids_are_validated_and_belong_to_the_compact_codec(tmp_path):
    for bad in ((17, 9, 10), (15, 1, 10), (15, 9, -1), (15.0, 9, 10), (True, 9, 10), (15, 9, 10, 12, 5),
                (15, 9, 10, 8, 15), (15, 9, 10, 8, 5, 15), (15, 9, 10, 8, 5, 0, 101)):
        with pytest.raises(OMG4Error, match="(bits|percentage) must be an integer|weights take 2-8 bits"):
            CompactGrids(*bad)
    for text in ("15,9", "15,9,10,1", "a,9,10", "-1,9,10", "15,9,10,8,5,1,1,1", "15,9,10,8,5,0,1000"):
        with pytest.raises(OMG4Error, match="three integers"):
            CompactGrids.parse(text)
    assert CompactGrids.parse(" 12, 7,7") == CompactGrids(12, 7, 7) and CompactGrids().label == "15/9/10"
    assert CompactGrids.parse("lossless") == CompactGrids(0, 16, 0, 16, 0) and CompactGrids.parse("default") == \
        CompactGrids()
    assert CompactGrids.parse("15,9,10,8,5") == CompactGrids() and CompactGrids.parse("16,12,12,16,10").label == \
        "16/12/12/16/10"
    assert CompactGrids.parse("15,9,10,8,5,6") == CompactGrids(codebooks=6) and CompactGrids(codebooks=6).label == \
        "15/9/10/8/5/6"
    assert CompactGrids.parse("12,7,7,8,5,0,2") == CompactGrids(12, 7, 7, exact=2) and \
        CompactGrids(12, 7, 7, exact=2).label == "12/7/7/8/5/0/2" and CompactGrids(weights=6).label == "15/9/10/6/5"
    for codec in ("ans", "paper"):
        with pytest.raises(OMG4Error, match="compact codec only"):
            encode_payload(make_payload(10), tmp_path / "x.omg4", codec=codec, precision=CompactGrids(12, 7, 7))
    assert not (tmp_path / "x.omg4").exists()


def test_a_compact_file_re_encoded_from_its_paper_copy_is_the_same_file(tmp_path):
    """``omg4 bench --grid-bits`` and ``benchmarks/studies/rate_front.py`` write their further grids from the paper coder's
    copy: that holds the payload's fp16 values exactly, so the compact file is byte for byte the direct one."""
    p = make_payload(2000)
    p.rotations, p.log_scaled = ("rotation",), ("scale",)
    encode_payload(p, tmp_path / "paper.omg4", codec="paper")
    for grids in (CompactGrids(), CompactGrids(12, 7, 7)):
        encode_payload(p, tmp_path / "direct.omg4", precision=grids)
        encode_payload(decode_payload(tmp_path / "paper.omg4"), tmp_path / "again.omg4", precision=grids)
        assert (tmp_path / "direct.omg4").read_bytes() == (tmp_path / "again.omg4").read_bytes()


def test_version_2_compact_files_still_decode(tmp_path):
    """A file in the version-2 layout — fp16 positions as Morton codes, fp16 time centres, 3 × 10-bit
    quaternions, codebooks as stored — assembled here from the writer's pieces, decodes to those values."""
    from omg4.codec.container import write_container
    from omg4.codec.sections import encode_xyz_morton, smallest_f16 as smallest
    p = make_payload(500).to_fp16()
    p = p.permuted(canonical_order(p.xyz))
    rotation = p.attributes.pop("rotation").reconstruct()
    sections, encodings = {"xyz": encode_xyz_morton(p.xyz)}, {"xyz": "morton"}
    encodings["t"], sections["t"] = smallest(p.t)
    shapes = {}
    for name, qa in p.attributes.items():
        shapes[name] = []
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            cb_enc, cb_bytes, ix_enc, ix_bytes, k = codewords.encode_codewords(cb, ix, smallest)
            sections[f"svq.{name}.codebook{j}"], encodings[f"svq.{name}.codebook{j}"] = cb_bytes, cb_enc
            sections[f"svq.{name}.index{j}"], encodings[f"svq.{name}.index{j}"] = ix_bytes, ix_enc
            shapes[name].append([k, cb.shape[1]])
    sections["quat.rotation"] = quaternions.encode_quaternions(rotation, bits=10)
    encodings["quat.rotation"] = "smallest-three-10"
    header = {"kind": "omg4-compressed-model", "codec": "compact", "order": "morton", "num_gaussians": 500,
              "meta": p.meta, "attributes": shapes, "mlp": {}, "encodings": encodings, "rotations": ["rotation"],
              "quaternions": ["rotation"]}
    write_container(tmp_path / "v2.omg4", header, sections, version=2)
    d = decode_payload(tmp_path / "v2.omg4")
    np.testing.assert_array_equal(d.xyz.view(np.uint16), p.xyz.view(np.uint16))
    np.testing.assert_array_equal(d.t.view(np.uint16), p.t.view(np.uint16))
    for name, qa in p.attributes.items():
        np.testing.assert_array_equal(d.attributes[name].reconstruct(), qa.reconstruct())
    np.testing.assert_allclose(_rotation_matrix(d.attributes["rotation"].reconstruct().astype(np.float64)),
                               _rotation_matrix(rotation.astype(np.float64)), atol=4 * np.sqrt(2) / 1023)


def test_compact_is_smaller_than_ans_and_paper(tmp_path):
    p = make_payload(5000)
    p.rotations = ("rotation", "rotation_r")
    total = {c: sum(encode_payload(p, tmp_path / f"{c}.omg4", codec=c).values()) for c in ("compact", "ans", "paper")}
    assert total["compact"] < 0.8 * total["ans"] < total["paper"]


def test_files_of_the_version_1_layout_still_decode(tmp_path):
    """The "ans" and "paper" writers keep version 1, byte for byte the layout older builds wrote and read."""
    p = make_payload(200)
    for codec in ("ans", "paper"):
        encode_payload(p, tmp_path / f"{codec}.omg4", codec=codec)
        data = (tmp_path / f"{codec}.omg4").read_bytes()
        assert int.from_bytes(data[8:10], "little") == 1
        header, _ = read_container(data)
        assert "quaternions" not in header
        d = decode_payload(data)
        assert d.num_gaussians == 200


def test_a_quaternion_list_on_a_version_1_codec_is_refused(tmp_path):
    from omg4.testing import forge
    path = tmp_path / "a.omg4"
    encode_payload(make_payload(50), path, codec="ans")
    header, sections = forge.split_container(path.read_bytes())
    header["quaternions"] = []
    with pytest.raises(CorruptFileError, match="quaternion"):
        decode_payload(forge.assemble_container(header, sections))


def test_rotation_declared_but_not_a_quaternion_stays_lossless(tmp_path):
    """Only 4-wide attributes can be unit quaternions; a declared 2-wide one keeps its codebooks."""
    rng = np.random.default_rng(8)
    attrs = {"rotation": QuantizedAttribute([rng.normal(size=(10, 2))], [rng.integers(0, 10, 30)])}
    p = CompressedPayload(rng.normal(size=(30, 3)), rng.uniform(size=30), attrs, {}, {}, ("rotation",))
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    d = decode_payload(tmp_path / "m.omg4")
    ref = p.to_fp16()
    ref = ref.permuted(position_order(ref.xyz))
    np.testing.assert_array_equal(d.attributes["rotation"].reconstruct(), ref.attributes["rotation"].reconstruct())


def test_a_rotation_codebook_longer_than_the_symbol_limit_is_stored_as_quaternions(tmp_path):
    """A decoded compact file holds one rotation row per Gaussian; with more Gaussians than the 65,536 symbols an
    index may take, re-encoding it must store that rotation as unit quaternions (its other slot being short
    does not make the long one codable)."""
    from omg4.codec.entropy import MAX_SYMBOLS

    rng = np.random.default_rng(21)
    n = MAX_SYMBOLS + 8
    grid = np.stack(np.meshgrid(np.linspace(-0.7, 0.7, 256), np.linspace(-0.7, 0.7, 257)), -1).reshape(-1, 2)[:n]
    assert len(np.unique(grid.astype(np.float16), axis=0)) == n  # every row its own fp16 codeword
    attrs = {"rotation": QuantizedAttribute([grid, rng.normal(size=(4, 2))], [np.arange(n), rng.integers(0, 4, n)])}
    p = CompressedPayload(rng.normal(size=(n, 3)), rng.uniform(size=n), attrs, {}, {}, ("rotation",))
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    header, sections = read_container(tmp_path / "m.omg4")
    assert header["quaternions"] == ["rotation"] and "svq.rotation.codebook0" not in sections
    d = decode_payload(tmp_path / "m.omg4")
    assert d.attributes["rotation"].reconstruct().shape == (n, 4)


def test_the_declared_values_bound_is_the_documented_sum(tmp_path):
    """docs/file-format.md §5: declared values = 8N (xyz, t, corrections) + 8N per quaternion-stored rotation
    + per attribute Σ K·s + N·slots + N·Σ s + the MLP elements, at most 64·B + 2²⁰ for B section bytes. An MLP
    weight declared large puts the sum past 2²⁰; the file's bytes then decide, one byte either side of the bound."""
    from omg4.codec.payload import _check_header

    from omg4.testing import forge

    forge.valid_file(tmp_path / "m.omg4", 50, codec="compact")
    header, _ = read_container(tmp_path / "m.omg4")
    header["mlp"]["declared.w"] = [1 << 21]
    n, quats = header["num_gaussians"], header["quaternions"]
    assert quats and n == 50
    declared = 8 * n + 8 * n * len(quats)
    for shapes in header["attributes"].values():
        declared += sum(k * s for k, s in shapes) + n * len(shapes) + n * sum(s for _, s in shapes)
    declared += sum(int(np.prod(shape)) for shape in header["mlp"].values())
    enough = -(-(declared - (1 << 20)) // 64)  # the fewest section bytes that may declare that many values
    _check_header(header, enough)
    with pytest.raises(CorruptFileError, match=f"declares {declared} values"):
        _check_header(header, enough - 1)
