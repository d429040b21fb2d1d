"""Benchmark: what the ``.splatv`` export's colour approximation costs, against our renderer, on the test views.

Exports a model (checkpoint or ``.omg4``) with :func:`omg4.io.splatv.export_splatv`, reads the file
back, draws each test view as splaTV's shader does (:func:`omg4.io.splatv.splatv_state`: linear
motion, temporal opacity, one RGB per Gaussian) with our rasterizer, and reports the PSNR of those
images against our renders of the model (and of both against the ground truth). Geometry maps
exactly; the loss is the view- and time-dependent colour that one RGBA8 per Gaussian cannot hold.

    python benchmarks/studies/splatv_fidelity.py DATA --models baseline.safetensors model.omg4 [--name demo]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/splatv_fidelity_<name>.json``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from omg4.testing.records import save_record

RESULTS = Path(__file__).resolve().parents[1] / "results"


def measure(path: Path, scene) -> dict:
    from omg4.io.splatv import export_splatv, read_splatv, splatv_state
    from omg4.metrics import psnr
    from omg4.models import load_model
    from omg4.render.api import rasterize
    from omg4.render.view import render_image, view_image

    model = load_model(path)
    t0, t1 = model.config.time_range
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "m.splatv"
        export_splatv(out, model, scene.test_cameras())
        size = out.stat().st_size
        _, fields = read_splatv(out)
    rows = []
    for view in scene.test_views:
        cam = view.camera
        means, covars, colors, opacities = splatv_state(fields, (view.timestamp - t0) / (t1 - t0))
        approx = rasterize(*(torch.as_tensor(a, dtype=torch.float32) for a in (means, covars, colors, opacities)),
                           torch.as_tensor(cam.viewmat, dtype=torch.float32), torch.as_tensor(cam.K, dtype=torch.float32),
                           cam.width, cam.height, backend="cpu").image.clamp(0, 1)
        ours = render_image(model, view, backend="cpu")
        gt = view_image(view)
        rows.append((psnr(approx, ours), psnr(ours, gt), psnr(approx, gt)))
    a = np.array(rows)
    return {"model": str(path), "num_gaussians": model.num_gaussians, "splatv_bytes": size,
            "psnr_splatv_vs_ours": float(a[:, 0].mean()), "psnr_ours_vs_gt": float(a[:, 1].mean()),
            "psnr_splatv_vs_gt": float(a[:, 2].mean()), "views": len(rows)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--models", type=Path, nargs="+", required=True)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--name", default="demo", help="the scene's name in the record's file name")
    args = ap.parse_args()
    from omg4.data import load_scene

    scene = load_scene(args.data, downscale=args.downscale, progress=False)
    results = [measure(m, scene) for m in args.models]
    for r in results:
        print(f"{r['model']}: {r['num_gaussians']} G, .splatv {r['splatv_bytes'] / 2**20:.2f} MB; PSNR splatv vs ours "
              f"{r['psnr_splatv_vs_ours']:.2f} dB; vs ground truth: ours {r['psnr_ours_vs_gt']:.2f}, splatv "
              f"{r['psnr_splatv_vs_gt']:.2f} dB")
    save_record(RESULTS / f"splatv_fidelity_{args.name}.json", {
        "command": shlex.join(["python", "benchmarks/studies/splatv_fidelity.py", *sys.argv[1:]]), "scene": args.name,
        "downscale": args.downscale, "rows": results})


if __name__ == "__main__":
    main()
