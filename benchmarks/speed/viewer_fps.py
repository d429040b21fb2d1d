"""Benchmark: frames per second the viewer (``omg4 view``) renders and encodes, server side.

For each model, the viewer's frame loop without a browser: the test camera's pose and vertical
field of view at ``--size`` (default 640×360, the 16:9 canvas of a browser window), successive
times as when playing, :meth:`omg4.app.viewer.Viewer.render` (:func:`omg4.app.viewer.render_frame`, our renderer) plus the JPEG encoding the
server sends. Target of the viewer: ≥ 10 frames per second for the demo's OMG4-M on 2 CPU cores.

    python benchmarks/speed/viewer_fps.py DATA --models baseline.safetensors model.omg4 [--frames 40] [--name demo]

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/viewer_fps_<name>.json``.
"""

from __future__ import annotations

import argparse
import io
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from omg4.testing.records import save_record

RESULTS = Path(__file__).resolve().parents[1] / "results"


def measure(path: Path, camera, frames: int, width: int, height: int) -> dict:
    from scipy.spatial.transform import Rotation

    from omg4.app.viewer import camera_from_pose, render_frame
    from omg4.models import load_model

    model = load_model(path)
    c2w = camera.camtoworld
    wxyz = Rotation.from_matrix(c2w[:3, :3]).as_quat()[[3, 0, 1, 2]]
    fov_y = 2 * np.arctan(0.5 * camera.height / camera.K[1, 1])
    view = camera_from_pose(c2w[:3, 3], wxyz, fov_y, width / height, max(width, height))
    t0, t1 = model.config.time_range
    times = [t0 + (t1 - t0) * i / frames for i in range(frames)]
    ms, visible = [], []
    for i, t in enumerate(times[:3] + times):
        start = time.perf_counter()
        image, fraction = render_frame(model, view, t, backend="cpu")
        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format="JPEG", quality=85)
        if i >= 3:
            ms.append(1000 * (time.perf_counter() - start))
            visible.append(fraction)
    median = statistics.median(ms)
    return {"model": str(path), "num_gaussians": model.num_gaussians, "size": [view.width, view.height],
            "ms_per_frame": median, "fps": 1000 / median, "visible_fraction": float(np.mean(visible)),
            "frames": frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--models", type=Path, nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--name", default="demo", help="the scene's name in the record's file name")
    args = ap.parse_args()
    from omg4.data import load_scene

    width, height = (int(x) for x in args.size.split("x"))
    scene = load_scene(args.data, decode=False, progress=False)
    camera = scene.test_cameras()[0]
    results = [measure(m, camera, args.frames, width, height) for m in args.models]
    for r in results:
        print(f"{r['model']}: {r['num_gaussians']} G, {r['fps']:.1f} FPS at {r['size'][0]}x{r['size'][1]} "
              f"({r['ms_per_frame']:.1f} ms, {100 * r['visible_fraction']:.0f} % visible)")
    save_record(RESULTS / f"viewer_fps_{args.name}.json", {
        "command": shlex.join(["python", "benchmarks/speed/viewer_fps.py", *sys.argv[1:]]), "scene": args.name,
        "torch_threads": torch.get_num_threads(), "rows": results})


if __name__ == "__main__":
    main()
