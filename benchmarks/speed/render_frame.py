"""Benchmark: one rendered frame of a baseline and of its compressed model (the appearance MLPs only on the Gaussians that pass the cull).

For each model file (a ``.safetensors`` checkpoint or an ``.omg4`` file) on the test views of
a dataset: median render time per frame (render only, as ``omg4 eval`` measures FPS; the models
take turns frame by frame so that a shared host's slow spells fall on all alike), the
aten operations one frame dispatches (the CPU proxy for GPU kernel launches), the mean
fraction of the model's Gaussians that reach the rasterizer (those passing the temporal
cull), and the compositing work per pixel, counted on the CPU whatever ``--device``: box pixels
the numba kernels visit and Gaussians blended, which every exact renderer must do
(:mod:`omg4.render.compositing_load`), and the aten operations of one time slice with the torch forms the CUDA path
runs instead of the CPU's numba kernels (a proxy for the slice's GPU kernel launches). The paper reports
OMG4 rendering 4.3× faster than its Real-Time4DGS baseline.

    python benchmarks/speed/render_frame.py DATA --models baseline.safetensors model.omg4 [--downscale 2]
                                      [--device cpu|cuda] [--frames 30] [--rounds 3] [--name demo]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/render_frame_<name>.json`` (``render_frame_<name>_cuda.json`` with ``--device cuda``),
``--name`` defaulting to the dataset folder's name. Run with ``PYTHONPATH=<another checkout>/src`` to time that
checkout's code: the run then records that code's commit as ``code_commit``.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import statistics
import sys
import time
from pathlib import Path
from typing import Iterator

import torch

from omg4.testing.records import save_record
from omg4.render.compositing_load import compositing_load  # noqa: E402
from train_step import OpCounter, code_under_test, keep_freed_memory_if_present, sync  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "results"


@contextlib.contextmanager
def timing_compositing() -> Iterator[list[float]]:
    """Inside, the CPU compositing kernel adds its seconds to the yielded one-item list (the rasterizer's reference to
    :func:`~omg4.render.cpu_kernels.composite_forward` — in ``omg4.render.arrays``, or ``omg4.render.api`` in code
    from before it — is wrapped, and restored on exit)."""
    import importlib
    import importlib.util

    caller = "omg4.render.arrays" if importlib.util.find_spec("omg4.render.arrays") else "omg4.render.api"
    render_api = importlib.import_module(caller)
    kernel, total = render_api.composite_forward, [0.0]

    def timed(*args):
        t0 = time.perf_counter()
        kernel(*args)
        total[0] += time.perf_counter() - t0

    render_api.composite_forward = timed
    try:
        yield total
    finally:
        render_api.composite_forward = kernel


@contextlib.contextmanager
def torch_forms() -> Iterator[None]:
    """Inside, the time slice runs the torch forms the CUDA path runs (conditioning, SH basis and colour sum)
    instead of the CPU's numba kernels, so its aten operations count about what a GPU would launch
    (``small_matmul`` still takes its CPU form, two or so operations more per call than on CUDA)."""
    import omg4.gaussians.covariance as covariance
    import omg4.gaussians.sh as sh
    import omg4.gaussians.sh_kernels as sh_kernels

    modules = (covariance, sh, sh_kernels)
    saved = [m.runs_cpu_kernels for m in modules]
    for m in modules:
        m.runs_cpu_kernels = lambda *tensors: False
    try:
        yield
    finally:
        for m, f in zip(modules, saved):
            m.runs_cpu_kernels = f


def slice_ops_torch_forms(model, view) -> int:
    """aten operations of one time slice (``slice_at``, no rasterizer) with the CUDA path's torch forms."""
    from omg4.render.view import camera_tensors

    center = camera_tensors(view.camera)[2]
    with torch.no_grad(), torch_forms():
        model.slice_at(view.timestamp, center)  # warm: first-call work is not counted
        counter = OpCounter()
        with counter:
            model.slice_at(view.timestamp, center)
    return sum(counter.ops.values())


