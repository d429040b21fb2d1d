"""Forged .omg4 files (checksums recomputed): bounded, one-line CorruptFileError, never another exception."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.testing import forge

from omg4.codec import entropy
from omg4.codec.payload import decode_payload, encode_payload
from omg4.errors import CorruptFileError, OMG4Error
from omg4.models.compact import load_omg4

@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """A small valid file per codec: {codec: bytes}."""
    folder = tmp_path_factory.mktemp("valid")
    return {codec: forge.valid_file(folder / f"{codec}.omg4", 300, codec=codec, codebook_scale=0.1)
            for codec in ("compact", "ans", "paper")}


def _forged(data: bytes, path: tuple, value) -> bytes:
    """``data`` with the header entry at ``path`` set to ``value`` (``"__forge_inf__"``: the JSON number 1e400),
    every checksum recomputed."""
    header, sections = forge.split_container(data)
    node = header
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return forge.assemble_container(header, sections)


@pytest.mark.parametrize("codec", ["compact", "ans", "paper"])
def test_every_forged_file_is_ok_or_a_one_line_corrupt_file_error(valid, codec, tmp_path):
    outcomes = {"ok": 0, "corrupt": 0}
    path = tmp_path / "case.omg4"
    for kind, data in forge.forged_files(valid[codec], 160, seed=7):
        path.write_bytes(data)
        try:
            outcomes[forge.exercise(path)] += 1
        except CorruptFileError as exc:
            assert "\n" not in str(exc), (kind, str(exc))
            outcomes["corrupt"] += 1
        # any other exception fails the test with its traceback: what the fuzzer exists to find
    assert outcomes["corrupt"] > 100 and outcomes["ok"] >= 1  # both ends exercised


def test_many_gaussians_declared_in_few_bytes_are_refused_before_any_decoding(monkeypatch):
    data = forge.inflated_file(2_000_000, "ans")  # a well-formed file: every Gaussian identical
    calls = []
    monkeypatch.setattr("omg4.codec.payload.decode_section", lambda *a, **k: calls.append(a))
    with pytest.raises(CorruptFileError, match="Gaussians"):
        decode_payload(data)
    assert calls == []


def test_a_file_that_spends_enough_bytes_per_gaussian_still_decodes(tmp_path):
    payload = forge.valid_payload(20000, codebook_scale=0.05)  # above the 4,096 always allowed
    encode_payload(payload, tmp_path / "m.omg4")
    assert decode_payload(tmp_path / "m.omg4").num_gaussians == 20000


@pytest.mark.parametrize("shape", [[2**24, 2**24, 2**14, 3], [2**62, 4], [-1, 3], [1, 2, 3, 4, 5], ["64", 3]])
def test_overflowing_or_malformed_mlp_shapes_are_refused(valid, shape):
    data = _forged(valid["ans"], ("mlp", "shared.0.weight"), shape)
    with pytest.raises(CorruptFileError, match="MLP weight"):
        decode_payload(data)


@pytest.mark.parametrize("path, value", [
    (("meta", "active_sh_degree"), "__forge_inf__"),
    (("meta", "active_sh_degree"), 99),
    (("meta", "active_sh_degree_t"), -1),
    (("meta", "active_sh_degree"), 2.0),
    (("meta", "gaussian_config", "time_range"), [0]),
    (("meta", "gaussian_config", "time_range"), [0, "__forge_inf__"]),
    (("meta", "gaussian_config", "time_range"), [1, 0]),
    (("meta", "gaussian_config", "time_cull"), None),
    (("meta", "gaussian_config", "time_cull"), 5),
    (("meta", "gaussian_config", "sh_degree"), 99),
    (("meta", "gaussian_config", "sh_degree"), True),
    (("meta", "gaussian_config", "rotation_convention"), "\u001b[31m"),
    (("meta", "gaussian_config", "surprise"), 1),
    (("meta", "gaussian_config"), [1, 2]),
])
def test_hostile_metadata_is_a_corrupt_file_error_at_load(valid, tmp_path, path, value):
    target = tmp_path / "m.omg4"
    target.write_bytes(_forged(valid["ans"], path, value))
    with pytest.raises(CorruptFileError):
        load_omg4(target)


def test_scales_that_overflow_are_refused_at_load(tmp_path):
    payload = forge.valid_payload(300, codebook_scale=0.1)
    payload.attributes["scale_t"].codebooks[0][:] = 20000.0  # exp(20000) = inf in float32
    encode_payload(payload, tmp_path / "m.omg4")
    with pytest.raises(CorruptFileError, match="scales overflow"):
        load_omg4(tmp_path / "m.omg4")


def test_huffman_bitstream_whose_length_disagrees_with_its_counts_is_refused():
    idx = np.random.default_rng(0).integers(0, 40, 5000)
    stream = entropy.encode_indices(idx, 64, "paper")
    np.testing.assert_array_equal(entropy.decode_indices(stream, 64, idx.size, "paper"), idx)
    import lzma

    plain = lzma.decompress(stream[1:], format=lzma.FORMAT_RAW, filters=entropy._LZMA_FILTERS)
    for forged in (plain + b"\x00" * 4096, plain[:-1]):  # bits appended (a longer walk) or cut
        data = bytes([stream[0]]) + lzma.compress(forged, format=lzma.FORMAT_RAW, filters=entropy._LZMA_FILTERS)
        with pytest.raises(CorruptFileError, match="Huffman"):
            entropy.decode_indices(data, 64, idx.size, "paper")


def test_info_refuses_a_forged_section_name_and_never_prints_control_characters(valid, tmp_path, capsys):
    from omg4.app.cli import main

    header, sections = forge.split_container(valid["ans"])
    forged = forge.assemble_container(header, [("\x1b[2J\x1b[31m" + sections[0][0], sections[0][1]), *sections[1:]])
    path = tmp_path / "m.omg4"
    path.write_bytes(forged)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and err.count("\n") == 1 and "does not match" in err


@pytest.mark.parametrize("value", [2**40, "12", None, -3])
def test_info_on_forged_counts_is_one_line(valid, tmp_path, capsys, value):
    from omg4.app.cli import main

    path = tmp_path / "m.omg4"
    path.write_bytes(_forged(valid["paper"], ("num_gaussians",), value))
    assert main(["info", str(path)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_printable_escapes_control_characters():
    from omg4.app.commands.common import printable

    assert printable("a\x1b[31mb\nc\u200bd") == "a\\x1b[31mb\\nc\\u200bd"
    assert printable("Gaußian 4D") == "Gaußian 4D"


def test_names_with_a_trailing_newline_are_refused(valid, tmp_path):
    """Attribute and MLP weight names must match their pattern whole: ``$`` alone lets ``"app\\n"`` through."""
    header, sections = forge.split_container(valid["ans"])
    attribute = next(iter(header["attributes"]))
    header["attributes"][attribute + "\n"] = header["attributes"].pop(attribute)
    with pytest.raises(CorruptFileError, match="invalid codebook shapes"):
        decode_payload(forge.assemble_container(header, sections))
    p = forge.valid_payload(50)
    p.attributes[attribute + "\n"] = p.attributes.pop(attribute)
    with pytest.raises(OMG4Error, match="invalid attribute name"):
        encode_payload(p, tmp_path / "x.omg4")


@pytest.mark.parametrize("codec", ["paper", "ans"])
def test_info_refuses_what_the_decoder_refuses(tmp_path, capsys, codec):
    """A file declaring 20,000 identical Gaussians in a few bytes: every section consistent with its header, so
    only the decoder's bounds catch it; ``info`` decodes as ``render`` does and refuses it the same way."""
    from omg4.app.cli import main
    from omg4.models.summary import describe_file

    path = tmp_path / "inflated.omg4"
    path.write_bytes(forge.inflated_file(20_000, codec))
    with pytest.raises(CorruptFileError) as decoder_error:
        load_omg4(path)
    with pytest.raises(CorruptFileError) as info_error:
        describe_file(path)
    assert str(info_error.value) == str(decoder_error.value)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(decoder_error.value) in err


def test_info_counts_bits_per_gaussian_from_the_file_size(tmp_path):
    """bits per Gaussian = 8 × the file's bytes / its Gaussian count."""
    from omg4.models.summary import describe_file

    path = tmp_path / "m.omg4"
    forge.valid_file(path, 300, codec="compact")
    summary = describe_file(path)
    assert summary["bits_per_gaussian"] == pytest.approx(8 * path.stat().st_size / 300)
