"""``omg4 eval DATA --model (CKPT|FILE.omg4)``: the paper's metrics on the test views."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omg4.commands.common import (add_background_argument, add_device_arguments, add_distributed_arguments,
                                  add_force_argument, add_scene_arguments, background_from_args, device_from_args,
                                  int_at_least, load_scene_from_args)
from omg4.data.scene import SPLITS


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--model", required=True, type=Path, help="checkpoint (.safetensors) or compressed .omg4 file")
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
    from omg4.atomic import write_text_atomic
    from omg4.evaluate import evaluate, load_model
    from omg4.outputs import check_outputs

    check_outputs({"--json": args.json}, inputs=[args.data, args.model], datasets=[args.data], force=args.force)
    world, device = distributed.init(device_from_args(args))
    model = load_model(args.model, device)
    scene = distributed.main_first(lambda: load_scene_from_args(args))
    views = scene.split_views(args.split)
    if args.max_views and len(views) > args.max_views:
        views = views[:: -(-len(views) // args.max_views)]
    bg = torch.tensor(background_from_args(args), device=device)
    nets = tuple(n.strip() for n in args.lpips.split(",") if n.strip())
    storage = getattr(model, "storage_bytes", None) or args.model.stat().st_size  # a sequence or run: all its files
    result = evaluate(model, views, storage_bytes=storage, lpips_nets=nets, background=bg,
                      backend=args.backend, device=device)
    if not world.main:
        return 0
    cols = ["psnr", "ssim", *[f"lpips_{n}" for n in nets], "psnr_dynamic", "ssim_dynamic", "fps", "num_gaussians",
            "visible_fraction", "storage_mb", "bitrate_mbps"]
    print(" | ".join(f"{c}" for c in cols))
    print(" | ".join(f"{result[c]:.4g}" if isinstance(result[c], float) else str(result[c]) for c in cols))
    if "boundary" in result:
        b, i = result["boundary"], result["interior"]
        print(f"{result['num_segments']} segments: boundary views {b['num_views']} (PSNR {b['psnr'] or 0:.4g}, SSIM "
              f"{b['ssim'] or 0:.4g}), interior views {i['num_views']} (PSNR {i['psnr'] or 0:.4g}, SSIM "
              f"{i['ssim'] or 0:.4g})")
    if args.json:
        write_text_atomic(args.json, json.dumps({"model": str(args.model), "split": args.split, **result,
                                                "world_size": world.size}, indent=2))
    return 0
