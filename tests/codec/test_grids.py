"""Positions and time centres on uniform grids (the "compact" codec, version 3): round trips within half a
step computed here independently, degenerate and extreme inputs, and damaged sections as one-line errors."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from omg4.codec import grids
from omg4.codec.entropy import encode_indices, encode_uints
from omg4.codec.payload import decode_payload, encode_payload
from omg4.errors import CorruptFileError
from omg4.gaussians.backbone import BACKBONES

from tests.codec.test_payload import make_payload


def _positions_round_trip(xyz: np.ndarray, bits: int = grids.POSITION_BITS) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz, np.float16).astype(np.float64)
    ordered = xyz[grids.position_order(xyz, bits)]
    return ordered, grids.decode_positions(grids.encode_positions(ordered, bits), len(ordered)).astype(np.float64)


@pytest.mark.parametrize("bits", [1, 8, 15, 16])
def test_positions_come_back_within_half_a_grid_step(bits):
    rng = np.random.default_rng(bits)
    xyz = rng.normal(size=(4000, 3)) * [3.0, 0.5, 8.0] + 100.0
    ordered, decoded = _positions_round_trip(xyz, bits)
    step = (ordered.max(axis=0) - ordered.min(axis=0)).max() / (2 ** bits - 1)
    assert (np.abs(decoded - ordered) <= step / 2 + 2.0 ** -11 * np.abs(ordered)).all()
    assert (decoded.min(axis=0) >= ordered.min(axis=0) - 2.0 ** -11 * np.abs(ordered.min(axis=0))).all()


@pytest.mark.parametrize("case", ["single", "all equal", "flat in z", "fp16 extremes", "duplicates"])
def test_degenerate_and_extreme_positions(case):
    rng = np.random.default_rng(1)
    xyz = {"single": np.array([[1.5, -2.0, 3.25]]),
           "all equal": np.tile([[0.25, 7.0, -1.0]], (50, 1)),
           "flat in z": np.c_[rng.normal(size=(300, 2)), np.zeros(300)],
           "fp16 extremes": np.array([[-65504.0, 0, 6e-8], [65504.0, -65504.0, 0], [0, 65504.0, -6e-8]]),
           "duplicates": np.repeat(rng.normal(size=(40, 3)), 5, axis=0)}[case]
    ordered, decoded = _positions_round_trip(xyz)
    step = max((ordered.max(axis=0) - ordered.min(axis=0)).max() / (2 ** 15 - 1), 0.0)
    assert np.isfinite(decoded).all()
    assert (np.abs(decoded - ordered) <= step / 2 + 2.0 ** -11 * np.abs(ordered) + 1e-12).all()


def test_positions_out_of_order_are_refused_by_the_writer():
    xyz = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="position_order"):
        grids.encode_positions(xyz)


def test_time_centres_come_back_within_half_a_step():
    rng = np.random.default_rng(2)
    t = np.r_[rng.uniform(0, 2, 3000), -1.4, 3.3]  # centres may lie outside the clip
    step = grids.time_step(t, [0.0, 2.0])
    assert step == 2.0 / 1024
    decoded = grids.decode_times(grids.encode_times(t, step), t.size).astype(np.float64)
    assert (np.abs(decoded - t) <= step / 2 + 2.0 ** -11 * np.abs(t)).all()


def test_time_step_falls_back_to_the_centres_range():
    t = np.array([0.5, 4.5, 2.0])
    for bad in (None, [1.0], [2.0, 2.0], [0.0, float("nan")], "x", [3.0, 1.0]):
        assert grids.time_step(t, bad) == 4.0 / 1024
    assert grids.time_step(np.full(5, 3.0), None) == 1 / 1024


def test_time_centres_too_spread_for_the_coder_stay_fp16(tmp_path):
    p = make_payload(200)
    p.t[:2] = [-60000.0, 60000.0]  # 1024 steps of the [0, 10] clip would need ~12 million levels
    assert grids.encode_times(p.t, grids.time_step(p.t, p.meta["time_range"])) is None
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    d = decode_payload(tmp_path / "m.omg4")
    np.testing.assert_array_equal(np.sort(d.t.view(np.uint16)), np.sort(np.asarray(p.t, np.float16).view(np.uint16)))


def _position_section(origin=(0.0, 0.0, 0.0), step=0.5, bits=4, gaps=(0, 1, 2)) -> bytes:
    return struct.pack("<3ddB", *origin, step, bits) + encode_uints(np.array(gaps, np.uint64))


@pytest.mark.parametrize("data, message", [
    (b"\x00" * 10, "truncated"),
    (_position_section(origin=(float("nan"), 0, 0)), "invalid position grid"),
    (_position_section(step=0.0), "invalid position grid"),
    (_position_section(step=-1.0), "invalid position grid"),
    (_position_section(step=float("inf")), "invalid position grid"),
    (_position_section(bits=0), "invalid position grid"),
    (_position_section(bits=17), "invalid position grid"),
    (_position_section(gaps=(0, 4095, 1)), "Morton"),  # beyond 3 × 4 bits
    (_position_section(origin=(65000.0, 0, 0), step=60000.0, gaps=(0, 1, 1)), "fp16"),
])
def test_damaged_position_sections_are_corrupt_file_errors(data, message):
    with pytest.raises(CorruptFileError, match=message):
        grids.decode_positions(data, 3)


@pytest.mark.parametrize("head, codes, message", [
    ((0.0, 0.0, 4), [0, 1, 2], "invalid time grid"),
    ((float("inf"), 0.1, 4), [0, 1, 2], "invalid time grid"),
    ((0.0, 0.1, 0), [0, 0, 0], "invalid time grid"),
    ((0.0, 0.1, 70000), [0, 1, 2], "invalid time grid"),
    ((65000.0, 1000.0, 4), [0, 1, 3], "fp16"),
])
def test_damaged_time_sections_are_corrupt_file_errors(head, codes, message):
    levels = max(head[2], 1)
    data = struct.pack("<ddI", *head) + encode_indices(np.array(codes), min(levels, 1 << 16), "ans")
    with pytest.raises(CorruptFileError, match=message):
        grids.decode_times(data, 3)
    with pytest.raises(CorruptFileError, match="truncated"):
        grids.decode_times(data[:10], 3)


def test_log_scaled_groups_are_the_exp_activated_attributes():
    assert BACKBONES["rt4dgs"].log_scaled_groups() == ("scale", "scale_t")
    assert BACKBONES["freetimegs"].log_scaled_groups() == ("scale", "duration")


def test_a_hostile_log_scale_list_is_a_corrupt_file_error(tmp_path):
    from omg4.testing import forge
    encode_payload(make_payload(50), tmp_path / "m.omg4", codec="compact")
    header, sections = forge.split_container((tmp_path / "m.omg4").read_bytes())
    for bad in ("scale", ["nope"], [1], ["scale"] * 40):
        header["log_scaled"] = bad
        with pytest.raises(CorruptFileError, match="log-scale"):
            decode_payload(forge.assemble_container(header, sections))


@pytest.mark.parametrize("time_range", [[0.0, 1e8], [-1e308, 1e308], [0.0, 1e-320], [0.0, 1e-300], ["a", "b"],
                                        [[0.0], 1.0], [0.0, 10 ** 400], "12", [0.0, 1e5]])
def test_odd_time_ranges_still_write_a_file_that_decodes(tmp_path, time_range):
    """Whatever the meta's time range, the compact writer keeps a grid it can decode or falls back to fp16."""
    p = make_payload(100)
    p.meta["time_range"] = time_range
    p.t[:2] = [65504.0, -65504.0] if time_range == [0.0, 1e5] else p.t[:2]  # a centre at the fp16 limit
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    d = decode_payload(tmp_path / "m.omg4")
    t = np.sort(np.asarray(p.t, np.float16).astype(np.float64))  # grid rounding is monotone: compare sorted
    assert np.isfinite(d.t).all() and d.num_gaussians == 100
    step = grids.time_step(t, time_range)
    if grids.encode_times(t, step) is None:  # fp16 kept
        np.testing.assert_array_equal(np.sort(d.t.astype(np.float64)), t)
    else:
        assert np.isfinite(step) and step > 0
        assert (np.abs(np.sort(d.t.astype(np.float64)) - t) <= step / 2 + 2.0 ** -11 * np.abs(t)).all()


