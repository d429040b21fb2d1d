"""The paper's measurements on one scene: the baseline, the ablation rows and the size presets.

Rows of a Real-Time4DGS baseline (paper Tab. 4 and Tab. 1): GS+AC; GS+GP+AC; GS+GP+GM+AC
(= OMG4-M); GS and GP applied at once, then GM+AC; and the L / M / S / T presets. Rows of a
FreeTimeGS baseline (paper Tab. 3): attribute compression only, and OMG4 at its L and S
presets. Every row reports PSNR, SSIM,
LPIPS-alex, PSNR and SSIM over the moving pixels, FPS, #Gaussians, MB, bytes per Gaussian
and the compression wall time. The SD scores of the baseline and the dynamic-region masks
are computed once and shared by every row.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from omg4.atomic import write_text_atomic
from omg4.report import format_table, rate_distortion_plot

AC = ("appearance", "svq3d", "svq4d")
FULL = ("sample", "prune", "merge", *AC)
ROWS: dict[str, tuple[str, tuple[str, ...]]] = {
    "GS+AC": ("M", ("sample", *AC)),
    "GS+GP+AC": ("M", ("sample", "prune", *AC)),
    "GS+GP+GM+AC (OMG4-M)": ("M", FULL),
    "(GS+GP)+GM+AC": ("M", ("sample+prune", "merge", *AC)),
    "OMG4-L": ("L", FULL),
    "OMG4-S": ("S", FULL),
    "OMG4-T": ("T", FULL),
}
ROWS_BY_BACKBONE: dict[str, dict[str, tuple[str, tuple[str, ...]]]] = {
    "rt4dgs": ROWS,
    "freetimegs": {"AC only": ("L", AC), "OMG4-FTGS-L": ("L", FULL), "OMG4-FTGS-S": ("S", FULL)},
}


def bench_table(rows: dict[str, dict]) -> str:
    """The paper's columns plus bytes per Gaussian, the same model's size with the paper's coder, and
    compression time."""
    base = format_table(rows).splitlines()
    head = base[0] + " B/Gaussian | MB, paper coder | compress s |"
    sep = base[1] + "---|---|---|"
    lines = [head, sep]
    for line, r in zip(base[2:], rows.values()):
        bpg = f"{r['bytes_per_gaussian']:.1f}" if r.get("bytes_per_gaussian") else "-"
        paper = f"{r['paper_codec_mb']:.3f}" if r.get("paper_codec_mb") else "-"
        secs = f"{r['compress_s']:.0f}" if r.get("compress_s") else "-"
        lines.append(f"{line} {bpg} | {paper} | {secs} |")
    return "\n".join(lines)


def run_bench(scene, baseline, baseline_path: Path, out: Path, *, schedule: str = "cpu", batch_size: int = 4,
              baseline_iterations: int = 30000, rows: list[str] | None = None, codec: str = "compact",
              backend: str = "auto", device: torch.device | str = "cpu", log=print) -> dict:
    """Compress ``baseline`` once per row of its backbone (:data:`ROWS_BY_BACKBONE`) and evaluate everything on
    the test views, computing on ``device``."""
    from omg4.codec.decoder import load_omg4
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.compress.score import compute_sd_scores
    from omg4.evaluate import dynamic_masks, evaluate

    out.mkdir(parents=True, exist_ok=True)
    baseline = baseline.to(device)
    scores_path = out / "sd_scores.npz"
    if not scores_path.exists():
        compute_sd_scores(baseline, scene.train_views, backend=backend, device=device).save(scores_path)
    results: dict[str, dict] = {}
    masks = dynamic_masks(scene.test_views)  # one dynamic region for every row
    log("evaluating the baseline")
    base_name = baseline.config.schema.title
    table_rows = ROWS_BY_BACKBONE[baseline.config.backbone]
    results[base_name] = evaluate(baseline, scene.test_views, storage_bytes=baseline_path.stat().st_size,
                                        backend=backend, device=device, masks=masks)
    for name in rows or list(table_rows):
        preset, stages = table_rows[name]
        log(f"row {name}: preset {preset}, stages {','.join(stages)}")
        path = out / (name.replace(" ", "_").replace("(", "").replace(")", "").replace("+", "-") + ".omg4")
        cfg = CompressConfig(preset=preset, stages=stages, schedule=schedule, batch_size=batch_size,
                             baseline_iterations=baseline_iterations, backend=backend, device=str(device))
        paper_copy = path.with_name(path.stem + "_paper_codec.omg4")
        report = compress_to_file(baseline, scene, cfg, path, codec=codec, scores_path=scores_path,
                                  paper_copy=paper_copy, log=log)
        r = evaluate(load_omg4(path, device), scene.test_views, storage_bytes=path.stat().st_size, backend=backend,
                     device=device, masks=masks)
        r.update(compress_s=report["wall_time_s"], bytes_per_gaussian=report["file_bytes"] / r["num_gaussians"],
                 paper_codec_mb=report["paper_file_bytes"] / 2**20,
                 stages=report["stages"], file=str(path))
        results[name] = r
        write_text_atomic(out / "bench.json", json.dumps(_strip(results), indent=2))
    base = results[base_name]
    base["bytes_per_gaussian"] = baseline_path.stat().st_size / base["num_gaussians"]
    table = bench_table(results)
    write_text_atomic(out / "bench.md", table + "\n")
    write_text_atomic(out / "bench.json", json.dumps(_strip(results), indent=2))
    rate_distortion_plot(out / "rate_distortion.png", results, f"{scene.name}: rate-distortion")
    print(table)
    return results


def _strip(results: dict[str, dict]) -> dict:
    return {k: {kk: vv for kk, vv in v.items() if kk != "per_view"} for k, v in results.items()}


__all__ = ["ROWS", "ROWS_BY_BACKBONE", "bench_table", "run_bench"]
