"""Benchmark: index-stream entropy coders and position coding of the .omg4 file (omg4 §8).

Index streams: 500k skewed indices for K = 8192 and K = 512, uniform indices, and real k-means
labels (200k rotation-like sub-vectors into 8192 centroids). For each: the empirical entropy
(ideal size), the raw fixed-width size, LZMA alone on uint16 indices, the paper's Huffman+LZMA
and the default ANS coder, with encode/decode times.

Positions: 200k clustered fp16 positions and time centres as written by ``encode_payload``
with the paper codec (fp16 + LZMA) and the default codec (Morton order + gap coding for xyz).

    python benchmarks/studies/entropy.py [--json PATH]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in ``benchmarks/results/entropy.json``.
"""

from __future__ import annotations

import argparse
import lzma
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from omg4.testing.records import save_record
from omg4.codec.entropy import decode_indices, encode_indices
from omg4.codec.payload import CompressedPayload, encode_payload
from omg4.compress.kmeans import kmeans

RESULTS = Path(__file__).resolve().parents[1] / "results" / "entropy.json"
KIB = 1024.0


def index_streams(seed: int = 0) -> list[tuple[str, np.ndarray, int]]:
    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(200_000, 4, generator=g) * torch.tensor([3.0, 1.0, 1.0, 1.0])
    _, labels = kmeans((q / q.norm(dim=1, keepdim=True))[:, :2], 8192, seed=seed)
    return [
        ("skewed", np.minimum(rng.geometric(1 / 1500, 500_000) - 1, 8191), 8192),
        ("skewed", np.minimum(rng.geometric(1 / 60, 500_000) - 1, 511), 512),
        ("uniform", rng.integers(0, 8192, 500_000), 8192),
        ("kmeans-labels", labels.numpy(), 8192),
    ]


def entropy_bytes(x: np.ndarray) -> float:
    counts = np.bincount(x).astype(np.float64)
    counts = counts[counts > 0]
    return float(-(counts * np.log2(counts / x.size)).sum()) / 8


def timed(fn, repeat: int = 3):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best * 1e3


def index_rows() -> list[dict]:
    rows = []
    for name, x, k in index_streams():
        row = {"data": name, "k": k, "n": int(x.size), "entropy_bits_per_symbol": 8 * entropy_bytes(x) / x.size,
               "ideal_kib": entropy_bytes(x) / KIB, "raw_kib": x.size * np.ceil(np.log2(k)) / 8 / KIB,
               "lzma_only_kib": len(lzma.compress(x.astype("<u2").tobytes())) / KIB}
        for method in ("ans", "paper"):
            data, enc_ms = timed(lambda: encode_indices(x, k, method), 3 if method == "ans" else 1)
            y, dec_ms = timed(lambda: decode_indices(data, k, x.size, method), 3 if method == "ans" else 1)
            assert np.array_equal(x, y)
            row.update({f"{method}_kib": len(data) / KIB, f"{method}_encode_ms": enc_ms, f"{method}_decode_ms": dec_ms})
        rows.append(row)
    return rows


def clustered_positions(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """xyz [n, 3] in [-2, 2]³ (blobs of spread 0.02–0.3 plus 10% background), t [n] in [0, 10]."""
    rng = np.random.default_rng(seed)
    blobs = max(50, n // 2000)
    centre, spread = rng.uniform(-1.8, 1.8, (blobs, 3)), np.exp(rng.uniform(np.log(0.02), np.log(0.3), blobs))
    b = rng.integers(0, blobs, n)
    xyz = np.clip(centre[b] + spread[b, None] * rng.normal(size=(n, 3)), -2, 2)
    background = rng.random(n) < 0.1
    xyz[background] = rng.uniform(-2, 2, (int(background.sum()), 3))
    t = np.clip(rng.uniform(0, 10, blobs)[b] + rng.uniform(0.2, 3, blobs)[b] * rng.normal(size=n), 0, 10)
    return xyz, t


def position_rows(n: int = 200_000) -> list[dict]:
    xyz, t = clustered_positions(n)
    payload = CompressedPayload(xyz, t)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for codec in ("paper", "ans"):
            sizes, ms = timed(lambda: encode_payload(payload, Path(tmp) / "p.omg4", codec), 1)
            rows.append({"codec": codec, "n": n, "xyz_kib": sizes["xyz"] / KIB, "t_kib": sizes["t"] / KIB,
                         "xyz_bits_per_gaussian": 8 * sizes["xyz"] / n, "t_bits_per_gaussian": 8 * sizes["t"] / n,
                         "encode_ms": ms})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(2)
    idx = index_rows()
    print(f"{'data':>14} {'K':>5} {'n':>7} {'H b/s':>6} {'raw':>7} {'ideal':>7} {'lzma':>7} {'paper':>7} {'ans':>7} "
          f"{'ans+%':>6} {'paper enc/dec ms':>17} {'ans enc/dec ms':>15}   (sizes KiB)")
    for r in idx:
        print(f"{r['data']:>14} {r['k']:>5} {r['n']:>7} {r['entropy_bits_per_symbol']:>6.2f} {r['raw_kib']:>7.1f} "
              f"{r['ideal_kib']:>7.1f} {r['lzma_only_kib']:>7.1f} {r['paper_kib']:>7.1f} {r['ans_kib']:>7.1f} "
              f"{100 * (r['ans_kib'] / r['ideal_kib'] - 1):>6.2f} "
              f"{r['paper_encode_ms']:>8.0f}/{r['paper_decode_ms']:<8.0f} "
              f"{r['ans_encode_ms']:>7.1f}/{r['ans_decode_ms']:<7.1f}")
    pos = position_rows()
    print(f"\n{'codec':>6} {'n':>7} {'xyz KiB':>8} {'xyz b/G':>8} {'t KiB':>7} {'t b/G':>6}   (fp16 raw: 48 + 16 b/G)")
    for r in pos:
        print(f"{r['codec']:>6} {r['n']:>7} {r['xyz_kib']:>8.1f} {r['xyz_bits_per_gaussian']:>8.2f} {r['t_kib']:>7.1f} "
              f"{r['t_bits_per_gaussian']:>6.2f}")
    save_record(args.json, {"command": shlex.join(["python", "benchmarks/studies/entropy.py", *sys.argv[1:]]),
                            "benchmark": "codec.entropy", "index_streams": idx, "positions": pos})


if __name__ == "__main__":
    main()
