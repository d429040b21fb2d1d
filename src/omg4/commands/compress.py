"""``omg4 compress DATA --model CKPT --out FILE.omg4``: run the OMG4 pipeline."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omg4.commands.common import (GRID_BITS_HELP, MAX_BATCH_SIZE, add_background_argument, add_codec_argument,
                                  add_device_arguments, add_force_argument, add_rate_weight_argument,
                                  add_scene_arguments, background_from_args, compact_grids, config_from_args,
                                  device_from_args, float_in, int_at_least, load_scene_from_args, seed)
from omg4.compress.pipeline import FULL_STAGES, CompressConfig
from omg4.compress.presets import PRESETS_BY_BACKBONE
from omg4.compress.schedule import MINIMIZING_STAGES, SCHEDULES, STAGE_NAMES


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--model", required=True, type=Path, help="trained baseline checkpoint (.safetensors)")
    p.add_argument("--out", required=True, type=Path,
                   help="output .omg4 file (with --stop-after: a .safetensors checkpoint of the minimized model)")
    p.add_argument("--preset", choices=sorted({name for presets in PRESETS_BY_BACKBONE.values() for name in presets}),
                   help="size preset (paper appendix): L, M, S, T for Real-Time4DGS (default M); L, S for "
                        "FreeTimeGS (default L)")
    p.add_argument("--schedule", choices=list(SCHEDULES),
                   help="fine-tuning lengths: official (1000 per stage, 5000 MLP; the default on cuda), cpu (a fifth; "
                        "the default elsewhere), short (a tenth, 600 MLP), tiny (smoke test)")
    p.add_argument("--stages", default=",".join(FULL_STAGES),
                   help="comma-separated stages in order, from " + ", ".join(STAGE_NAMES) + " (ablations: e.g. "
                        "sample,appearance,svq3d,svq4d or sample+prune,merge,appearance,svq3d,svq4d)")
    p.add_argument("--stop-after", choices=list(MINIMIZING_STAGES),
                   help="stop after this stage and write a checkpoint of the minimized model")
    p.add_argument("--num-merge", type=int_at_least(1), default=CompressConfig.num_merge, help="merge rounds M")
    p.add_argument("--batch-size", type=int_at_least(1, MAX_BATCH_SIZE), default=CompressConfig.batch_size,
                   help=f"views per fine-tuning step (at most {MAX_BATCH_SIZE})")
    p.add_argument("--tau-gs", type=float_in(0.0, 1.0), help="override the preset's sampling ratio, in (0, 1]")
    p.add_argument("--prune-quantile", type=float_in(0.0, 1.0, low_open=False, high_open=True),
                   help="override the preset's pruning quantile p, in [0, 1)")
    add_codec_argument(p)
    p.add_argument("--grid-bits", type=compact_grids, metavar="POS,ROT,TIME[,W,LS[,CB[,EX]]]", help=GRID_BITS_HELP)
    add_rate_weight_argument(p)
    p.add_argument("--scores", type=Path, help="reuse SD scores saved by an earlier run (.npz)")
    p.add_argument("--official-score-quirk", action="store_true",
                   help="accumulate the time gradient without zeroing, as the official release does")
    p.add_argument("--baseline-iterations", type=int_at_least(1), default=CompressConfig.baseline_iterations,
                   help="iterations the baseline was trained for (the position learning rate continues its decay)")
    add_background_argument(p)
    add_device_arguments(p)
    p.add_argument("--seed", type=seed, default=CompressConfig.seed)
    p.add_argument("--json", type=Path, help="write the stage log and sizes as JSON")
    add_force_argument(p)


def run(args) -> int:
    from omg4.atomic import write_text_atomic
    from omg4.codec.payload import CompactGrids, check_codec
    from omg4.compress.api import compress_to_file
    from omg4.compress.schedule import default_schedule
    from omg4.errors import OMG4Error
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.outputs import check_outputs

    precision = args.grid_bits or CompactGrids()
    check_codec(args.codec, precision)
    if args.stop_after and args.grid_bits:
        raise OMG4Error("--grid-bits sets how an .omg4 file is coded; --stop-after writes a checkpoint instead")
    stages = tuple(s.strip() for s in args.stages.split(",") if s.strip())
    computes_scores = args.scores is None and any(s in stages for s in ("sample", "prune", "sample+prune"))
    scores_out = args.out.with_name(args.out.name + ".scores.npz") if computes_scores else None
    check_outputs({"--out": args.out, "--json": args.json, "the SD scores": scores_out},
                  inputs=[args.data, args.model, args.scores], datasets=[args.data], force=args.force)
    device = device_from_args(args)
    scene = load_scene_from_args(args)
    baseline, _ = load_gaussians(args.model, device)
    cfg = config_from_args(CompressConfig, args, stages=stages, schedule=args.schedule or default_schedule(device),
                           device=str(device), background=background_from_args(args))
    report = compress_to_file(baseline, scene, cfg, args.out, codec=args.codec, stop_after=args.stop_after,
                              scores_path=args.scores, precision=precision)
    for r in report["stages"]:
        print(f"  {r['stage']:<13} at iteration {r['iteration']:>6}: {r['num_gaussians']:>8} Gaussians")
    print(f"wrote {args.out} ({report['file_bytes'] / 2**20:.3f} MB, {report['num_gaussians']} Gaussians, "
          f"{report['wall_time_s']:.0f} s)")
    if args.json:
        write_text_atomic(args.json, json.dumps(report, indent=2))
    return 0
