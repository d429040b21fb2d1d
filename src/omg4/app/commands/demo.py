"""``omg4 demo [--out DIR]``: the whole pipeline on the built-in synthetic scene."""

from __future__ import annotations

import argparse
from pathlib import Path

from omg4.app.commands.common import (add_codec_argument, add_device_arguments, add_paper_argument, device_from_args,
                                      seed)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("omg4_demo"), help="output folder (default: ./omg4_demo)")
    p.add_argument("--quick", action="store_true", help="a tiny run (seconds) to check the installation")
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    add_paper_argument(p)
    add_codec_argument(p, from_settings=True)
    p.add_argument("--equal-training-control", action="store_true",
                   help="also train a baseline for as many steps as the baseline and the compression's fine-tuning "
                        "together, and report OMG4-M against it (about twice the demo's time)")
    add_device_arguments(p, backend=False)


def run(args) -> int:
    from dataclasses import replace

    from omg4.app.demo import QUICK, DemoSettings, run_demo
    from omg4.app.outputs import check_outputs

    check_outputs({"--out": args.out}, folders=["--out"])
    device = device_from_args(args)
    settings = replace(QUICK if args.quick else DemoSettings(), seed=args.seed,
                       equal_training_control=args.equal_training_control, paper=bool(args.paper), codec=args.codec)
    run_demo(args.out, settings, device=device)
    return 0
