"""Every frame of a scene against its baseline: OMG4-M as the paper runs it and with the changes beyond it.

Scenes (``--scene``, :data:`SCENES`): ``demo``, the demo's synthetic scene (16 cameras × 60 frames, 128×96) and
baseline (1,500 iterations, 60k Gaussians, batch 2, as ``omg4 demo``) with the demo's compression lengths
(:data:`omg4.app.demo.DEMO_LENGTHS`); ``basketball``, ``../shared/data/n3dv_basketball`` at 320×180, all 60 frames;
``basketball-segment``, its first segment of a long capture (frames 0-49); ``mutant``, D-NeRF's mutant at 200×200.
The real scenes get a cpu-small baseline of 1,500 iterations and the ``cpu`` compression schedule.

For each seed: the scene, its baseline and SD scores once, then OMG4-M from the same baseline and scores once per
variant (:data:`VARIANTS`): the paper's; lifetime-weighted SD scores (:func:`omg4.compress.score.lifetime_weights`);
fine-tuning views drawn by each span's fall below the baseline (:mod:`omg4.compress.time_balance`); both; the
default (both, with pruning's frame floor). Each
file is decoded and evaluated on the test camera frame by frame. The record keeps every frame's ΔPSNR (OMG4-M −
baseline), the mean, the worst frame, the 5th percentile and the file size of each, and — the mechanism of the
score weighting — the share of each frame's visible baseline (opacity × temporal marginal, summed over the
Gaussians that pass the cull at the frame's time) that sampling and pruning keep, before any fine-tuning. With
``--control`` each seed also trains the equal-training control (the baseline's steps plus the compression's
fine-tuning steps, otherwise the same) and every variant's per-frame ΔPSNR against it is kept too.

Steps already done in ``--work`` (a scene, a baseline, a control, scores, a compressed file) are reused, so a run
can be continued or extended by seeds and variants (``--variants`` with no name only makes the baselines).

Usage: ``python benchmarks/studies/every_frame.py [--scene demo] [--seeds 0 1 2] [--variants ...] [--control]
[--device cpu|cuda] [--work runs/every_frame]``; about 10 minutes a seed and variant of the demo on two cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the omg4 command: idle threads must not spin

from omg4.app.demo import DEMO_LENGTHS  # noqa: E402
from omg4.testing.records import save_record  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results"
SHARED = Path(os.environ.get("OMG4_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
VARIANTS = {"paper": {"score_weighting": "paper", "time_sampling": "uniform", "frame_floor": 0.0},
            "lifetime": {"score_weighting": "lifetime", "time_sampling": "uniform", "frame_floor": 0.0},
            "deficit": {"score_weighting": "paper", "time_sampling": "deficit", "frame_floor": 0.0},
            "lifetime+deficit": {"score_weighting": "lifetime", "time_sampling": "deficit", "frame_floor": 0.0},
            "default": {}}
"""Each variant's :class:`~omg4.compress.pipeline.CompressConfig` fields beside the scene's: the paper's selection
and draw (``omg4 compress --paper`` but for the coder: every variant is coded alike), either change beyond it, both,
and the default (both and pruning's frame floor, :func:`omg4.compress.pruning.pruning_mask`)."""
BASELINE_ITERATIONS = 1500


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A scene of the study: where it comes from, its baseline's training settings beside cpu-small with
    :data:`BASELINE_ITERATIONS`, and its compression's settings beside OMG4-M."""

    data: str | None  # a folder under the shared data, or None: the demo's synthetic scene
    reader: dict
    train: dict
    compress: dict


SCENES = {
    "demo": SceneSpec(None, {}, {"batch_size": 2, "strategy": {"max_gaussians": 60_000}}, {"lengths": DEMO_LENGTHS, "batch_size": 2}),
    "basketball": SceneSpec("n3dv_basketball", {"downscale": 2}, {}, {"schedule": "cpu"}),
    "basketball-segment": SceneSpec("n3dv_basketball", {"downscale": 2, "frames": range(0, 50)}, {},
                                    {"schedule": "cpu"}),
    "mutant": SceneSpec("dnerf_mutant", {"downscale": 4}, {}, {"schedule": "cpu"}),
}


def load_study_scene(spec: SceneSpec, root: Path, seed: int):
    """The scene (the demo's synthetic one is written in ``root`` once)."""
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    if spec.data is None:
        folder = root / "scene"
        if not folder.exists():
            write_synthetic_scene(folder, SynthConfig(seed=seed, num_cameras=16, num_frames=60, width=128, height=96),
                                  force=True)
    else:
        folder = SHARED / spec.data
        if not folder.is_dir():
            raise SystemExit(f"this scene needs {folder} (set OMG4_SHARED_DATA)")
    return load_scene(folder, progress=False, **spec.reader)


def compress_config(spec: SceneSpec, seed: int, device: str, variant: str):
    from omg4.compress.pipeline import CompressConfig

    return CompressConfig(preset="M", seed=seed, baseline_iterations=BASELINE_ITERATIONS, device=device, **spec.compress,
                          **VARIANTS[variant])


def trained(spec: SceneSpec, scene, run: Path, seed: int, device: str, iterations: int):
    """A cpu-small baseline of ``iterations`` steps in ``run`` (trained once), as a model; a captured scene's
    starts from ``--init auto``'s points, as ``omg4 train``'s, the demo's from its own points."""
    import torch

    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.train import Trainer, make_config
    from omg4.train.init import initial_points

    if not (run / "model.safetensors").exists():
        cfg = make_config("cpu-small", iterations=iterations, seed=seed, checkpoint_interval=0, device=device,
                          **spec.train)
        torch.manual_seed(seed)
        # a captured scene starts where omg4 train starts it (--init auto: plane-sweep stereo on multi-view video)
        points = None if spec.data is None else initial_points(scene, "auto", cfg, log=lambda s: None)
        Trainer(scene, cfg, run, points=points, progress=False, log=lambda s: None).run()
    return load_gaussians(run / "model.safetensors")[0]


def baseline_and_scores(spec: SceneSpec, root: Path, seed: int, device: str):
    """The seed's scene, trained baseline and SD scores (made once in ``root``)."""
    from omg4.compress.score import SDScores, compute_sd_scores

    scene = load_study_scene(spec, root, seed)
    model = trained(spec, scene, root / "base", seed, device, BASELINE_ITERATIONS)
    scores_path = root / "scores.npz"
    if scores_path.exists():
        scores = SDScores.load(scores_path, model.num_gaussians)
    else:
        batch = spec.train.get("batch_size", 2)
        scores = compute_sd_scores(model.to(device), scene.train_views, progress=False, batch_size=batch,
                                   device=device)
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


def run_seed(spec: SceneSpec, root: Path, seed: int, variants: list[str], device: str, control: bool) -> dict:
    from omg4.compress.api import compress_to_file
    from omg4.metrics.frames import frame_differences, frame_summary
    from omg4.models import load_model

    scene, model, scores, scores_path = baseline_and_scores(spec, root, seed, device)
    base = frame_rows(model.to(device), scene.test_views, device)
    row = {"seed": seed, "baseline_psnr": statistics.fmean(r["psnr"] for r in base),
           "baseline_gaussians": model.num_gaussians, "baseline_iterations": BASELINE_ITERATIONS}
    reference = None
    if control:  # the baseline trained for as long as the baseline and the compression's fine-tuning together
        steps = BASELINE_ITERATIONS + compress_config(spec, seed, device, "paper").fine_tuning_iterations()
        reference = frame_rows(trained(spec, scene, root / "control", seed, device, steps).to(device),
                               scene.test_views, device)
        row.update(control_iterations=steps, control_psnr=statistics.fmean(r["psnr"] for r in reference))
    for variant in variants:
        out = root / f"M_{variant}.omg4"
        cfg = compress_config(spec, seed, device, variant)
        if not out.exists():
            compress_to_file(model, scene, cfg, out, scores_path=scores_path)
        rows = frame_rows(load_model(out, device), scene.test_views, device)
        delta = frame_differences(rows, base, keys=("psnr",))
        summary = frame_summary(delta, "psnr")
        row[variant] = {"mode": dataclasses.replace(cfg, codec="compact").mode(), "file_bytes": out.stat().st_size, "mean_delta_psnr": summary["mean"],
                        "worst_delta_psnr": summary["min"], "worst_frame": summary["worst"]["frame"],
                        "p5_delta_psnr": summary["p5"], "delta_psnr_per_frame": [r["psnr"] for r in delta],
                        "kept_visible_share_per_frame": kept_shares(model, scene, scores, cfg.score_weighting)}
        if reference is not None:
            against = frame_summary(frame_differences(rows, reference, keys=("psnr",)), "psnr")
            row[variant].update(mean_delta_psnr_control=against["mean"], worst_delta_psnr_control=against["min"],
                                worst_frame_control=against["worst"]["frame"])
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=list(SCENES), default="demo")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--work", type=Path, default=Path("runs/every_frame"))
    ap.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=["paper", "deficit"])
    ap.add_argument("--control", action="store_true", help="also train the equal-training control")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, help="record (default benchmarks/results/every_frame_<scene>.json)")
    args = ap.parse_args()
    spec = SCENES[args.scene]
    work = args.work if args.scene == "demo" else args.work / args.scene
    rows = [run_seed(spec, work / f"seed{seed}", seed, args.variants, args.device, args.control)
            for seed in args.seeds]
    if not args.variants:
        return
    command = (f"python benchmarks/studies/every_frame.py --scene {args.scene} --seeds {' '.join(map(str, args.seeds))}"
               f" --variants {' '.join(args.variants)}{' --control' if args.control else ''} --device {args.device}")
    save_record(args.json or RESULTS / f"every_frame_{args.scene}.json",
                {"command": command, "scene": args.scene, "device": args.device, "seeds": rows})
    print("| seed | variant | mean ΔPSNR | worst frame ΔPSNR (frame) | 5th percentile | against the control: mean / "
          "worst (frame) | file B | visible weight kept: first / middle / last frame |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        for variant in args.variants:
            r = row[variant]
            shares = r["kept_visible_share_per_frame"]
            control = (f"{r['mean_delta_psnr_control']:+.3f} / {r['worst_delta_psnr_control']:+.3f} "
                       f"({r['worst_frame_control']})" if "mean_delta_psnr_control" in r else "-")
            print(f"| {row['seed']} | {variant} | {r['mean_delta_psnr']:+.3f} | {r['worst_delta_psnr']:+.3f} "
                  f"({r['worst_frame']}) | {r['p5_delta_psnr']:+.3f} | {control} | {r['file_bytes']:,} | "
                  + " / ".join(f"{share:.3f}" for share in (shares[0], shares[len(shares) // 2], shares[-1])) + " |")


if __name__ == "__main__":
    main()
