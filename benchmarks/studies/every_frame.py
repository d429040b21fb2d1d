"""Every frame of the demo against its baseline: OMG4-M as the paper runs it and with the changes beyond it.

For each seed: the demo's scene (16 cameras × 60 frames, 128×96) and its baseline (1,500 iterations, 60k
Gaussians, batch 2, as ``omg4 demo``), the SD scores once, then the demo's whole OMG4-M compression
(:data:`omg4.app.demo.DEMO_LENGTHS`) from the same baseline and scores once per variant (:data:`VARIANTS`): the
paper's; lifetime-weighted SD scores (:func:`omg4.compress.score.lifetime_weights`); fine-tuning views drawn by
each span's fall below the baseline (:mod:`omg4.compress.time_balance`); both. Each file is decoded and
evaluated on the test camera frame by frame. The record keeps every frame's ΔPSNR (OMG4-M − baseline), the
mean, the worst frame, the 5th percentile and the file size of each, and — the mechanism of the score
weighting — the share of each frame's visible baseline (opacity × temporal marginal, summed over the Gaussians
that pass the cull at the frame's time) that sampling and pruning keep, before any fine-tuning.

Steps already done in ``--work`` (a scene, a baseline, scores, a compressed file) are reused, so a run can be
continued or extended by seeds and variants (``--variants`` with no name only makes the baselines).

Usage: ``python benchmarks/studies/every_frame.py [--seeds 0 1 2] [--variants ...] [--device cpu|cuda]
[--work runs/every_frame]``; about 10 minutes a seed and variant on two cores.
"""

from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the omg4 command: idle threads must not spin

from omg4.testing.records import save_record  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results" / "every_frame_demo.json"
VARIANTS = {"paper": {}, "lifetime": {"score_weighting": "lifetime"}, "deficit": {"time_sampling": "deficit"},
            "lifetime+deficit": {"score_weighting": "lifetime", "time_sampling": "deficit"}}
"""Each variant's :class:`~omg4.compress.pipeline.CompressConfig` fields beside the demo's."""


def baseline_and_scores(root: Path, seed: int, device: str):
    """The seed's scene, trained baseline and SD scores (made once in ``root``)."""
    import torch

    from omg4.compress.score import SDScores, compute_sd_scores
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.train import Trainer, make_config

    scene_dir = root / "scene"
    if not scene_dir.exists():
        write_synthetic_scene(scene_dir, SynthConfig(seed=seed, num_cameras=16, num_frames=60, width=128, height=96),
                              force=True)
    scene = load_scene(scene_dir, progress=False)
    run = root / "base"
    if not (run / "model.safetensors").exists():
        cfg = make_config("cpu-small", iterations=1500, batch_size=2, max_gaussians=60_000, seed=seed,
                          checkpoint_interval=0, device=device)
        torch.manual_seed(seed)
        Trainer(scene, cfg, run, progress=False, log=lambda s: None).run()
    model = load_gaussians(run / "model.safetensors")[0]
    scores_path = root / "scores.npz"
    if scores_path.exists():
        scores = SDScores.load(scores_path, model.num_gaussians)
    else:
        scores = compute_sd_scores(model.to(device), scene.train_views, progress=False, batch_size=2, device=device)
        scores.save(scores_path)
    return scene, model, scores, scores_path


def frame_rows(model, views, device: str) -> list[dict]:
    """:func:`omg4.evaluate.evaluate`'s per-view rows (PSNR; no LPIPS, no timing)."""
    from omg4.evaluate import evaluate

    return evaluate(model, views, time_frames=False, lpips_nets=(), progress=False, fps_views=0,
                    device=device)["per_view"]


def kept_shares(model, scene, scores, weighting: str) -> list[float]:
    """Per frame: the share of the baseline's visible weight that sampling then pruning keep (M preset)."""
    import torch

    from omg4.compress.presets import size_preset
    from omg4.compress.pruning import pruning_mask
    from omg4.compress.sampling import sampling_mask
    from omg4.compress.score import lifetime_weights

    times = sorted({v.timestamp for v in scene.train_views})
    if weighting == "lifetime":
        scores = scores.weighted(lifetime_weights(model, times))
    size = size_preset("M")
    keep = sampling_mask(scores, size.tau_gs)
    keep[keep.clone()] = pruning_mask(scores.select(keep), size.prune_quantile)
    with torch.no_grad():
        geom = model.config.schema.geometry(model.params, model.config, torch.tensor(times, dtype=torch.float32))
        weight = torch.sigmoid(model.params["opacity"][:, 0]).index_select(0, geom.index) * geom.marginal
    kept = weight * keep.index_select(0, geom.index)
    frames = len(times)
    return (torch.zeros(frames).index_add_(0, geom.views, kept.float())
            / torch.zeros(frames).index_add_(0, geom.views, weight.float())).tolist()


def run_seed(root: Path, seed: int, variants: list[str], device: str) -> dict:
    from omg4.app.demo import DEMO_LENGTHS
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.metrics.frames import frame_differences, frame_summary
    from omg4.models import load_model

    scene, model, scores, scores_path = baseline_and_scores(root, seed, device)
    base = frame_rows(model.to(device), scene.test_views, device)
    row = {"seed": seed, "baseline_psnr": statistics.fmean(r["psnr"] for r in base),
           "baseline_gaussians": model.num_gaussians}
    for variant in variants:
        out = root / f"M_{variant}.omg4"
        cfg = CompressConfig(preset="M", lengths=DEMO_LENGTHS, batch_size=2, seed=seed, baseline_iterations=1500,
                             device=device, **VARIANTS[variant])
        if not out.exists():
            compress_to_file(model, scene, cfg, out, scores_path=scores_path)
        delta = frame_differences(frame_rows(load_model(out, device), scene.test_views, device), base, keys=("psnr",))
        summary = frame_summary(delta, "psnr")
        row[variant] = {"file_bytes": out.stat().st_size, "mean_delta_psnr": summary["mean"],
                          "worst_delta_psnr": summary["min"], "worst_frame": summary["worst"]["frame"],
                          "p5_delta_psnr": summary["p5"], "delta_psnr_per_frame": [r["psnr"] for r in delta],
                          "kept_visible_share_per_frame": kept_shares(model, scene, scores, cfg.score_weighting)}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--work", type=Path, default=Path("runs/every_frame"))
    ap.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=["paper", "deficit"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, default=RESULTS)
    args = ap.parse_args()
    rows = [run_seed(args.work / f"seed{seed}", seed, args.variants, args.device) for seed in args.seeds]
    if not args.variants:
        return
    save_record(args.json, {"command": "python benchmarks/studies/every_frame.py --seeds " + " ".join(map(str, args.seeds))
                            + " --variants " + " ".join(args.variants) + f" --device {args.device}",
                            "device": args.device, "seeds": rows})
    print("| seed | variant | mean ΔPSNR | worst frame ΔPSNR (frame) | 5th percentile | file B "
          "| visible weight kept: first / middle / last frame |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        for variant in args.variants:
            r = row[variant]
            shares = r["kept_visible_share_per_frame"]
            print(f"| {row['seed']} | {variant} | {r['mean_delta_psnr']:+.3f} | {r['worst_delta_psnr']:+.3f} "
                  f"({r['worst_frame']}) | {r['p5_delta_psnr']:+.3f} | {r['file_bytes']:,} | "
                  + " / ".join(f"{share:.3f}" for share in (shares[0], shares[len(shares) // 2], shares[-1])) + " |")


if __name__ == "__main__":
    main()