def frame_views(views, frames: int) -> list:
    """``frames`` test views spread evenly over ``views``."""
    return views[::max(1, len(views) // frames)][:frames]


def measure_models(paths: list[Path], models: list, timed: list, device: str, rounds: int) -> list[dict]:
    """Per model (``models`` loaded from ``paths`` on ``device``): median ms per frame over ``rounds`` passes of the
    views ``timed``, and of those the median ms in the CPU compositing kernel (None on CUDA). The models take
    turns frame by frame, so a slow spell of a shared host falls on all of them alike."""
    from omg4.render.view import render_view

    def frame(model, v):
        with torch.no_grad():
            _, sl = render_view(model, v.camera, v.timestamp, device=device)
        return sl

    for model in models:
        for v in timed[:3]:
            frame(model, v)
    times = [[] for _ in models]
    compositing = [[] for _ in models]
    fractions = [[] for _ in models]
    with timing_compositing() as kernel_seconds:
        for _ in range(rounds):
            for v in timed:
                for i, model in enumerate(models):
                    sync(device)
                    before = kernel_seconds[0]
                    t0 = time.perf_counter()
                    sl = frame(model, v)
                    sync(device)
                    times[i].append(time.perf_counter() - t0)
                    compositing[i].append(kernel_seconds[0] - before)
                    fractions[i].append(sl.index.numel() / model.num_gaussians)
    rows = []
    for path, model, ts, cs, fs in zip(paths, models, times, compositing, fractions):
        counter = OpCounter()
        with counter:
            frame(model, timed[len(timed) // 2])
        ms = 1000 * statistics.median(ts)
        rows.append({"model": str(path), "num_gaussians": int(model.num_gaussians), "ms_per_frame": ms,
                     "fps": 1000 / ms, "aten_ops_per_frame": sum(counter.ops.values()),
                     "slice_ops_torch_forms": slice_ops_torch_forms(model, timed[len(timed) // 2]),
                     "compositing_ms_per_frame": 1000 * statistics.median(cs) if any(cs) else None,
                     "visible_fraction": statistics.mean(fs), "frames": len(timed), "rounds": rounds})
    return rows


def add_compositing_load(rows: list[dict], models: list, views: list) -> None:
    """Add each model's mean ``visited_per_pixel`` and ``blended_per_pixel`` over ``views`` (``models`` on the
    CPU)."""
    for row, model in zip(rows, models):
        loads = [compositing_load(model, v.camera, v.timestamp) for v in views]
        for key in loads[0]:
            row[key] = statistics.mean(load[key] for load in loads)


def main(argv: list[str] | None = None) -> int:
    from omg4.data import load_scene
    from omg4.models import load_model

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--models", type=Path, nargs="+", required=True, help="baseline first, then compressed models")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=3, help="passes over the frames (models alternate frame by frame)")
    ap.add_argument("--name", default=None, help="the scene's name in the record's file name (default: the dataset "
                                                 "folder's name)")
    ap.add_argument("--json", type=Path, default=None,
                    help="record file (default benchmarks/results/render_frame_<name>[_cuda].json)")
    ap.add_argument("--against", type=Path, default=None, metavar="CHECKOUT",
                    help="time that checkout's code too, the two taking turns in separate processes (alternate.py)")
    ap.add_argument("--repeats", type=int, default=2, help="with --against: runs of each side")
    args = ap.parse_args(argv)
    command = shlex.join(["python", "benchmarks/speed/render_frame.py", *(sys.argv[1:] if argv is None else argv)])
    name = args.name or args.data.name
    suffix = "" if args.device == "cpu" else "_" + args.device.split(":")[0]
    record = args.json or RESULTS / f"render_frame_{name}{suffix}.json"
    if args.against is not None:
        return _before_and_after(args, command, record)
    keep_freed_memory_if_present()
    scene = load_scene(args.data, downscale=args.downscale, progress=False)
    timed = frame_views(scene.test_views, args.frames)
    models = [load_model(p, args.device) for p in args.models]
    rows = measure_models(args.models, models, timed, args.device, args.rounds)
    cpu_models = models if args.device == "cpu" else [load_model(p, "cpu") for p in args.models]
    add_compositing_load(rows, cpu_models, timed)
    base = rows[0]["ms_per_frame"]
    for r in rows:
        r["speedup_vs_first"] = base / r["ms_per_frame"]
    print("| model | #Gaussians | ms/frame | of it compositing | FPS | speed-up | aten ops/frame | time-slice ops, "
          "CUDA path | visible fraction | visited / pixel | blended / pixel |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        kernel_ms = "–" if r["compositing_ms_per_frame"] is None else f"{r['compositing_ms_per_frame']:.2f}"
        print(f"| {Path(r['model']).name} | {r['num_gaussians']:,} | {r['ms_per_frame']:.2f} | {kernel_ms} | "
              f"{r['fps']:.1f} | {r['speedup_vs_first']:.2f}x | {r['aten_ops_per_frame']:,} | "
              f"{r['slice_ops_torch_forms']} | "
              f"{r['visible_fraction']:.3f} | {r['visited_per_pixel']:.1f} | {r['blended_per_pixel']:.1f} |")
    save_record(record, {
        "command": command, **code_under_test(), "scene": name, "device": args.device, "downscale": args.downscale,
        "torch": torch.__version__, "torch_threads": torch.get_num_threads(), "rows": rows})
    return 0


def _before_and_after(args, command: str, record: Path) -> int:
    """``--against``: the benchmark on both codes in alternating processes, one record with every run and the medians
    (ms per frame, aten operations, and each model's frames per second over the first model's)."""
    from alternate import alternating, median_of, save_alternating

    argv = [str(args.data), "--models", *map(str, args.models), "--downscale", str(args.downscale), "--device",
            args.device, "--frames", str(args.frames), "--rounds", str(args.rounds), "--name", args.name or args.data.name]
    runs = alternating(Path(__file__), argv, args.against, args.repeats)
    summary = {}
    for i, path in enumerate(args.models):
        row = {}
        for code in ("before", "after"):
            row[f"ms_{code}"] = median_of(runs, code, lambda r: r["rows"][i]["ms_per_frame"])
            row[f"speedup_vs_first_{code}"] = median_of(runs, code, lambda r: r["rows"][i]["speedup_vs_first"])
            row[f"aten_ops_{code}"] = next(r["rows"][i]["aten_ops_per_frame"] for r in runs if r["code"] == code)
        summary[path.name] = row
        print(f"{path.name}: {row['ms_before']:.2f} → {row['ms_after']:.2f} ms/frame, aten ops {row['aten_ops_before']} "
              f"→ {row['aten_ops_after']}, × the first model's FPS {row['speedup_vs_first_before']:.2f} → "
              f"{row['speedup_vs_first_after']:.2f}")
    save_alternating(record, command, args.against, summary, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
