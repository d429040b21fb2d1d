"""Fuzz benchmark: forged ``.omg4`` files through info, decoding, loading and rendering.

Valid compressed models of three size classes (every codec) are mutated by
:mod:`omg4.testing.forge` — hostile header values, damaged or re-split sections, hostile
names, all with recomputed checksums, plus raw damage — and each case runs through
its ``exercise`` in this process. Per case: the outcome ("ok",
"CorruptFileError", or the escaping exception's type), the wall time, and the peak resident
memory (Linux ``VmHWM``, reset before each case through ``/proc/self/clear_refs``). Each
size class's valid file is measured the same way; the target is every failure a
``CorruptFileError``, no case over 2 s, none over 4× its class's valid peak memory.

    python tools/fuzz_omg4.py [--cases 10000] [--seed 0] [--codecs compact,ans,paper]
                                   [--grid-bits 15,9,10]  # the compact files' grids (version 5 by default)
                                   [--layouts single,sequence,predicted]  # single models; sequences of three
                                   # segments, each alone or predicted from the one before

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/fuzz_omg4.json``.
"""

from __future__ import annotations

import argparse
import collections
import shlex
import signal
import sys
import tempfile
import time
from pathlib import Path

from omg4.testing.records import save_record
from omg4.codec.payload import CODECS

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "fuzz_omg4.json"
#: size class → (Gaussians, codebook scale): a tiny file, a demo-sized one, a larger one
CLASSES = {"small": (300, 0.1), "medium": (5000, 1.0), "large": (40000, 1.0)}
CASE_TIMEOUT_S = 20


def _peak_rss_reset() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _alarm(signum, frame):
    raise TimeoutError("case took too long")


def run_case(path: Path) -> tuple[str, float, float]:
    """(outcome, seconds, peak RSS MB) of one file through ``forge.exercise``."""
    from omg4.errors import CorruptFileError
    from omg4.testing.forge import exercise

    _peak_rss_reset()
    signal.alarm(CASE_TIMEOUT_S)
    t0 = time.perf_counter()
    try:
        outcome = exercise(path)
    except CorruptFileError as exc:
        outcome = "CorruptFileError" if "\n" not in str(exc) else "CorruptFileError (multi-line)"
    except TimeoutError:
        outcome = "timeout"
    except Exception as exc:  # what the fuzzer is looking for: report it, keep going
        outcome = type(exc).__name__
    finally:
        signal.alarm(0)
    return outcome, time.perf_counter() - t0, _peak_rss_mb()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=10000, help="forged files in total (split over classes and codecs)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--codecs", default=",".join(CODECS), help="comma-separated codecs to fuzz")
    ap.add_argument("--grid-bits", default="15,9,10", help="the compact codec's grids (omg4 compress --grid-bits)")
    ap.add_argument("--layouts", default="single,sequence,predicted",
                    help="single models and/or sequences of three segments of the class's size: each coded alone "
                         "(sequence) or the last two predicted from the one before (predicted)")
    args = ap.parse_args()

    import torch

    from omg4.codec.payload import CompactGrids
    from omg4.testing.forge import forged_files, valid_file, valid_sequence

    grids = CompactGrids.parse(args.grid_bits)

    torch.set_num_threads(1)
    signal.signal(signal.SIGALRM, _alarm)
    codecs = args.codecs.split(",")
    layouts = args.layouts.split(",")
    per_base = max(1, args.cases // (len(codecs) * len(CLASSES) * len(layouts)))
    rows, outcomes, escapes = [], collections.Counter(), collections.Counter()
    with tempfile.TemporaryDirectory() as tmp:
        case_path = Path(tmp) / "case.omg4"
        valid_file(Path(tmp) / "warm.omg4", 50)
        run_case(Path(tmp) / "warm.omg4")  # loads the rasterizer kernels before anything is measured
        for name, (n, scale), codec, layout in ((*c, k, lay) for c in CLASSES.items() for k in codecs
                                                for lay in layouts):
            base_path = Path(tmp) / f"{name}_{codec}_{layout}.omg4"
            precision = grids if codec == "compact" else CompactGrids()
            base = (valid_file(base_path, n, codec=codec, seed=1, codebook_scale=scale, precision=precision)
                    if layout == "single" else
                    valid_sequence(base_path, 3, n, codec=codec, seed=1, codebook_scale=scale, precision=precision,
                                   key_interval=3 if layout == "predicted" else 1))
            valid_outcome, valid_s, valid_mb = run_case(base_path)
            assert valid_outcome == "ok", valid_outcome
            worst_s, worst_mb, slowest = 0.0, 0.0, None
            counts = collections.Counter()
            for k, (kind, data) in enumerate(forged_files(base, per_base, seed=args.seed)):
                case_path.write_bytes(data)
                outcome, seconds, mb = run_case(case_path)
                counts[outcome] += 1
                if outcome not in ("ok", "CorruptFileError"):
                    escapes[(kind, outcome)] += 1
                if seconds > worst_s:
                    worst_s, slowest = seconds, f"{kind} #{k}"
                worst_mb = max(worst_mb, mb)
            outcomes.update(counts)
            row = {"class": name, "codec": codec, "layout": layout, "gaussians": n, "file_bytes": len(base),
                   "cases": per_base,
                   "outcomes": dict(counts), "valid_s": round(valid_s, 4), "valid_peak_mb": round(valid_mb, 1),
                   "slowest_s": round(worst_s, 4), "slowest_case": slowest, "peak_mb": round(worst_mb, 1),
                   "peak_ratio": round(worst_mb / valid_mb, 3)}
            rows.append(row)
            print(f"{name:<7} {codec:<6} {layout:<8} {len(base):>9} B  {dict(counts)}  slowest {worst_s:.3f} s "
                  f"({slowest}), peak {worst_mb:.0f} MB = {worst_mb / valid_mb:.2f}x valid ({valid_mb:.0f} MB)")
    result = {"command": shlex.join(["python", "tools/fuzz_omg4.py", *sys.argv[1:]]), "seed": args.seed,
              "codecs": codecs, "layouts": layouts, "grids": grids.label, "cases": sum(r["cases"] for r in rows),
              "outcomes": dict(outcomes), "escapes": {f"{k} {o}": c for (k, o), c in escapes.items()},
              "slowest_s": max(r["slowest_s"] for r in rows), "max_peak_ratio": max(r["peak_ratio"] for r in rows),
              "rows": rows}
    print(f"{result['cases']} cases: {dict(outcomes)}; slowest {result['slowest_s']:.3f} s; "
          f"peak memory at most {result['max_peak_ratio']:.2f}x the valid file's")
    save_record(RESULTS, result)


if __name__ == "__main__":
    main()
