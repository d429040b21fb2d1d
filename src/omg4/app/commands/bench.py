"""``omg4 bench DATA --model CKPT --out DIR``: the ablation rows and size presets on one scene."""

from __future__ import annotations

import argparse
from pathlib import Path

from omg4.app.commands.common import (GRID_BITS_HELP, MAX_BATCH_SIZE, add_codec_argument, add_device_arguments, add_paper_argument,
                                  add_distributed_arguments, add_scene_arguments,
                                  compact_grids, device_from_args, int_at_least, load_scene_from_args,
                                  rate_weight_list)
from omg4.compress.pipeline import CompressConfig
from omg4.compress.schedule import SCHEDULES


def configure(p: argparse.ArgumentParser) -> None:
    add_scene_arguments(p)
    p.add_argument("--model", required=True, type=Path, help="trained baseline checkpoint (.safetensors)")
    p.add_argument("--out", type=Path, default=Path("omg4_bench"), help="output folder")
    p.add_argument("--control", type=Path, metavar="CKPT",
                   help="an equal-training control: the same baseline trained for as many steps as the baseline and "
                        "the full pipeline's fine-tuning together (omg4 train ... --iterations N+F; the log names "
                        "N+F), reported beside the baseline so a row's cost is measured against equal training")
    p.add_argument("--schedule", choices=list(SCHEDULES),
                   help="fine-tuning lengths (see omg4 compress --help; default: official on cuda, cpu elsewhere)")
    p.add_argument("--batch-size", type=int_at_least(1, MAX_BATCH_SIZE), default=CompressConfig.batch_size,
                   help=f"views per fine-tuning step (at most {MAX_BATCH_SIZE})")
    p.add_argument("--baseline-iterations", type=int_at_least(1),
                   help="iterations the baseline was trained for (the position learning rate continues its decay; "
                        "default: what its checkpoint records, else "
                        f"{CompressConfig.baseline_iterations})")
    p.add_argument("--rows", help="comma-separated subset of rows (default: all of the baseline's backbone): "
                   + "; ".join(f"{b}: {', '.join(rows)}" for b, rows in _row_names().items()))
    add_paper_argument(p)
    add_codec_argument(p, from_settings=True)
    p.add_argument("--rate-weights", type=rate_weight_list, default=(0.0,), metavar="BETA[,BETA...]",
                   help="beyond the paper: run every row once per rate weight of entropy-constrained codebooks "
                        "(see omg4 compress --help, --rate-weight), e.g. 0,30; the figure then shows each coder's "
                        "rate-distortion front (default 0: the paper's k-means)")
    p.add_argument("--grid-bits", type=compact_grids, nargs="+", metavar="POS,ROT,TIME[,W,LS[,CB[,EX]]]",
                   help="write every row at each of these grids (the first by the pipeline run, the others "
                        "re-encoded from its paper-coder copy; one curve each). " + GRID_BITS_HELP)
    add_device_arguments(p)
    add_distributed_arguments(p, replicas=False)


def _row_names() -> dict[str, list[str]]:
    from omg4.gaussians.backbone import BACKBONES

    return {name: list(b.paper_rows) for name, b in BACKBONES.items()}


def run(args) -> int:
    from omg4 import distributed
    from omg4.app.bench import run_bench
    from omg4.app.outputs import check_outputs
    from omg4.codec.payload import CompactGrids, check_codec
    from omg4.compress.api import baseline_file, read_baseline, trained_iterations
    from omg4.compress.schedule import default_schedule
    from omg4.errors import OMG4Error
    from omg4.gaussians.checkpoint import describe_checkpoint

    grids = tuple(args.grid_bits or (CompactGrids(),))
    codec = CompressConfig(paper=bool(args.paper), codec=args.codec).choice("codec")
    for g in grids:
        check_codec(codec, g)
    check_outputs({"--out": args.out}, inputs=[args.data, args.model, args.control], datasets=[args.data],
                  folders=["--out"])
    world, device = distributed.init(device_from_args(args))
    baseline, metadata = read_baseline(args.model, device)
    control = None
    if args.control is not None:  # its header alone: run_bench loads it once, to evaluate it
        try:
            control_path = baseline_file(args.control)
            described = describe_checkpoint(control_path)
        except OMG4Error as exc:
            raise OMG4Error(f"--control: {exc}") from None
        if described["backbone"] != baseline.config.backbone:
            raise OMG4Error(f"--control {args.control} is a {described['backbone']} model and --model a "
                            f"{baseline.config.backbone} one: the control trains the same backbone longer")
        control = (control_path, trained_iterations(described))
    iterations = args.baseline_iterations or trained_iterations(metadata) or CompressConfig.baseline_iterations
    known = baseline.config.schema.paper_rows
    rows = [r.strip() for r in args.rows.split(",")] if args.rows else None
    unknown = [r for r in rows or [] if r not in known]
    if unknown:
        raise OMG4Error(f"unknown bench rows {unknown} for a {baseline.config.backbone} baseline; known: "
                        f"{', '.join(known)}")
    scene = distributed.main_first(lambda: load_scene_from_args(args))
    run_bench(scene, baseline, args.model, args.out, schedule=args.schedule or default_schedule(device), batch_size=args.batch_size,
              baseline_iterations=iterations, rows=rows, paper=bool(args.paper), codec=codec, backend=args.backend,
              device=device, rate_weights=args.rate_weights, grids=grids, control=control)
    return 0
