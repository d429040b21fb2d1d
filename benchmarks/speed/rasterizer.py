"""Benchmark: the differentiable rasterizer (docs/paper-map.md "Rasterizer backends").

Scene as in the reference measurements: N Gaussians at random in a box 2–4 units in front
of a pinhole camera with f = 1.2·W, arbitrary random SPD covariances ``A·Aᵀ`` with
``A ~ 0.035·N(0, 1)`` (about 4.5 tiles per Gaussian at 128², 10 at 256²), opacity
0.1–0.9, RGB colours. "fwd" is one render without grad; "fwd+bwd" is projection with
autograd, binning, compositing and backward to means, covariances, colours and opacities.
Each figure is the median of ``--runs`` timed runs after one warm-up. "work" is the number
of (pixel, Gaussian) pairs inside the Gaussians' boxes, i.e. pixels × Gaussians per pixel;
``us_per_kpair`` lets cases of different density be compared (time should grow no worse
than linearly with work). Compile time is measured in fresh processes: "cold" with an
empty ``NUMBA_CACHE_DIR``, "warm" with the cache the cold run left.

    python benchmarks/speed/rasterizer.py [--backend cpu|gsplat] [--device cpu|cuda] [--runs 7] [--quick]
                                    [--torch-threads N] [--no-compile] [--json PATH]

``--torch-threads`` sets torch's intra-op threads (numba keeps its own); on a 2-core
machine that other processes also load, torch's OpenMP threads can stall badly, so the
setting is recorded with the results.

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/rasterizer.json`` (the CPU backend) or ``rasterizer_gsplat.json``.
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
from pathlib import Path

import torch

from omg4.testing.records import save_record
from omg4.render import rasterize
from omg4.render.api import bin_gaussians
from omg4.render.binning import sigma_cutoff
from omg4.render.projection import project_gaussians

RESULTS = Path(__file__).resolve().parents[1] / "results"
TARGET = "cpu fwd+bwd at 128x128/20k <= 50 ms on a 2-core machine"
CASES = [(128, 128, 20_000), (256, 256, 50_000), (640, 360, 100_000)]
QUICK_CASES = [(128, 128, 20_000)]


def make_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu") -> dict:
    """Keyword arguments of ``rasterize`` for the benchmark scene (float32)."""
    g = torch.Generator().manual_seed(seed)
    f = 1.2 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    z = 2 + 2 * torch.rand(n, generator=g)
    uv = torch.rand(n, 2, generator=g) * torch.tensor([width, height])
    means = torch.stack([(uv[:, 0] - width / 2) / f * z, (uv[:, 1] - height / 2) / f * z, z], -1)
    A = torch.randn(n, 3, 3, generator=g) * 0.035
    covars = A @ A.transpose(1, 2) + 1e-5 * torch.eye(3)
    colors = torch.rand(n, 3, generator=g)
    opacities = 0.1 + 0.8 * torch.rand(n, generator=g)
    tensors = dict(means=means, covars=covars, colors=colors, opacities=opacities, viewmat=torch.eye(4), K=K)
    out = {k: v.to(device) for k, v in tensors.items()}
    out.update(width=width, height=height)
    return out


def scene_stats(scene: dict) -> dict:
    """Intersections per Gaussian and (pixel, Gaussian) pairs inside the boxes (CPU projection)."""
    s = {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in scene.items()}
    w, h = s["width"], s["height"]
    p = project_gaussians(s["means"], s["covars"], s["viewmat"], s["K"], w, h, opacities=s["opacities"])
    bins, boxes = bin_gaussians(p, sigma_cutoff(s["opacities"]), None, 1, w, h)
    boxes = boxes.long()
    area = ((boxes[:, 1] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 2]))[p.visible]
    return {"visible": int(p.visible.sum()), "isect_per_gaussian": bins.num_intersections / len(p.visible),
            "gaussians_per_pixel": float(area.sum()) / (w * h), "work_pairs": int(area.sum())}


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_ms(fn, runs: int, device: str) -> list[float]:
    fn()
    _sync(device)
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def run_case(width: int, height: int, n: int, backend: str, device: str, runs: int) -> dict:
    scene = make_scene(n, width, height, device=device)

    def forward():
        with torch.no_grad():
            rasterize(**scene, backend=backend)

    leaves = {k: scene[k].clone().requires_grad_() for k in ("means", "covars", "colors", "opacities")}

    def forward_backward():
        r = rasterize(**{**scene, **leaves}, backend=backend)
        r.image.sum().backward()

    fwd = time_ms(forward, runs, device)
    fwd_bwd = time_ms(forward_backward, runs, device)
    stats = scene_stats(scene)
    row = {"width": width, "height": height, "n": n, **stats,
           "fwd_ms": round(statistics.median(fwd), 2), "fwd_bwd_ms": round(statistics.median(fwd_bwd), 2),
           "fwd_ms_runs": [round(t, 2) for t in fwd], "fwd_bwd_ms_runs": [round(t, 2) for t in fwd_bwd]}
    row["us_per_kpair_fwd_bwd"] = round(row["fwd_bwd_ms"] * 1e6 / max(stats["work_pairs"], 1), 3)
    return row


_COMPILE_PROBE = """
import time, torch
t0 = time.perf_counter()
from omg4.render import rasterize
t1 = time.perf_counter()
m = torch.tensor([[0.0, 0.0, 3.0], [0.1, 0.0, 3.5]], requires_grad=True)
args = (m, torch.eye(3).expand(2, 3, 3) * 0.01, torch.ones(2, 3), torch.full((2,), 0.5), torch.eye(4),
        torch.tensor([[10.0, 0, 8], [0, 10, 8], [0, 0, 1]]), 16, 16)
