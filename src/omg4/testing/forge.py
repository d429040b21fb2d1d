"""Forged ``.omg4`` files: what a hostile or damaged file can look like *past* the checksums.

The container's CRCs catch accidental damage; a forged file recomputes them. This module
makes valid compressed models of several sizes (:func:`valid_file`) and mutates them
(:func:`forged_files`) in the ways a decoder must survive: hostile header values (huge,
negative, overflowing, non-finite, wrong-typed, control characters) at any place of the
header and its ``meta``, deleted fields, changed codec, damaged, truncated, extended,
swapped or re-split section bytes, hostile section names — each with every checksum
recomputed — plus raw byte flips and truncations that the checksums must catch.
:func:`exercise` runs a file through everything a user's command does with it (``omg4
info``, decoding, loading, rendering a frame). ``tools/fuzz_omg4.py`` and the test
suite drive it; a correct decoder lets every case end as "ok" or a one-line
:class:`~omg4.errors.CorruptFileError`. Its valid models take the M preset's codebook sizes and the SVQ layout
from the backbone table.
"""

from __future__ import annotations

import functools
import json
import random
from pathlib import Path
from typing import Iterator

import numpy as np

from omg4.codec.container import crc32, read_container, stored_json
from omg4.codec.rig import rig_json
from omg4.codec.payload import (CompactGrids, CompressedPayload, QuantizedAttribute, container_version,
                                encode_payload)

#: stand-ins for JSON numbers that ``json.dumps`` refuses to write (overflowing to ±inf when parsed)
_RAW_NUMBERS = {"__forge_inf__": "1e400", "__forge_ninf__": "-1e400", "__forge_tiny__": "1e-400"}
_HOSTILE = [None, True, False, -1, 0, 1, 2, 3, 99, 2**24, 2**31 - 1, 2**31, 2**53 + 1, 2**63, 2**64 + 1, -2**63, 0.5,
            -0.5, 1e308, "__forge_inf__", "__forge_ninf__", "__forge_tiny__", "", "x", "\x1b[31mred\x1b[0m\n",
            "a" * 300, [], [0], [1, 1], [2**24, 2**24, 2**14, 3], [-1, 3], [[1, 1]], [[2**16, 64]] * 64, {},
            {"a": 1}, [None], ["1", "2"]]


def _rig() -> list:
    """Three cameras on a circle of radius 4 around the origin, looking at it (a forged file's camera rig)."""
    from omg4.data.scene import Camera, look_at_viewmat

    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    return [Camera(K=K, viewmat=look_at_viewmat(np.array([4 * np.sin(a), -4 * np.cos(a), 1.0]), np.zeros(3)),
                   width=64, height=48, name=f"cam{i:02d}") for i, a in enumerate((0.0, 0.5, -0.5))]


#: the log-space offset of a forged attribute's codebook (scales of about e^-4, time scales and durations about e^0.5)
_OFFSETS = {"scale": -4.0, "scale_t": 0.5, "duration": 0.5}


