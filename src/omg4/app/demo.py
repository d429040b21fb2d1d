"""The main job on a fresh machine: the whole OMG4 mission on the built-in synthetic scene.

synth → train the Real-Time4DGS baseline → compress with the M preset → decode the file
alone → evaluate both on the test camera (full image and moving pixels) → print the table
and write ``results.json``, a rate–distortion figure, a side-by-side video (ground truth |
baseline | OMG4) and the ``.omg4`` file (plus the same model with the paper's coder).

The sizes are chosen so that OMG4-M means what the paper's M means within ten minutes on
two CPU cores: OMG4 prunes a *dense* baseline (the paper's N3DV models hold 2.5 Gaussians
per pixel; M keeps about 5 % of them), so the demo renders 128×96 and lets the baseline grow
to 60k Gaussians (4.9 per pixel) in 1500 iterations, then fine-tunes the compression for
4,700 iterations (the paper's 11,000 scaled to the run, with more weight on the recovery
after pruning and on the MLPs). The M preset's ratios (τ_GS 0.2, p 0.8) are untouched.

The compression's fine-tuning keeps training the baseline's Gaussians, so against an under-trained baseline it
can gain. ``--equal-training-control`` also trains a baseline for as many steps as the baseline and that
fine-tuning together (6,200) and reports OMG4-M against it: what compression costs at equal training.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from omg4.app.report import equal_training_row, format_table, per_frame_plot, rate_distortion_plot
from omg4.atomic import write_text_atomic
from omg4.compress.modes import choice_value
from omg4.compress.schedule import SCHEDULES, StageLengths
from omg4.errors import OMG4Error
from omg4.metrics.frames import frame_differences, per_frame

CONTROL_ROW = equal_training_row("Real-Time4DGS")
"""The results row of the baseline trained for as many steps as the baseline and the compression together."""

DEMO_LENGTHS = StageLengths(sample=300, prune=600, merge=300, appearance=2400, svq3d=400, svq4d=400)
"""Fine-tuning after each OMG4 stage in the demo: 4,700 iterations (the official schedule has 11,000)."""


@dataclass(frozen=True)
class DemoSettings:
    """Sizes of the demo run (defaults: 16 cameras × 60 frames at 128×96, a 60k-Gaussian baseline);
    ``equal_training_control``: also train a baseline for as many steps as the baseline and the compression's
    fine-tuning together, the control that tells what compression costs from what more training gives; ``paper``:
    compress the paper's way (:mod:`omg4.compress.modes`: its selection, view sampling and coder); ``codec``: the
    main file's coder (None: the mode's; the paper coder's copy is written beside it either way)."""

    cameras: int = 16
    frames: int = 60
    width: int = 128
    height: int = 96
    train_iterations: int = 1500
    max_gaussians: int = 60_000
    compress_lengths: StageLengths = DEMO_LENGTHS
    batch_size: int = 2
    seed: int = 0
    smoke_check: bool = False
    equal_training_control: bool = False
    paper: bool = False
    codec: str | None = None


QUICK = DemoSettings(cameras=6, frames=8, width=96, height=64, train_iterations=60, max_gaussians=20_000,
                     compress_lengths=SCHEDULES["tiny"], smoke_check=True)
"""``omg4 demo --quick``: every step of the demo in seconds, to check an installation; its numbers mean nothing."""

SMOKE_CHECK_NOTE = ("--quick is a smoke check of the installation (60 training steps, a few compression steps): its "
                    "numbers are not the method's quality; omg4 demo without --quick measures it (about 4 to 6 minutes "
                    "on two CPU cores)")


def side_by_side_video(path: Path, views, models: list, labels: list[str], fps: float = 30.0,
                       device: torch.device | str = "cpu") -> int:
    """An MP4 of ground truth beside each model's render (models on ``device``) over ``views`` (one test camera)."""
    from omg4.io.video import side_by_side, write_video
    from omg4.render.view import render_image

    def frames():
        for v in views:
            panels = [v.image()] + [render_image(m, v, device=device).cpu().numpy() for m in models]
            yield side_by_side(*panels, labels=labels)

    return write_video(path, frames(), fps=fps)


DEMO_OUTPUTS = ("scene", "baseline", "control", "scene_M.omg4", "scene_M.omg4.scores.npz", "scene_M_paper_codec.omg4",
                "rate_distortion.png", "per_frame.png", "per_frame_control.png", "side_by_side.mp4", "results.json")
"""What ``omg4 demo`` writes into its folder (``scene`` is replaced whole on a re-run)."""


