"""``omg4 import-rt4dgs CKPT --out MODEL --time-range T0 T1 [--legacy-rotation]``.

Converts an official Real-Time4DGS ``chkpnt*.pth`` into an omg4 checkpoint (rt4dgs §5).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from omg4.app.commands.common import finite_float
from omg4.gaussians.model import SH_DIRECTIONS


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", type=Path, help="official Real-Time4DGS checkpoint (chkpnt*.pth)")
    parser.add_argument("--out", type=Path, required=True, help="output omg4 checkpoint (.safetensors)")
    parser.add_argument("--time-range", type=finite_float, nargs=2, required=True, metavar=("T0", "T1"),
                        help="time_duration the model was trained with (N3V: 0 10, D-NeRF: 0 1)")
    parser.add_argument("--legacy-rotation", action="store_true",
                        help="unflipped 4D rotation of official code before commit 900c592 (September 2024)")
    parser.add_argument("--sh-direction", choices=list(SH_DIRECTIONS), default=SH_DIRECTIONS[0],
                        help="SH view direction from the time-conditioned mean (default) or the canonical mean "
                             "(parity with official CUDA renders)")
    parser.add_argument("--json", type=Path, help="also write the summary as JSON to this file")


def run(args) -> int:
    from omg4.app.outputs import check_outputs
    from omg4.atomic import write_text_atomic
    from omg4.errors import OMG4Error
    from omg4.io.rt4dgs_import import import_rt4dgs_file

    if not args.time_range[1] > args.time_range[0]:
        raise OMG4Error(f"--time-range needs T0 < T1, got {args.time_range[0]:g} {args.time_range[1]:g}")
    check_outputs({"--out": args.out, "--json": args.json}, inputs=[args.checkpoint])

    result = import_rt4dgs_file(args.checkpoint, args.out, tuple(args.time_range),
                                legacy_rotation=args.legacy_rotation, sh_direction=args.sh_direction)
    for w in result.warnings:
        print(f"omg4 import-rt4dgs: warning: {w}", file=sys.stderr)
    m = result.model
    summary = {
        "out": str(args.out),
        "num_gaussians": m.num_gaussians,
        "iteration": result.iteration,
        "active_sh_degree": m.active_sh_degree,
        "active_sh_degree_t": m.active_sh_degree_t,
        "time_range": list(m.config.time_range),
        "rotation_convention": m.config.rotation_convention,
        "warnings": result.warnings,
    }
    print(f"imported {m.num_gaussians} Gaussians (iteration {result.iteration}, SH degrees "
          f"{m.active_sh_degree}+{m.active_sh_degree_t}, {m.config.rotation_convention} rotation) -> {args.out}")
    if args.json:
        write_text_atomic(args.json, json.dumps(summary, indent=2))
    return 0
