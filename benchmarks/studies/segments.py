"""Long captures as segments: memory and time against capture length, and quality across boundaries.

``scaling``: synthetic captures of 60, 120, 240 and 480 frames, each trained and compressed once as a whole
clip and once as segments of 60 frames (sharing 10, each coded alone): wall time and peak resident memory of the ``omg4 train``
and ``omg4 compress`` processes (``ru_maxrss`` of each child), and the files' sizes. Every model (the whole clip,
or each segment) gets the same iterations, so the segments' work grows with the length while one model's does
not — the point is the memory.

``quality``: one capture trained as segments, compressed with OMG4-M into a sequence file (each segment alone) and evaluated on the
test camera: PSNR and SSIM of the boundary frames (:func:`omg4.data.segments.near_boundary`) against the
interior ones, and temporal flicker — the mean absolute difference between consecutive rendered frames minus
that of the ground truth, over the pairs that touch a boundary frame against the others — and the bitrate.

Usage::

    python benchmarks/studies/segments.py scaling [--lengths 60 120 240 480] [--work runs/segments]
    python benchmarks/studies/segments.py quality DATA [--downscale 2] [--segment-frames 50] [--overlap 10]
        [--iterations 1500] [--schedule cpu] [--name basketball]
    python benchmarks/studies/segments.py quality --synthetic 240 [--segment-frames 60] [--overlap 10] [--name synthetic240]
        [--whole-clip] [--compress-from-video]

``prediction``: one capture trained as segments once, then compressed at each ``--key-intervals`` value (1: every
segment coded alone; K: every K-th, the others predicted from the segment before, ``omg4 compress --key-interval``):
bytes (per segment too), Mbit/s, PSNR/SSIM overall and on boundary and interior frames (and their gap to the trained
segments' on the same frames), flicker, and the time and
bytes of a seek to the last segment (decoding its chain back to its key segment in a fresh process state); with
``--whole-clip`` also one model of the whole capture trained for as many steps as all segments together (or
``--whole-iterations``; ``--key-intervals --whole-clip`` with no interval: that model alone). Every model is
compressed with ``--preset`` (default M).

    python benchmarks/studies/segments.py prediction --synthetic 240 [--key-intervals 1 4 8] [--whole-clip]
    python benchmarks/studies/segments.py prediction DATA --downscale 2 --segment-frames 24 --overlap 6 --name bb
        [--preset T] [--carry auto|lasting|0.5|0]

``--compress-from-video`` compresses segments trained as usual (taught by the segment before) from the video alone.
``--whole-clip`` adds the control: one model of the whole capture, trained for as many steps as all segments
together and compressed alike, scored on the same boundary and interior frames; the segmented run's trained
models (before compression) are scored the same way.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

from omg4.testing.records import save_record

RESULTS = Path(__file__).resolve().parents[1] / "results"
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
TAUGHT = "the crossfade from the segment before into the video"  # omg4.optimize.teaching.taught_by


def run(args: list[str]) -> dict:
    """Run ``omg4 args`` in a child process: its wall seconds and peak resident memory (MB; the only child of the
    process that measures, :func:`_measure_in_fresh_process`)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "omg4", *args], env=ENV, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"seconds": round(seconds, 1), "peak_mb": round(peak / 1024, 1)}


