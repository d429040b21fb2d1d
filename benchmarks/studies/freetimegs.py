"""FreeTimeGS beside Real-Time4DGS, and OMG4 on FreeTimeGS (paper Table 3), on the CPU.

For one scene: train a Real-Time4DGS and a FreeTimeGS baseline with the same command
(same iterations, batch, initial points; FreeTimeGS's fixed budget = ``--budget``), evaluate
both on the test camera (PSNR, SSIM, LPIPS, and PSNR/SSIM over the moving pixels), then run
``omg4 bench`` on the FreeTimeGS baseline (rows: attribute compression only, OMG4 at the L
and S presets). Records the run (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/freetimegs_<scene>.json`` and writes its table to ``freetimegs_<scene>.md``.

Scenes:

* ``demo`` — the demo's synthetic scene (16 cameras × 60 frames, 160×120), 1500 iterations,
  budget 80k (the demo baseline's cap);
* ``basketball`` — N3DV-layout basketball at 320×180 (all 60 frames, cam00 held out), 2000
  iterations, plane-sweep initialization with 40k points (the command of
  ``baseline_quality.py`` at half its iterations), budget 60k.

Usage: ``python benchmarks/studies/freetimegs.py --scene demo|basketball [--work DIR] [--schedule cpu]``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

from omg4.testing.records import save_record
from omg4.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
# scene -> (reader options, training options, budget)
SCENES = {
    "demo": ([], ["--iterations", "1500", "--batch-size", "2", "--max-gaussians", "80000", "--seed", "0"], 80_000),
    "basketball": (["--downscale", "2"], ["--iterations", "2000", "--batch-size", "2", "--num-random-points", "40000"],
                   60_000),
}


def omg4(*args: str) -> float:
    """Run an ``omg4`` command; returns its wall time in seconds."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "omg4", *args], check=True)
    return time.perf_counter() - start


def without_option(options: list[str], flag: str) -> list[str]:
    """``options`` without ``flag`` and its value."""
    if flag not in options:
        return list(options)
    i = options.index(flag)
    return options[:i] + options[i + 2:]


def scene_folder(name: str, work: Path) -> Path:
    if name == "basketball":
        return DATA / "n3dv_basketball"
    folder = work / "scene"
    if not folder.exists():
        omg4("synth", str(folder), "--cameras", "16", "--frames", "60", "--width", "160", "--height", "120")
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="demo")
    ap.add_argument("--work", type=Path, help="working folder (default runs/freetimegs_<scene>)")
    ap.add_argument("--schedule", default="cpu", help="OMG4 fine-tuning lengths for the bench rows")
    ap.add_argument("--rows", default="AC only,OMG4-FTGS-L")
    ap.add_argument("--reuse", action="store_true", help="keep baselines already trained and evaluated in --work")
    ap.add_argument("--paper", action="store_true", help="compress the paper's way (omg4 bench --paper)")
    args = ap.parse_args()
    work = args.work or Path("runs") / f"freetimegs_{args.scene}"
    work.mkdir(parents=True, exist_ok=True)
    reader, training, budget = SCENES[args.scene]
    data = scene_folder(args.scene, work)
    results: dict = {"command": shlex.join(["python", "benchmarks/studies/freetimegs.py", *sys.argv[1:]]), "scene": args.scene,
                     "reader_options": reader, "training_options": training, "budget": budget}
    for backbone in ("rt4dgs", "freetimegs"):
        run = work / backbone
        extra = ["--backbone", backbone] + training
        if backbone == "freetimegs":  # the fixed budget replaces the cap
            extra = without_option(extra, "--max-gaussians") + ["--budget", str(budget)]
        if not (args.reuse and (run / "eval.json").exists()):
            wall = omg4("train", str(data), *reader, *extra, "--preset", "cpu-small", "--checkpoint-interval", "0",
                        "--out", str(run), "--force", "--json", str(run / "train.json"))
            omg4("eval", str(data), *reader, "--model", str(run / "model.safetensors"), "--json",
                 str(run / "eval.json"), "--force")
            (run / "command_s.txt").write_text(f"{wall}\n")
        wall_file = run / "command_s.txt"
        results[backbone] = {"train": json.loads((run / "train.json").read_text()),
                             "train_command_s": float(wall_file.read_text()) if wall_file.exists() else None,
                             "eval": {k: v for k, v in json.loads((run / "eval.json").read_text()).items()
                                      if k != "per_view"}}
    bench = work / "bench"
    wall = omg4("bench", str(data), *reader, "--model", str(work / "freetimegs" / "model.safetensors"), "--out",
                str(bench), "--schedule", args.schedule, "--batch-size", "2", "--baseline-iterations",
                training[training.index("--iterations") + 1], "--rows", args.rows, *(["--paper"] if args.paper else []))
    results["bench"] = json.loads((bench / "bench.json").read_text())
    results["bench_command_s"] = wall
    out = ROOT / "benchmarks" / "results" / f"freetimegs_{args.scene}"
    save_record(out.with_suffix(".json"), results)
    rt, ft = results["rt4dgs"]["eval"], results["freetimegs"]["eval"]
    lines = ["| model | PSNR | SSIM | LPIPS | PSNR dyn | SSIM dyn | #G | MB |", "|---|---|---|---|---|---|---|---|"]
    rows = {"Real-Time4DGS": rt, **results["bench"]}
    for name, r in rows.items():
        lines.append(f"| {name} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips_alex']:.4f} | "
                     f"{r.get('psnr_dynamic', float('nan')):.2f} | {r.get('ssim_dynamic', float('nan')):.4f} | "
                     f"{r['num_gaussians']} | {r['storage_mb']:.3f} |")
    write_text_atomic(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"FreeTimeGS {ft['psnr'] - rt['psnr']:+.2f} dB vs Real-Time4DGS -> {out.with_suffix('.json')}")


if __name__ == "__main__":
    main()
