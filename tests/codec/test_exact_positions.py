"""Exact positions in the compact codec (``CompactGrids.exact``; ``grid-morton-exact``, container version 5)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omg4.codec import grids
from omg4.codec.container import describe_container, read_container
from omg4.codec.entropy import encode_uints, join_streams, pack_varints
from omg4.codec.payload import CompactGrids, QuantizedAttribute, decode_payload, encode_payload
from omg4.errors import CorruptFileError

from tests.codec.test_payload import make_payload


def _payload(n: int, seed: int = 0):
    """A payload whose Gaussians all have different scales (one codeword each), so "the largest" has no ties."""
    p = make_payload(n, seed)
    p.rotations, p.log_scaled = ("rotation",), ("scale",)
    rng = np.random.default_rng(seed + 100)
    log_scales = rng.uniform(-6, 0, size=(n, 3))
    p.attributes["scale"] = QuantizedAttribute([log_scales[:, j:j + 1] for j in range(3)], [np.arange(n)] * 3)
    return p


def _largest_by_hand(p, percent: int) -> np.ndarray:
    """Indices (input order) of the ⌈percent·N/100⌉ Gaussians whose two largest scales, as the fp16 payload holds
    them, have the largest product."""
    scales = np.exp(p.to_fp16().attributes["scale"].reconstruct().astype(np.float64))
    two_largest = -np.sort(-scales, axis=1)[:, :2]
    product = two_largest[:, 0] * two_largest[:, 1]
    count = math.ceil(percent * p.num_gaussians / 100)
    return np.argsort(-product)[:count]


@pytest.mark.parametrize("n, percent", [(2000, 1), (2010, 3), (2000, 7), (2000, 100)])
def test_the_largest_gaussians_keep_their_fp16_positions_bit_for_bit(tmp_path, n, percent):
    """Row by row: the chosen Gaussians decode to their own fp16 positions, every other one to its grid value (the
    file without exact positions), and no attribute moves."""
    p = _payload(n)
    encode_payload(p, tmp_path / "e.omg4", precision=CompactGrids(12, 7, 7, exact=percent))
    encode_payload(p, tmp_path / "g.omg4", precision=CompactGrids(12, 7, 7, exact=0))
    exact, grid = decode_payload(tmp_path / "e.omg4"), decode_payload(tmp_path / "g.omg4")
    assert read_container(tmp_path / "e.omg4")[0]["encodings"]["xyz"] == "grid-morton-exact"
    assert read_container(tmp_path / "g.omg4")[0]["encodings"]["xyz"] == "grid-morton"
    ref16 = np.asarray(p.xyz, np.float16)
    order = grids.position_order(ref16, 12)  # storage row i holds input Gaussian order[i]
    np.testing.assert_array_equal(exact.attributes["app"].reconstruct(),
                                  p.to_fp16().attributes["app"].reconstruct()[order])  # the rows are those Gaussians
    chosen = np.isin(order, _largest_by_hand(p, percent))
    assert chosen.sum() == math.ceil(percent * n / 100)  # 61 of 2010 at 3 %: rounded up
    np.testing.assert_array_equal(exact.xyz[chosen].view(np.uint16), ref16[order][chosen].view(np.uint16))
    np.testing.assert_array_equal(exact.xyz[~chosen].view(np.uint16), grid.xyz[~chosen].view(np.uint16))
    moved_by_grid = (grid.xyz[chosen].view(np.uint16) != ref16[order][chosen].view(np.uint16)).any(axis=1)
    assert moved_by_grid.mean() > 0.5
    for name in ("scale", "app"):
        np.testing.assert_array_equal(exact.attributes[name].reconstruct(), grid.attributes[name].reconstruct())
    assert describe_container(tmp_path / "e.omg4")["version"] == 5
    encode_payload(p, tmp_path / "e16.omg4", precision=CompactGrids(12, 7, 7, weights=16, exact=percent))
    encode_payload(p, tmp_path / "g16.omg4", precision=CompactGrids(12, 7, 7, weights=16, exact=0))
    assert describe_container(tmp_path / "e16.omg4")["version"] == 5  # exact positions alone need version 5
    assert describe_container(tmp_path / "g16.omg4")["version"] == 3


@pytest.mark.parametrize("bits", range(1, 17))
def test_every_grid_with_every_position_exact_decodes_the_fp16_values(bits):
    """Encoder and decoder agree on each grid value to the last bit (a correction is relative to it), at every grid."""
    rng = np.random.default_rng(bits)
    xyz = (rng.normal(size=(300, 3)) * [3.0, 0.5, 40.0]).astype(np.float16)
    order = grids.position_order(xyz, bits)
    decoded = grids.decode_positions(grids.encode_positions(xyz[order], bits, np.ones(300, bool)), 300, exact=True)
    np.testing.assert_array_equal(decoded.view(np.uint16), xyz[order].view(np.uint16))


def test_the_exact_mask_is_checked():
    xyz = np.zeros((5, 3))
    for bad in (np.ones(4, bool), np.array([0, 1, 0, 0, 1]), np.ones((5, 1), bool)):
        with pytest.raises(ValueError, match="boolean mask of 5"):
            grids.encode_positions(xyz, 8, bad)


def test_exact_positions_cost_a_few_bits_each(tmp_path):
    """The corrections are differences of ordered fp16 keys from the grid value: at 12 bits over a box of a few
    units the fp16 value lies within a few keys, so 3 % exact adds well under 0.2 bytes per Gaussian."""
    p = _payload(4000)
    sizes = {e: encode_payload(p, tmp_path / "x.omg4", precision=CompactGrids(12, 7, 7, exact=e))["xyz"]
             for e in (0, 3, 100)}
    assert sizes[0] < sizes[3] < sizes[0] + 0.2 * 4000
    assert sizes[100] < sizes[0] + 4000 * 3  # under 8 bits per Gaussian for all three axes


def test_adversarial_positions_round_trip(tmp_path):
    """Values the grid cannot hold: around zero (fp16 keys far finer than the grid, −0.0 and subnormals), at the
    box's corners and near the fp16 limit; with every Gaussian exact they all decode bit for bit."""
    p = _payload(64, seed=3)
    xyz = np.asarray(p.xyz, np.float64)
    xyz[:8] = [[0.0, -0.0, 1e-7], [-1e-7, 6e-8, -6e-8], [2.0 ** -14, -(2.0 ** -14), 0.0], [3e4, -3e4, 6.5e4],
               [-6.5e4, 1.0, -1.0], [1e-3, 1e-3, 1e-3], [-0.0, -0.0, -0.0], [0.5, 0.25, 0.125]]
    p.xyz = xyz
    encode_payload(p, tmp_path / "a.omg4", precision=CompactGrids(4, 7, 7, exact=100))
    d = decode_payload(tmp_path / "a.omg4")
    np.testing.assert_array_equal(np.sort(d.xyz.view(np.uint16), axis=0),
                                  np.sort(np.asarray(xyz, np.float16).view(np.uint16), axis=0))