def valid_payload(num_gaussians: int, seed: int = 0, codebook_scale: float = 1.0,
                  backbone: str = "rt4dgs") -> CompressedPayload:
    """A fully specified compressed model of ``num_gaussians`` Gaussians with random (but well-formed) values:
    the SVQ layout of ``backbone``'s default preset (M for Real-Time4DGS; codebooks scaled by ``codebook_scale``),
    default appearance MLPs, and the metadata the decoder reads."""
    from omg4.gaussians.appearance import AppearanceMLP
    from omg4.gaussians.backbone import BACKBONES
    from omg4.gaussians.model import GaussianConfig

    import torch

    schema = BACKBONES[backbone]
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    n = num_gaussians
    xyz = rng.normal(size=(n, 3)) * 0.8
    attributes = {}
    for group in schema.svq_groups:
        name, sub = group.name, group.sub_length
        width = sum(w for _, w in schema.svq_widths(name))
        k = max(2, int(schema.size_presets[schema.default_preset].codebook_sizes[name] * codebook_scale))
        attributes[name] = QuantizedAttribute(
            [_OFFSETS.get(name, 0.0) + 0.3 * rng.normal(size=(k, sub)) for _ in range(width // sub)],
            [rng.integers(0, k, n) for _ in range(width // sub)])
    config = GaussianConfig(time_range=(0.0, 1.0), backbone=backbone,
                            **({} if schema.sh_degree_t is None else {"sh_degree_t": schema.sh_degree_t}))
    meta = {"preset": "M", "scene": "forge", "time_range": [0.0, 1.0], "gaussian_config": config.to_json(),
            "active_sh_degree": config.sh_degree, "active_sh_degree_t": config.sh_degree_t,
            "normalization": {"scale": 1.0, "rotation": np.eye(3).tolist(), "translation": [0.0, 0.0, 0.0]},
            "rig": rig_json(_rig(), 1)}
    mlp = AppearanceMLP(num_rest=config.num_coeffs - 1, num_inputs=schema.mlp_inputs).to_fp16_state()
    return CompressedPayload(xyz, rng.uniform(0, 1, n), attributes, mlp, meta, schema.quaternion_groups(),
                             schema.log_scaled_groups())


def valid_file(path: str | Path, num_gaussians: int, codec: str = "ans", seed: int = 0,
               codebook_scale: float = 1.0, precision: CompactGrids = CompactGrids(), backbone: str = "rt4dgs") -> bytes:
    """Write :func:`valid_payload` to ``path`` with ``codec`` (at ``precision``, the compact codec's grids); returns
    the file's bytes."""
    encode_payload(valid_payload(num_gaussians, seed, codebook_scale, backbone), path, codec=codec,
                   precision=precision)
    return Path(path).read_bytes()


# ------------------------------------------------------------------------- assembly
def split_container(data: bytes) -> tuple[dict, list[tuple[str, bytes]]]:
    """(header, [(section name, bytes)] in file order) of a valid container."""
    header, sections = read_container(data)
    return header, list(sections.items())


def assemble_container(header: object, sections: list[tuple[str, bytes]]) -> bytes:
    """A container with correct checksums (JSON and sections) around any JSON ``header`` and any section names
    (what :func:`~omg4.codec.container.write_container` would refuse); the :data:`_RAW_NUMBERS` tokens become
    numbers JSON cannot hold. The version is the one the writer gives such a codec and encodings
    (:func:`~omg4.codec.payload.container_version`)."""
    table = [[name, len(data), crc32(data)] for name, data in sections]
    text = json.dumps({"header": header, "sections": table}, separators=(",", ":"), ensure_ascii=False)
    for token, raw in _RAW_NUMBERS.items():
        text = text.replace(f'"{token}"', raw)
    fields = header if isinstance(header, dict) else {}
    version = container_version(fields.get("codec"), fields.get("encodings"))
    head = stored_json(text.encode("utf-8", "surrogatepass"), version)
    return head + b"".join(data for _, data in sections)


# ------------------------------------------------------------------------ mutations
def _paths(node: object, prefix: tuple = ()) -> list[tuple]:
    """Every key/index path inside a JSON value (containers and leaves)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list) and len(node) <= 16:
        for i, v in enumerate(node):
            out += _paths(v, prefix + (i,))
    return out


def _get(node, path):
    for key in path:
        node = node[key]
    return node


def _hostile_value(rng: random.Random, current: object) -> object:
    if isinstance(current, (int, float)) and not isinstance(current, bool) and rng.random() < 0.4:
        v = current
        return rng.choice([v + 1, v - 1, -v, 2 * v, v * 1000, v * 2**20, (int(v) or 1) * 2**31, v / 3])
    return rng.choice(_HOSTILE)


def _mutate_header(rng: random.Random, header: dict, sections) -> bytes:
    header = json.loads(json.dumps(header))
    path = rng.choice(_paths(header))
    parent = _get(header, path[:-1])
    if isinstance(parent, dict) and rng.random() < 0.2:
        del parent[path[-1]]
    else:
        parent[path[-1]] = _hostile_value(rng, parent[path[-1]])
    return assemble_container(header, sections)


def _damaged_bytes(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    choice = rng.randrange(7)
    if choice == 0 and b:  # a few flipped bits
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
    elif choice == 1 and b:  # a run of up to 64 bytes replaced by 0x00 or 0xFF (past the end: appended)
        i = rng.randrange(len(b))
        b[i:i + rng.randint(1, 64)] = bytes([rng.choice((0, 255))]) * len(b[i:i + 64])
    elif choice == 2:  # truncated
        b = b[:rng.randrange(len(b) + 1)]
    elif choice == 3:  # extended
        b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
    elif choice == 4:  # replaced by noise of the same length
        b = bytearray(rng.randbytes(len(b)))
    elif choice == 5 and b:  # the first bytes (tags, modes, varint sizes) changed
        b[rng.randrange(min(len(b), 12))] = rng.randrange(256)
    else:  # a varint-looking huge length spliced in
        i = rng.randrange(len(b) + 1)
        b[i:i] = b"\xff\xff\xff\xff\xff\xff\xff\xff\x7f"
    return bytes(b)


def _mutate_section(rng: random.Random, header: dict, sections) -> bytes:
    i = rng.randrange(len(sections))
    sections = list(sections)
    sections[i] = (sections[i][0], _damaged_bytes(rng, sections[i][1]))
    return assemble_container(header, sections)


def _swap_sections(rng: random.Random, header: dict, sections) -> bytes:
    i, j = rng.sample(range(len(sections)), 2)
    sections = list(sections)
    sections[i], sections[j] = (sections[i][0], sections[j][1]), (sections[j][0], sections[i][1])
    return assemble_container(header, sections)


def _resplit_sections(rng: random.Random, header: dict, sections) -> bytes:
    """Move the boundary between two neighbouring sections: sizes lie about where data starts."""
    i = rng.randrange(len(sections) - 1)
    blob = sections[i][1] + sections[i + 1][1]
    cut = rng.randrange(len(blob) + 1)
    sections = list(sections)
    sections[i], sections[i + 1] = (sections[i][0], blob[:cut]), (sections[i + 1][0], blob[cut:])
    return assemble_container(header, sections)


def _rename_section(rng: random.Random, header: dict, sections) -> bytes:
    i = rng.randrange(len(sections))
    name = rng.choice(["\x1b[2J\x1b[31mxyz", "xyz", "t", "svq.rotation.index0", "mlp.x\n", "é" * 50, "svq..", "."])
    sections = list(sections)
    sections[i] = (name, sections[i][1])
    return assemble_container(header, sections)


@functools.lru_cache(maxsize=8)
def inflated_file(num_gaussians: int, codec: str) -> bytes:
    """A file declaring many Gaussians in few bytes, its sections consistent with the count: every Gaussian
    identical, so each index stream is one constant symbol and the Morton gaps are all zero (what a
    memory-exhaustion attack would send; :func:`encode_payload` itself refuses to write it)."""
    import tempfile

    from omg4.codec.entropy import encode_indices
    from omg4.codec.sections import encode_f16, encode_xyz_morton

    n = num_gaussians
    with tempfile.TemporaryDirectory() as tmp:
        encode_payload(valid_payload(2, codebook_scale=0.01), Path(tmp) / "base.omg4", codec=codec)
        header, sections = split_container((Path(tmp) / "base.omg4").read_bytes())
    float_encoding = "f16-lzma" if codec == "paper" else "f16-planes"
    replaced = {"xyz": encode_xyz_morton(np.zeros((n, 3), np.float16)) if codec == "ans"
                else encode_f16(np.zeros(3 * n, np.float16), float_encoding),
                "t": encode_f16(np.full(n, 0.5, np.float16), float_encoding)}
    for attr, shapes in header["attributes"].items():
        for j, (k, _) in enumerate(shapes):
            replaced[f"svq.{attr}.index{j}"] = encode_indices(np.zeros(n, np.int64), k, codec)
    header = {**header, "num_gaussians": n,
              "encodings": {**header["encodings"], "t": float_encoding} | ({} if codec == "ans" else
                                                                              {"xyz": float_encoding})}
    return assemble_container(header, [(name, replaced.get(name, data)) for name, data in sections])


MUTATIONS = ("header", "section", "swap", "resplit", "rename", "raw", "inflate")


def forged_files(base: bytes, count: int, seed: int = 0) -> Iterator[tuple[str, bytes]]:
    """``count`` forged variants of the valid container ``base``: ``(mutation kind, file bytes)``.

    Kinds cycle through :data:`MUTATIONS` (headers twice as often: they hold every count and shape);
    all but "raw" carry correct checksums.
    """
    rng = random.Random(seed)
    header, sections = split_container(base)
    kinds = ("header",) + MUTATIONS
    inflated = [inflated_file(n, codec) for n in (10**5, 2 * 10**6) for codec in ("ans", "paper")] if count >= 8 else []
    for k in range(count):
        kind = kinds[k % len(kinds)]
        if kind == "header":
            data = _mutate_header(rng, header, sections)
        elif kind == "section":
            data = _mutate_section(rng, header, sections)
        elif kind == "swap":
            data = _swap_sections(rng, header, sections)
        elif kind == "resplit":
            data = _resplit_sections(rng, header, sections)
        elif kind == "rename":
            data = _rename_section(rng, header, sections)
        elif kind == "inflate" and inflated:
            data = inflated[(k // len(kinds)) % len(inflated)]
        else:
            kind, data = "raw", _damaged_bytes(rng, base)
        yield kind, data


# -------------------------------------------------------------------------- running
def valid_sequence(path: str | Path, segments: int, num_gaussians: int, codec: str = "ans", seed: int = 0,
                   codebook_scale: float = 1.0, precision: CompactGrids = CompactGrids(), key_interval: int = 1) -> bytes:
    """A sequence file (:mod:`omg4.codec.sequence`) of ``segments`` valid models of ``num_gaussians`` each, segments of
    10 frames sharing 2 at 10 fps; every ``key_interval``-th a key segment, each other one predicted from the one
    before (its MLPs and non-rotation codebooks the decoded ones of that segment, but its first MLP weight moved by
    noise, one column of it far, which the compact codec stores as a change; its indices drawn anew; a third of that
    segment's decoded Gaussians carried as they are, :mod:`omg4.codec.carry`); returns the file's bytes."""
    import tempfile

    from omg4.codec.payload import decode_payload
    from omg4.codec.references import reference_sections
    from omg4.codec.sequence import write_sequence

    parts, references, previous = [], [], None
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(segments):
            payload = valid_payload(num_gaussians, seed + i, codebook_scale)
            reference = reference_sections(previous) if i % key_interval else None
            if reference is not None:
                rng = np.random.default_rng(seed + i)
                payload.mlp = {name: reference[f"mlp.{name}"] for name in payload.mlp}
                moved = next(iter(payload.mlp))
                noise = rng.normal(0.0, 0.01, payload.mlp[moved].shape)
                noise[:, 0] *= 1000  # a column whose change needs a coarser step
                payload.mlp[moved] = payload.mlp[moved] + noise
                for attr, qa in payload.attributes.items():
                    if attr not in payload.rotations:
                        qa.codebooks = [reference[f"svq.{attr}.codebook{j}"] for j in range(len(qa.codebooks))]
                        qa.indices = [rng.integers(0, len(cb), num_gaussians) for cb in qa.codebooks]
                count = previous.num_gaussians
                payload.carried = np.sort(rng.choice(count, size=max(1, count // 3), replace=False))
            encode_payload(payload, Path(tmp) / f"s{i}.omg4", codec=codec, precision=precision, reference=reference)
            data = (Path(tmp) / f"s{i}.omg4").read_bytes()
            previous = decode_payload(data, reference)
            parts.append(((8 * i, 8 * i + 10), (0.8 * i, 0.8 * i + 1.0), data))
            references.append(None if reference is None else i - 1)
    write_sequence(path, parts, fps=10.0, references=references, key_interval=key_interval)
    return Path(path).read_bytes()


def exercise(path: str | Path) -> str:
    """What the commands do with an ``.omg4`` file (or sequence): ``omg4 info``'s summary (which decodes every
    segment of a sequence), decoding and loading it, and one 64×48 frame at the middle of its time range. Returns
    "ok"; a bad file raises (CorruptFileError if right)."""
    import torch

    from omg4.codec.sequence import is_sequence
    from omg4.data.scene import Camera
    from omg4.models import load_model
    from omg4.models.summary import describe_file, describe_sequence
    from omg4.render.view import render_view

    (describe_sequence if is_sequence(path) else describe_file)(path)
    model = load_model(path)
    t0, t1 = model.config.time_range
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    viewmat = np.eye(4)
    viewmat[2, 3] = 4.0
    with torch.no_grad():
        render_view(model, Camera(K=K, viewmat=viewmat, width=64, height=48), 0.5 * (t0 + t1))
    return "ok"


__all__ = ["MUTATIONS", "assemble_container", "exercise", "forged_files", "inflated_file", "split_container", "valid_file",
           "valid_payload", "valid_sequence"]
