"""Rate–distortion fronts of the compact codec's grids against the paper coder, from an ``omg4 bench`` folder.

Every full-pipeline row's paper-coder copy in the folder (``*_paper_codec.omg4``: the pipeline's fp16 result,
OMG4's own coder) is re-encoded with the "compact" codec at each ``--grid-bits`` setting
(:class:`omg4.codec.payload.CompactGrids`) — what ``omg4 bench --grid-bits`` writes, without running the
pipelines again — and every file is decoded alone and evaluated on the test views. The table lists size, bytes
per Gaussian (all, and the per-Gaussian sections as ``benchmarks/studies/rate.py`` splits them), PSNR and SSIM per
preset, rate weight β and grid; the figure has one panel per preset with every compact file, their Pareto
front and the paper coder's files.
Per preset, ``dominates`` says whether some compact file is smaller than the paper coder's file of the β = 0
run and renders at least as well (PSNR and SSIM, float-order noise aside): a compact front strictly better
than the paper coder's (``--grid-bits 0,16,0,16,0`` holds the paper coder's values exactly).

Usage: python benchmarks/studies/rate_front.py BENCH_DIR DATA [--downscale F] --grid-bits 15,9,10 12,7,7 ... [--name NAME]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/rate_front_<name>.json``; its table and figure are written beside it (``.md``, ``.png``).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

from omg4.testing.records import save_record
from rate import measure
from omg4.app.bench import row_label
from omg4.app.commands.common import compact_grids
from omg4.atomic import write_text_atomic
from omg4.codec.payload import CompactGrids, decode_payload, encode_payload
from omg4.compress.pipeline import FULL_STAGES
from omg4.data import load_scene
from omg4.evaluate import dynamic_masks

ROOT = Path(__file__).resolve().parents[2]


def measure_front(path: Path, scene, masks) -> dict:
    """:func:`rate.measure` of one file, its size in MB as ``storage_mb`` (the bench's name, which the curves use)."""
    row = measure(path, scene, masks, show=False)
    row["storage_mb"] = row.pop("MB")
    return row


SAME_PSNR, SAME_SSIM = 1e-4, 1e-6
"""Differences below these count as equal: the same values stored in another Gaussian order render within 2.4e-5 dB
and 1e-7 SSIM of each other (float sums in another order; the lossless grids 0,16,0,16,0 on the demo's presets)."""


def dominated(results: dict[str, dict]) -> dict[str, bool]:
    """Per preset: whether a compact file is smaller than the paper coder's β = 0 file and renders at least as well
    (PSNR and SSIM, up to :data:`SAME_PSNR` / :data:`SAME_SSIM`)."""
    out = {}
    for r in results.values():
        if r["rate_weight"] == 0:
            mb, psnr, ssim = r["paper_codec_mb"], r["paper_codec_psnr"], r["paper_codec_ssim"]
            out[r["preset"]] = any(c["preset"] == r["preset"] and c["storage_mb"] < mb and c["psnr"] >= psnr - SAME_PSNR
                                   and c["ssim"] >= ssim - SAME_SSIM for c in results.values())
    return out


def pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The (MB, PSNR) points no other point beats on both (smaller and at least as good), by size."""
    front, best = [], -float("inf")
    for mb, psnr in sorted(points, key=lambda p: (p[0], -p[1])):
        if psnr > best:
            front.append((mb, psnr))
            best = psnr
    return front


def front_plot(path: Path, results: dict[str, dict], name: str) -> None:
    """One panel per preset: every compact file (dots), their Pareto front (line) and the paper coder's files of
    the same pipeline runs (squares, the β = 0 one large)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg4.atomic import atomic_path

    presets = sorted({r["preset"] for r in results.values()}, key="LMST".find)
    fig, axes = plt.subplots(1, len(presets), figsize=(3.2 * len(presets), 3.2), squeeze=False)
    for ax, preset in zip(axes[0], presets):
        rows = [r for r in results.values() if r["preset"] == preset]
        compact = [(r["storage_mb"], r["psnr"]) for r in rows]
        ax.scatter(*zip(*compact), s=10, color="tab:blue", alpha=0.35, label="compact files")
        ax.plot(*zip(*pareto(compact)), color="tab:blue", marker="o", markersize=4, label="compact front")
        for r in rows:
            if CompactGrids(**r["grids"]) == CompactGrids():  # one paper copy per run
                ax.scatter(r["paper_codec_mb"], r["paper_codec_psnr"], marker="s", color="tab:red",
                           s=60 if r["rate_weight"] == 0 else 20, zorder=3,
                           label="paper coder" if r["rate_weight"] == 0 else None)
        ax.set_xscale("log")
        ax.set_title(f"OMG4-{preset}", fontsize=9)
        ax.set_xlabel("storage (MB, log scale)", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("PSNR (dB)")
    axes[0][0].legend(fontsize=7, loc="lower right")
    fig.suptitle(f"{name}: compact grids and rate weights against the paper coder", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bench_dir", type=Path)
    p.add_argument("data", type=Path)
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--grid-bits", type=compact_grids, nargs="+", default=[CompactGrids()])
    p.add_argument("--name", default="scene")
    args = p.parse_args()
    out_json = ROOT / "benchmarks" / "results" / f"rate_front_{args.name}.json"
    scene = load_scene(args.data, downscale=args.downscale, progress=False)
    masks = dynamic_masks(scene.test_views)
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for paper_file in sorted(args.bench_dir.glob("*_paper_codec.omg4")):
            payload = decode_payload(paper_file)
            meta = payload.meta
            if tuple(meta.get("stages", ())) != FULL_STAGES:
                continue
            preset, beta = meta["preset"], float(meta.get("rate_weight", 0.0))
            paper = measure_front(paper_file, scene, masks)
            print(f"OMG4-{preset} β={beta:g}: paper coder {paper['storage_mb']:.4f} MB {paper['psnr']:.3f} dB")
            for g in args.grid_bits:
                path = Path(tmp) / "compact.omg4"
                encode_payload(payload, path, codec="compact", precision=g)
                r = measure_front(path, scene, masks)
                r.update(paper_codec_mb=paper["storage_mb"], paper_codec_psnr=paper["psnr"],
                         paper_codec_ssim=paper["ssim"], paper_codec_B_per_G=paper["bytes_per_gaussian"],
                         rate_weight=beta, grids=asdict(g),
                         preset=preset, full_pipeline=True, source=str(paper_file),
                         mode=meta.get("mode", "not recorded in the file"))
                results[row_label(f"OMG4-{preset}", beta, g)] = r
                print(f"  grids {g.label}: {r['storage_mb']:.4f} MB, per-Gaussian {r['per_gaussian_B_per_G']:.1f} B/G, "
                      f"{r['psnr']:.3f} dB, SSIM {r['ssim']:.4f}", flush=True)
    lines = ["| row | MB | B/G | per-Gaussian B/G | fixed KB | PSNR | SSIM | PSNR dyn | paper coder MB | paper PSNR |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['storage_mb']:.4f} | {r['bytes_per_gaussian']:.1f} | {r['per_gaussian_B_per_G']:.1f} | "
                     f"{r['fixed_bytes'] / 1000:.1f} | {r['psnr']:.3f} | {r['ssim']:.4f} | {r['psnr_dynamic']:.3f} | "
                     f"{r['paper_codec_mb']:.4f} | {r['paper_codec_psnr']:.3f} |")
    table = "\n".join(lines)
    fronts = dominated(results)
    print(table)
    print("compact front strictly better than the paper coder's, per preset:", fronts)
    front_plot(out_json.with_suffix(".png"), results, args.name)
    write_text_atomic(out_json.with_suffix(".md"), table + "\n")
    save_record(out_json, {"command": shlex.join(["python", "benchmarks/studies/rate_front.py", *sys.argv[1:]]),
                           "benchmark": "rate_front", "name": args.name, "bench_dir": str(args.bench_dir),
                           "data": str(args.data), "downscale": args.downscale,
                           "grids": [g.label for g in args.grid_bits], "rows": results, "dominates": fronts,
                           "table": table})
    return 0


if __name__ == "__main__":
    sys.exit(main())
