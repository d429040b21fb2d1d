"""A lossless rewrite of an ``.omg4`` file into the sections the browser player decodes (``omg4 export --format web``).

The player (``src/omg4/web/decoder/``) decodes the ``compact`` and ``ans`` codecs' sections bit for bit as
:func:`omg4.codec.payload.decode_payload` does, except two kinds the browser has no decoder for: LZMA-coded fp16
sections (``f16-lzma``, which the writers pick when LZMA happens to be the smallest float encoding) and the
``paper`` codec's Huffman + LZMA index streams. Those sections are decoded here and written again as ``f16`` or
``f16-planes`` (the smaller) and as ``ans`` streams; a ``paper`` file becomes an ``ans`` file of the same values.
Every other section is copied byte for byte. Re-encoding to the ``compact`` codec instead would move values onto
its grids (docs/file-format.md §3a), so the rewrite keeps the file's codec. A sequence is rewritten segment by
segment.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from omg4.codec.coders import CODERS
from omg4.codec.container import SEQUENCE_VERSION, read_versioned, container_bytes
from omg4.codec.entropy import decode_indices, encode_indices
from omg4.codec.payload import check_sections, container_version
from omg4.codec.sections import decode_f16, encode_f16

#: the float encodings the browser decodes, in order of preference on a tie
BROWSER_FLOATS = ("f16", "f16-planes")


def browser_decodable(source: str | os.PathLike | bytes) -> bytes:
    """The bytes of ``source`` (a single-model or sequence ``.omg4`` file, or its bytes) with every section the
    browser cannot decode re-encoded losslessly; the file's own bytes when it has none."""
    in_memory = isinstance(source, (bytes, bytearray, memoryview))
    data = bytes(source) if in_memory else Path(source).read_bytes()
    version, header, sections = read_versioned(data if in_memory else source)  # a file's errors name the file
    if version == SEQUENCE_VERSION:
        segments = {name: browser_decodable(segment) for name, segment in sections.items()}
        return data if segments == sections else container_bytes(header, segments, SEQUENCE_VERSION)
    rewritten, out = _single_model(header, sections)
    if out == sections:
        return data
    return container_bytes(rewritten, out, container_version(rewritten["codec"], rewritten["encodings"]))


def _single_model(header: dict, sections: dict[str, bytes]) -> tuple[dict, dict[str, bytes]]:
    """(header, sections) of one model with every LZMA float and Huffman index section re-encoded."""
    check_sections(header, {name: len(data) for name, data in sections.items()})
    n, encodings, out = header["num_gaussians"], dict(header["encodings"]), dict(sections)
    alphabets = {f"svq.{attr}.index{j}": k for attr, shapes in header["attributes"].items()
                 for j, (k, _) in enumerate(shapes)}
    for name, encoding in header["encodings"].items():
        if encoding == "f16-lzma":
            values = decode_f16(sections[name], encoding, _float_count(header, name))
            options = [(e, encode_f16(values, e)) for e in BROWSER_FLOATS]
            encodings[name], out[name] = min(options, key=lambda o: len(o[1]))
        elif encoding == "paper" and name in alphabets:
            indices = decode_indices(sections[name], alphabets[name], n, "paper")
            encodings[name], out[name] = "ans", encode_indices(indices, alphabets[name], "ans")
    return {**header, "codec": CODERS[header["codec"]].browser_codec, "encodings": encodings}, out


def _float_count(header: dict, name: str) -> int:
    """How many fp16 values the float section ``name`` holds (docs/file-format.md §3)."""
    n = header["num_gaussians"]
    if name == "xyz":
        return 3 * n
    if name == "t":
        return n
    if name.startswith("mlp."):
        return math.prod(header["mlp"][name[len("mlp."):]])
    attr, slot = name[len("svq."):].rsplit(".codebook", 1)
    k, s = header["attributes"][attr][int(slot)]
    return k * s


__all__ = ["BROWSER_FLOATS", "browser_decodable"]
