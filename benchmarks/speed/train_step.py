"""Benchmark: a training step and the compression steps the pipeline runs — wall time per step, aten operations
(the CPU proxy of GPU kernel launches) and where a step's time goes; on CUDA also the kernels launched, their GPU
time, the host synchronizations and the GPU busy share (torch profiler).

On a GPU a step is bound by kernel launches and Python, not by the rasterizer; the number of aten operations a step
dispatches (forward, backward and optimizer together) is the CPU-measurable proxy for that, and the wall time per
step is what a CPU user waits.

Workloads (fixed seeds):

* ``demo``: the demo's synthetic scene (16 cameras × 60 frames, 128×96), the demo's batch of 2; training: 60,000
  Gaussians from random points, densification off, every SH degree active (with ``--model``: the trained
  checkpoint given instead, the demo's ``omg4_demo/baseline/model.safetensors``);
* ``basketball``: ``../shared/data/n3dv_basketball`` at 320×180 (``--downscale 2``), 60,000 Gaussians, batch 4;
* with ``--device cuda``: basketball at 200k Gaussians (320×180) and at 1M Gaussians (its full 640×360), batch 4.

"train" is :meth:`omg4.train.Trainer.train_step`. "compress" runs the OMG4 pipeline on the baseline (``--model``,
else the training workload's model) as ``omg4 compress --preset M`` runs it — the demo's stage lengths on the demo,
the ``cpu`` schedule on basketball (``--compress-steps N``: at most N fine-tuning steps per stage, for a quick run)
— and times every fine-tuning step of every stage on the model the pipeline holds then (after sampling, pruning
and merging: a few thousand Gaussians). Per stage it records the median step, the steps per second, the Gaussians,
the aten operations of its 20th step and a torch profile of its 30th: self CPU time by part (rasterization forward
and backward, the time slice with the appearance MLPs and SH, the loss, the SVQ gathers, the optimizer, the
autograd engine and the rest).

    python benchmarks/speed/train_step.py [--workloads demo basketball] [--device cpu|cuda] [--steps 10]
                                    [--parts train compress] [--model CKPT] [--kernels MODE] [--json PATH]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/train_step.json`` (``train_step_cuda.json`` with ``--device cuda``). To time another
checkout's code, run with ``PYTHONPATH=<that checkout>/src``: the run records its commit as ``code_commit``;
``--against CHECKOUT`` does that in alternating processes.
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


METADATA_OPS = frozenset({"aten.detach", "aten.lift_fresh", "aten.view", "aten.t", "aten.slice", "aten.as_strided",
                          "aten.expand", "aten.unsqueeze", "aten.squeeze", "aten.select", "aten._unsafe_view",
                          "aten.alias", "aten.transpose", "aten.permute"})
"""Operations that make a tensor over memory that exists (views, the tensor of a kernel's output): they launch no
kernel on a GPU; counted apart (``metadata_ops``)."""


class OpCounter(TorchDispatchMode):
    """Counts every aten operator dispatched while active, but the benchmark's own profiler labels."""

    def __init__(self):
        super().__init__()
        self.ops: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket)
        if not name.startswith("profiler."):
            self.ops[name] += 1
        return func(*args, **(kwargs or {}))

    @property
    def metadata(self) -> int:
        """How many of the counted operations are :data:`METADATA_OPS`."""
        return sum(n for op, n in self.ops.items() if op in METADATA_OPS)


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
    """The demo's scene (its :class:`~omg4.app.demo.DemoSettings` sizes)."""
    from omg4.data import load_scene
    from omg4.data.synthetic import SynthConfig, write_synthetic_scene

    write_synthetic_scene(tmp / "demo", SynthConfig(seed=0, num_cameras=16, num_frames=60, width=128, height=96),
                          force=True)
    return load_scene(tmp / "demo", progress=False)


def basketball_scene(downscale: int = 2):
    from omg4.data import load_scene

    path = SHARED / "n3dv_basketball"
    if not path.is_dir():
        raise SystemExit(f"basketball needs {path} (set OMG4_SHARED_DATA)")
    return load_scene(path, downscale=downscale, progress=False)


