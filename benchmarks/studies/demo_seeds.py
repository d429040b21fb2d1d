"""The demo's headline figures with their spread: ``omg4 demo`` run with several seeds.

Each seed synthesizes the scene, trains the baseline, compresses it with OMG4-M and evaluates both on
the test camera, exactly as ``omg4 demo --seed S`` does (:func:`omg4.app.demo.run_demo`). The record holds
every seed's row and the mean ± standard deviation (sample, n − 1) of the baseline's and OMG4-M's PSNR,
their difference, SSIM, PSNR on the moving pixels, file sizes, the size ratio and the FPS ratio (the
two models timed together, frame by frame), so a reader can tell a real difference from the spread of
seeds and processors.

With ``--equal-training-control`` each seed also trains a baseline for as many steps as the baseline and the
compression's fine-tuning together (``omg4 demo --equal-training-control``) and the rows add its PSNR, OMG4-M's
difference to it (mean and worst frame) and the baseline's worst frame; the record is
``demo_seeds_control.json``.

Usage: ``python benchmarks/studies/demo_seeds.py [--seeds 0 1 2] [--work runs/demo_seeds] [--equal-training-control]``;
about 15 minutes a seed on two cores (30 with the control).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the omg4 command: idle threads must not spin

from omg4.testing.records import save_record  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results" / "demo_seeds.json"


def row_of(results: dict) -> dict:
    """The figures of one demo run (``results.json``)."""
    base, omg4 = results["methods"]["Real-Time4DGS (baseline)"], results["methods"]["OMG4-M"]
    return {
        "baseline_psnr": base["psnr"], "omg4_psnr": omg4["psnr"], "delta_psnr": omg4["psnr"] - base["psnr"],
        "baseline_ssim": base["ssim"], "omg4_ssim": omg4["ssim"], "delta_ssim": omg4["ssim"] - base["ssim"],
        "baseline_lpips": base["lpips_alex"], "omg4_lpips": omg4["lpips_alex"],
        "baseline_psnr_dynamic": base["psnr_dynamic"], "omg4_psnr_dynamic": omg4["psnr_dynamic"],
        "delta_psnr_dynamic": omg4["psnr_dynamic"] - base["psnr_dynamic"],
        "baseline_gaussians": base["num_gaussians"], "omg4_gaussians": omg4["num_gaussians"],
        "baseline_mb": base["storage_mb"], "omg4_mb": omg4["storage_mb"], "paper_codec_mb": results["paper_codec_mb"],
        "size_ratio": base["storage_mb"] / omg4["storage_mb"],
        "baseline_fps": base["fps"], "omg4_fps": omg4["fps"], "fps_ratio": omg4["fps"] / base["fps"],
        "wall_s": sum(results["timings"].values()),
        "worst_frame_delta_psnr": results["per_frame_difference"]["psnr"]["min"],
        **(control_row(results) if "equal_training_control" in results else {}),
    }


def control_row(results: dict) -> dict:
    """OMG4-M against the equal-training control of one demo run."""
    from omg4.app.demo import CONTROL_ROW

    control, record = results["methods"][CONTROL_ROW], results["equal_training_control"]
    return {"control_iterations": record["iterations"], "control_psnr": control["psnr"],
            "control_ssim": control["ssim"], "control_gaussians": control["num_gaussians"],
            "delta_psnr_control": record["delta_psnr"],
            "worst_frame_delta_psnr_control": record["per_frame_difference"]["psnr"]["min"],
            "control_minus_baseline_psnr": control["psnr"] - results["methods"]["Real-Time4DGS (baseline)"]["psnr"]}


def spread(rows: list[dict]) -> dict:
    """Mean and sample standard deviation of every figure over the seeds."""
    return {key: {"mean": statistics.fmean(r[key] for r in rows),
                  "std": statistics.stdev(r[key] for r in rows) if len(rows) > 1 else 0.0}
            for key in rows[0]}


def main() -> None:
    from omg4.app.demo import DemoSettings, run_demo

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--work", type=Path, default=Path("runs/demo_seeds"))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--equal-training-control", action="store_true",
                    help="also train and report the equal-training control (record demo_seeds_control.json)")
    ap.add_argument("--paper", action="store_true", help="compress the paper's way (omg4 demo --paper)")
    args = ap.parse_args()
    control = args.equal_training_control
    rows = {}
    t0 = time.perf_counter()
    for seed in args.seeds:
        results = run_demo(args.work / f"seed{seed}", DemoSettings(seed=seed, equal_training_control=control,
                                                                   paper=args.paper))
        rows[seed] = row_of(results)
    name = "demo_seeds" + ("_control" if control else "") + ("_paper" if args.paper else "") + ".json"
    save_record(args.json or RESULTS.with_name(name), {
        "command": "python benchmarks/studies/demo_seeds.py --seeds " + " ".join(map(str, args.seeds))
                   + (" --equal-training-control" if control else "") + (" --paper" if args.paper else ""),
        "mode": results["mode"],
        "settings": {k: str(v) for k, v in DemoSettings(paper=args.paper).__dict__.items() if k != "seed"},
        "seeds": {str(s): r for s, r in rows.items()},
        "spread": spread(list(rows.values())),
        "wall_time_s": round(time.perf_counter() - t0, 1),
    })


if __name__ == "__main__":
    main()
