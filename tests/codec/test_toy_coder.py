"""A fourth coder declared in this one file: a class and one table entry make it known to the writer, the reader,
the commands and the browser player (the codecs' table, :mod:`omg4.codec.coders`)."""

from __future__ import annotations

import numpy as np
import pytest

from omg4.codec import coders
from omg4.codec.coders import Coder, register_coder
from omg4.codec.entropy import encode_indices
from omg4.codec.payload import CompactGrids, check_codec, decode_payload, encode_payload
from omg4.codec.sections import encode_f16
from omg4.errors import CorruptFileError, OMG4Error
from omg4.io.web_player import export_web
from omg4.testing.browser import DIGESTS, python_digests, served
from omg4.testing.forge import valid_payload


class PlainCoder(Coder):
    """Every float as raw fp16, the Gaussians in their own order, the indices ANS-coded."""

    name = "plain"
    order = "original"
    index_encodings = ("ans",)
    morton_positions = False

    def float_section(self, values):
        return "f16", encode_f16(values, "f16")

    def arrange(self, q, precision):
        return q

    def positions(self, q, precision):
        return self.float_section(q.xyz)

    def attribute(self, name, qa, q, precision):
        sections = {f"svq.{name}.codebook{j}": self.float_section(cb) for j, cb in enumerate(qa.codebooks)}
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            sections[f"svq.{name}.index{j}"] = ("ans", encode_indices(ix, cb.shape[0], "ans"))
        return [list(cb.shape) for cb in qa.codebooks], sections


@pytest.fixture
def plain(monkeypatch):
    monkeypatch.setattr(coders, "CODERS", dict(coders.CODERS))  # the table as it was, after the test
    monkeypatch.setattr("omg4.codec.payload.CODERS", coders.CODERS)
    monkeypatch.setattr("omg4.codec.browser.CODERS", coders.CODERS)
    register_coder(PlainCoder())
    return coders.CODERS["plain"]


def test_a_registered_coder_writes_files_the_reader_decodes_to_the_same_values(plain, tmp_path):
    p = valid_payload(500, seed=4)
    path = tmp_path / "m.omg4"
    sizes = encode_payload(p, path, codec="plain")
    q, want = decode_payload(path), p.to_fp16()
    np.testing.assert_array_equal(q.xyz, want.xyz)  # stored in the Gaussians' own order
    np.testing.assert_array_equal(q.t, want.t)
    for attr, qa in want.attributes.items():
        for a, b in zip(q.attributes[attr].codebooks + q.attributes[attr].indices, qa.codebooks + qa.indices):
            np.testing.assert_array_equal(a, b)
    for name, w in want.mlp.items():
        np.testing.assert_array_equal(q.mlp[name], w)
    assert sizes["xyz"] == 2 * 3 * 500 and sum(sizes.values()) == path.stat().st_size  # raw fp16, as declared
    check_codec("plain")


def test_its_files_may_not_hold_another_codecs_encodings(plain, tmp_path):
    """The header names the coder; an index encoding of another codec is refused, not decoded."""
    from omg4.codec.container import read_container, write_container

    path = tmp_path / "m.omg4"
    encode_payload(valid_payload(200, seed=1), path, codec="plain")
    header, sections = read_container(path)
    header["encodings"]["svq.scale.index0"] = "paper"
    write_container(path, header, sections)
    with pytest.raises(CorruptFileError, match="not an index encoding of the codec 'plain'"):
        decode_payload(path)


def test_the_commands_offer_it_and_a_name_is_taken_once(plain):
    import argparse

    from omg4.app.commands.common import add_codec_argument

    parser = argparse.ArgumentParser()
    add_codec_argument(parser)
    assert parser.parse_args(["--codec", "plain"]).codec == "plain"
    with pytest.raises(OMG4Error, match="a coder needs a new name"):
        register_coder(PlainCoder())
    with pytest.raises(OMG4Error, match="apply to the compact codec only, not 'plain'"):
        check_codec("plain", CompactGrids(positions=12))


def test_the_browser_reads_its_files_as_python_does(plain, chromium, tmp_path):
    """The player gets the codecs' table with its modules (codecs.js, written at export): a coder added in Python
    from encodings the browser decodes plays without a line of JavaScript."""
    encode_payload(valid_payload(400, seed=6), tmp_path / "m.omg4", codec="plain")
    export_web(tmp_path / "web", tmp_path / "m.omg4")
    assert (tmp_path / "web" / "model.omg4").read_bytes() == (tmp_path / "m.omg4").read_bytes()  # nothing rewritten
    with served(tmp_path / "web") as url:
        chromium.call("Page.navigate", url=f"{url}/index.html?ui=0&time=0&case=plain")
        assert chromium.evaluate(DIGESTS) == python_digests(tmp_path / "m.omg4")
