"""Benchmark: evaluation metrics on CPU (PSNR, 3DGS SSIM, MS-SSIM, LPIPS-alex/-vgg).

Sizes: 320×180 (the CPU training resolution of basketball) and 1352×1014 (N3DV at half
resolution, the paper's evaluation size). Each entry is timed with
:func:`omg4.metrics.measure_fps`, one call per round after a warm-up call, the cases
interleaved round by round; the table gives the median and minimum over rounds.
``ssim fwd+bwd`` is the training-loss cost; ``ssim separable`` times two 1-D passes
instead of the one depthwise 11×11 convolution the package uses, the measurement behind
that choice. LPIPS-vgg runs once per size after the others (about 14 s at 1352×1014 on
2 idle cores, data §2).

    python benchmarks/speed/metrics.py [--threads 2] [--repeats 7] [--quick] [--json PATH]

On a machine shared with other jobs, run with ``OMP_WAIT_POLICY=PASSIVE`` in the
environment: with spinning OpenMP threads and more runnable jobs than cores, small torch
ops measured 15–30× slower (PSNR at 320×180: 92 ms instead of 5 ms).

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in ``benchmarks/results/metrics.json``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from omg4.testing.records import save_record
from omg4.metrics import LPIPS, measure_fps, ms_ssim, psnr, ssim
from omg4.metrics.ssim import C1, C2

RESULTS = Path(__file__).resolve().parents[1] / "results" / "metrics.json"
SIZES = [(320, 180), (1352, 1014)]


def image_pair(width: int, height: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth image [H, W, 3] and a noisy copy, float32 in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    gt = torch.stack([0.5 + 0.4 * torch.sin(xx / (17.0 + 5 * k) + yy / 23.0) for k in range(3)], -1)
    img = (gt + 0.05 * torch.randn(gt.shape, generator=g)).clamp(0, 1)
    return img.float(), gt.float()


def ssim_separable(img: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """The same 3DGS SSIM with the Gaussian applied as two zero-padded 1-D passes (comparison only)."""
    x, y = img.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    coords = torch.arange(11, dtype=torch.float32) - 5
    g = torch.exp(-coords**2 / (2 * 1.5**2))
    g = g / g.sum()
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    k = stacked.shape[1]
    blurred = F.conv2d(stacked, g.view(1, 1, 1, 11).expand(k, 1, 1, 11), padding=(0, 5), groups=k)
    blurred = F.conv2d(blurred, g.view(1, 1, 11, 1).expand(k, 1, 11, 1), padding=(5, 0), groups=k)
    mx, my, exx, eyy, exy = blurred.split(3, dim=1)
    vx, vy, cxy = exx - mx * mx, eyy - my * my, exy - mx * my
    return (((2 * mx * my + C1) * (2 * cxy + C2)) / ((mx * mx + my * my + C1) * (vx + vy + C2))).mean()


def ssim_loss_step(img: torch.Tensor, gt: torch.Tensor) -> None:
    """Forward and backward of ``1 - ssim`` as in the training loss."""
    x = img.clone().requires_grad_(True)
    with torch.enable_grad():
        (1.0 - ssim(x, gt)).backward()


def run(repeats: int, quick: bool) -> list[dict]:
    """Time every case at every size; cases are interleaved round by round so that load
    changes on a shared machine hit all of them alike (median and minimum over rounds)."""
    alex, vgg = LPIPS("alex"), LPIPS("vgg")
    rows = []
    for width, height in SIZES[:1] if quick else SIZES:
        img, gt = image_pair(width, height)
        cases = {
            "psnr": lambda _: psnr(img, gt),
            "ssim fwd": lambda _: ssim(img, gt),
            "ssim fwd+bwd": lambda _: ssim_loss_step(img, gt),
            "ssim separable fwd": lambda _: ssim_separable(img, gt),
            "ms-ssim": lambda _: ms_ssim(img, gt),
            "lpips-alex": lambda _: alex(img, gt),
        }
        times: dict[str, list[float]] = {name: [] for name in cases}
        for fn in cases.values():  # warm-up
            measure_fps(fn, [None], warmup=1, device="cpu")
        for _ in range(repeats):
            for name, fn in cases.items():
                times[name].append(measure_fps(fn, [None], warmup=0, device="cpu")["median_ms"])
        times["lpips-vgg"] = [measure_fps(lambda _: vgg(img, gt), [None], warmup=0, device="cpu")["median_ms"]]
        for name, values in times.items():
            row = {"metric": name, "width": width, "height": height, "calls": len(values),
                   "median_ms": round(statistics.median(values), 2), "min_ms": round(min(values), 2)}
            rows.append(row)
            print(f"{name:20s} {width:5d}x{height:<5d} {row['median_ms']:10.1f} {row['min_ms']:10.1f} "
                  f"{row['calls']:6d}", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (LPIPS-vgg: 1 call)")
    parser.add_argument("--quick", action="store_true", help="320×180 only")
    parser.add_argument("--json", type=Path, default=RESULTS, help=f"output JSON (default {RESULTS})")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{'metric':20s} {'size':11s} {'median ms':>10s} {'min ms':>10s} {'calls':>6s}")
    rows = run(args.repeats, args.quick)
    policy = os.environ.get("OMP_WAIT_POLICY", "default")
    command = shlex.join(["python", "benchmarks/speed/metrics.py", *sys.argv[1:]])
    if policy != "default":
        command = f"OMP_WAIT_POLICY={shlex.quote(policy)} {command}"
    save_record(args.json, {"command": command, "benchmark": "metrics",
                            "device": "cpu", "threads": args.threads, "torch": torch.__version__,
                            "omp_wait_policy": policy, "load_average_1min_at_end": round(os.getloadavg()[0], 2),
                            "rows": rows})


if __name__ == "__main__":
    main()
