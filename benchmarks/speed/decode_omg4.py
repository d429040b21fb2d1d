"""Decode time of ``.omg4`` files of about 3 MB, per codec (the "compact" codec's speed bound).

A well-formed compressed model (:func:`omg4.testing.forge.valid_payload`: the M preset's codebook sizes,
random values) is grown until its file holds at least ``--megabytes`` MB, written with each
codec, then decoded ``--repeats`` times: ``decode_payload`` (file → arrays) and ``load_omg4``
(file → renderable model with its visibility index). Reports the median seconds.

Usage: python benchmarks/speed/decode_omg4.py [--megabytes 3] [--repeats 5] [--json FILE]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/decode_omg4.json``.
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import tempfile
import time
from pathlib import Path

from omg4.testing.records import save_record
from omg4.codec.payload import CODECS, decode_payload, encode_payload
from omg4.models.compact import load_omg4

ROOT = Path(__file__).resolve().parents[2]
from omg4.testing.forge import valid_payload


def sized_file(path: Path, codec: str, megabytes: float) -> tuple[int, int]:
    """Write a payload whose ``codec`` file is at least ``megabytes`` MB; returns (Gaussians, bytes)."""
    n = 20_000
    while True:
        payload = valid_payload(n, seed=0)
        size = sum(encode_payload(payload, path, codec=codec).values())
        if size >= megabytes * 2**20:
            return n, size
        n = int(n * 1.05 * megabytes * 2**20 / size) + 1


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--megabytes", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "decode_omg4.json")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for codec in CODECS:
            path = Path(tmp) / f"{codec}.omg4"
            n, size = sized_file(path, codec, args.megabytes)
            load_omg4(path)  # warm up numba and imports
            rows.append({"codec": codec, "gaussians": n, "bytes": size, "MB": round(size / 2**20, 3),
                         "decode_payload_s": round(median_seconds(lambda: decode_payload(path), args.repeats), 4),
                         "load_omg4_s": round(median_seconds(lambda: load_omg4(path), args.repeats), 4)})
            r = rows[-1]
            print(f"{codec:<8} {n:>8} G {r['MB']:>7.3f} MB  decode {r['decode_payload_s']:.3f} s  "
                  f"load {r['load_omg4_s']:.3f} s")
    save_record(args.json, {"command": shlex.join(["python", "benchmarks/speed/decode_omg4.py", *sys.argv[1:]]),
                            "benchmark": "decode_omg4", "megabytes": args.megabytes, "repeats": args.repeats,
                            "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