WORKLOADS = {  # name → (scene factory, Gaussians, batch, devices)
    "demo": (demo_scene, 60_000, 2, ("cpu", "cuda")),
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
           "aten_ops_per_step": sum(counter.ops.values()), "metadata_ops": counter.metadata, "top_ops": dict(top)}
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
                 parts: tuple[str, ...] = ("train", "compress"), compress_steps: int | None = None) -> dict:
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
    lengths = compression_lengths(name, compress_steps)
    ccfg = CompressConfig(preset="M", lengths=lengths, batch_size=batch, seed=0, device=device,
                          baseline_iterations=1500 if name == "demo" else 30_000)
    pipe = CompressionPipeline(trainer.model.detach_copy(), scene, ccfg, progress=False, log=lambda s: None)
    row["compress"] = time_pipeline(pipe, device)
    row["compress_schedule"] = dict(lengths.__dict__)
    return row


def compression_lengths(name: str, limit: int | None):
    """The stage lengths the workload's compression runs: the demo's on the demo, the cpu schedule elsewhere, each
    stage at most ``limit`` steps."""
    from dataclasses import replace

    from omg4.app.demo import DEMO_LENGTHS
    from omg4.compress.schedule import SCHEDULES

    lengths = DEMO_LENGTHS if name == "demo" else SCHEDULES["cpu"]
    if limit is None:
        return lengths
    return replace(lengths, **{k: min(v, limit) for k, v in lengths.__dict__.items()})


OPS_AT, PROFILED_AT = 20, 30
"""Each stage's fine-tuning step whose aten operations are counted, and the one profiled (counted from 1)."""


def time_pipeline(pipe, device: str) -> dict:
    """Run ``pipe`` whole, timing every fine-tuning step: per stage the median step, steps per second, Gaussians,
    the aten operations of its :data:`OPS_AT`-th step and the profile of its :data:`PROFILED_AT`-th."""
    stages: dict[str, dict] = {}
    original = pipe.finetune_step

    def timed(step: int) -> float:
        stage = pipe.records[-1].stage
        entry = stages.setdefault(stage, {"gaussians": pipe.model.num_gaussians, "times": []})
        k = len(entry["times"]) + 1
        if k == OPS_AT:
            counter = OpCounter()
            with counter:
                loss = original(step)
            entry["aten_ops_per_step"] = sum(counter.ops.values())
            entry["metadata_ops"] = counter.metadata
            entry["top_ops"] = dict(counter.ops.most_common(8))
            entry["times"].append(None)
            return loss
        if k == PROFILED_AT and not device.startswith("cuda"):
            entry["profile"], loss = profiled_step(original, step)
            entry["times"].append(None)
            return loss
        sync(device)
        t0 = time.perf_counter()
        loss = original(step)
        sync(device)
        entry["times"].append(time.perf_counter() - t0)
        return loss

    pipe.finetune_step = timed
    labels = install_profile_labels()
    try:
        pipe.run()
    finally:
        restore(labels)
    out = {}
    for stage, entry in stages.items():
        times = [t for t in entry.pop("times") if t is not None]
        if not times:
            continue
        ms = 1000 * statistics.median(times)
        out[stage] = {**entry, "steps": len(times), "ms_per_step": ms, "ms_min": 1000 * min(times),
                      "steps_per_second": 1000 / ms}
    return out


PROFILE_SCOPES = (  # label → (module, attribute) whose calls it covers; the first found of a row's alternatives
    ("slice", (("omg4.compress.model", "CompressibleModel.slice_views"),)),
    ("svq", (("omg4.compress.model", "quantized_values"), ("omg4.compress.svq", "SubVectorQuantizer.forward"))),
    ("appearance MLPs", (("omg4.gaussians.appearance_arrays", "forward"),
                         ("omg4.gaussians.appearance", "AppearanceMLP.predict_from_position_term"),
                         ("omg4.gaussians.appearance", "AppearanceMLP.position_term"))),
    ("rasterization", (("omg4.render.view", "rasterize_views"),)),
    ("loss", (("omg4.optimize.step", "losses_and_errors"), ("omg4.optimize.step", "photometric_losses"))),
    ("optimizer", (("omg4.compress.pipeline", "step_optimizers"),)),
)


