"""Benchmark: one training step and one compression step — wall time and aten operations (the CPU proxy of GPU kernel launches); on CUDA also the kernels launched, their GPU time, the host synchronizations and the GPU busy share (torch profiler).

On a GPU a step is bound by kernel launches and Python, not by the rasterizer; the number
of aten operations a step dispatches (forward, backward and optimizer together) is the
CPU-measurable proxy for that, and the wall time per step is what a CPU user waits.

Workloads (fixed seeds, densification off, every SH degree active so the step is the
steady-state one):

* ``demo``: the demo's synthetic scene (16 cameras × 60 frames, 256×192), 19,000 Gaussians
  from random points in the common view volume, the demo's batch of 2 (with ``--model``: the
  trained checkpoint given instead, e.g. the demo's baseline ``omg4_demo/baseline/model.safetensors``);
* ``basketball``: ``../shared/data/n3dv_basketball`` at 320×180 (``--downscale 2``),
  60,000 Gaussians, batch 4;
* with ``--device cuda``: basketball at 200k Gaussians (320×180) and at 1M Gaussians (its full 640×360),
  batch 4.

"train" is :meth:`omg4.train.Trainer.train_step`; "compress" is
:meth:`omg4.compress.pipeline.CompressionPipeline.finetune_step` after the appearance,
3D-SVQ and 4D-SVQ stages (the MLP/SVQ fine-tuning that most of OMG4's iterations are).
Times are the median of ``--steps`` steps after ``--warmup``; the aten count is one step
under a ``TorchDispatchMode`` that counts every dispatched operator.

    python benchmarks/speed/train_step.py [--workloads demo basketball] [--device cpu|cuda]
                                    [--steps 10] [--parts train compress] [--model CKPT] [--kernels MODE] [--json PATH]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/train_step.json`` (``train_step_cuda.json`` with ``--device cuda``). To time another
checkout's code, run with ``PYTHONPATH=<that checkout>/src``: the run records its commit as ``code_commit``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"
SHARED = Path(os.environ.get("OMG4_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))


class OpCounter(TorchDispatchMode):
    """Counts every aten operator dispatched while active."""

    def __init__(self):
        super().__init__()
        self.ops: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


def keep_freed_memory_if_present() -> None:
    """Keep freed memory in the heap as the ``omg4`` command does (``omg4.allocator``), where the code under test has
    that setting; code from before it is timed without, as its own command ran."""
    try:
        from omg4.allocator import keep_freed_memory
    except ImportError:
        return
    keep_freed_memory()


def code_under_test() -> dict:
    """``{"code_commit", "code_path"}`` when the imported ``omg4`` is not this checkout's (``PYTHONPATH=<other
    checkout>/src``), so that each side of a before/after pair records the code it timed; else ``{}``."""
    import omg4

    src = Path(omg4.__file__).resolve().parents[1]
    if src == REPO / "src":
        return {}
    head = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=src, capture_output=True, text=True)
    return {"code_commit": head.stdout.strip() or "unknown", "code_path": str(src)}


def demo_scene(tmp: Path):
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    write_synthetic_scene(tmp / "demo", SynthConfig(seed=0, num_cameras=16, num_frames=60, width=256, height=192),
                          force=True)
    return load_scene(tmp / "demo", progress=False)


def basketball_scene(downscale: int = 2):
    from omg4.data import load_scene

    path = SHARED / "n3dv_basketball"
    if not path.is_dir():
        raise SystemExit(f"basketball needs {path} (set OMG4_SHARED_DATA)")
    return load_scene(path, downscale=downscale, progress=False)


WORKLOADS = {  # name → (scene factory, Gaussians, batch, devices)
    "demo": (demo_scene, 19_000, 2, ("cpu", "cuda")),
    "basketball": (lambda tmp: basketball_scene(), 60_000, 4, ("cpu", "cuda")),
    "basketball-200k": (lambda tmp: basketball_scene(), 200_000, 4, ("cuda",)),
    "basketball-1m": (lambda tmp: basketball_scene(downscale=1), 1_000_000, 4, ("cuda",)),
}


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def measure(step_fn, device: str, warmup: int, steps: int) -> dict:
    """Median wall time of ``step_fn(i)`` and the aten operators of one step."""
    i = 0
    for _ in range(warmup):
        i += 1
        step_fn(i)
    times = []
    for _ in range(steps):
        i += 1
        sync(device)
        t0 = time.perf_counter()
        step_fn(i)
        sync(device)
        times.append(time.perf_counter() - t0)
    counter = OpCounter()
    with counter:
        step_fn(i + 1)
    top = counter.ops.most_common(8)
    row = {"ms_per_step": 1000 * statistics.median(times), "ms_min": 1000 * min(times),
           "aten_ops_per_step": sum(counter.ops.values()), "top_ops": dict(top)}
    if device.startswith("cuda"):
        row.update(gpu_profile(step_fn, i + 2, row["ms_per_step"]))
    return row


def gpu_profile(step_fn, i: int, ms_per_step: float) -> dict:
    """One step under ``torch.profiler``: the device operations it launches (kernels, copies, fills), the GPU time
    they take (overlaps merged) and that time's share of the median step — the GPU busy share."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        step_fn(i)
        torch.cuda.synchronize()
    device_ops = [e for e in prof.events() if e.device_type == DeviceType.CUDA]
    spans = sorted((e.time_range.start, e.time_range.end) for e in device_ops)
    busy_us, end = 0.0, float("-inf")
    for start, stop in spans:  # union of the intervals
        busy_us += max(0.0, stop - max(start, end))
        end = max(end, stop)
    copies = sum(e.name.startswith(("Memcpy", "Memset")) for e in device_ops)
    top = Counter(e.name[:60] for e in device_ops).most_common(6)
    kernel_us: Counter = Counter()
    for e in device_ops:
        kernel_us[e.name[:60]] += e.time_range.end - e.time_range.start
    return {"gpu_launches_per_step": len(device_ops) - copies, "gpu_copies_per_step": copies,
            "gpu_busy_ms": busy_us / 1000, "gpu_busy_share": busy_us / 1000 / ms_per_step,
            "host_syncs_per_step": host_synchronizations(step_fn, i + 1),
            "top_kernels": dict(top), "top_kernels_ms": {k: v / 1000 for k, v in kernel_us.most_common(8)}}


