"""Baseline quality runs of issue 4: train Real-Time4DGS on the shared scenes on the CPU, then evaluate.

* ``n3dv_basketball`` at half resolution (320×180), all 60 frames, cam00 held out;
* ``dnerf_mutant`` at 200×200 (downscale 4), its test split.

Each run uses ``--preset cpu-small --iterations 3000 --batch-size 2`` (basketball with
``--init rays``; ``--init random`` gave 19.02 dB there) and writes the
training summary and the evaluation (PSNR, SSIM, LPIPS-alex, FPS, #Gaussians, MB) to
``benchmarks/results/baseline_<scene>.json``. Usage: ``python benchmarks/baseline_quality.py
[--scenes basketball,mutant] [--work DIR]``; about 10–20 minutes per scene on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
# scene -> (folder, reader options, training-only options)
SCENES = {
    "basketball": (DATA / "n3dv_basketball", ["--downscale", "2"], ["--num-random-points", "30000", "--init", "rays"]),
    "mutant": (DATA / "dnerf_mutant", ["--downscale", "4"], []),
}


def omg4(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "omg4.cli", *args], check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="basketball,mutant")
    ap.add_argument("--work", type=Path, default=Path("runs/baseline_quality"))
    args = ap.parse_args()
    for name in args.scenes.split(","):
        data, options, train_options = SCENES[name]
        run = args.work / name
        omg4("train", str(data), *options, *train_options, "--out", str(run), "--preset", "cpu-small", "--iterations", "3000",
             "--batch-size", "2", "--test-interval", "1000", "--json", str(run / "train.json"))
        omg4("eval", str(data), *options, "--model", str(run / "model.safetensors"), "--json",
             str(run / "eval.json"))
        result = json.loads((run / "eval.json").read_text())
        result["training"] = json.loads((run / "train.json").read_text())
        out = ROOT / "benchmarks" / "results" / f"baseline_{name}.json"
        out.write_text(json.dumps(result, indent=2))
        print(f"{name}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, LPIPS {result['lpips_alex']:.4f}, "
              f"{result['num_gaussians']} Gaussians, train {result['training']['wall_time_s']:.0f} s -> {out}")


if __name__ == "__main__":
    main()
