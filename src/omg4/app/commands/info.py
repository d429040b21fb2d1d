"""``omg4 info PATH [--json FILE]``: summary of a dataset folder, a checkpoint or an ``.omg4`` file.

The path's kind picks a summarizer (:data:`SUMMARIZERS`); each returns a JSON-ready dict and
a human-readable text. Dataset summaries come from the readers with ``decode=False``: video
sizes and frame counts are read from stream metadata, no frame is decoded.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Callable

from omg4.app.commands.common import add_format_argument, printable
from omg4.atomic import write_text_atomic
from omg4.errors import OMG4Error


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=Path, help="dataset folder (N3DV, D-NeRF/Blender or Panoptic), checkpoint (.safetensors) or .omg4 file")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the summary as JSON to FILE")
    add_format_argument(parser)
    parser.add_argument("--force", action="store_true",
                        help="allow --json to replace an existing file inside the dataset folder PATH")


def run(args) -> int:
    from omg4.app.outputs import check_outputs

    check_outputs({"--json": args.json}, inputs=[args.path], datasets=[args.path] if args.path.is_dir() else [],
                  force=args.force)
    summary, text = summarize(args.path, format=args.format)
    print(text)
    if args.json:
        write_text_atomic(args.json, json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def summarize(path: Path, **options) -> tuple[dict, str]:
    """(JSON-ready summary, text) of ``path`` by the first summarizer that accepts its kind."""
    for accepts, summarizer in SUMMARIZERS:
        if accepts(path):
            return summarizer(path, **options)
    if not path.exists():
        raise OMG4Error(f"{path} does not exist")
    raise OMG4Error(f"{path} is neither a dataset folder, a .safetensors checkpoint nor an .omg4 file")


def dataset_summary(path: Path, format: str | None = None) -> tuple[dict, str]:
    """Summary of a dataset folder: counts, time range, normalization and every camera.

    JSON keys: ``kind`` ("dataset"), ``path``, ``name``, ``format``, ``num_frames``,
    ``time_range``, ``num_train_views``, ``num_test_views``, ``extent``, ``normalization``
    {scale, rotation 3×3, translation 3}, ``initial_points`` (count or null) and ``cameras``:
    ``[{name, split, K, viewmat, width, height}]`` in the normalized world.
    """
    from omg4.data import load_scene
    from omg4.train.init import auto_initialization

    scene = load_scene(path, format=format, decode=False, progress=False)
    cameras = [{**cam.to_json(), "split": split}
               for split, cams in (("train", scene.train_cameras()), ("test", scene.test_cameras())) for cam in cams]
    summary = {
        "kind": "dataset",
        "path": str(path),
        "name": scene.name,
        "format": scene.format,
        "num_frames": scene.num_frames,
        "time_range": [float(t) for t in scene.time_range],
        "num_train_views": len(scene.train_views),
        "num_test_views": len(scene.test_views),
        "extent": scene.extent if scene.train_views else None,
        "normalization": scene.normalization.to_json(),
        "initial_points": None if scene.initial_points is None else int(len(scene.initial_points.xyz)),
        "auto_initialization": auto_initialization(scene) if scene.train_views else None,
        "cameras": cameras,
    }
    return summary, _dataset_text(summary)


def _dataset_text(s: dict) -> str:
    sizes = sorted({(c["width"], c["height"]) for c in s["cameras"]})
    n_train = sum(c["split"] == "train" for c in s["cameras"])
    n_test = len(s["cameras"]) - n_train
    norm = s["normalization"]
    lines = [
        f"dataset      {printable(s['path'])} ({s['format']})",
        f"frames       {s['num_frames']}, time range [{s['time_range'][0]:g}, {s['time_range'][1]:g}]",
        f"views        {s['num_train_views']} train, {s['num_test_views']} test",
        f"cameras      {n_train} train, {n_test} test; "
        f"{', '.join(f'{w}x{h}' for w, h in sizes[:4])}{' ...' if len(sizes) > 4 else ''}",
        f"normalized   scale {norm['scale']:.6g}, translation "
        f"[{', '.join(f'{x:.4g}' for x in norm['translation'])}]"
        + (f", extent {s['extent']:.4g}" if s["extent"] is not None else ""),
        f"init points  {_initialization_text(s)}",
    ]
    return "\n".join(lines)


def _initialization_text(summary: dict) -> str:
    if summary["initial_points"] is not None:
        return f"{summary['initial_points']} (points3d.ply)"
    made = {"mvs": "plane-sweep stereo of the first frame", "random": "random points in the cameras' common view"}
    return f"none: omg4 train --init auto makes them by {made.get(summary['auto_initialization'], 'no method')}"


def checkpoint_summary(path: Path, **_) -> tuple[dict, str]:
    """Summary of a baseline checkpoint (``.safetensors``, any backbone): count, degrees, time range, size."""
    from omg4.gaussians.checkpoint import describe_checkpoint

    d = {"kind": "checkpoint", "path": str(path), **describe_checkpoint(path)}
    text = "\n".join(f"{k:<20} {printable(v)}" for k, v in d.items() if not isinstance(v, (dict, list)))
    return d, text


def omg4_summary(path: Path, **_) -> tuple[dict, str]:
    """Per-section size breakdown of an ``.omg4`` file and its bits per Gaussian, once the decoder has accepted the
    whole file (:func:`omg4.models.summary.describe_file`). The JSON also carries the container version and each
    section's encoding (which names the compact codec's grids)."""
    from omg4.models.summary import describe_file

    d = describe_file(path)
    n, total, groups = d["num_gaussians"], d["total_bytes"], d["groups"]
    summary = {"kind": "omg4", **{k: v for k, v in d.items() if k != "backbone_title"}, "mode": _mode(d["meta"])}
    lines = [f"{printable(path)}: OMG4 file ({printable(d['backbone_title'])}), codec {printable(d['codec'])} "
             f"(container version {d['version']}), {n} Gaussians, {total} bytes ({d['storage_mb']:.4f} MB), "
             f"{d['bits_per_gaussian'] or 0:.1f} bits/Gaussian, {d['bitrate_mbps']:.3g} Mbit/s",
             f"  mode: {printable(summary['mode'] or 'not recorded (a file from before modes were recorded)')}"]
    for key, size in groups.items():
        lines.append(f"  {printable(key):<22} {size:>10} B  {100 * size / total:5.1f}%  "
                     f"{8 * size / n if n else 0:7.2f} bits/G")
    return summary, "\n".join(lines)


def sequence_summary(path: Path, **_) -> tuple[dict, str]:
    """An ``.omg4`` sequence file: its segments (frames, times, Gaussians, bytes, the segment each is predicted from),
    every one decoded first, the key interval and the bitrate over the capture
    (:func:`omg4.models.summary.describe_sequence`)."""
    from omg4.models.summary import describe_sequence

    d = describe_sequence(path)
    keys = sum(s["reference"] is None for s in d["segments"])
    lines = [f"{printable(path)}: OMG4 sequence of {len(d['segments'])} segments ({keys} key, "
             f"{len(d['segments']) - keys} predicted; key interval {d['key_interval']}), {d['duration_s']:.3g} s at "
             f"{d['fps']:g} fps, {d['total_bytes']} bytes ({d['storage_mb']:.4f} MB), {d['bitrate_mbps']:.3g} Mbit/s, "
             f"{d['num_gaussians']} Gaussians",
             f"  mode: {printable(_mode(d['meta']) or 'not recorded (a file from before modes were recorded)')}"]
    for s in d["segments"]:
        chain = "key" if s["reference"] is None else f"predicted from {s['reference']}"
        chain += f", {s['carried']} of them carried" if s["carried"] else ""
        chain += _carry_decision(s.get("carry"))
        lines.append(f"  segment {s['index']:>3}: frames {s['frames'][0]}-{s['frames'][1] - 1}, "
                     f"{s['num_gaussians']:>8} Gaussians, {s['total_bytes']:>10} B ({printable(s['codec'])}, {chain})")
    return {"kind": "omg4-sequence", **d, "mode": _mode(d["meta"])}, "\n".join(lines)


def _carry_decision(decision) -> str:
    """How a predicted segment's carry was decided, as ``info`` prints it (docs/file-format.md §8b; "" where the file
    records none): the share of its Gaussians the segment before's lasting ones cover and what it carried, or, in a
    file of an earlier build, the share that matched and the tolerance."""
    if not isinstance(decision, dict):
        return ""
    number = lambda key: isinstance(decision.get(key), (int, float)) and not isinstance(decision.get(key), bool)
    setting = printable(decision.get("setting"))
    if number("covered_share"):
        carried = {"lasting": "the lasting ones carried", "none": "none carried"}.get(decision.get("carried"), "")
        return f"; carry {setting}: {100 * decision['covered_share']:.1f} % covered by lasting Gaussians" + (
            f", {carried}" if carried else "")
    if number("matched_share") and number("tolerance"):
        tolerance = decision["tolerance"]
        return f"; carry {setting}: {100 * decision['matched_share']:.1f} % matched, " + (
            f"carried within {tolerance:g}" if tolerance else "none carried")
    return ""


def _mode(meta) -> str | None:
    """The mode a file's metadata records (:mod:`omg4.compress.modes`: ``paper``, ``omg4`` or ``mixed (…)``)."""
    mode = meta.get("mode") if isinstance(meta, dict) else None
    return mode if isinstance(mode, str) else None


