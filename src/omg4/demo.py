"""The main job on a fresh machine: the whole OMG4 mission on the built-in synthetic scene.

synth → train the Real-Time4DGS baseline → compress with the M preset → decode the file
alone → evaluate both on the test camera → print the paper's table and write
``results.json``, a rate–distortion plot, a side-by-side video (ground truth | baseline |
OMG4) and the ``.omg4`` file. Schedules are scaled so the whole run fits in about ten
minutes on two CPU cores.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from omg4.atomic import write_text_atomic
from omg4.compress.schedule import SCHEDULES, StageLengths

TABLE_COLUMNS = (("PSNR", "psnr", "{:.2f}"), ("SSIM", "ssim", "{:.4f}"), ("LPIPS", "lpips_alex", "{:.4f}"),
                 ("FPS", "fps", "{:.1f}"), ("#Gaussians", "num_gaussians", "{:,}"), ("MB", "storage_mb", "{:.3f}"))


@dataclass(frozen=True)
class DemoSettings:
    """Sizes of the demo run (defaults: 16 cameras × 60 frames at 256×192)."""

    cameras: int = 16
    frames: int = 60
    width: int = 256
    height: int = 192
    train_iterations: int = 1500
    max_gaussians: int = 20_000
    compress_lengths: StageLengths = SCHEDULES["short"]
    batch_size: int = 2
    seed: int = 0


QUICK = DemoSettings(cameras=6, frames=8, width=96, height=64, train_iterations=60,
                     compress_lengths=SCHEDULES["tiny"])


def format_table(rows: dict[str, dict]) -> str:
    """A markdown table with the paper's columns, one row per method."""
    head = "| method | " + " | ".join(c for c, _, _ in TABLE_COLUMNS) + " |"
    sep = "|---" * (len(TABLE_COLUMNS) + 1) + "|"
    lines = [head, sep]
    for name, r in rows.items():
        cells = [fmt.format(r[key]) if r.get(key) is not None else "-" for _, key, fmt in TABLE_COLUMNS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def rate_distortion_plot(path: Path, points: dict[str, dict], title: str) -> None:
    """PSNR against storage (MB, log axis) for each method, written as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg4.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=120)
    for name, r in points.items():
        ax.scatter([r["storage_mb"]], [r["psnr"]], s=40)
        ax.annotate(name, (r["storage_mb"], r["psnr"]), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("storage (MB)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def side_by_side_video(path: Path, views, models: list, labels: list[str], fps: float = 30.0,
                       device: torch.device | str = "cpu") -> int:
    """An MP4 of ground truth beside each model's render (models on ``device``) over ``views`` (one test camera)."""
    from omg4.evaluate import render_image
    from omg4.io.video import side_by_side, write_video

    def frames():
        for v in views:
            panels = [v.image()] + [render_image(m, v, device=device).cpu().numpy() for m in models]
            yield side_by_side(*panels, labels=labels)

    return write_video(path, frames(), fps=fps)


def run_demo(out: str | Path, settings: DemoSettings = DemoSettings(), log=print,
             device: torch.device | str = "cpu") -> dict:
    """Run the whole pipeline into ``out`` computing on ``device``; returns the results written to ``results.json``."""
    from omg4.codec.decoder import load_omg4
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.evaluate import evaluate
    from omg4.train import Trainer, make_config

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    torch.manual_seed(settings.seed)

    t = time.perf_counter()
    log("[1/5] synthesizing the built-in scene")
    scene_dir = out / "scene"
    write_synthetic_scene(scene_dir, SynthConfig(seed=settings.seed, num_cameras=settings.cameras,
                                                 num_frames=settings.frames, width=settings.width,
                                                 height=settings.height), force=True)
    scene = load_scene(scene_dir)
    timings["synth_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log(f"[2/5] training the Real-Time4DGS baseline ({settings.train_iterations} iterations)")
    cfg = make_config("cpu-small", iterations=settings.train_iterations, batch_size=settings.batch_size,
                      max_gaussians=settings.max_gaussians, seed=settings.seed, checkpoint_interval=0,
                      device=str(device))
    baseline = Trainer(scene, cfg, out / "baseline").run()
    timings["train_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log("[3/5] compressing with OMG4 (M preset)")
    omg4_path = out / "scene_M.omg4"
    ccfg = CompressConfig(preset="M", lengths=settings.compress_lengths, batch_size=settings.batch_size,
                          seed=settings.seed, baseline_iterations=settings.train_iterations,
                          device=str(device))
    report = compress_to_file(baseline.model, scene, ccfg, omg4_path)
    timings["compress_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log("[4/5] decoding the file alone and evaluating both models on the test camera")
    decoded = load_omg4(omg4_path, device)
    rows = {
        "Real-Time4DGS (baseline)": evaluate(baseline.model, scene.test_views,
                                             storage_bytes=baseline.model_path.stat().st_size, device=device),
        "OMG4-M": evaluate(decoded, scene.test_views, storage_bytes=omg4_path.stat().st_size, device=device),
    }
    timings["eval_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log("[5/5] writing results, plot and video")
    table = format_table(rows)
    rate_distortion_plot(out / "rate_distortion.png", rows, f"omg4 demo ({settings.width}×{settings.height})")
    side_by_side_video(out / "side_by_side.mp4", scene.test_views, [baseline.model, decoded],
                       ["ground truth", "baseline", "OMG4-M"], device=device)
    timings["outputs_s"] = time.perf_counter() - t
    results = {
        "scene": {"path": str(scene_dir), "cameras": settings.cameras, "frames": settings.frames,
                  "width": settings.width, "height": settings.height},
        "methods": {name: {k: v for k, v in r.items() if k != "per_view"} for name, r in rows.items()},
        "per_view": {name: r["per_view"] for name, r in rows.items()},
        "compression": report,
        "device": str(device),
        "timings": timings,
        "table": table,
    }
    write_text_atomic(out / "results.json", json.dumps(results, indent=2))
    print(table)
    ratio = rows["Real-Time4DGS (baseline)"]["storage_mb"] / rows["OMG4-M"]["storage_mb"]
    print(f"OMG4-M is {ratio:.0f}x smaller than the baseline; outputs in {out}")
    return results
