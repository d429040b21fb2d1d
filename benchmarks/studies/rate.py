"""Rate of one OMG4 pipeline result under each coder, and the quality each file renders at.

Input: the pipeline's ``.omg4`` written with the paper-faithful coder (fp16 values exactly as
the pipeline produced them; ``omg4 compress --codec paper``, or the ``*_paper_codec.omg4`` copy
that ``omg4 demo`` and ``omg4 bench`` write). The same payload is re-encoded with the "ans"
and "compact" codecs; every file is decoded alone and evaluated on the scene's test views
(PSNR, SSIM and their moving-pixel versions; "ans" holds the paper file's values bit for bit,
so it is not rendered again). Sizes are split as ``omg4 info`` groups them, and summed into
the per-Gaussian sections (positions, time centres, index streams, unit quaternions) and the
fixed part (codebooks, MLP weights, header).

Extra rows (``--also LABEL=FILE``): other files of the same pipeline run, e.g. one an earlier omg4 build wrote
(before/after a coder change), split and evaluated the same way.

Usage: python benchmarks/studies/rate.py PAPER_FILE DATA [--downscale F] [--name NAME] [--json FILE] [--also LABEL=FILE ...]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/rate_<name>.json``; its table is written beside it as ``rate_<name>.md``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

from omg4.app.commands.info import omg4_summary
from omg4.atomic import write_text_atomic
from omg4.codec.payload import decode_payload, encode_payload
from omg4.data import load_scene
from omg4.evaluate import dynamic_masks, evaluate
from omg4.gaussians.backbone import BACKBONES
from omg4.models.compact import load_omg4
from omg4.testing.records import save_record

ROOT = Path(__file__).resolve().parents[2]
PER_GAUSSIAN = ("positions", "time centres", "indices", "quaternions")
QUALITY = ("psnr", "ssim", "psnr_dynamic", "ssim_dynamic")


def split(groups: dict[str, int]) -> tuple[int, int]:
    """(per-Gaussian bytes, fixed bytes) of an ``omg4 info`` grouping."""
    per = sum(size for key, size in groups.items() if any(word in key for word in PER_GAUSSIAN))
    return per, sum(groups.values()) - per


def measure(path: Path, scene=None, masks=None, show: bool = True) -> dict:
    """Size of one ``.omg4`` file split as ``omg4 info`` groups it (its text printed with ``show``) and, given
    ``scene``, its quality on the test views (PSNR, SSIM and their moving-pixel versions over ``masks``)."""
    summary, text = omg4_summary(path)
    if show:
        print(text)
    per, fixed = split(summary["groups"])
    n = summary["num_gaussians"]
    row = {"bytes": summary["total_bytes"], "MB": summary["total_bytes"] / 2**20,
           "bytes_per_gaussian": summary["total_bytes"] / n, "per_gaussian_bytes": per,
           "per_gaussian_B_per_G": per / n, "fixed_bytes": fixed, "groups": summary["groups"], "num_gaussians": n}
    if scene is not None:
        r = evaluate(load_omg4(path), scene.test_views, storage_bytes=summary["total_bytes"], masks=masks,
                     lpips_nets=(), fps_views=1, progress=False)
        row.update({k: r[k] for k in QUALITY})
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("paper_file", type=Path)
    p.add_argument("data", type=Path)
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--name", default="scene")
    p.add_argument("--json", type=Path)
    p.add_argument("--also", action="append", default=[], metavar="LABEL=FILE",
                   help="another file of the same run to report (e.g. written by an earlier build)")
    args = p.parse_args()
    also = dict(item.split("=", 1) for item in args.also)
    out_json = args.json or ROOT / "benchmarks" / "results" / f"rate_{args.name}.json"
    payload = decode_payload(args.paper_file)
    backbone = BACKBONES[payload.meta.get("gaussian_config", {}).get("backbone", "rt4dgs")]
    payload.rotations = payload.rotations or backbone.quaternion_groups()  # files before the header named them
    payload.log_scaled = payload.log_scaled or backbone.log_scaled_groups()
    scene = load_scene(args.data, downscale=args.downscale, progress=False)
    masks = dynamic_masks(scene.test_views)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        files = {"paper": args.paper_file}
        for codec in ("ans", "compact"):
            files[codec] = Path(tmp) / f"{codec}.omg4"
            encode_payload(payload, files[codec], codec=codec)
        files.update({label: Path(path) for label, path in also.items()})
        for codec, path in files.items():  # "ans" holds the paper file's values bit for bit: not rendered again
            rows[codec] = measure(path, None if codec == "ans" else scene, masks)
    rows["ans"].update({k: rows["paper"][k] for k in QUALITY})
    lines = ["| coder | MB | B/G | per-Gaussian B/G | fixed KB | PSNR | SSIM | PSNR dyn |", "|---|---|---|---|---|---|---|---|"]
    for codec, r in rows.items():
        lines.append(f"| {codec} | {r['MB']:.4f} | {r['bytes_per_gaussian']:.1f} | {r['per_gaussian_B_per_G']:.1f} | "
                     f"{r['fixed_bytes'] / 1000:.1f} | {r['psnr']:.3f} | {r['ssim']:.4f} | {r['psnr_dynamic']:.3f} |")
    table = "\n".join(lines)
    print(table)
    delta = {k: rows["compact"][k] - rows["paper"][k] for k in QUALITY}
    print("compact - paper:", {k: round(v, 4) for k, v in delta.items()},
          f"size {rows['compact']['bytes'] / rows['paper']['bytes']:.3f}x")
    result = {"command": shlex.join(["python", "benchmarks/studies/rate.py", *sys.argv[1:]]), "benchmark": "rate",
              "name": args.name, "paper_file": str(args.paper_file), "data": str(args.data),
              "downscale": args.downscale, "num_gaussians": payload.num_gaussians,
              "mode": payload.meta.get("mode", "not recorded in the file"), "rows": rows,
              "compact_minus_paper": delta, "table": table}
    write_text_atomic(out_json.with_suffix(".md"), table + "\n")
    save_record(out_json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