def install_profile_labels() -> list:
    """Wrap each scope's function in a ``record_function`` label (what :func:`profiled_step` sorts time by);
    returns what :func:`restore` puts back."""
    import importlib

    from torch.profiler import record_function

    saved = []
    for label, places in PROFILE_SCOPES:
        for module_name, attr in places:
            try:
                module = importlib.import_module(module_name)
            except ImportError:
                continue
            owner, name = (module, attr) if "." not in attr else (getattr(module, attr.split(".")[0], None),
                                                                   attr.split(".")[1])
            fn = getattr(owner, name, None) if owner is not None else None
            if fn is None:
                continue

            def wrapper(*a, __fn=fn, __label=label, **k):
                with record_function(f"scope:{__label}"):
                    return __fn(*a, **k)

            saved.append((owner, name, fn))
            setattr(owner, name, wrapper)
    return saved


def restore(saved: list) -> None:
    for owner, name, fn in reversed(saved):
        setattr(owner, name, fn)


def profiled_step(step_fn, step: int) -> tuple[dict, float]:
    """One step under the torch profiler: self CPU milliseconds by part. A forward operation counts for the innermost
    scope label around it; a backward one for the scope of the forward operation that made its autograd node
    ("… backward"); "Python and glue" is the step's wall time no profiled operation took."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        loss = step_fn(step)
        wall = time.perf_counter() - t0
    events = prof.events()
    scope_of_seq: dict[int, str] = {}

    def scope(e):
        p = e
        while p is not None:
            if p.name.startswith("scope:"):
                return p.name[len("scope:"):]
            if p.name.startswith("autograd::engine::evaluate_function"):
                return p
            p = p.cpu_parent
        return None

    for e in sorted(events, key=lambda e: e.time_range.start):
        if e.sequence_nr is not None and e.sequence_nr >= 0 and not e.name.startswith("autograd::"):
            label = scope(e)
            if isinstance(label, str):
                scope_of_seq[e.sequence_nr] = label
    parts: Counter = Counter()
    for e in events:
        if e.name.startswith("scope:"):
            parts[e.name[len("scope:"):] + " (Python)"] += e.self_cpu_time_total
            continue
        label = scope(e)
        if isinstance(label, str):
            parts[label] += e.self_cpu_time_total
        elif label is None:
            parts["other operations"] += e.self_cpu_time_total
        else:
            forward = scope_of_seq.get(label.sequence_nr)
            parts[f"{forward} backward" if forward else "autograd engine"] += e.self_cpu_time_total
    total_us = sum(parts.values())
    parts["Python and glue"] = max(0.0, 1e6 * wall - total_us)
    return ({"wall_ms": 1000 * wall, "self_cpu_ms": {k: round(v / 1000, 3) for k, v in parts.most_common()}},
            loss)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workloads", nargs="+", default=None, choices=sorted(WORKLOADS))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--parts", nargs="+", default=["train", "compress"], choices=["train", "compress"],
                    help="which steps to time (the compression step needs its stages fitted first)")
    ap.add_argument("--model", type=Path, default=None, help="a trained checkpoint for the demo workload")
    ap.add_argument("--basketball-model", type=Path, default=None,
                    help="a trained checkpoint for the basketball workload (omg4 train ... --downscale 2)")
    ap.add_argument("--compress-steps", type=int, default=None,
                    help="at most this many fine-tuning steps per compression stage (default: the whole schedule)")
    ap.add_argument("--json", type=Path, default=None,
                    help="record file (default benchmarks/results/train_step.json, train_step_cuda.json on CUDA)")
    ap.add_argument("--against", type=Path, default=None, metavar="CHECKOUT",
                    help="time that checkout's code too, the two taking turns in separate processes (alternate.py)")
    ap.add_argument("--repeats", type=int, default=2, help="with --against: runs of each side")
    ap.add_argument("--kernels", default=None, help="the per-Gaussian kernels (omg4's --kernels: fused or reference; "
                                                     "default: $OMG4_KERNELS or fused)")
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
            model = {"demo": args.model, "basketball": args.basketball_model}.get(name)
            row = run_workload(name, args.device, args.warmup, args.steps, Path(tmp), model, tuple(args.parts),
                               args.compress_steps)
            rows.append(row)
            if "train" in row:
                print(f"{name:16s} {row['device']:6s} N={row['gaussians']:>9,} B={row['batch']} train "
                      f"{row['train']['ms_per_step']:8.1f} ms {row['train']['aten_ops_per_step']:6d} ops", flush=True)
            for stage, r in row.get("compress", {}).items():
                print(f"{name:16s} {row['device']:6s} N={r['gaussians']:>9,} B={row['batch']} compress [{stage}] "
                      f"{r['ms_per_step']:8.1f} ms {r.get('aten_ops_per_step', 0):6d} ops", flush=True)
            if kind == "cuda" and "train" in row:
                for part in ("train",):
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
    print("| workload | device | step | Gaussians | batch | ms/step | steps/s | aten ops |")
    print("|---|---|---|---|---|---|---|---|")
    for row, step, r in step_rows(rows):
        print(f"| {row['workload']} | {row['device']} | {step} | {r.get('gaussians', row['gaussians']):,} | "
              f"{row['batch']} | {r['ms_per_step']:.1f} | {1000 / r['ms_per_step']:.1f} | "
              f"{r.get('aten_ops_per_step', 0):,} |")
    return 0


def step_rows(rows: list[dict]):
    """``(row, step name, measurement)`` of every step a run timed: the training step, then each compression
    stage's."""
    for row in rows:
        if "train" in row:
            yield row, "train", row["train"]
        for stage, r in row.get("compress", {}).items():
            yield row, f"compress [{stage}]", r


