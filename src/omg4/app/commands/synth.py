"""``omg4 synth OUT_DIR``: write the built-in procedural dynamic scene in N3DV layout."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from omg4.app.commands.common import seed


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("out_dir", type=Path, help="folder to create (camXX.mp4, poses_bounds.npy, points3d.ply, synth.json)")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the scene and rig (default 0)")
    p.add_argument("--cameras", type=int, default=16, help="number of cameras, cam00 = test camera (default 16)")
    p.add_argument("--frames", type=int, default=60, help="frames per video (default 60)")
    p.add_argument("--width", type=int, default=256, help="image width, even (default 256)")
    p.add_argument("--height", type=int, default=192, help="image height, even (default 192)")
    p.add_argument("--fps", type=float, default=30.0, help="video frame rate; timestamps are frame / fps (default 30)")
    p.add_argument("--points", type=int, default=4000, help="points in points3d.ply (default 4000)")
    p.add_argument("--crf", type=int, default=17, help="H.264 quality, 0 = lossless (default 17)")
    p.add_argument("--force", action="store_true", help="replace OUT_DIR if it exists and is not empty")


def run(args) -> int:
    from omg4.app.outputs import check_outputs
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    check_outputs({"OUT_DIR": args.out_dir}, folders=["OUT_DIR"])
    config = SynthConfig(seed=args.seed, num_cameras=args.cameras, num_frames=args.frames, width=args.width,
                         height=args.height, fps=args.fps, num_points=args.points, crf=args.crf)
    start = time.perf_counter()
    result = write_synthetic_scene(args.out_dir, config, force=args.force)
    elapsed = time.perf_counter() - start
    print(f"wrote {len(result.cameras)} cameras x {config.num_frames} frames ({config.width}x{config.height}, "
          f"{config.fps:g} fps) and {result.num_points} points to {result.path} in {elapsed:.1f} s")
    return 0