def _measure_in_fresh_process(argv: list[str]) -> dict:
    """Run this script's ``measure`` mode in a new process, so ``ru_maxrss`` covers that one command alone."""
    out = subprocess.run([sys.executable, __file__, "measure", *argv], env=ENV, check=True, capture_output=True,
                         text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def scaling(args) -> None:
    work = Path(args.work)
    rows = []
    for frames in args.lengths:
        scene = work / f"scene{frames}"
        if not scene.exists():
            subprocess.run([sys.executable, "-m", "omg4", "synth", str(scene), "--cameras", str(args.cameras),
                            "--frames", str(frames), "--width", str(args.width), "--height", str(args.height),
                            "--points", "2000"], env=ENV, check=True, stdout=subprocess.DEVNULL)
        train = [str(scene), "--preset", "cpu-small", "--iterations", str(args.iterations), "--batch-size", "2",
                 "--checkpoint-interval", "0", "--backend", "cpu", "--force"]
        for mode, extra in (("whole clip", []), ("segments", ["--segment-frames", "60", "--overlap", "10"])):
            if mode == "whole clip" and frames > args.max_whole:
                continue
            run_dir = work / f"run{frames}_{'seg' if extra else 'whole'}"
            out = run_dir.with_suffix(".omg4")
            trained = _measure_in_fresh_process(["train", *train, "--out", str(run_dir), *extra])
            compressed = _measure_in_fresh_process(["compress", str(scene), "--model", str(
                run_dir if extra else run_dir / "model.safetensors"), "--out", str(out), "--schedule", "tiny",
                "--batch-size", "2", "--backend", "cpu", "--force", *(["--key-interval", "1"] if extra else []),
                *paper_flag(args)])
            row = {"frames": frames, "mode": mode, "train": trained, "compress": compressed,
                   "file_bytes": out.stat().st_size}
            rows.append(row)
            print(f"{frames:>4} frames, {mode:<10}: train {trained['seconds']:7.1f} s, {trained['peak_mb']:7.1f} MB; "
                  f"compress {compressed['seconds']:6.1f} s, {compressed['peak_mb']:7.1f} MB; {row['file_bytes']} B",
                  flush=True)
    save_record(args.json or RESULTS / "segments_scaling.json", {
        "command": "python benchmarks/studies/segments.py " + shlex.join(sys.argv[1:]),
        "cameras": args.cameras, "size": [args.width, args.height], "iterations": args.iterations, "rows": rows})


def frame_split(model, views, ranges: list, fps: float) -> dict:
    """``model``'s PSNR/SSIM on the boundary frames of a sequence with segment ``ranges`` (any model: a whole-clip
    one is scored on the same frames) and on the others, and its flicker there: the mean absolute difference
    between consecutive rendered frames of a test camera minus that of the ground truth, over the pairs touching
    a boundary frame and over the others, and their ratio. Each view is rendered once and scored as
    :func:`omg4.evaluate.evaluate` scores it."""
    import numpy as np
    import torch

    from omg4.data.segments import near_boundary
    from omg4.metrics import psnr, ssim
    from omg4.render.view import view_image
    from omg4.render.view import render_view

    by_camera: dict[str, list] = {}
    for v in views:
        by_camera.setdefault(v.camera.name, []).append(v)
    scores = {"boundary": [], "interior": []}
    flicker = {"boundary": [], "interior": []}
    for camera_views in by_camera.values():
        previous = None
        for v in sorted(camera_views, key=lambda v: v.timestamp):
            with torch.no_grad():
                image = render_view(model, v.camera, v.timestamp)[0].image.clamp(0, 1)
            truth = view_image(v)
            near = near_boundary(v.timestamp, ranges, fps)
            scores["boundary" if near else "interior"].append((psnr(image, truth), float(ssim(image, truth))))
            if previous is not None:
                excess = float((image - previous[0]).abs().mean()) - float((truth - previous[1]).abs().mean())
                flicker["boundary" if near or previous[2] else "interior"].append(excess)
            previous = (image, truth, near)
    split = {name: {"num_views": len(rows), "psnr": float(np.mean([p for p, _ in rows])),
                    "ssim": float(np.mean([q for _, q in rows]))} for name, rows in scores.items()}
    split["flicker"] = {k: float(np.mean(v)) if v else None for k, v in flicker.items()}
    b, i = split["flicker"]["boundary"], split["flicker"]["interior"]
    split["flicker_ratio"] = b / i if b is not None and i else None
    return split


def quality(args) -> None:
    from omg4.data import load_scene
    from omg4.evaluate import evaluate
    from omg4.models import load_model

    work = Path(args.work) / args.name
    data = _capture(args)
    reader = ["--downscale", str(args.downscale)]
    independent = ["--independent-segments"] if args.independent_segments else []
    segmented = ["--segment-frames", str(args.segment_frames), "--overlap", str(args.overlap), *independent]
    compress_independent = independent or (["--independent-segments"] if args.compress_from_video else [])
    compress_independent = [*compress_independent, "--key-interval", "1"]  # segments coded alone, as its records

    def train_and_compress(run_dir: Path, out: Path, extra: list[str], model: Path, compress_extra: list[str],
                           iterations: int = args.iterations):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "omg4", "train", str(data), *reader, "--out", str(run_dir), "--preset",
                        "cpu-small", "--iterations", str(iterations), "--checkpoint-interval", "0", "--resume",
                        *extra], env=ENV, check=True, stdout=subprocess.DEVNULL)
        train_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "omg4", "compress", str(data), *reader, "--model", str(model), "--out",
                        str(out), "--preset", "M", "--schedule", args.schedule, "--force", *compress_extra,
                        *paper_flag(args)], env=ENV,
                       check=True, stdout=subprocess.DEVNULL)
        return round(train_s, 1), round(time.perf_counter() - t0, 1)

    run_dir, out = work / "run", work / "sequence_M.omg4"
    train_s, compress_s = train_and_compress(run_dir, out, segmented, run_dir, compress_independent)
    scene = load_scene(data, downscale=args.downscale, progress=False)
    model = load_model(out)
    result = evaluate(model, scene.test_views, storage_bytes=out.stat().st_size, lpips_nets=(), progress=False)
    ranges, fps = model.ranges, model.meta["fps"]
    compressed = frame_split(model, scene.test_views, ranges, fps)
    record = {
        "command": "python benchmarks/studies/segments.py " + shlex.join(sys.argv[1:]),
        "data": str(data), "frames": scene.num_frames, "segment_frames": args.segment_frames, "overlap": args.overlap,
        "iterations_per_segment": args.iterations, "schedule": args.schedule, "segments": model.num_segments,
        "shared_frames_learnt_from": "the video" if args.independent_segments else TAUGHT,
        "compression_shared_frames_learnt_from": "the video" if compress_independent else TAUGHT,
        "psnr": result["psnr"], "ssim": result["ssim"], "boundary": result["boundary"],
        "interior": result["interior"], "flicker": compressed["flicker"], "flicker_ratio": compressed["flicker_ratio"],
        "file_bytes": out.stat().st_size, "bitrate_mbps": result["bitrate_mbps"],
        "num_gaussians": result["num_gaussians"], "train_s": train_s, "compress_s": compress_s,
        "trained": frame_split(load_model(run_dir), scene.test_views, ranges, fps)}
    if args.whole_clip:  # the control: one model of the whole capture, scored on the same frames
        whole_dir, whole_out = work / "whole", work / "whole_M.omg4"
        iterations = args.iterations * model.num_segments  # the segments' training steps, all in one model
        whole_train_s, whole_compress_s = train_and_compress(whole_dir, whole_out, [],
                                                             whole_dir / "model.safetensors", [], iterations)
        record["whole_clip"] = {"iterations": iterations,
            "trained": frame_split(load_model(whole_dir / "model.safetensors"), scene.test_views, ranges, fps),
            "compressed": frame_split(load_model(whole_out), scene.test_views, ranges, fps),
            "file_bytes": whole_out.stat().st_size, "train_s": whole_train_s, "compress_s": whole_compress_s}
    b, i = result["boundary"], result["interior"]
    print(f"{model.num_segments} segments: boundary PSNR {b['psnr']:.2f} / interior {i['psnr']:.2f} dB; flicker "
          f"{compressed['flicker']['boundary']:.4f} / {compressed['flicker']['interior']:.4f}; "
          f"{record['bitrate_mbps']:.2f} Mbit/s")
    save_record(args.json or RESULTS / f"segments_quality_{args.name}.json", record)


