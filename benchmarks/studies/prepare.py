"""Benchmark: ``omg4 prepare`` against known poses — synthetic rigs, the CMU Panoptic basketball dome, planted audio
offsets, and training on the prepared dataset against training on the true poses.

* ``synthetic``: ``omg4 synth`` rigs (``--rigs CAMERASxWIDTHxHEIGHT``, ``--seeds``), their videos renamed and their
  poses dropped, prepared; with ``--train N`` a cpu-small baseline of N steps is trained on the true and on the
  prepared dataset (the same test camera) and their test PSNR compared.
* ``basketball``: ``../shared/data/panoptic_basketball/ims`` (31 cameras' image folders, 60 frames at 640×360)
  prepared; the truth is each camera's own intrinsics and pose in ``train_meta.json`` / ``test_meta.json``.
* ``audio``: synthetic videos started at random planted frames, each with the same sound from its start:
  the offsets found against the planted ones.

Poses are compared after one similarity: the rotation that best aligns the orientations (chordal mean), then the
scale from the centres; errors are per camera, rotation in degrees and centre in % of the rig's diameter.

    python benchmarks/studies/prepare.py synthetic [--rigs 8x320x240 12x640x360] [--seeds 0 1] [--frames 30] [--train 0]
                                           [--shared-intrinsics]
    python benchmarks/studies/prepare.py basketball
    python benchmarks/studies/prepare.py audio [--trials 5]

Records: ``benchmarks/results/prepare_<kind>.json`` (:func:`environment.save_record`).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from omg4.errors import OMG4Error
from omg4.prepare.check import pose_differences
from omg4.testing.records import save_record

RESULTS = Path(__file__).resolve().parents[1] / "results"
SHARED = Path(os.environ.get("OMG4_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


def calibrated(record: dict) -> dict[str, tuple[np.ndarray, float]]:
    """source stem → (w2c, focal) of the trusted cameras of a ``calibration.json`` record."""
    return {Path(c["source"]).stem: (np.array(c["w2c"]), c["K"][0][0]) for c in record["cameras"] if c["reliable"]}


def synthetic(args) -> dict:
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.prepare import prepare_capture

    rows = []
    for rig in args.rigs:
        cameras, width, height = (int(v) for v in rig.split("x"))
        for seed in args.seeds:
            with tempfile.TemporaryDirectory() as tmp:
                tmp = Path(tmp)
                write_synthetic_scene(tmp / "scene", SynthConfig(seed=seed, num_cameras=cameras, num_frames=args.frames,
                                                                 width=width, height=height), progress=False)
                (tmp / "raw").mkdir()
                for i in range(cameras):  # renamed, no poses
                    shutil.copy(tmp / "scene" / f"cam{i:02d}.mp4", tmp / "raw" / f"clip_{i:02d}.mp4")
                t0 = time.perf_counter()
                try:
                    record = prepare_capture(tmp / "raw", tmp / "data", test_camera="clip_00",
                                             shared_intrinsics=args.shared_intrinsics)
                except OMG4Error as exc:  # a calibration prepare does not trust: its message is the result
                    rows.append({"rig": rig, "seed": seed, "frames": args.frames, "refused": str(exc),
                                 "prepare_s": time.perf_counter() - t0, "shared_intrinsics": args.shared_intrinsics})
                    print(f"rig={rig} seed={seed} refused: {exc}", flush=True)
                    continue
                wall = time.perf_counter() - t0
                truth = {f"clip_{i:02d}": (c.viewmat, c.K[0, 0]) for i, c in
                         enumerate(load_scene(tmp / "scene", decode=False, progress=False).cameras())}
                row = {"rig": rig, "seed": seed, "frames": args.frames, "prepare_s": wall,
                       "shared_intrinsics": args.shared_intrinsics, "lens": record["lens"], "halves": record["halves"],
                       **pose_differences(calibrated(record), truth)}
                if args.train:
                    row.update(training_gap(tmp / "scene", tmp / "data", args.train, tmp))
                rows.append(row)
                print(_line(row), flush=True)
    return {"rows": rows}


def training_gap(true_scene: Path, prepared: Path, iterations: int, tmp: Path) -> dict:
    """Test PSNR of a cpu-small baseline of ``iterations`` steps on the true poses and on the prepared dataset
    (cam00 of each: the same camera, clip_00)."""
    from omg4.data import load_scene
    from omg4.train import Trainer, make_config
    from omg4.train.init import initial_points
    from omg4.train.trainer import evaluate_psnr

    out = {}
    for label, folder in (("true_poses", true_scene), ("prepared", prepared)):
        scene = load_scene(folder, progress=False)
        cfg = make_config("cpu-small", iterations=iterations, checkpoint_interval=0, backend="cpu")
        trainer = Trainer(scene, cfg, tmp / f"run_{label}", points=initial_points(scene, "auto", cfg),
                          progress=False, log=lambda *_: None)
        result = trainer.run()
        out[f"psnr_{label}"] = evaluate_psnr(result.model, scene.test_views, trainer.background, "cpu")
    out["psnr_gap_db"] = out["psnr_true_poses"] - out["psnr_prepared"]
    out["train_iterations"] = iterations
    return out


def basketball(args) -> dict:
    from omg4.prepare import prepare_capture

    root = SHARED / "panoptic_basketball"
    if not root.is_dir():
        raise SystemExit(f"basketball needs {root} (set OMG4_SHARED_DATA)")
    truth = {}
    for meta in ("train_meta.json", "test_meta.json"):
        data = json.loads((root / meta).read_text())
        ids = data["cam_id"][0] if isinstance(data["cam_id"][0], list) else data["cam_id"]
        for j, cam in enumerate(ids):
            truth[str(cam)] = (np.array(data["w2c"][0][j]), float(np.array(data["k"][0][j])[0, 0]))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        record = prepare_capture(root / "ims", Path(tmp) / "data", test_camera="0")
        wall = time.perf_counter() - t0
    row = {"capture": "panoptic_basketball", "cameras_in": len(truth), "prepare_s": wall, "lens": record["lens"],
           "halves": record["halves"],
           "reregistered": [c["source"] for c in record["cameras"] if c.get("reregistered")],
           "left_out": [c["source"] for c in record["cameras"] if not c["reliable"]],
           **pose_differences(calibrated(record), truth)}
    print(_line(row), flush=True)
    return {"rows": [row]}


def audio(args) -> dict:
    import av

    from omg4.data.synthetic import SynthConfig, write_synthetic_scene
    from omg4.io.video import write_video
    from omg4.prepare.sources import find_sources
    from omg4.prepare.sync import synchronize

    rate, fps, frames = 16_000, 30, 90
    rng = np.random.default_rng(0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_synthetic_scene(tmp / "scene", SynthConfig(num_cameras=4, num_frames=frames, width=128, height=96),
                              progress=False)
        clips = []
        for i in range(4):
            with av.open(str(tmp / "scene" / f"cam{i:02d}.mp4")) as container:
                clips.append([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])
        sound = rng.normal(0, 6000, int((frames / fps + 1) * rate)).clip(-32000, 32000).astype(np.int16)
        for trial in range(args.trials):
            late = [int(v) for v in rng.integers(0, 30, 4)]
            folder = tmp / f"trial{trial}"
            folder.mkdir()
            for i, start in enumerate(late):
                write_video(folder / f"cam_{i}.mkv", clips[i][start:], fps=fps,
                            audio=(sound[start * rate // fps:], rate))
            offsets = synchronize(find_sources(folder), "audio")
            expected = [max(late) - k for k in late]
            rows.append({"planted_late_frames": late, "expected_skip": expected, "found_skip": offsets.frames,
                         "exact": offsets.frames == expected,
                         "confidence_min": float(min(c for c in offsets.confidence if c is not None))})
            print(rows[-1], flush=True)
    return {"rows": rows, "all_exact": all(r["exact"] for r in rows)}


def _line(row: dict) -> str:
    keys = ("rig", "capture", "seed", "cameras", "of", "rotation_deg_median", "rotation_deg_max", "centre_pct_median",
            "centre_pct_max", "focal_pct_median", "prepare_s", "psnr_gap_db")
    halves = " halves=" + "/".join(f"{h['rotation_deg_median']:.2f}°,{h['focal_pct_median']:.1f}%"
                                   for h in row.get("halves", []) if "rotation_deg_median" in h)
    return " ".join(f"{k}={row[k]:.3f}" if isinstance(row.get(k), float) else f"{k}={row[k]}" for k in keys
                    if k in row) + halves


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=("synthetic", "basketball", "audio"))
    ap.add_argument("--rigs", nargs="+", default=["8x320x240", "12x640x360"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--train", type=int, default=0, help="train baselines of this many steps on both datasets")
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--shared-intrinsics", action="store_true", help="synthetic: one camera model for the rig")
    args = ap.parse_args(argv)
    result = {"synthetic": synthetic, "basketball": basketball, "audio": audio}[args.kind](args)
    result["command"] = shlex.join(["python", "benchmarks/studies/prepare.py", *(sys.argv[1:] if argv is None else argv)])
    name = args.kind + (f"_train{args.train}" if args.train else "") + ("_shared" if args.shared_intrinsics else "")
    save_record(RESULTS / f"prepare_{name}.json", result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
