"""What an ``.omg4`` file holds, byte by byte (``omg4 info``), once the decoder has accepted all of it.

The file is first decoded exactly as ``render`` and ``eval`` decode it (:func:`omg4.models.compact.load_omg4`:
every checksum, bound and section), so a file the decoder refuses is refused here with the same one-line
:class:`~omg4.errors.CorruptFileError`. Sections are then grouped by what they store — positions, time
centres, each SVQ attribute's indices and codebooks (or its unit quaternions), the MLP weights — plus the
container header; the groups add up to the file size.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from omg4.codec.container import describe_container
from omg4.codec.sequence import SegmentDecoder, read_segment
from omg4.models.compact import CompactModel, load_omg4

_PLAIN_GROUPS = {"xyz": "positions", "t": "time centres", "mlp": "MLPs", "carry": "carried Gaussians"}


def section_group(name: str) -> str:
    """The group a section belongs to: ``svq.scale.index0`` → ``scale indices``, ``quat.rotation`` →
    ``rotation quaternions``, ``xyz`` → ``positions``, ``mlp.dc.0`` → ``MLPs``."""
    parts = name.split(".")
    if parts[0] == "svq" and len(parts) > 2:
        return f"{parts[1]} {'indices' if parts[2].startswith('index') else 'codebooks'}"
    if parts[0] == "quat" and len(parts) > 1:
        return f"{parts[1]} quaternions"
    return _PLAIN_GROUPS.get(parts[0], parts[0])


def describe_file(path: str | os.PathLike, model=None) -> dict:
    """Codec, container version, backbone, Gaussian count (``carried``: how many of them a predicted segment takes
    from the segment before, docs/file-format.md §8b), encodings, total bytes, bits per Gaussian, bitrate (megabits
    per second of the model's time range), bytes per group and per section, and the file's metadata — after
    decoding the whole file (see the module docstring), or given its decoded ``model`` (a predicted segment of a
    sequence, decoded after its reference)."""
    model = model or load_omg4(path)
    d = describe_container(path)
    header = d["header"]
    groups: dict[str, int] = {}
    for name, size in d["sections"].items():
        groups[section_group(name)] = groups.get(section_group(name), 0) + size
    groups["header"] = d["header_bytes"]
    n, total = model.num_gaussians, d["total_bytes"]
    t0, t1 = model.config.time_range
    return {"codec": header.get("codec"), "version": d["version"], "backbone": model.config.backbone,
            "backbone_title": model.config.schema.title, "num_gaussians": n, "encodings": header.get("encodings"),
            "total_bytes": total, "storage_mb": total / 2**20, "bits_per_gaussian": 8 * total / n if n else None,
            "bitrate_mbps": 8 * total / (t1 - t0) / 1e6, "groups": groups, "sections": d["sections"],
            "meta": header.get("meta", {}), "path": str(Path(path)), "carried": header.get("carried", 0)}


__all__ = ["section_group", "describe_file"]


def describe_sequence(path: str | os.PathLike) -> dict:
    """The index of an ``.omg4`` sequence file and each segment's :func:`describe_file` (each segment decoded as
    the decoder does, a predicted one after its reference), with the file's bitrate over the capture and the
    key interval; each segment's ``reference`` is the segment it is predicted from (None: a key segment) and
    ``carried`` how many of its Gaussians are that segment's, as they decoded there (docs/file-format.md §8b), and
    ``carry`` the compressor's decision (docs/file-format.md §8b: the setting, what it carried and, for ``auto`` and ``lasting``, the
    share of the segment's Gaussians the segment before's lasting ones covered; None where the file records none)."""
    decoder = SegmentDecoder(path)
    index = decoder.index
    segments = []
    with tempfile.TemporaryDirectory() as tmp:
        for entry in index.segments:
            part = Path(tmp) / f"segment_{entry.index:03d}.omg4"
            part.write_bytes(read_segment(path, entry))
            d = describe_file(part, CompactModel(decoder.payload(entry.index)))
            segments.append({"index": entry.index, "frames": list(entry.frames), "time_range": list(entry.time_range),
                             "offset": entry.offset, "reference": entry.reference,
                             **{k: d[k] for k in ("codec", "version", "backbone", "num_gaussians", "total_bytes",
                                                  "groups", "carried")}, "carry": d["meta"].get("carry")})
            part.unlink()
    total = index.total_bytes
    return {"layout": "sequence", "path": str(Path(path)), "fps": index.fps, "key_interval": index.key_interval,
            "time_range": list(index.time_range),
            "duration_s": index.duration_s, "total_bytes": total, "storage_mb": total / 2**20,
            "bitrate_mbps": index.bitrate_mbps, "num_gaussians": sum(s["num_gaussians"] for s in segments),
            "segments": segments, "meta": index.meta}


__all__ += ["describe_sequence"]
