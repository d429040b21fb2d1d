"""``omg4 eval DATA --model (CKPT|FILE.omg4)``: the paper's metrics on the test views."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omg4.app.commands.common import (add_background_argument, add_device_arguments, add_distributed_arguments,
                                  add_force_argument, add_scene_arguments, background_from_args, device_from_args,
                                  int_at_least, load_scene_from_args)
from omg4.data.scene import SPLITS


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--model", required=True, type=Path, action="append",
                   help="checkpoint (.safetensors), compressed .omg4 file or training run folder; given twice, both "
                        "are evaluated and compared frame by frame (the second against the first)")
    p.add_argument("--plot", type=Path, help="PNG of every frame's PSNR (with two models: both, and the difference)")
    p.add_argument("--lpips", default="alex", help="LPIPS backbones, comma-separated: alex, vgg (vgg is slow on CPU)")
    p.add_argument("--split", default=SPLITS[0], choices=list(SPLITS), help="views to evaluate")
    p.add_argument("--max-views", type=int_at_least(1), help="evaluate at most this many views (evenly spaced)")
    add_background_argument(p)
    add_device_arguments(p)
    p.add_argument("--json", type=Path, help="write per-view and mean metrics as JSON")
    add_force_argument(p)
    add_distributed_arguments(p, replicas=False)


def run(args) -> int:
    import torch

    from omg4 import distributed
    from omg4.app.outputs import check_outputs
    from omg4.app.report import per_frame_plot
    from omg4.atomic import write_text_atomic
    from omg4.errors import OMG4Error
    from omg4.evaluate import evaluate
    from omg4.metrics.frames import frame_differences, per_frame
    from omg4.models import load_model

    if len(args.model) > 2:
        raise OMG4Error("--model: give one model, or two to compare")
    check_outputs({"--json": args.json, "--plot": args.plot}, inputs=[args.data, *args.model], datasets=[args.data],
                  force=args.force)
    world, device = distributed.init(device_from_args(args))
    models = [load_model(path, device) for path in args.model]  # a wrong file fails before the videos are decoded
    scene = distributed.main_first(lambda: load_scene_from_args(args))
    views = scene.split_views(args.split)
    if args.max_views and len(views) > args.max_views:
        views = views[:: -(-len(views) // args.max_views)]
    bg = torch.tensor(background_from_args(args), device=device)
    nets = tuple(n.strip() for n in args.lpips.split(",") if n.strip())
    results = []
    for path, model in zip(args.model, models):
        storage = getattr(model, "storage_bytes", None) or _size(path)  # a sequence or run: all its files
        results.append(evaluate(model, views, storage_bytes=storage, lpips_nets=nets, background=bg,
                                backend=args.backend, device=device))
    if not world.main:
        return 0
    cols = ["psnr", "ssim", *[f"lpips_{n}" for n in nets], "psnr_dynamic", "ssim_dynamic", "fps", "num_gaussians",
            "visible_fraction", "storage_mb", "bitrate_mbps"]
    print(" | ".join(["model", *cols]))
    for path, result in zip(args.model, results):
        print(" | ".join([path.name, *(f"{result[c]:.4g}" if isinstance(result[c], float) else str(result[c])
                                       for c in cols)]))
    for path, result in zip(args.model, results):
        _print_frames(path.name, result["per_frame"]["psnr"])
        if "boundary" in result:
            b, i = result["boundary"], result["interior"]
            print(f"{result['num_segments']} segments: boundary views {b['num_views']} (PSNR {b['psnr'] or 0:.4g}, "
                  f"SSIM {b['ssim'] or 0:.4g}), interior views {i['num_views']} (PSNR {i['psnr'] or 0:.4g}, SSIM "
                  f"{i['ssim'] or 0:.4g})")
    record = {"model": str(args.model[0]), "split": args.split, **results[0], "world_size": world.size}
    if len(results) == 2:
        difference = frame_differences(results[1]["per_view"], results[0]["per_view"])
        summary = per_frame(difference)
        _print_frames(f"{args.model[1].name} − {args.model[0].name}", summary["psnr"], difference=True)
        record = {"models": [{"model": str(p), **r} for p, r in zip(args.model, results)], "split": args.split,
                  "difference": {**summary, "per_view": difference}, "world_size": world.size}
    if args.plot:
        per_frame_plot(args.plot, {p.name: r["per_view"] for p, r in zip(args.model, results)})
    if args.json:
        write_text_atomic(args.json, json.dumps(record, indent=2))
    return 0


def _size(path: Path) -> int:
    from omg4.gaussians.checkpoint import run_model

    return run_model(path).stat().st_size


def _print_frames(label: str, summary: dict, difference: bool = False) -> None:
    worst = summary["worst"]
    sign = "+" if difference else ""
    print(f"{label}: every frame's PSNR {summary['min']:{sign}.2f} (worst: {worst['camera']} frame {worst['frame']}) "
          f"to {summary['max']:{sign}.2f} dB, 5th percentile {summary['p5']:{sign}.2f}, spread (std) "
          f"{summary['std']:.2f}")