def segmented_run_summary(path: Path, **_) -> tuple[dict, str]:
    """A segmented training run: its plan and each segment's final model (or that it is not trained yet)."""
    from omg4.data.segments import read_run_plan
    from omg4.gaussians.checkpoint import describe_checkpoint

    plan = read_run_plan(path)
    segments = []
    for seg in plan["segments"]:
        model = path / seg["folder"] / "model.safetensors"
        info = describe_checkpoint(model) if model.is_file() else None
        segments.append({**seg, "num_gaussians": info and info["num_gaussians"],
                         "file_size_bytes": info and info["file_size_bytes"]})
    lines = [f"{printable(path)}: segmented training run, {len(segments)} segments of {plan['segment_frames']} "
             f"frames sharing {plan['overlap']}, {plan['fps']:g} fps"]
    for s in segments:
        state = f"{s['num_gaussians']} Gaussians" if s["num_gaussians"] is not None else "not trained yet"
        lines.append(f"  segment {s['index']:>3}: frames {s['frames'][0]}-{s['frames'][1] - 1}, {state}")
    return {"kind": "segmented-run", "path": str(path), **plan, "segments": segments}, "\n".join(lines)


def _is_sequence(path: Path) -> bool:
    from omg4.codec.sequence import is_sequence

    return is_sequence(path)


