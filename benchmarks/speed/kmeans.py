"""Benchmark: k-means for SVQ codebooks (paper §4.4, omg4 §7).

Target: 200k sub-vectors of length 2 into 8192 centroids in under 60 s on 2 cores. Inputs mimic
the quantized attributes: halves of random unit quaternions (rotation, s = 2), log-scales (s = 1),
appearance-feature pairs (s = 2). For each case: wall time of ``kmeans`` with its defaults, the
inertia, and the inertia of a long run (300 Lloyd iterations, no early stop) for reference.

    python benchmarks/speed/kmeans.py [--threads 2] [--quick] [--json PATH]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in ``benchmarks/results/kmeans.json``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import torch

from omg4.testing.records import save_record
from omg4.compress.kmeans import KDTREE_MAX_DIM, inertia, kmeans

RESULTS = Path(__file__).resolve().parents[1] / "results" / "kmeans.json"


def attribute_like(kind: str, n: int, seed: int = 0) -> torch.Tensor:
    """Synthetic sub-vectors [n, d] shaped like one SVQ slot of an OMG4 attribute."""
    g = torch.Generator().manual_seed(seed)
    if kind == "rotation":  # (w, x) of unit quaternions concentrated near identity
        q = torch.randn(n, 4, generator=g) * torch.tensor([3.0, 1.0, 1.0, 1.0])
        return (q / q.norm(dim=1, keepdim=True))[:, :2]
    if kind == "log_scale":
        return torch.randn(n, 1, generator=g) * 0.8 - 4.0
    if kind == "app":  # features of a few colour clusters
        centres = torch.randn(64, 2, generator=g)
        return centres[torch.randint(0, 64, (n,), generator=g)] + 0.2 * torch.randn(n, 2, generator=g)
    if kind == "wide":  # exercises the chunked matrix-product path
        return torch.randn(n, 6, generator=g)
    raise ValueError(kind)


CASES = [("rotation", 200_000, 8192), ("app", 200_000, 1024), ("log_scale", 200_000, 512),
         ("rotation", 500_000, 8192), ("wide", 50_000, 1024)]


def run_case(kind: str, n: int, k: int, reference: bool) -> dict:
    x = attribute_like(kind, n)
    t0 = time.perf_counter()
    c, labels = kmeans(x, k, seed=0)
    seconds = time.perf_counter() - t0
    d = x.shape[1]
    path = "sorted" if d == 1 else "kdtree" if d <= KDTREE_MAX_DIM else "mm"
    row = {"attribute": kind, "n": n, "d": d, "k": k, "path": path,
           "seconds": round(seconds, 3), "inertia": inertia(x, c, labels), "centroids": int(c.shape[0])}
    if reference:
        t0 = time.perf_counter()
        row["inertia_long_run"] = inertia(x, *kmeans(x, k, seed=0, iters=300, tol=0.0))
        row["seconds_long_run"] = round(time.perf_counter() - t0, 3)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="only the 200k × 2 → 8192 target, no long run")
    ap.add_argument("--json", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cases = CASES[:1] if args.quick else CASES
    print(f"{'attribute':>10} {'n':>8} {'d':>2} {'k':>5} {'path':>6} {'time s':>7} {'inertia':>11} "
          f"{'long-run':>11} {'long s':>7}")
    rows = []
    for kind, n, k in cases:
        r = run_case(kind, n, k, reference=not args.quick)
        rows.append(r)
        print(f"{kind:>10} {n:>8} {r['d']:>2} {k:>5} {r['path']:>6} {r['seconds']:>7.2f} {r['inertia']:>11.5g} "
              f"{r.get('inertia_long_run', float('nan')):>11.5g} {r.get('seconds_long_run', float('nan')):>7.2f}",
              flush=True)
    save_record(args.json, {"command": shlex.join(["python", "benchmarks/speed/kmeans.py", *sys.argv[1:]]),
                            "benchmark": "compress.kmeans", "threads": args.threads, "torch": torch.__version__,
                            "rows": rows})


if __name__ == "__main__":
    main()
