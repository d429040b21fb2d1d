"""What a predicted segment's base layer (:mod:`omg4.compress.stream`) saves and costs, per setting.

One predicted segment of a segmented training run (``--segment``, default 1), compressed from the segment before as
it decoded from an existing sequence file (so the key segment is the same in every row), once per ``--variants``
entry: a ``carry`` setting (``0``, ``lasting``, ``auto`` or a tolerance), optionally with ``COVER``,
``LASTING_MARGINAL`` or ``STILL`` (:mod:`omg4.compress.stream`) set for that
run (``lasting:cover=0.5``, ``lasting:margin=0.8``, ``lasting:still=1e9`` for no limit on motion). Each row: the
segment's bytes, its own and carried Gaussians, and PSNR / SSIM on the test camera over the segment's frames. Every
compression runs in a fresh process, one at a time.

Usage::

    python benchmarks/studies/base_layer.py DATA --downscale 2 --run runs/segments/basketball24/run \\
        --sequence runs/segments/basketball24/sequence_M_key3.omg4 --name basketball24 \\
        --variants 0 lasting lasting:still=1e9 lasting:cover=0.5,still=1e9
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from omg4.testing.records import save_record

RESULTS = Path(__file__).resolve().parents[1] / "results"
KNOBS = {"cover": "COVER", "margin": "LASTING_MARGINAL", "still": "STILL"}
"""Variant knobs and the constants of omg4.compress.stream they set (the base layer's cover, the lasting rule)."""


def set_knobs(knobs: dict[str, float]) -> None:
    """Set each constant of omg4.compress.stream named in ``knobs`` (one it does not have stops the study: a
    constant that moved would otherwise be set where nothing reads it)."""
    import omg4.compress.stream as stream

    for name, value in knobs.items():
        if not hasattr(stream, name):
            raise SystemExit(f"omg4.compress.stream has no constant {name}")
        setattr(stream, name, value)


def parse_variant(text: str) -> tuple[str, dict[str, float]]:
    """``SETTING[:knob=value,...]`` → (setting, {constant name: value})."""
    setting, _, rest = text.partition(":")
    knobs = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in KNOBS:
            raise SystemExit(f"unknown knob {key!r} in {text!r} (choose from {', '.join(KNOBS)})")
        knobs[KNOBS[key]] = float(value)
    return setting, knobs


def one(args, setting: str, knobs: dict[str, float], out: Path) -> dict:
    """Compress and score the segment for one variant (in this process)."""
    import time

    from omg4.codec.payload import decode_payload
    from omg4.codec.references import reference_sections
    from omg4.codec.sequence import SegmentDecoder
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.compress.stream import SegmentBefore
    from omg4.data import load_scene
    from omg4.data.segments import read_run_plan, shared_frames
    from omg4.evaluate import evaluate
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.models.compact import CompactModel
    from omg4.optimize.teaching import taught_by

    set_knobs(knobs)
    plan = read_run_plan(args.run)
    k = args.segment
    before = SegmentDecoder(args.sequence).payload(k - 1)
    seg, seg_before = plan["segments"][k], plan["segments"][k - 1]
    scene = load_scene(args.data, downscale=args.downscale, frames=range(*seg["frames"]), progress=False)
    carry = setting if setting in ("auto", "lasting") else float(setting)
    cfg = CompressConfig(preset=args.preset, schedule=args.schedule, carry=carry)
    taught = taught_by(scene, CompactModel(before, "cpu"), shared_frames(seg_before, seg), background=cfg.background)
    baseline, _ = load_gaussians(Path(args.run) / seg["folder"] / "model.safetensors")
    t0 = time.perf_counter()
    report = compress_to_file(baseline, taught, cfg, out, before=SegmentBefore.decoded(before), log=lambda *_: None)
    seconds = time.perf_counter() - t0
    model = CompactModel(decode_payload(out.read_bytes(), reference_sections(before)), "cpu")
    result = evaluate(model, scene.test_views, storage_bytes=out.stat().st_size, lpips_nets=(), progress=False)
    return {"variant": args.variant, "carry": setting, **{k.lower(): v for k, v in knobs.items()},
            "file_bytes": out.stat().st_size, "own_gaussians": report["num_gaussians"] - report["carried_gaussians"],
            "carried_gaussians": report["carried_gaussians"], "psnr": result["psnr"], "ssim": result["ssim"],
            "compress_s": round(seconds, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("--run", required=True, help="the segmented training run")
    ap.add_argument("--sequence", required=True, help="a sequence file of that run (the segment before decodes from it)")
    ap.add_argument("--segment", type=int, default=1)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--preset", default="M")
    ap.add_argument("--schedule", default="short")
    ap.add_argument("--variants", nargs="+", default=["0", "lasting"])
    ap.add_argument("--name", default="basketball24")
    ap.add_argument("--work", type=Path, default=Path("runs/base_layer"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--variant", help=argparse.SUPPRESS)  # one variant, in a child process
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    if args.variant:
        setting, knobs = parse_variant(args.variant)
        print(json.dumps(one(args, setting, knobs, args.work / f"segment{args.segment}_{args.variant}.omg4")))
        return
    rows = []
    for variant in args.variants:
        parse_variant(variant)  # a wrong one stops before any run
        out = subprocess.run([sys.executable, __file__, *sys.argv[1:], "--variant", variant], check=True,
                             stdout=subprocess.PIPE, text=True).stdout  # a failing run's error shows
        rows.append(json.loads(out.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{variant}: {r['file_bytes']:,} B, {r['own_gaussians']:,} own + {r['carried_gaussians']:,} carried, "
              f"PSNR {r['psnr']:.3f}, SSIM {r['ssim']:.4f}", flush=True)
    save_record(args.json or RESULTS / f"base_layer_{args.name}.json",
                {"data": args.data, "run": str(args.run), "sequence": str(args.sequence), "segment": args.segment,
                 "preset": args.preset, "schedule": args.schedule, "rows": rows})


if __name__ == "__main__":
    main()