def check_demo_folder(out: str | Path) -> None:
    """Refuse a folder the demo would damage: one holding anything but an earlier demo's outputs (its ``scene``
    written by ``omg4 synth`` — the demo writes it first and replaces it whole —, its ``baseline`` and ``control``
    only a training run's files). Hidden entries (``.name``: stale temporaries of an interrupted run) are ignored."""
    from omg4.data.synthetic.writer import is_synthetic_scene
    from omg4.train.run_state import RUN_FILES

    out = Path(out)
    if not out.is_dir():
        return
    try:
        entries = [p.name for p in out.iterdir() if not p.name.startswith(".")]
        foreign = sorted(name for name in entries if name not in DEMO_OUTPUTS)
        scene, baseline = out / "scene", out / "baseline"
        synth_made = is_synthetic_scene(scene)
        foreign_run = sorted(f"{run.name}/{p.name}" for run in (baseline, out / "control") if run.is_dir()
                             for p in run.iterdir() if p.name not in RUN_FILES)
    except OSError as exc:
        raise OMG4Error(f"cannot look into {out}: {exc}") from None
    if foreign:
        raise OMG4Error(f"{out} holds {foreign[0]!r}, which the demo does not write: choose a new or empty folder")
    if entries and not synth_made:
        raise OMG4Error(f"{out} is not a folder an earlier demo wrote ({scene} is no scene it synthesized): choose a "
                        "new or empty folder")
    if foreign_run:
        raise OMG4Error(f"{out} holds {foreign_run[0]!r}, which the demo's training does not write: choose a new "
                        "or empty folder")


