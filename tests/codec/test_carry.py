"""Carried Gaussians of a predicted segment (omg4.codec.carry; docs/file-format.md §8b)."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.codec.payload import decode_payload, encode_payload
from omg4.codec.references import reference_sections
from omg4.errors import CorruptFileError, OMG4Error
from omg4.testing import forge

SCALE = 1 / 32  # small codebooks: a Gaussian of its own then costs what its indices, position and time cost


def _reference(tmp_path, n: int, codec: str):
    """The decoded payload of a key segment of ``n`` Gaussians, and its reference sections."""
    encode_payload(forge.valid_payload(n, 0, SCALE), tmp_path / "key.omg4", codec=codec)
    decoded = decode_payload(tmp_path / "key.omg4")
    return decoded, reference_sections(decoded)


def _predicted(reference: dict, n: int, seed: int = 1):
    """A segment of ``n`` Gaussians of its own with the reference's codebooks and MLPs."""
    p = forge.valid_payload(n, seed, SCALE)
    p.mlp = {name: reference[f"mlp.{name}"] for name in p.mlp}
    rng = np.random.default_rng(seed)
    for attr, qa in p.attributes.items():
        if attr not in p.rotations:
            qa.codebooks = [reference[f"svq.{attr}.codebook{j}"] for j in range(len(qa.codebooks))]
            qa.indices = [rng.integers(0, len(cb), n) for cb in qa.codebooks]
    return p


def _write(tmp_path, p, reference, codec: str, name: str) -> bytes:
    encode_payload(p, tmp_path / name, codec=codec, reference=reference)
    return (tmp_path / name).read_bytes()


@pytest.mark.parametrize("codec", ["compact", "ans"])
def test_carried_gaussians_decode_as_the_reference_decoded_them_then_the_segments_own(tmp_path, codec):
    """The decoded segment holds the reference's decoded rows, value for value (positions, time centres, every
    attribute's values), followed by what the same segment decodes to without carrying anything."""
    key, reference = _reference(tmp_path, 900, codec)
    p = _predicted(reference, 300)
    rows = np.sort(np.random.default_rng(2).choice(900, 400, replace=False))
    own = decode_payload(_write(tmp_path, p, reference, codec, "own.omg4"), reference)
    p.carried = rows
    both = decode_payload(_write(tmp_path, p, reference, codec, "carry.omg4"), reference)
    assert both.num_gaussians == 700
    assert np.array_equal(both.xyz, np.concatenate([key.xyz[rows], own.xyz]))
    assert np.array_equal(both.t, np.concatenate([key.t[rows], own.t]))
    for attr, qa in both.attributes.items():
        expected = np.concatenate([key.attributes[attr].reconstruct()[rows], own.attributes[attr].reconstruct()])
        assert np.array_equal(qa.reconstruct(), expected), attr
    assert all(np.array_equal(both.mlp[k], own.mlp[k]) for k in own.mlp)


def test_a_carried_gaussian_costs_about_a_bit(tmp_path):
    """Carrying three quarters of a 4,000-Gaussian reference costs about H(3/4) = 0.81 bit per reference Gaussian,
    1.08 bits per carried one, against the tens of bits of each Gaussian the segment codes itself; carrying all of
    them costs a few bytes in all."""
    _, reference = _reference(tmp_path, 4000, "compact")
    p = _predicted(reference, 1000)
    alone = len(_write(tmp_path, p, reference, "compact", "none.omg4"))
    small = _predicted(reference, 500)
    own_bits = 8 * (alone - len(_write(tmp_path, small, reference, "compact", "half.omg4"))) / 500
    p.carried = np.sort(np.random.default_rng(3).choice(4000, 3000, replace=False))
    carried_bits = 8 * (len(_write(tmp_path, p, reference, "compact", "three.omg4")) - alone) / 3000
    p.carried = np.arange(4000)
    everything = len(_write(tmp_path, p, reference, "compact", "all.omg4")) - alone
    print(f"own Gaussian {own_bits:.1f} bits, carried {carried_bits:.2f} bits, all 4,000 carried {everything} B")
    assert 0.8 < carried_bits < 1.4 and own_bits > 40
    assert everything < 48


def _forged(data: bytes, edit=None, sections=None) -> bytes:
    header, parts = forge.split_container(data)
    if edit is not None:
        edit(header)
    return forge.assemble_container(header, sections(parts) if sections else parts)


def test_forged_carries_end_as_one_line_errors(tmp_path):
    key, reference = _reference(tmp_path, 600, "compact")
    p = _predicted(reference, 200)
    own_codebooks = _write(tmp_path, p, None, "compact", "alone.omg4")
    p.carried = np.arange(0, 600, 3)
    data = _write(tmp_path, p, reference, "compact", "carry.omg4")
    mask = dict(forge.split_container(data)[1])["carry"]
    cases = [
        (_forged(data, lambda h: h.update(carried=201)), "marks 200 carried Gaussians, the header declares 201"),
        (_forged(data, lambda h: h.update(carried=0)), "invalid count of carried Gaussians"),
        (_forged(data, lambda h: h.update(carried=True)), "invalid count of carried Gaussians"),
        (_forged(data, lambda h: h.update(carried="200")), "invalid count of carried Gaussians"),
        (_forged(data, sections=lambda s: [x for x in s if x[0] != "carry"]), "section list does not match"),
        (_forged(data, lambda h: h["encodings"].update(carry="ranks")), "encoding 'ranks' is not 'mask'"),
        (_forged(data, sections=lambda s: [(n, b[:-3] if n == "carry" else b) for n, b in s]), "section carry"),
        (_forged(own_codebooks, lambda h: h.update(carried=200, encodings={**h["encodings"], "carry": "mask"}),
                 lambda s: [*s, ("carry", mask)]), "carried Gaussians index the reference's codebooks"),
    ]
    for forged, message in cases:
        with pytest.raises(CorruptFileError, match=message):
            decode_payload(forged, reference)
    with pytest.raises(CorruptFileError, match="decode it through its sequence file"):
        decode_payload(data)
    other = reference_sections(decode_payload(forge.valid_file(tmp_path / "other.omg4", 500, "compact")))
    with pytest.raises(CorruptFileError, match="section carry"):  # a mask over another segment's Gaussians
        decode_payload(data, {**reference, **{k: v for k, v in other.items() if k.startswith("gaussians.")}})


def test_the_writer_refuses_what_cannot_be_carried(tmp_path):
    _, reference = _reference(tmp_path, 300, "compact")
    p = _predicted(reference, 100)
    for rows, message in [(np.array([0, 0]), "distinct rows"), (np.array([300]), "distinct rows"),
                          (np.array([], np.int64), "distinct rows"), (np.array([0.5]), "distinct rows")]:
        p.carried = rows
        with pytest.raises(OMG4Error, match=message):
            encode_payload(p, tmp_path / "x.omg4", reference=reference)
    p.carried = np.arange(10)
    with pytest.raises(OMG4Error, match="segment before"):
        encode_payload(p, tmp_path / "x.omg4")
    p.attributes["app"].codebooks[0] = p.attributes["app"].codebooks[0] + 0.5  # codebooks of its own
    with pytest.raises(OMG4Error, match="app has its own"):
        encode_payload(p, tmp_path / "x.omg4", reference=reference)
    assert not (tmp_path / "x.omg4").exists()
