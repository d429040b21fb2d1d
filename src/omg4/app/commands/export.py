"""``omg4 export MODEL --out FILE [--time T | --times A:B:N] [--format ply|gltf|splatv|web] [--original-world]``.

``ply``: the standard 3DGS ``.ply`` of one time slice (or ``--times A:B:N``: N slices from A to
B, written as ``<stem>_0000.ply``, ``<stem>_0001.ply``, … beside ``--out``) for the 3DGS viewers
users already have (SuperSplat, PlayCanvas, …), in their y-down world: :func:`omg4.io.ply_export.export_ply`.
``gltf``: the same slices as glTF 2.0 binaries (``.glb``) with Khronos's ``KHR_gaussian_splatting``
(:func:`omg4.io.gltf_export.export_gltf`), for engines that read splats from glTF.
``splatv``: the whole 4D model for the splaTV web viewer (:mod:`omg4.io.splatv`), with the
dataset's cameras as presets when ``--data`` is given. MODEL is a checkpoint or an ``.omg4`` file.
``web``: a static folder (``--out DIR``) that plays the ``.omg4`` file in any browser, decoded and rendered on
the client (:mod:`omg4.io.web_player`), the dataset's cameras as presets when ``--data`` is given.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from omg4.app.commands.common import add_force_argument, finite_float
from omg4.io import EXPORT_FOLDERS, EXPORT_FORMATS

MAX_SLICES = 100_000


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="checkpoint (.safetensors) or compressed .omg4 file")
    p.add_argument("--out", required=True, type=Path,
                   help="output: .ply or .glb (a time slice), .splatv (the 4D model) or, with --format web, a "
                        "folder")
    p.add_argument("--format", choices=sorted({*EXPORT_FORMATS.values(), *EXPORT_FOLDERS}),
                   help="output format (default: from --out's suffix); web: a folder that plays the .omg4 file in a "
                        "browser")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--time", type=finite_float,
                      help="ply, gltf: the slice's time (default: the start of the time range)")
    when.add_argument("--times", metavar="A:B:N",
                      help="ply, gltf: N slices at evenly spaced times from A to B (inclusive)")
    p.add_argument("--original-world", action="store_true",
                   help="ply, gltf: write the dataset's original world as it is (the model file's normalization "
                        "undone) instead of omg4's turned into the format's convention (ply: y down as 3DGS viewers "
                        "read it; gltf: +Y up)")
    p.add_argument("--data", type=Path, help="splatv, web: dataset folder whose cameras become the viewer's presets "
                                             "(default: one camera framing the model)")
    add_force_argument(p)


def _requested_times(args) -> tuple[float, float, int] | None:
    """``--times A:B:N`` parsed (one-line error when malformed), or None."""
    from omg4.errors import OMG4Error

    if args.times is None:
        return None
    try:
        a, b, n = args.times.split(":")
        a, b, n = float(a), float(b), int(n)
    except ValueError:
        raise OMG4Error(f"--times expects A:B:N (two times and a count), got '{args.times}'") from None
    if not (np.isfinite(a) and np.isfinite(b) and a <= b and 1 <= n <= MAX_SLICES):
        raise OMG4Error(f"--times {args.times}: need finite A <= B and 1 <= N <= {MAX_SLICES}")
    return a, b, n


def _times(args, requested: tuple[float, float, int] | None, model_range: tuple[float, float]) -> list[float]:
    from omg4.errors import OMG4Error

    t0, t1 = model_range
    if requested is None:
        t = t0 if args.time is None else args.time
        if not t0 <= t <= t1:
            raise OMG4Error(f"--time {t:g} lies outside the model's time range [{t0:g}, {t1:g}]")
        return [t]
    a, b, n = requested
    if not (t0 <= a and b <= t1):
        raise OMG4Error(f"--times {args.times}: the times must lie in the model's time range [{t0:g}, {t1:g}]")
    return [a + (b - a) * i / max(n - 1, 1) for i in range(n)]


def _outputs(out: Path, count: int) -> list[Path]:
    if count == 1:
        return [out]
    return [out.with_name(f"{out.stem}_{i:04d}{out.suffix}") for i in range(count)]


def run(args) -> int:
    from omg4.app.outputs import check_outputs
    from omg4.errors import OMG4Error

    fmt = args.format or EXPORT_FORMATS.get(args.out.suffix.lower())
    if fmt is None:
        raise OMG4Error(f"--out must end in .ply, .glb or .splatv (or give --format), got '{args.out.name}'")
    if fmt in ("splatv", "web") and (args.time is not None or args.times or args.original_world):
        raise OMG4Error(f"--time, --times and --original-world apply to time slices (ply, gltf); a {fmt} export "
                        "holds the whole 4D model in the normalized world")
    if fmt == "web":
        return _export_web(args)
    if fmt in SLICE_FORMATS and args.data is not None:
        raise OMG4Error(f"--data gives a .splatv its camera presets; a {fmt} slice needs none")
    requested = _requested_times(args)
    planned = _outputs(args.out, requested[2] if requested else 1)
    check_outputs({f"--out ({p.name})": p for p in planned}, inputs=[args.model, args.data],
                  datasets=[args.data] if args.data else [], force=args.force)
    from omg4.models import load_model

    model = load_model(args.model)
    if fmt == "splatv":
        if hasattr(model, "parts_at"):
            raise OMG4Error(f"{args.model} is a sequence of {model.num_segments} segments and a .splatv holds one model:"
                            " export its time slices as .ply (--times A:B:N)")
        return _export_splatv(args, model)
    times = _times(args, requested, model.config.time_range)
    normalization = _normalization(args, model) if args.original_world else None
    from tqdm.auto import tqdm

    from omg4.io.gltf_export import export_gltf
    from omg4.io.ply_export import export_ply

    export_slice = {"ply": export_ply, "gltf": export_gltf}[fmt]
    outputs = _outputs(args.out, len(times))
    counts = [export_slice(path, model, t, normalization=normalization)
              for path, t in tqdm(list(zip(outputs, times)), desc="export", disable=len(times) == 1)]
    world = ("the dataset's original world" if normalization is not None else
             {"ply": "omg4's world turned y down for 3DGS viewers", "gltf": "omg4's world turned +Y up"}[fmt])
    if len(outputs) == 1:
        print(f"wrote {outputs[0]} ({counts[0]} Gaussians at t={times[0]:g}, {world})")
    else:
        print(f"wrote {outputs[0]} … {outputs[-1].name} ({len(outputs)} slices, {min(counts)}–{max(counts)} "
              f"Gaussians, t {times[0]:g} to {times[-1]:g}, {world})")
    return 0


SLICE_FORMATS = ("ply", "gltf")
"""Formats that hold one time slice a file."""


def _normalization(args, model):
    from omg4.data.scene import Normalization
    from omg4.errors import OMG4Error

    meta = model.meta.get("normalization")
    if meta is None:
        raise OMG4Error(f"{args.model} records no scene normalization: cannot write the original world")
    try:
        return Normalization.from_json(meta)
    except (KeyError, TypeError, ValueError) as exc:
        raise OMG4Error(f"{args.model} records an invalid scene normalization ({exc}): cannot write the original "
                        "world") from None


def _export_splatv(args, model) -> int:
    from omg4.data import load_scene
    from omg4.io.splatv import export_splatv
    from omg4.render.paths import bounds_camera

    if args.data is not None:
        cameras = load_scene(args.data, decode=False, progress=False).cameras()
    else:
        cameras = [bounds_camera(model.values["xyz"].cpu().numpy(), 1280, 720)]
    count = export_splatv(args.out, model, cameras)
    print(f"wrote {args.out} ({count} Gaussians, {len(cameras)} camera preset{'s' if len(cameras) > 1 else ''}; "
          "open it in the splaTV viewer)")
    return 0


def _export_web(args) -> int:
    from omg4.app.outputs import check_outputs
    from omg4.codec.container import has_magic
    from omg4.errors import OMG4Error
    from omg4.io.web_player import check_export_folder, export_web

    if not args.model.is_file():
        raise OMG4Error(f"{args.model} does not exist or is not a file")
    if not has_magic(args.model):
        raise OMG4Error(f"{args.model} is not an .omg4 file (wrong magic bytes): the web player plays compressed "
                        "models (omg4 compress writes one)")
    check_outputs({"--out": args.out}, inputs=[args.model, args.data], datasets=[args.data] if args.data else [],
                  folders=["--out"], force=args.force)
    check_export_folder(args.out)
    cameras, held_out = None, 0
    if args.data is not None:
        from omg4.data import load_scene

        scene = load_scene(args.data, decode=False, progress=False)
        cameras, held_out = scene.cameras(), len(scene.test_cameras())
    manifest = export_web(args.out, args.model, cameras, held_out)
    rewritten = " (rewritten losslessly for the browser)" if manifest["rewritten"] else ""
    print(f"wrote {args.out}/ ({manifest['model_bytes']:,} B model{rewritten}; serve it with "
          f"python -m http.server -d {args.out} and open http://localhost:8000)")
    return 0