def test_a_payload_without_log_scales_keeps_the_plain_grid(tmp_path):
    p = _payload(300)
    p.log_scaled = ()
    encode_payload(p, tmp_path / "n.omg4", precision=CompactGrids(12, 7, 7, exact=50))
    assert read_container(tmp_path / "n.omg4")[0]["encodings"]["xyz"] == "grid-morton"
    p = _payload(300)
    p.attributes["scale"] = QuantizedAttribute([np.zeros((4, 2), np.float16)], [np.zeros(300, np.int64)])  # 2 wide
    encode_payload(p, tmp_path / "w.omg4", precision=CompactGrids(12, 7, 7, exact=50))
    assert read_container(tmp_path / "w.omg4")[0]["encodings"]["xyz"] == "grid-morton"


def _section(xyz: np.ndarray, bits: int, tail: bytes) -> bytes:
    """A ``grid-morton-exact`` section laid out by hand: the plain grid section of ``xyz``, then ``tail``."""
    return join_streams(grids.encode_positions(xyz, bits), tail)


def _tail(count: int, ranks, diffs) -> bytes:
    return pack_varints(np.array([count])) + join_streams(encode_uints(np.diff(np.asarray(ranks, np.uint64),
                                                                                prepend=np.uint64(0))),
                                                          encode_uints(np.asarray(diffs, np.uint64)))


@pytest.mark.parametrize("tail, message", [
    (lambda: _tail(0, [0], [0, 0, 0]), "exact positions for"),
    (lambda: _tail(9, [0], [0, 0, 0]), "exact positions for"),
    (lambda: _tail(1, [8], [0, 0, 0]), "exact-position ranks"),
    (lambda: _tail(2, [3, 3], [0] * 6), "exact-position ranks"),
    (lambda: _tail(1, [2], [2 * 70000, 0, 0]), "uint stream|exact positions"),
    (lambda: _tail(1, [2], [2 * 40000, 2 * 40000, 2 * 40000]), "exact positions"),  # keys past 0xFFFF
    (lambda: _tail(1, [0], [2 * 32769 - 1, 0, 0]), "damaged exact positions"),  # x: key 0x8000 − 32769 < 0
    (lambda: _tail(1, [2], [0, 2 * 0x7C00, 0]), "exact positions beyond"),  # y: from +0.0 to +inf
    (lambda: _tail(1, [2], [0, 2 * 0x7C01, 0]), "exact positions beyond"),  # to a NaN
    (lambda: _tail(1, [2], [0, 0]), "holds 2 symbols, expected 3"),
    (lambda: b"\x01", "truncated|damaged"),
])
def test_forged_exact_sections_are_corrupt_file_errors(tail, message):
    xyz = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [1.0, 0, 0], [1.5, 0, 0], [1.7, 0, 0],
                    [2.0, 0, 0]])
    with pytest.raises(CorruptFileError, match=message):
        grids.decode_positions(_section(xyz, 6, tail()), 8, exact=True)


def test_a_valid_forged_section_decodes_to_the_corrected_value():
    """The same hand-made layout with a correction of +3 keys on one axis decodes to the grid value moved by
    exactly three fp16 steps — the format as documented, not as the writer happens to produce it."""
    xyz = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [1.0, 0, 0], [1.5, 0, 0], [1.7, 0, 0],
                    [2.0, 0, 0]])
    plain = grids.decode_positions(grids.encode_positions(xyz, 6), 8)
    got = grids.decode_positions(_section(xyz, 6, _tail(1, [2], [6, 0, 1])), 8, exact=True)
    expected = plain.copy()
    expected[2, 0] = np.nextafter(np.nextafter(np.nextafter(plain[2, 0], np.float16(9)), np.float16(9)), np.float16(9))
    assert plain[2, 2] == 0 and not np.signbit(plain[2, 2])
    expected[2, 2] = np.float16(-0.0)  # zigzag 1 is −1, and in key order −0.0 lies one step below +0.0
    np.testing.assert_array_equal(got.view(np.uint16), expected.view(np.uint16))
