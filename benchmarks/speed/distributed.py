"""Data-parallel training steps: 1 rank against N ranks (torch.distributed; gloo on the CPU, NCCL on CUDA).

Loads a trained baseline (or makes ``--random N`` Gaussians from random points of the scene; either way every
run steps the same Gaussians), and times training steps of a fixed global
batch with densification off, once per world size: the whole step (render, loss, backward, gradient all-reduce,
Adam) per rank, images per second, and the all-reduce alone — its bytes per rank and its seconds — so the
communication's share of a step is visible. Each world is started with ``torch.distributed.run`` (one thread
per rank on the CPU). Scaling efficiency = images/s with N ranks / (N × images/s with one).

Usage::

    python benchmarks/speed/distributed.py DATA (--model BASELINE.safetensors | --random N) [--downscale 2] [--ranks 1 2]
        [--batch-size 4] [--steps 30] [--warmup 5] [--device cpu|cuda] [--name demo]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results"


def worker(args) -> None:
    """One rank of a timed run (started by :func:`main` through ``torch.distributed.run``)."""
    import torch

    from omg4 import distributed
    from omg4.app.commands.common import load_scene_from_args
    from omg4.device import resolve_device
    from omg4.gaussians.checkpoint import load_gaussians
    from omg4.train.config import TrainConfig
    from omg4.optimize.parameters import baseline_lrs, make_adam, step_optimizers
    from omg4.optimize.step import backward_batch, step_generator

    world, device = distributed.init(resolve_device(args.device))
    args.format, args.frames, args.cameras = None, None, None
    scene = distributed.main_first(lambda: load_scene_from_args(args, decode=True))
    if args.model:
        model, _ = load_gaussians(args.model, device)
    else:
        from omg4.train import make_config
        from omg4.train.trainer import initial_model

        model = initial_model(scene, make_config("cpu-small", num_random_points=args.random,
                                                 strategy={"max_gaussians": args.random}, seed=0)).to(device)
    for p in model.params.values():
        p.requires_grad_(True)
    optimizer = make_adam(model.params, baseline_lrs(TrainConfig(), scene.extent, model.config.schema))
    reduce_time, reduce_bytes = [], []
    plain = distributed.all_reduce_gradients

    def timed_reduce(params, what="summing the gradients"):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        sent = plain(params, what)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        reduce_time.append(time.perf_counter() - t0)
        reduce_bytes.append(sent)
        return sent

    distributed.all_reduce_gradients = timed_reduce
    background = torch.zeros(3, device=device)
    steps = []
    for step in range(1, args.warmup + args.steps + 1):
        distributed.barrier()
        t0 = time.perf_counter()
        batch = torch.randint(len(scene.train_views), (args.batch_size,), generator=step_generator(0, step))
        backward_batch(model, scene.train_views, batch, background=background, backend="auto", lambda_dssim=0.2,
                       what="timing", step=step, device=device)
        step_optimizers([optimizer], device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        steps.append(time.perf_counter() - t0)
    timed = slice(args.warmup, None)
    result = {"world_size": world.size, "step_s": statistics.median(steps[timed]),
              "allreduce_s": statistics.median(reduce_time[timed]) if world.parallel else 0.0,
              "allreduce_bytes_per_rank": reduce_bytes[-1] if world.parallel else 0,
              "num_gaussians": model.num_gaussians, "threads": torch.get_num_threads()}
    result["images_per_s"] = args.batch_size / result["step_s"]
    if world.main:
        Path(args.worker_out).write_text(json.dumps(result))
    distributed.finish()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", type=Path, help="a trained baseline checkpoint")
    source.add_argument("--random", type=int, metavar="N", help="N Gaussians from random points of the scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="world sizes to time")
    ap.add_argument("--repeats", type=int, default=3,
                    help="rounds over the world sizes, taking turns (a shared host's slow spells fall on all of them)")
    ap.add_argument("--batch-size", type=int, default=4, help="the global batch (views per step over all ranks)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="threads per rank on the CPU")
    ap.add_argument("--name", help="the scene's name in the record file (default: the data folder's)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--worker-out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker_out:
        worker(args)
        return
    from omg4.testing.records import save_record

    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "NUMBA_NUM_THREADS": str(args.threads),
           "OMP_WAIT_POLICY": "PASSIVE"}
    rounds: dict[int, list[dict]] = {n: [] for n in args.ranks}
    for _ in range(args.repeats):
        for n in args.ranks:
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / "result.json"
                cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={n}",
                       __file__, *sys.argv[1:], "--worker-out", str(out)]
                subprocess.run(cmd, env=env, check=True)
                rounds[n].append(json.loads(out.read_text()))
            r = rounds[n][-1]
            print(f"{n} rank(s): {r['step_s'] * 1000:.1f} ms/step, {r['images_per_s']:.2f} images/s, all-reduce "
                  f"{r['allreduce_s'] * 1000:.1f} ms of {r['allreduce_bytes_per_rank'] / 2**20:.1f} MB", flush=True)
    runs = []
    for n, results in rounds.items():  # the median round of each world size
        median = sorted(results, key=lambda r: r["step_s"])[len(results) // 2]
        runs.append({**median, "rounds_step_s": [round(r["step_s"], 4) for r in results]})
    single = next((r for r in runs if r["world_size"] == 1), None)
    for r in runs:
        if single:
            r["speedup"] = r["images_per_s"] / single["images_per_s"]
            r["scaling_efficiency"] = r["speedup"] / r["world_size"]
    name = args.name or args.data.name
    suffix = "" if args.device == "cpu" else "_" + args.device.split(":")[0]
    save_record(args.json or RESULTS / f"distributed_{name}{suffix}.json", {
        "command": "python benchmarks/speed/distributed.py " + " ".join(sys.argv[1:]),
        "scene": name, "device": args.device, "batch_size": args.batch_size, "threads_per_rank": args.threads,
        "steps": args.steps, "runs": runs})


if __name__ == "__main__":
    main()