def host_synchronizations(step_fn, i: int) -> int:
    """How often one step makes the host wait for the GPU (a read of a device value, a ``nonzero``, a copy from
    pageable memory): the warnings of torch's CUDA sync debug mode. Each one drains the GPU's queue, which stays
    idle until the host has launched the next kernels."""
    import warnings

    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            step_fn(i)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return sum("synchroniz" in str(w.message) for w in caught)


def run_workload(name: str, device: str, warmup: int, steps: int, tmp: Path, model_path: Path | None = None,
                 parts: tuple[str, ...] = ("train", "compress")) -> dict:
    from omg4.compress.pipeline import CompressConfig, CompressionPipeline
    from omg4.data import random_initial_points
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.train import Trainer, make_config

    factory, n, batch, _ = WORKLOADS[name]
    scene = factory(tmp)
    points = random_initial_points(scene, n, seed=0)
    cfg = make_config("official", iterations=100_000, batch_size=batch, densify_until=0, opacity_reset_interval=10**9,
                      sh_increase_interval=1, checkpoint_interval=0, device=device, max_gaussians=n)
    trainer = Trainer(scene, cfg, tmp / f"run_{name}", points=points, progress=False, log=lambda s: None)
    if model_path is not None:  # a trained model instead of the random initialization
        trainer.model = load_gaussians(model_path)[0].to(device)
        trainer.optimizer = trainer._make_optimizer()
    num = trainer.model.num_gaussians
    base = 10  # SH degrees all active from step 5 on
    row = {"workload": name, "device": device, "gaussians": num, "batch": batch,
           "model": str(model_path) if model_path else "random initialization",
           "resolution": f"{scene.train_views[0].camera.width}x{scene.train_views[0].camera.height}"}
    if "train" in parts:
        row["train"] = measure(lambda i: trainer.train_step(base + i), device, warmup, steps)
    if "compress" not in parts:
        return row
    ccfg = CompressConfig(preset="M", stages=("appearance", "svq3d", "svq4d"), schedule="short", batch_size=batch,
                          device=device)
    pipe = CompressionPipeline(trainer.model.detach_copy(), scene, ccfg, progress=False, log=lambda s: None)
    for e in pipe.events:
        pipe.apply_event(e.name, e.round, e.iteration)
    row["compress"] = measure(lambda i: pipe.finetune_step(i), device, warmup, steps)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workloads", nargs="+", default=None, choices=sorted(WORKLOADS))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--parts", nargs="+", default=["train", "compress"], choices=["train", "compress"],
                    help="which steps to time (the compression step needs its stages fitted first)")
    ap.add_argument("--model", type=Path, default=None, help="a trained checkpoint for the demo workload")
    ap.add_argument("--json", type=Path, default=None,
                    help="record file (default benchmarks/results/train_step.json, train_step_cuda.json on CUDA)")
    ap.add_argument("--against", type=Path, default=None, metavar="CHECKOUT",
                    help="time that checkout's code too, the two taking turns in separate processes (alternate.py)")
    ap.add_argument("--repeats", type=int, default=2, help="with --against: runs of each side")
    ap.add_argument("--kernels", default=None, help="the per-Gaussian kernels (omg4's --kernels: fused, reference, "
                                                     "compiled; default: $OMG4_KERNELS or fused)")
    args = ap.parse_args(argv)
    if args.kernels:
        os.environ["OMG4_KERNELS"] = args.kernels  # read by omg4.kernels; inherited by --against's processes
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    command = shlex.join(["python", "benchmarks/speed/train_step.py", *(sys.argv[1:] if argv is None else argv)])
    record = args.json or RESULTS / ("train_step.json" if kind == "cpu" else f"train_step_{kind}.json")
    if args.against is not None:
        return _before_and_after(args, command, record)
    keep_freed_memory_if_present()
    names = args.workloads or [k for k, w in WORKLOADS.items() if kind in w[3]]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            row = run_workload(name, args.device, args.warmup, args.steps, Path(tmp),
                               args.model if name == "demo" else None, tuple(args.parts))
            rows.append(row)
            print(f"{name:16s} {row['device']:6s} N={row['gaussians']:>9,} B={row['batch']} "
                  + " | ".join(f"{part} {row[part]['ms_per_step']:8.1f} ms {row[part]['aten_ops_per_step']:6d} ops"
                               for part in args.parts), flush=True)
            if kind == "cuda":
                for part in args.parts:
                    r = row[part]
                    print(f"  {part}: {r['gpu_launches_per_step']} kernels + {r['gpu_copies_per_step']} copies/fills "
                          f"per step, {r['host_syncs_per_step']} host synchronizations, "
                          f"GPU busy {r['gpu_busy_ms']:.1f} ms ({100 * r['gpu_busy_share']:.0f}%); "
                          f"top {r['top_kernels']}; GPU ms {r['top_kernels_ms']}", flush=True)
    result = {"command": command, **code_under_test(), "kernels": os.environ.get("OMG4_KERNELS", "fused"),
              "torch": torch.__version__,
              "torch_threads": torch.get_num_threads()}
    if kind == "cuda":
        result["gpu"] = torch.cuda.get_device_name()
    result["rows"] = {f"{row['workload']}/{row['device']}"
                      f"{'/trained' if row['model'] != 'random initialization' else ''}": row for row in rows}
    save_record(record, result)
    print("| workload | device | N | batch | train ms/step | train aten ops | compress ms/step | compress aten ops |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        cells = [f"{row[part]['ms_per_step']:.1f} | {row[part]['aten_ops_per_step']:,}" if part in row else "– | –"
                 for part in ("train", "compress")]
        print(f"| {row['workload']} | {row['device']} | {row['gaussians']:,} | {row['batch']} | {' | '.join(cells)} |")
    return 0