def test_positions_at_the_fp16_limit_on_a_narrower_axis_decode(tmp_path):
    """The widest axis spans ±65504; another reaches 65504 and may round half a step up: still a readable file."""
    p = make_payload(50)
    p.xyz[:3] = [[-65504.0, 0.0, 0.0], [65504.0, 65504.0, 0.0], [0.0, 65000.0, 1.0]]
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    d = decode_payload(tmp_path / "m.omg4")
    assert np.isfinite(d.xyz).all() and (np.abs(d.xyz.astype(np.float64)).max(axis=0) >= 65000).any()


@pytest.mark.parametrize("name, bits", [("smallest-three-9", 9), ("smallest-three-10", 10), ("smallest-three-15", 15),
                                        ("smallest-three-2", 2), ("smallest-three-1", None), ("smallest-three-16", None),
                                        ("smallest-three-09", None), ("smallest-three-²", None),
                                        ("smallest-three-١٠", None), ("smallest-three-１５", None),
                                        ("smallest-three-9x", None), ("smallest-three-", None), ("f16", None)])
def test_quaternion_encoding_names(name, bits):
    from omg4.codec import quaternions
    assert quaternions.bits_of(name) == bits


def test_a_hostile_quaternion_encoding_name_is_a_corrupt_file_error(tmp_path):
    from omg4.testing import forge
    p = make_payload(50)
    p.rotations = ("rotation",)
    encode_payload(p, tmp_path / "m.omg4", codec="compact")
    header, sections = forge.split_container((tmp_path / "m.omg4").read_bytes())
    for bad in ("smallest-three-²", "smallest-three-09", "smallest-three-99"):
        header["encodings"]["quat.rotation"] = bad
        with pytest.raises(CorruptFileError, match="quaternion encoding"):
            decode_payload(forge.assemble_container(header, sections))
