"""Decode throughput of the N3DV reader (frame cache) on ``n3dv_basketball``.

cold:  ``load_scene`` into an empty cache folder (PyAV decode + RGB conversion + memmap write),
       then read every frame back as float32 through ``View.image()``;
warm:  ``load_scene`` again on the filled cache and read every frame as float32.
Throughput counts output frames and uint8 RGB megabytes (H × W × 3 bytes per frame).

Usage: python benchmarks/speed/decode.py [--data DIR] [--downscale F] [--cameras N] [--json FILE]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in ``benchmarks/results/decode.json``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

from omg4.testing.records import save_record
from omg4.data import load_scene

ROOT = Path(__file__).resolve().parents[2]


def run_once(data: Path, cache: Path, downscale: float, cameras: list[str] | None) -> dict:
    """Seconds to load (decode into the cache when cold) and to read all frames as float32."""
    t0 = time.perf_counter()
    scene = load_scene(data, downscale=downscale, cameras=cameras, cache_dir=cache, progress=False)
    t1 = time.perf_counter()
    views = scene.train_views + scene.test_views
    for v in views:
        v.image()
    t2 = time.perf_counter()
    cam = views[0].camera
    return {"frames": len(views), "width": cam.width, "height": cam.height, "load_s": t1 - t0, "read_s": t2 - t1}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "n3dv_basketball")
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--cameras", type=int, default=0, help="use only the first N cameras (0: all)")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "decode.json")
    args = p.parse_args()
    if not args.data.exists():
        print(f"data folder {args.data} not found", file=sys.stderr)
        return 2
    cameras = [v.stem for v in sorted(args.data.glob("*.mp4"))][: args.cameras] if args.cameras else None
    with tempfile.TemporaryDirectory() as cache:
        cold = run_once(args.data, Path(cache), args.downscale, cameras)
        warm = run_once(args.data, Path(cache), args.downscale, cameras)
        cache_mb = sum(f.stat().st_size for f in Path(cache).iterdir()) / 1e6
    rows = []
    for name, r in (("cold", cold), ("warm", warm)):
        mb = r["frames"] * r["width"] * r["height"] * 3 / 1e6
        total = r["load_s"] + r["read_s"]
        rows.append({"mode": name, "frames": r["frames"], "width": r["width"], "height": r["height"],
                     "load_s": round(r["load_s"], 4), "read_float32_s": round(r["read_s"], 4),
                     "total_s": round(total, 4), "frames_per_s": round(r["frames"] / total, 1),
                     "MB_per_s": round(mb / total, 1)})
    print(f"N3DV decode throughput: {args.data.name}, downscale {args.downscale:g}, cache {cache_mb:.1f} MB")
    print(f"{'mode':<6} {'frames':>7} {'size':>9} {'load s':>8} {'read s':>8} {'frames/s':>9} {'MB/s':>8}")
    for r in rows:
        print(f"{r['mode']:<6} {r['frames']:>7} {r['width']:>4}x{r['height']:<4} {r['load_s']:>8.2f} "
              f"{r['read_float32_s']:>8.2f} {r['frames_per_s']:>9.1f} {r['MB_per_s']:>8.1f}")
    result = {"command": shlex.join(["python", "benchmarks/speed/decode.py", *sys.argv[1:]]), "benchmark": "decode",
              "data": args.data.name, "downscale": args.downscale,
              "cache_MB": round(cache_mb, 1),
              "results": rows}
    save_record(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
