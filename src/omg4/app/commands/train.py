"""``omg4 train DATA --out RUN_DIR [--backbone freetimegs] [--config FILE] [--set KEY=VALUE]``: train a baseline
(Real-Time4DGS by default). Every :class:`~omg4.train.config.TrainConfig` field is reachable (:mod:`omg4.settings`);
the run folder's ``config.json`` records them all, and ``--config`` of it reproduces the run."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omg4.app.commands.common import (MAX_BATCH_SIZE, add_background_argument, add_device_arguments,
                                  add_distributed_arguments, add_scene_arguments, add_settings_arguments,
                                  device_from_args, fill_device_arguments, int_at_least, load_scene_from_args, seed,
                                  segment_scenes, settings_from_args)
from omg4.gaussians.backbone import BACKBONES
from omg4.train.config import PRESETS, TrainConfig
from omg4.train.init import INIT_MODES
from omg4.train.segmented import PARALLEL_MODES

#: the TrainConfig fields this command has its own flags for
SHORTCUTS = ("iterations", "batch_size", "backbone", "strategy.max_gaussians", "strategy.densify_until",
             "strategy.densify_interval",
             "test_interval", "checkpoint_interval", "num_random_points", "seed", "background", "backend", "device",
             "kernels")


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--out", required=True, type=Path, help="run folder (checkpoints, config, final model.safetensors)")
    p.add_argument("--preset", choices=list(PRESETS),
                   help="training schedule: official (the Real-Time4DGS N3DV schedule, 30k iterations; the default on "
                        "cuda) or cpu-small (3k iterations, at most 60k Gaussians; the default on the CPU)")
    p.add_argument("--iterations", type=int_at_least(1), help="optimizer steps (overrides the preset)")
    p.add_argument("--batch-size", type=int_at_least(1, MAX_BATCH_SIZE), help=f"views per step (at most {MAX_BATCH_SIZE})")
    p.add_argument("--backbone", choices=list(BACKBONES),
                   help="representation: rt4dgs (Real-Time4DGS 4D Gaussians; the default) or freetimegs (FreeTimeGS "
                        "moving Gaussians with a fixed budget and periodic relocation)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--max-gaussians", type=int_at_least(0), help="cap on the Gaussian count (0 = none)")
    budget.add_argument("--budget", type=int_at_least(1), dest="max_gaussians", metavar="N",
                        help="FreeTimeGS: the fixed Gaussian count (default: one per initial point); "
                             "the same as --max-gaussians")
    # settings with flags of their own that --help leaves to --settings
    p.add_argument("--densify-until", type=int_at_least(0), help=argparse.SUPPRESS)
    p.add_argument("--densify-interval", type=int_at_least(1), help=argparse.SUPPRESS)
    p.add_argument("--test-interval", type=int_at_least(0), help=argparse.SUPPRESS)
    p.add_argument("--num-random-points", type=int_at_least(1), help=argparse.SUPPRESS)
    p.add_argument("--checkpoint-interval", type=int_at_least(0),
                   help="write a resumable checkpoint every N iterations (0 = only at the end)")
    p.add_argument("--init", choices=list(INIT_MODES), default="auto",
                   help="initial points: auto (points3d.ply if present, else mvs for multi-view video, else "
                        "random), random, rays (coloured points along the first frame's pixel rays), mvs "
                        "(plane-sweep stereo of the first frame) or colmap (pycolmap triangulation of the "
                        "first frame)")
    p.add_argument("--seed", type=seed, help="random seed")
    add_background_argument(p)
    add_device_arguments(p, from_settings=True)
    run = p.add_mutually_exclusive_group()
    run.add_argument("--resume", action="store_true", help="continue from the run folder's last checkpoint")
    run.add_argument("--force", action="store_true",
                     help="start afresh in an existing run folder: its checkpoints and model are deleted")
    p.add_argument("--json", type=Path, help="write a summary (iterations, wall time, test PSNR) as JSON")
    add_distributed_arguments(p)
    segments = p.add_argument_group("long captures: one model per segment of the capture")
    segments.add_argument("--segment-frames", type=int_at_least(2), metavar="F",
                          help="train one model per segment of F frames (default: one model of the whole capture); "
                               "compress then writes one sequence file")
    segments.add_argument("--overlap", type=int_at_least(0), metavar="K",
                          help="frames neighbouring segments share, blended across (default: F/6, rounded)")
    segments.add_argument("--independent-segments", action="store_true",
                          help="each segment starts afresh and learns every frame from the video (by default a segment "
                               "starts from the Gaussians of the one before that show in its frames, holds at most as many "
                               "Gaussians as the first segment, and learns the frames it shares with the one before "
                               "as the crossfade from that segment's renders into the video, so the blend of the two "
                               "has no jump)")
    segments.add_argument("--parallel", choices=PARALLEL_MODES, default=PARALLEL_MODES[0],
                          help="in a distributed run: every rank trains every segment together (data, the default) or "
                               "each rank trains whole segments on its own (segments)")
    add_settings_arguments(p, TrainConfig, shortcuts=SHORTCUTS, section="train_config",
                           defaults="the defaults shown are the official preset's")


def run(args) -> int:
    from omg4 import distributed
    from omg4.app.outputs import check_outputs
    from omg4.atomic import write_text_atomic
    from omg4.errors import OMG4Error
    from omg4.settings import check_settings, parse_assignments
    from omg4.train import make_config
    from omg4.train.config import default_preset
    from omg4.train.init import initial_points
    from omg4.train.resume import finished, recorded_config, recorded_preset, resumed_config
    from omg4.train.run_state import RUN_FILES, clear_run, holds_files, latest_iteration
    from omg4.train.trainer import Trainer, evaluate_psnr

    check_outputs({"--out": args.out, "--json": args.json}, inputs=[args.data], datasets=[args.data],
                  folders=["--out"], reserved={"--out": RUN_FILES}, force=args.force)
    if holds_files(args.out) and not (args.resume or args.force):
        raise OMG4Error(f"{args.out} already holds a training run: add --resume to continue it or --force to "
                        "start afresh (its checkpoints and model are deleted)")
    settings = settings_from_args(args, TrainConfig, section="train_config")
    recorded = recorded_config(args.out) if args.resume else None
    device_named = args.device is not None or "device" in settings
    if recorded is not None:  # where the run computed, unless this command says otherwise
        for name in ("device", "backend"):
            if getattr(args, name) is None and name not in settings:
                setattr(args, name, getattr(recorded, name))
    fill_device_arguments(args, settings)
    try:
        world, device = distributed.init(device_from_args(args))
    except OMG4Error as exc:
        if recorded is None or device_named:
            raise
        raise OMG4Error(f"{exc}; the run trained on {recorded.device}: add --device cpu to resume it here") from None
    flags = {"iterations": args.iterations, "batch_size": args.batch_size, "strategy.max_gaussians": args.max_gaussians,
             "backbone": args.backbone, "strategy.densify_until": args.densify_until,
             "strategy.densify_interval": args.densify_interval}
    flags.update(dict(test_interval=args.test_interval, checkpoint_interval=args.checkpoint_interval,
                      num_random_points=args.num_random_points, seed=args.seed, kernels=args.kernels,
                      background=(1.0, 1.0, 1.0) if args.white_background else None))
    asked = {**settings, **{k: v for k, v in flags.items() if v is not None}}
    if recorded is not None:
        overrides = check_settings(TrainConfig, parse_assignments(args.settings))
        given = {k: v for k, v in asked.items() if k not in overrides}
        preset = recorded_preset(args.out)
        cfg = resumed_config(recorded, asked={**given, "device": str(device), "backend": args.backend},
                             preset=args.preset, recorded_preset=preset, overrides=overrides)
        if world.main:
            changed = f"; changed by --set: {', '.join(f'{k}={v!r}' for k, v in overrides.items())}" if overrides else ""
            print(f"resuming {args.out} with its recorded settings ({cfg.iterations:,} iterations of {cfg.batch_size} "
                  f"views{changed})")
        if not args.segment_frames and finished(args.out, cfg):
            if world.main:
                print(f"{args.out} is finished ({cfg.iterations:,} of {cfg.iterations:,} iterations, "
                      f"{args.out / 'model.safetensors'}): nothing to resume")
            return 0
    else:
        preset = args.preset or default_preset(device)
        cfg = make_config(preset, {**asked, "backend": args.backend, "device": str(device)})
        if world.main:
            origin = "" if args.preset else f" (the default on {device.type}; --preset chooses)"
            budget = cfg.strategy.max_gaussians
            cap = f"at most {budget:,} Gaussians" if budget else "no cap on the Gaussian count"
            print(f"preset {preset}{origin}: {cfg.iterations:,} iterations of {cfg.batch_size} views, {cap}")
    if args.segment_frames:
        return _train_segments(args, cfg, world, preset)
    if args.overlap is not None:
        raise OMG4Error("--overlap needs --segment-frames")
    scene = distributed.main_first(lambda: load_scene_from_args(args, background=cfg.background))
    resuming = args.resume and latest_iteration(args.out) is not None
    points = None if resuming else initial_points(scene, args.init, cfg)  # a resumed run has its Gaussians
    if args.force and world.main:  # only once the initial points exist: a failing initialization keeps the old run
        clear_run(args.out)
    distributed.barrier()
    trainer = Trainer(scene, cfg, args.out, points=points, resume=args.resume, check_replicas=args.check_replicas,
                      preset=preset)
    result = trainer.run()
    test_psnr = evaluate_psnr(result.model, scene.test_views, trainer.background, cfg.backend, device)
    camera = scene.train_views[0].camera
    per_pixel = result.model.num_gaussians / (camera.width * camera.height)
    summary = {"iterations": result.iterations, "wall_time_s": result.wall_time_s,
               "num_gaussians": result.model.num_gaussians, "gaussians_per_pixel": per_pixel,
               "image_size": [camera.width, camera.height], "test_psnr": test_psnr,
               "model": str(result.model_path), "world_size": world.size, "history": result.history}
    if not world.main:
        return 0
    print(f"trained {result.iterations} iterations in {result.wall_time_s:.0f} s: {result.model.num_gaussians} "
          f"Gaussians ({per_pixel:.2f} per pixel at {camera.width}x{camera.height}), test PSNR {test_psnr:.2f} dB "
          f"-> {result.model_path}")
    if args.json:
        write_text_atomic(args.json, json.dumps(summary, indent=2))
    return 0


def _train_segments(args, cfg, world, preset: str | None) -> int:
    """``--segment-frames``: plan the segments of the capture and train one model per segment (resumable)."""
    from omg4 import distributed
    from omg4.atomic import write_text_atomic
    from omg4.train.init import initial_points
    from omg4.train.run_state import clear_run
    from omg4.train.segmented import plan_capture, train_segments, write_plan

    capture = load_scene_from_args(args, decode=False, background=cfg.background)
    plan = plan_capture(capture, args.segment_frames, args.overlap)
    if args.force and world.main:
        import shutil

        for seg in plan["segments"]:
            clear_run(args.out / seg["folder"])
        (args.out / "segments.json").unlink(missing_ok=True)
        shutil.rmtree(args.out / "checkpoints", ignore_errors=True)
    distributed.barrier()
    write_plan(args.out, plan)
    distributed.barrier()

    summaries = train_segments(args.out, plan, cfg, segment_scenes(args, cfg.background), lambda scene: initial_points(scene, args.init, cfg),
                               parallel=args.parallel, check_replicas=args.check_replicas,
                               teach=not args.independent_segments, preset=preset)
    if not world.main:
        return 0
    print(f"trained {len(summaries)} segments of {args.segment_frames} frames (sharing {plan['overlap']}) -> {args.out}")
    for s in summaries:
        print(f"  segment {s['index']}: frames {s['frames'][0]}-{s['frames'][1] - 1}, {s['num_gaussians']} Gaussians")
    if args.json:
        write_text_atomic(args.json, json.dumps({"segments": summaries, "plan": plan, "world_size": world.size},
                                                indent=2))
    return 0