def step():
    r = rasterize(*args, backend="cpu")
    r.image.sum().backward()
t2 = time.perf_counter(); step(); t3 = time.perf_counter(); step(); t4 = time.perf_counter()
print(t1 - t0, (t3 - t2) - (t4 - t3))
"""


def compile_times() -> dict:
    """First-call cost of the numba kernels (fwd + bwd) in fresh processes, cold and warm cache."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label in ("cold", "warm"):
            res = subprocess.run([sys.executable, "-c", _COMPILE_PROBE], env=env, capture_output=True, text=True,
                                 check=True)
            import_s, first_call_s = (float(x) for x in res.stdout.split())
            out[f"{label}_first_call_s"] = round(first_call_s, 3)
            out[f"{label}_import_s"] = round(import_s, 3)
    return out


def setup_info(device: str) -> dict:
    """Library versions, threads and the load at the start (the machine itself is in the record's run)."""
    import numba

    info = {"torch": torch.__version__, "numba": numba.__version__, "torch_threads": torch.get_num_threads(),
            "numba_threads": numba.get_num_threads(), "loadavg_at_start": [round(x, 2) for x in os.getloadavg()]}
    if device == "cuda":
        info["gpu"] = torch.cuda.get_device_name()
        import gsplat

        info["gsplat"] = gsplat.__version__
    return info


def print_table(backend: str, rows: list[dict], compile_info: dict | None) -> None:
    print(f"\nrasterizer backend={backend}")
    print(f"{'size':>10} {'N':>7} {'isect/G':>8} {'G/pixel':>8} {'fwd ms':>8} {'fwd+bwd ms':>11} {'us/kpair':>9}")
    for r in rows:
        print(f"{r['width']}x{r['height']:<6} {r['n']:>7} {r['isect_per_gaussian']:>8.2f} "
              f"{r['gaussians_per_pixel']:>8.1f} {r['fwd_ms']:>8.1f} {r['fwd_bwd_ms']:>11.1f} "
              f"{r['us_per_kpair_fwd_bwd']:>9.3f}")
    if compile_info:
        print("numba first call (fwd+bwd compile or cache load): "
              f"cold {compile_info['cold_first_call_s']:.2f} s, warm {compile_info['warm_first_call_s']:.2f} s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cpu", choices=["cpu", "gsplat"])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="only 128x128 / 20k")
    ap.add_argument("--torch-threads", type=int, default=0, help="torch intra-op threads (0: leave torch's default)")
    ap.add_argument("--no-compile", action="store_true", help="skip the compile-time probes")
    ap.add_argument("--json", type=Path, default=None,
                    help="record file (default benchmarks/results/rasterizer.json, rasterizer_gsplat.json for gsplat)")
    args = ap.parse_args(argv)
    if args.backend == "gsplat" and args.device != "cuda":
        ap.error("--backend gsplat needs --device cuda")

    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    info = setup_info(args.device)
    rows = [run_case(w, h, n, args.backend, args.device, args.runs) for w, h, n in (QUICK_CASES if args.quick
                                                                                     else CASES)]
    if args.backend == "cpu":
        import numba

        info["numba_threading_layer"] = numba.threading_layer()
    info["loadavg_at_end"] = [round(x, 2) for x in os.getloadavg()]
    compile_info = None if (args.no_compile or args.backend != "cpu") else compile_times()
    print_table(args.backend, rows, compile_info)

    result = {"command": shlex.join(["python", "benchmarks/speed/rasterizer.py", *(sys.argv[1:] if argv is None else argv)]),
              "backend": args.backend, "device": args.device, "torch_threads": info["torch_threads"], "setup": info,
              "cases": rows}
    if compile_info:
        result["compile"] = compile_info
    result["target"] = TARGET
    save_record(args.json or RESULTS / ("rasterizer.json" if args.backend == "cpu" else
                                        f"rasterizer_{args.backend}.json"), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
