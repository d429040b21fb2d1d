"""Benchmark: how long ``omg4 demo`` takes, as a user runs it — the whole command in a fresh folder, timed by GNU time
(wall time, peak memory), with the demo's own timings (synthesis, baseline, compression, evaluation, outputs) and
speeds (training steps per second, each compression stage's fine-tuning steps per second) and its headline figures.

    python benchmarks/speed/demo_time.py [--against CHECKOUT] [--repeats 1] [--json PATH]

With ``--against``, that checkout's code runs too (``PYTHONPATH=<CHECKOUT>/src``), the two taking turns, so a slow
spell of a shared host falls on both. Recorded in ``benchmarks/results/demo_time.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"


def run_demo(src: Path, folder: Path) -> dict:
    """One ``omg4 demo --out folder`` on the code in ``src``: GNU time's wall time and peak memory, the results'
    timings, speeds and headline figures."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")])}
    argv = ["/usr/bin/time", "-v", sys.executable, "-m", "omg4", "demo", "--out", str(folder)]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"omg4 demo failed ({src}): {done.stderr[-2000:]}")
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", done.stderr).group(1)
    seconds = sum(float(part) * 60 ** i for i, part in enumerate(reversed(wall.split(":"))))
    rss = float(re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr).group(1)) / 1024
    results = json.loads((folder / "results.json").read_text())
    methods = {name: {k: row[k] for k in ("psnr", "ssim", "lpips_alex", "psnr_dynamic", "fps", "num_gaussians",
                                          "storage_mb") if k in row}
               for name, row in results["methods"].items()}
    timings = {k: v for k, v in results["timings"].items() if not isinstance(v, dict)}
    speeds = results.get("speeds") or {  # code from before the demo recorded its speeds apart
        "train_steps_per_second": timings.pop("train_steps_per_second", None),
        "compress_steps_per_second": results["timings"].get("compress_steps_per_second")
        or {r["stage"]: r.get("steps_per_second") for r in results["compression"].get("stages", [])}}
    return {"wall_time_s": seconds, "max_rss_mb": rss, "timings": timings, "speeds": speeds, "methods": methods,
            "per_frame_difference": {k: v for k, v in results["per_frame_difference"].items()
                                     if not isinstance(v, (list, dict))}}


def commit_of(checkout: Path) -> str:
    out = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=checkout, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", type=Path, default=None, metavar="CHECKOUT",
                    help="also time that checkout's code, the two taking turns (before first)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each side")
    ap.add_argument("--json", type=Path, default=RESULTS / "demo_time.json")
    args = ap.parse_args(argv)
    sides = ([("before", args.against / "src")] if args.against else []) + [("after", REPO / "src")]
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(1, args.repeats + 1):
            for code, src in sides:
                folder = Path(tmp) / f"{code}{rep}"
                run = run_demo(src, folder)
                runs.append({"code": code, "rep": rep, "code_commit": commit_of(src.parent), **run})
                steps = run["speeds"]["compress_steps_per_second"]
                print(f"{code} {rep}: {run['wall_time_s']:.0f} s (training {run['timings']['train_s']:.0f} s, "
                      f"compression {run['timings']['compress_s']:.0f} s); steps/s: training "
                      f"{run['speeds']['train_steps_per_second'] or float('nan'):.1f}, "
                      + ", ".join(f"{k} {v:.1f}" for k, v in steps.items() if v), flush=True)
    command = shlex.join(["python", "benchmarks/speed/demo_time.py", *(sys.argv[1:] if argv is None else argv)])
    save_record(args.json, {"command": command, "method": "omg4 demo in a fresh folder under GNU time, nothing else "
                            "running; with --against the two codes take turns, before first",
                            **({"before_commit": commit_of(args.against)} if args.against else {}), "runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