def run_demo(out: str | Path, settings: DemoSettings = DemoSettings(), log=print,
             device: torch.device | str = "cpu") -> dict:
    """Run the whole pipeline into ``out`` computing on ``device``; returns the results written to ``results.json``.

    Refuses (:func:`check_demo_folder`) a folder that holds anything but an earlier demo's outputs."""
    from omg4.compress.api import compress_to_file
    from omg4.compress.pipeline import CompressConfig
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.evaluate import dynamic_masks, evaluate, frame_rates
    from omg4.models import load_model
    from omg4.models.compact import load_omg4
    from omg4.train import Trainer

    out = Path(out)
    check_demo_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}  # seconds of each part
    torch.manual_seed(settings.seed)
    steps = 6 if settings.equal_training_control else 5
    step = iter(range(1, steps + 1))

    t = time.perf_counter()
    log(f"[{next(step)}/{steps}] synthesizing the built-in scene")
    scene_dir = out / "scene"
    write_synthetic_scene(scene_dir, SynthConfig(seed=settings.seed, num_cameras=settings.cameras,
                                                 num_frames=settings.frames, width=settings.width,
                                                 height=settings.height), force=True)
    scene = load_scene(scene_dir)
    timings["synth_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log(f"[{next(step)}/{steps}] training the Real-Time4DGS baseline ({settings.train_iterations} iterations)")
    baseline = Trainer(scene, _baseline_config(settings, settings.train_iterations, device), out / "baseline").run()
    timings["train_s"] = time.perf_counter() - t

    t = time.perf_counter()
    way = ", the paper's way" if settings.paper else ""
    log(f"[{next(step)}/{steps}] compressing with OMG4 (M preset{way})")
    omg4_path = out / "scene_M.omg4"
    ccfg = CompressConfig(paper=settings.paper, preset="M", lengths=settings.compress_lengths, batch_size=settings.batch_size,
                          seed=settings.seed, baseline_iterations=settings.train_iterations,
                          device=str(device), codec=settings.codec)
    codec = ccfg.choice("codec")
    # the same pipeline result with the paper-faithful coder (the main file itself when it is coded so)
    paper_path = omg4_path if codec == choice_value("codec", paper=True) else out / "scene_M_paper_codec.omg4"
    report = compress_to_file(baseline.model, scene, ccfg, omg4_path,
                              paper_copy=None if paper_path == omg4_path else paper_path, progress=True)
    timings["compress_s"] = time.perf_counter() - t
    # the steps' own speed: the training loop's (its checkpoints and test renders included) and each compression
    # stage's fine-tuning (its steps alone)
    speeds = {"train_steps_per_second": baseline.iterations / baseline.wall_time_s,
              "compress_steps_per_second": {r["stage"]: r["steps_per_second"] for r in report["stages"]}}

    control, fine_tuning = None, ccfg.fine_tuning_iterations()
    control_length = settings.train_iterations + fine_tuning
    if settings.equal_training_control:
        t = time.perf_counter()
        log(f"[{next(step)}/{steps}] training the equal-training control: a baseline of {control_length} iterations "
            f"(the baseline's {settings.train_iterations} and the compression's {fine_tuning})")
        control = Trainer(scene, _baseline_config(settings, control_length, device), out / "control").run()
        timings["control_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log(f"[{next(step)}/{steps}] decoding the file alone and evaluating the models on the test camera")
    decoded = load_omg4(omg4_path, device)
    base_render = load_model(baseline.model_path, device)  # render-only from its file, as the .omg4 model is
    masks = dynamic_masks(scene.test_views)  # one dynamic region for both models
    rows = {
        "Real-Time4DGS (baseline)": evaluate(base_render, scene.test_views, masks=masks, time_frames=False,
                                             storage_bytes=baseline.model_path.stat().st_size, device=device),
        "OMG4-M": evaluate(decoded, scene.test_views, storage_bytes=omg4_path.stat().st_size, masks=masks,
                           time_frames=False, device=device),
    }
    rendered = [base_render, decoded]
    if control is not None:
        rendered.append(load_model(control.model_path, device))
        rows[CONTROL_ROW] = evaluate(rendered[-1], scene.test_views, masks=masks, time_frames=False,
                                     storage_bytes=control.model_path.stat().st_size, device=device)
    # the models' frames take turns, so the FPS ratio is not a slow spell of the host
    for row, fps in zip(rows.values(), frame_rates(rendered, scene.test_views, device=device)):
        row.update(fps=fps["fps"], fps_detail={**fps, "timed_with": "models alternating frame by frame"})
    paper_row = evaluate(load_omg4(paper_path, device), scene.test_views, storage_bytes=paper_path.stat().st_size,
                         masks=masks, device=device, lpips_nets=(), time_frames=False)
    rd_points = {**rows, "OMG4-M, paper coder": paper_row}
    timings["eval_s"] = time.perf_counter() - t

    t = time.perf_counter()
    log(f"[{next(step)}/{steps}] writing results, plots and video")
    table = format_table(rows)
    rate_distortion_plot(out / "rate_distortion.png", rd_points, f"omg4 demo ({settings.width}×{settings.height})")
    base_rows, omg4_rows = rows["Real-Time4DGS (baseline)"]["per_view"], rows["OMG4-M"]["per_view"]
    per_frame_plot(out / "per_frame.png", {"baseline": base_rows, "OMG4-M": omg4_rows}, "omg4 demo: every test frame")
    frames = per_frame(frame_differences(omg4_rows, base_rows))
    against_control = None
    if control is not None:
        control_rows = rows[CONTROL_ROW]["per_view"]
        per_frame_plot(out / "per_frame_control.png", {"equal-training control": control_rows, "OMG4-M": omg4_rows},
                       "omg4 demo: every test frame against a baseline trained as long")
        against_control = {"iterations": control_length,
                           "delta_psnr": rows["OMG4-M"]["psnr"] - rows[CONTROL_ROW]["psnr"],
                           "per_frame_difference": per_frame(frame_differences(omg4_rows, control_rows))}
    side_by_side_video(out / "side_by_side.mp4", scene.test_views, [base_render, decoded],
                       ["ground truth", "baseline", "OMG4-M"], device=device)
    timings["outputs_s"] = time.perf_counter() - t
    results = {
        "scene": {"path": str(scene_dir), "cameras": settings.cameras, "frames": settings.frames,
                  "width": settings.width, "height": settings.height},
        "methods": {name: {k: v for k, v in r.items() if k != "per_view"} for name, r in rows.items()},
        "per_view": {name: r["per_view"] for name, r in rows.items()},
        "per_frame_difference": frames,
        **({"equal_training_control": against_control} if against_control is not None else {}),
        "compression": report,
        "paper_codec_mb": paper_path.stat().st_size / 2**20,
        "paper_codec": {k: paper_row[k] for k in ("psnr", "ssim", "psnr_dynamic", "ssim_dynamic", "storage_mb")},
        "dynamic_region": {"fraction": {cam: float(m.mean()) for cam, m in masks.items()},
                           "rule": "pixels whose value leaves the clip's temporal median by > 0.1, dilated 2 px"},
        "device": str(device),
        "mode": report["config"]["mode"],
        "smoke_check": settings.smoke_check,
        "timings": timings,
        "speeds": speeds,
        "table": table,
    }
    write_text_atomic(out / "results.json", json.dumps(results, indent=2))
    print(table)
    base, omg4 = rows["Real-Time4DGS (baseline)"], rows["OMG4-M"]
    print(f"OMG4-M is {base['storage_mb'] / omg4['storage_mb']:.0f}x smaller than the baseline and "
          f"{omg4['psnr'] - base['psnr']:+.2f} dB PSNR ({omg4['psnr_dynamic'] - base['psnr_dynamic']:+.2f} dB on the "
          f"moving pixels); outputs in {out}")
    print(f"every test frame: OMG4-M − baseline {_frame_range(frames, 'per_frame.png')}")
    if against_control is not None:
        print(f"against the equal-training control ({control_length} iterations): OMG4-M "
              f"{against_control['delta_psnr']:+.2f} dB PSNR, every test frame "
              f"{_frame_range(against_control['per_frame_difference'], 'per_frame_control.png')}")
    if settings.smoke_check:
        print(SMOKE_CHECK_NOTE)
    return results


def _frame_range(summary: dict, plot: str) -> str:
    """The PSNR range of a per-frame difference record, worst frame named: ``from −0.64 dB (frame 0) to +0.35 dB
    (plot)``."""
    psnr = summary["psnr"]
    return f"from {psnr['min']:+.2f} dB (frame {psnr['worst']['frame']}) to {psnr['max']:+.2f} dB ({plot})"


def _baseline_config(settings: DemoSettings, iterations: int, device):
    """The demo's baseline training run of ``iterations`` steps (the ``cpu-small`` schedule scaled to them)."""
    from omg4.train import make_config

    return make_config("cpu-small", iterations=iterations, batch_size=settings.batch_size,
                       strategy={"max_gaussians": settings.max_gaussians}, seed=settings.seed, checkpoint_interval=0,
                       device=str(device))