def _before_and_after(args, command: str, record: Path) -> int:
    """``--against``: the benchmark on both codes in alternating processes, one record with every run and the medians."""
    from alternate import alternating, median_of, save_alternating

    argv = ["--device", args.device, "--steps", str(args.steps), "--warmup", str(args.warmup), "--parts", *args.parts,
            *(["--workloads", *args.workloads] if args.workloads else []),
            *(["--model", str(args.model)] if args.model else [])]
    runs = alternating(Path(__file__), argv, args.against, args.repeats)
    summary = {}
    for key in runs[0]["rows"]:
        for part in args.parts:
            before, after = (median_of(runs, code, lambda r: r["rows"][key][part]["ms_per_step"])
                             for code in ("before", "after"))
            ops = {code: next(r["rows"][key][part]["aten_ops_per_step"] for r in runs if r["code"] == code)
                   for code in ("before", "after")}
            summary[f"{key}/{part}"] = {"ms_before": before, "ms_after": after, "speedup": before / after,
                                        "aten_ops_before": ops["before"], "aten_ops_after": ops["after"]}
            print(f"{key} {part}: {before:.1f} → {after:.1f} ms ({before / after:.2f}×), aten ops {ops['before']} → "
                  f"{ops['after']}")
    save_alternating(record, command, args.against, summary, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