def _is_segmented_run(path: Path) -> bool:
    from omg4.data.segments import is_segmented_run

    return is_segmented_run(path)


def _is_omg4(path: Path) -> bool:
    """An ``.omg4`` container by its magic bytes, as ``omg4 render`` and ``eval`` decide, or a file named ``.omg4``
    (it gets the container's own error). Asked after :func:`_is_checkpoint` (:data:`SUMMARIZERS`), so a checkpoint
    named ``.omg4`` is already taken."""
    from omg4.codec.container import has_magic

    return path.is_file() and (path.suffix == ".omg4" or has_magic(path))


def _is_checkpoint(path: Path) -> bool:
    """A checkpoint: a ``.safetensors`` file without the container's magic, or any file holding an omg4
    checkpoint header (what ``omg4 render`` and ``eval`` load whatever its name)."""
    from omg4.codec.container import has_magic
    from omg4.errors import CorruptFileError
    from omg4.gaussians.checkpoint import describe_checkpoint

    if not path.is_file() or has_magic(path):
        return False
    if path.suffix == ".safetensors":
        return True
    try:
        describe_checkpoint(path)
    except CorruptFileError:
        return False
    return True


#: (accepts(path), summarize(path, **options)) in order; each file kind has one entry.
SUMMARIZERS: list[tuple[Callable[[Path], bool], Callable[..., tuple[dict, str]]]] = [
    (_is_segmented_run, segmented_run_summary),
    (Path.is_dir, dataset_summary),
    (_is_checkpoint, checkpoint_summary),
    (_is_sequence, sequence_summary),
    (_is_omg4, omg4_summary),
]
