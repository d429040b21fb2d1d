"""Benchmark: Gaussian Merging cluster building (paper §4.3) for 100k / 300k / 1M Gaussians.

Synthetic but realistic inputs: positions clustered in the [-2, 2]³ box of the normalized world
(blobs of log-uniform spread 0.02–0.3 plus 10% uniform background), times in [0, 10] over the
time range (0, 10) (each blob lives around its own time), and random colours (per-blob base
colour plus noise, SH DC units). Each size runs in a fresh subprocess so its peak resident
memory (``resource.getrusage``) is its own; ``extra_mib`` is the peak minus the memory held
before clustering (inputs, torch). ``cpu_seconds`` (user + system, all threads) is reported
beside wall time because shared machines make wall time noisy. Target: 300k in under 60 s on
2 cores.

    python benchmarks/speed/merging.py [--sizes 100000 300000 1000000] [--threads 2] [--json PATH]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in ``benchmarks/results/merging.json``.
"""

from __future__ import annotations

import argparse
import json
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

import torch

from omg4.testing.records import save_record
from omg4.compress.merging import MergeConfig, build_merge_groups
from omg4.compress.merge_clusters import merge_cells

RESULTS = Path(__file__).resolve().parents[1] / "results" / "merging.json"


def synthetic_gaussians(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """xyz [n, 3] in [-2, 2]³ (clustered), t [n, 1] in [0, 10], features_dc [n, 1, 3]."""
    g = torch.Generator().manual_seed(seed)
    n_blobs = max(50, n // 2000)
    n_bg = n // 10
    centre = torch.rand(n_blobs, 3, generator=g) * 3.6 - 1.8
    spread = torch.exp(torch.empty(n_blobs).uniform_(float(torch.log(torch.tensor(0.02))),
                                                     float(torch.log(torch.tensor(0.3))), generator=g))
    weight = torch.empty(n_blobs).exponential_(generator=g)
    blob = torch.multinomial(weight / weight.sum(), n - n_bg, replacement=True, generator=g)
    xyz = centre[blob] + spread[blob, None] * torch.randn(n - n_bg, 3, generator=g)
    xyz = torch.cat([xyz, torch.rand(n_bg, 3, generator=g) * 4 - 2]).clamp(-2, 2)
    t_centre, t_spread = torch.rand(n_blobs, generator=g) * 10, torch.rand(n_blobs, generator=g) * 3 + 0.2
    t = torch.cat([t_centre[blob] + t_spread[blob] * torch.randn(n - n_bg, generator=g),
                   torch.rand(n_bg, generator=g) * 10]).clamp(0, 10)
    base = torch.randn(n_blobs, 3, generator=g)
    dc = torch.cat([base[blob] + 0.05 * torch.randn(n - n_bg, 3, generator=g), torch.randn(n_bg, 3, generator=g)])
    perm = torch.randperm(n, generator=g)
    return xyz[perm].float(), t[perm, None].float(), dc[perm, None].float()


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_s() -> float:
    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def run_one(n: int, threads: int) -> dict:
    """Time cluster building for ``n`` Gaussians in this process."""
    torch.set_num_threads(threads)
    cfg = MergeConfig()
    xyz, t, dc = synthetic_gaussians(n)
    cells = torch.bincount(merge_cells(xyz, t.reshape(-1), (0.0, 10.0), cfg.grid_size, cfg.time_cell_fraction))
    before, cpu0 = _rss_mib(), _cpu_s()
    t0 = time.perf_counter()
    groups = build_merge_groups(xyz, t, dc, (0.0, 10.0), cfg.grid_size, cfg)
    seconds, cpu = time.perf_counter() - t0, _cpu_s() - cpu0
    peak = _rss_mib()
    return {"gaussians": n, "threads": threads, "seconds": round(seconds, 3), "cpu_seconds": round(cpu, 3),
            "peak_rss_mib": round(peak, 1), "extra_mib": round(peak - before, 1), "cells": int(len(cells)),
            "largest_cell": int(cells.max()), "pairs": int((cells * (cells - 1) // 2).sum()), "groups": groups.num_groups,
            "merged_members": int(groups.members.numel()), "removed": groups.num_removed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 300_000, 1_000_000])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=RESULTS)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    args = ap.parse_args()
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.threads)))
        return
    rows = []
    head = f"{'N':>9} {'time s':>8} {'cpu s':>8} {'peak MiB':>9} {'extra MiB':>9} {'cells':>8} {'max cell':>8} " \
           f"{'pairs':>11} {'groups':>8} {'removed':>8}"
    print(head)
    for n in args.sizes:
        out = subprocess.run([sys.executable, __file__, "--one", str(n), "--threads", str(args.threads)],
                             check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        rows.append(r)
        print(f"{n:>9} {r['seconds']:>8.2f} {r['cpu_seconds']:>8.2f} {r['peak_rss_mib']:>9.0f} {r['extra_mib']:>9.0f} "
              f"{r['cells']:>8} {r['largest_cell']:>8} {r['pairs']:>11} {r['groups']:>8} {r['removed']:>8}", flush=True)
    save_record(args.json, {"command": shlex.join(["python", "benchmarks/speed/merging.py", *sys.argv[1:]]),
                            "benchmark": "merging.build_merge_groups", "grid_size": MergeConfig().grid_size,
                            "torch": torch.__version__, "rows": rows})


if __name__ == "__main__":
    main()