def _before_and_after(args, command: str, record: Path) -> int:
    """``--against``: the benchmark on both codes in alternating processes, one record with every run and the medians."""
    from alternate import alternating, save_alternating

    argv = ["--device", args.device, "--steps", str(args.steps), "--warmup", str(args.warmup), "--parts", *args.parts,
            *(["--workloads", *args.workloads] if args.workloads else []),
            *(["--model", str(args.model)] if args.model else []),
            *(["--basketball-model", str(args.basketball_model)] if args.basketball_model else []),
            *(["--compress-steps", str(args.compress_steps)] if args.compress_steps else [])]
    runs = alternating(Path(__file__), argv, args.against, args.repeats)
    summary = {}
    for key, first in runs[0]["rows"].items():
        steps = (["train"] if "train" in first else []) + [f"compress/{stage}" for stage in first.get("compress", {})]
        for step in steps:
            def value(run, field, code=None):
                r = run["rows"][key]
                r = r["train"] if step == "train" else r["compress"].get(step.split("/", 1)[1], {})
                return r.get(field)

            times = {code: statistics.median(v for run in runs if run["code"] == code
                                             if (v := value(run, "ms_per_step")) is not None)
                     for code in ("before", "after")}
            ops = {code: next((value(run, "aten_ops_per_step") for run in runs if run["code"] == code), None)
                   for code in ("before", "after")}
            summary[f"{key}/{step}"] = {"ms_before": times["before"], "ms_after": times["after"],
                                        "speedup": times["before"] / times["after"],
                                        "aten_ops_before": ops["before"], "aten_ops_after": ops["after"]}
            print(f"{key} {step}: {times['before']:.1f} → {times['after']:.1f} ms "
                  f"({times['before'] / times['after']:.2f}×), aten ops {ops['before']} → {ops['after']}")
    save_alternating(record, command, args.against, summary, runs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
