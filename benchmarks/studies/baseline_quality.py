"""Baseline quality runs: train Real-Time4DGS on the shared scenes on the CPU, then evaluate.

* ``n3dv_basketball`` at half resolution (320×180), all 60 frames, cam00 held out;
* ``dnerf_mutant`` at 200×200 (downscale 4), its test split.

Each run uses ``--preset cpu-small --batch-size 2`` and the default ``--init auto`` (basketball,
which has no ``points3d.ply``: plane-sweep stereo of the first frame; ``--init rays`` gave
23.35 dB and ``--init random`` 19.02 dB there at 3000 iterations) and writes the training
summary, the wall time of the whole ``omg4 train`` command (loading, initialization,
training) and the evaluation (PSNR, SSIM, LPIPS-alex, FPS, #Gaussians, MB) as a run of the record
``benchmarks/results/baseline_<scene>.json`` (:func:`environment.save_record`: commit, date, machine).
Usage: ``python benchmarks/studies/baseline_quality.py [--scenes basketball,mutant] [--work DIR]``; about
10–25 minutes per scene on 2 cores.
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

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
# scene -> (folder, reader options, training-only options)
SCENES = {
    "basketball": (DATA / "n3dv_basketball", ["--downscale", "2"],
                   ["--num-random-points", "40000", "--iterations", "4000", "--test-interval", "2000"]),
    "mutant": (DATA / "dnerf_mutant", ["--downscale", "4"], ["--iterations", "3000", "--test-interval", "1000"]),
}


def omg4(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "omg4", *args], check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="basketball,mutant")
    ap.add_argument("--work", type=Path, default=Path("runs/baseline_quality"))
    args = ap.parse_args()
    for name in args.scenes.split(","):
        data, options, train_options = SCENES[name]
        run = args.work / name
        start = time.perf_counter()
        omg4("train", str(data), *options, *train_options, "--out", str(run), "--preset", "cpu-small",
             "--batch-size", "2", "--json", str(run / "train.json"))
        command_wall_s = time.perf_counter() - start
        omg4("eval", str(data), *options, "--model", str(run / "model.safetensors"), "--json",
             str(run / "eval.json"))
        result = {"command": shlex.join(["python", "benchmarks/studies/baseline_quality.py", *sys.argv[1:]]), "init": "auto",
                  **json.loads((run / "eval.json").read_text())}
        result["training"] = json.loads((run / "train.json").read_text())
        result["training"]["command_wall_time_s"] = command_wall_s
        out = ROOT / "benchmarks" / "results" / f"baseline_{name}.json"
        save_record(out, result)
        print(f"{name}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, LPIPS {result['lpips_alex']:.4f}, "
              f"{result['num_gaussians']} Gaussians, train {command_wall_s:.0f} s -> {out}")


if __name__ == "__main__":
    main()