def _capture(args) -> Path:
    """The capture: DATA, or a synthetic one of ``--synthetic`` frames written once in the work folder."""
    data = Path(args.data) if args.data else Path(args.work) / args.name / "scene"
    if args.synthetic and not data.exists():
        subprocess.run([sys.executable, "-m", "omg4", "synth", str(data), "--cameras", str(args.cameras), "--frames",
                        str(args.synthetic), "--width", str(args.width), "--height", str(args.height)], env=ENV,
                       check=True, stdout=subprocess.DEVNULL)
    return data


def paper_flag(args) -> list[str]:
    """``omg4 compress``'s flag for the study's mode (the paper's way with ``--paper``)."""
    return ["--paper"] if getattr(args, "paper", False) else []


def _omg4(*argv: str) -> float:
    """Run ``omg4 argv``; its wall seconds."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "omg4", *argv], env=ENV, check=True, stdout=subprocess.DEVNULL)
    return round(time.perf_counter() - t0, 1)


def seek_to_last(path: Path) -> dict:
    """Decode the last segment of a sequence file as a reader seeking there does (its chain back to its key
    segment, then the model): seconds and segment bytes read."""
    from omg4.codec.sequence import SegmentDecoder
    from omg4.models.compact import CompactModel

    t0 = time.perf_counter()
    decoder = SegmentDecoder(path)
    last = len(decoder.index.segments) - 1
    CompactModel(decoder.payload(last))
    return {"seconds": round(time.perf_counter() - t0, 3), "bytes_read": decoder.bytes_read,
            "segments_decoded": len(decoder.index.chain(last))}


def carried(path: Path, entry) -> tuple[int, dict | None]:
    """How many Gaussians of the segment before a segment of a sequence file carries, and the compressor's
    decision (its header meta's ``carry``, docs/file-format.md §8b; None for a key segment)."""
    from omg4.codec.container import read_versioned
    from omg4.codec.sequence import read_segment

    header = read_versioned(read_segment(path, entry))[1]
    return header.get("carried", 0), header.get("meta", {}).get("carry")


def prediction(args) -> None:
    from omg4.codec.sequence import read_index
    from omg4.data import load_scene
    from omg4.data.segments import read_run_plan
    from omg4.evaluate import evaluate
    from omg4.models import load_model

    work = Path(args.work) / args.name
    data = _capture(args)
    reader = ["--downscale", str(args.downscale)]
    train = ["--preset", "cpu-small", "--checkpoint-interval", "0", "--resume"]
    compress = ["--preset", args.preset, "--schedule", args.schedule, "--force", "--predicted-mlp", args.predicted_mlp,
                *(["--carry", str(args.carry)] if args.carry is not None else []), *paper_flag(args)]
    run_dir = work / "run"
    train_s = _omg4("train", str(data), *reader, "--out", str(run_dir), "--iterations", str(args.iterations), *train,
                    "--segment-frames", str(args.segment_frames), "--overlap", str(args.overlap))
    scene = load_scene(data, downscale=args.downscale, progress=False)
    record = {"command": "python benchmarks/studies/segments.py " + shlex.join(sys.argv[1:]), "data": str(data),
              "frames": scene.num_frames, "segment_frames": args.segment_frames, "overlap": args.overlap,
              "iterations_per_segment": args.iterations, "schedule": args.schedule, "preset": args.preset,
              "predicted_mlp": args.predicted_mlp, "carry": args.carry or ("0" if args.paper else "auto"),
              "train_s": train_s,
              "segments": len(read_run_plan(run_dir)["segments"]), "rows": []}
    for key_interval in args.key_intervals:
        out = work / f"sequence_{args.preset}_key{key_interval}.omg4"
        compress_s = _omg4("compress", str(data), *reader, "--model", str(run_dir), "--out", str(out), *compress,
                           "--key-interval", str(key_interval))
        model = load_model(out)
        result = evaluate(model, scene.test_views, storage_bytes=out.stat().st_size, lpips_nets=(), progress=False)
        split = frame_split(model, scene.test_views, model.ranges, model.meta["fps"])
        if "trained" not in record:  # the trained segments (the baselines), scored on the same frames once
            record["trained"] = frame_split(load_model(run_dir), scene.test_views, model.ranges, model.meta["fps"])
        gap = {part: split[part]["psnr"] - record["trained"][part]["psnr"] for part in ("boundary", "interior")}
        index = read_index(out)
        row = {"key_interval": key_interval, "file_bytes": out.stat().st_size,
               "segment_bytes": [e.size for e in index.segments],
               "references": [e.reference for e in index.segments], "bitrate_mbps": result["bitrate_mbps"],
               "psnr": result["psnr"], "ssim": result["ssim"], "boundary": split["boundary"],
               "interior": split["interior"], "flicker": split["flicker"], "compress_s": compress_s,
               "gap_to_trained_db": {**gap, "boundary_minus_interior": gap["boundary"] - gap["interior"]},
               "seek_to_last": seek_to_last(out), "num_gaussians": result["num_gaussians"],
               "carried_gaussians": [carried(out, e)[0] for e in index.segments],
               "carry_decisions": [carried(out, e)[1] for e in index.segments]}
        record["rows"].append(row)
        print(f"key interval {key_interval}: {row['file_bytes']:,} B ({row['segment_bytes']}), PSNR {row['psnr']:.3f}, "
              f"boundary {split['boundary']['psnr']:.2f} / interior {split['interior']['psnr']:.2f} (against the "
              f"trained segments {gap['boundary']:+.2f} / {gap['interior']:+.2f} dB), seek "
              f"{row['seek_to_last']['seconds']:.3f} s", flush=True)
    if args.whole_clip:  # one model of the whole capture, trained for as many steps as all the segments
        whole_dir, whole_out = work / "whole", work / f"whole_{args.preset}.omg4"
        iterations = args.whole_iterations or args.iterations * record["segments"]
        whole_train_s = _omg4("train", str(data), *reader, "--out", str(whole_dir), "--iterations", str(iterations),
                              *train)
        whole_compress_s = _omg4("compress", str(data), *reader, "--model", str(whole_dir / "model.safetensors"),
                                 "--out", str(whole_out), *compress)
        model = load_model(whole_out)
        result = evaluate(model, scene.test_views, storage_bytes=whole_out.stat().st_size, lpips_nets=(),
                          progress=False)
        record["whole_clip"] = {"iterations": iterations, "file_bytes": whole_out.stat().st_size,
                                "bitrate_mbps": result["bitrate_mbps"], "psnr": result["psnr"], "ssim": result["ssim"],
                                "train_s": whole_train_s, "compress_s": whole_compress_s}
        print(f"whole clip: {record['whole_clip']['file_bytes']:,} B, PSNR {result['psnr']:.3f}", flush=True)
    save_record(args.json or RESULTS / f"segments_prediction_{args.name}.json", record)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    s = sub.add_parser("scaling")
    s.add_argument("--lengths", type=int, nargs="+", default=[60, 120, 240, 480])
    s.add_argument("--max-whole", type=int, default=480, help="longest capture also trained as one model")
    q = sub.add_parser("quality")
    q.add_argument("--schedule", default="cpu")
    q.add_argument("--independent-segments", action="store_true",
                   help="train and compress each segment on the video alone (--independent-segments)")
    q.add_argument("--compress-from-video", action="store_true",
                   help="segments trained from the segment before, compressed from the video alone")
    q.add_argument("--whole-clip", action="store_true",
                   help="also train (for as many steps as all segments together) and compress one model of the whole "
                        "capture and score it on the same boundary and interior frames (a control: how much harder "
                        "those frames are)")
    r = sub.add_parser("prediction")
    r.add_argument("--schedule", default="short")
    r.add_argument("--preset", default="M", help="the size preset of every model (omg4 compress --preset)")
    r.add_argument("--key-intervals", type=int, nargs="*", default=[1, 8],
                   help="key intervals to compress the trained segments at (none: only the --whole-clip control)")
    r.add_argument("--whole-clip", action="store_true", help="also one model of the whole capture")
    r.add_argument("--whole-iterations", type=int, help="its training steps (default: all the segments' together)")
    r.add_argument("--predicted-mlp", choices=["tune", "keep"], default="tune",
                   help="what a predicted segment does with the MLPs of the one before (omg4 compress --predicted-mlp)")
    r.add_argument("--carry",
                   help="what a predicted segment carries of the segment before's Gaussians: auto, lasting, a "
                        "tolerance or 0 (omg4 compress --carry; unset: its default, auto, or 0 with --paper)")
    for p in (q, r):  # a capture cut into segments
        p.add_argument("data", nargs="?")
        p.add_argument("--synthetic", type=int, help="synthesize a capture of this many frames instead of DATA")
        p.add_argument("--downscale", type=float, default=1.0)
        p.add_argument("--segment-frames", type=int, default=60)
        p.add_argument("--overlap", type=int, default=10)
        p.add_argument("--name", default="synthetic")
    for p in (s, q, r):
        p.add_argument("--paper", action="store_true",
                       help="compress the paper's way (omg4 compress --paper; a key interval named here still holds)")
        p.add_argument("--cameras", type=int, default=6)
        p.add_argument("--width", type=int, default=96)
        p.add_argument("--height", type=int, default=64)
        p.add_argument("--iterations", type=int, default=600)
        p.add_argument("--work", default="runs/segments")
        p.add_argument("--json", type=Path)
    m = sub.add_parser("measure")
    m.add_argument("argv", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    if args.mode == "measure":
        print(json.dumps(run(args.argv)))
    elif args.mode == "scaling":
        scaling(args)
    elif args.mode == "prediction":
        prediction(args)
    else:
        quality(args)


if __name__ == "__main__":
    main()
