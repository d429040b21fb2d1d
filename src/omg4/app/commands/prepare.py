"""``omg4 prepare SRC --out DATA``: raw multi-view videos (or per-camera image folders) → a dataset in N3DV layout,
synchronized, calibrated with pycolmap, checked and undistorted (:mod:`omg4.prepare`; docs/prepare.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from omg4.app.commands.common import float_in, int_at_least


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", type=Path, help="folder of videos (any names, any container and codec PyAV reads) or of "
                                          "per-camera image folders")
    p.add_argument("--out", required=True, type=Path,
                   help="dataset folder to write (camXX.mp4, poses_bounds.npy, points3d.ply, calibration.json, "
                        "rig.png)")
    p.add_argument("--sync", default="auto", metavar="auto|audio|none|FILE",
                   help="synchronization: audio (cross-correlate the audio tracks), none (the videos are "
                        "synchronized), a FILE of frames to skip per camera (JSON {name: frames} or lines 'name "
                        "frames'), or auto (audio when every video has sound, else none; the default)")
    p.add_argument("--test-camera", metavar="NAME",
                   help="the held-out camera, cam00 of the dataset (a file name or its stem; default: the most "
                        "central camera)")
    p.add_argument("--shared-intrinsics", action="store_true",
                   help="one focal length and distortion for every camera (identical cameras)")
    p.add_argument("--instants", type=int_at_least(2),
                   help="instants of the shared span the calibration pools (default: about 4,000 image pairs' "
                        "worth, from 10 for 30 cameras to 30 for 12 or fewer)")
    p.add_argument("--max-features", type=int_at_least(100), default=8192,
                   help="SIFT features per frame (default 8192)")
    p.add_argument("--fps", type=float_in(0.0, 1000.0), default=30.0,
                   help="frame rate of image folders (videos keep their own; default 30)")
    p.add_argument("--threads", type=int_at_least(1), default=None,
                   help="threads of feature extraction, matching and mapping (default: every core); 1 makes the "
                        "calibration repeat itself exactly")
    p.add_argument("--force", action="store_true", help="replace DATA if it exists")


def run(args) -> int:
    import importlib.util

    from omg4.app.commands.common import printable
    from omg4.errors import OMG4Error
    from omg4.app.outputs import check_outputs
    from omg4.prepare import prepare_capture
    from omg4.prepare.calibrate import DISTORTION_GAIN

    if importlib.util.find_spec("pycolmap") is None:  # before any video is read
        raise OMG4Error("omg4 prepare calibrates with pycolmap, a dependency of omg4 missing here: "
                        "pip install 'pycolmap>=4.0,<5'")
    check_outputs({"--out": args.out}, inputs=[args.src], folders=["--out"])  # writable, before any work
    record = prepare_capture(args.src, args.out, sync=args.sync, test_camera=args.test_camera,
                             shared_intrinsics=args.shared_intrinsics, instants=args.instants,
                             max_features=args.max_features, image_fps=args.fps, threads=args.threads or -1,
                             force=args.force, progress=True)
    kept = [c for c in record["cameras"] if c["reliable"]]
    print(f"{len(kept)} of {len(record['cameras'])} cameras calibrated, {record['frames']} shared frames at "
          f"{record['fps']:g} fps (sync: {record['sync']}); test camera {record['test_camera']} = "
          f"{printable(record['test_source'])}")
    lens = record["lens"]
    print(f"lens distortion {lens['distortion']}: reprojection RMS {lens['rms_with_px']:.3f} px with it, "
          f"{lens['rms_without_px']:.3f} px without (kept when leaving it out costs more than "
          f"{DISTORTION_GAIN:.0%})")
    halves = [(label, h) for label, h in zip(("even", "odd"), record["halves"]) if h.get("cameras", 0) >= 2]
    if halves:  # the rig is trusted when one of them reproduces it (docs/prepare.md)
        print("calibrated again from each half of the instants: " + "; ".join(
            f"{label} ones {h['rotation_deg_median']:.2f}° and {h['focal_pct_median']:.1f} % in focal length apart "
            f"({h['cameras']} cameras)" for label, h in halves))
    print("| source | name | skipped frames | focal (px) | k1 | reprojection (px) | matches agreeing | note |")
    print("|---|---|---|---|---|---|---|---|")
    for c in record["cameras"]:
        focal = f"{c['K'][0][0]:.1f}" if "K" in c else "–"
        k1 = f"{c['distortion']['k1']:+.3f}" if "distortion" in c else "–"
        error = f"{c['reprojection_error_px']:.2f}" if c.get("reprojection_error_px") is not None else "–"
        note = c.get("reason", "registered again" if c.get("reregistered") else "")
        print(f"| {printable(c['source'])} | {c['name'] or 'left out'} | {c['offset_frames']} | {focal} | {k1} | "
              f"{error} | {c['match_agreement']:.0%} | {note} |")
    print(f"wrote {args.out} in {record['wall_time_s']:.0f} s: train with omg4 train {args.out} --out RUN")
    return 0
