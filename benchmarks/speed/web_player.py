"""Benchmark: the .omg4 web player (``omg4 export --format web``) in headless Chromium with software WebGL2.

For each model: the export folder served by a local static server, the page opened at ``--size`` (default
640×360) from the first test camera (``--data``) or the file's camera rig, playing. Measured: load to first frame
(navigation start to ``window.omg4Ready``, which includes fetching, decoding, the per-Gaussian set-up and the
first frame), the bytes transferred (every file the page fetched), frames per second while playing (frames the
page drew in ``--seconds`` of playback: each a new time, so a new slice through the MLPs) and while the camera
orbits a paused frame (the median of finished frames, each drawn and read back: a new view of the same time). ``--forged N`` adds a file of N
random Gaussians (:mod:`omg4.testing.forge`) to measure the player at that size.

    python benchmarks/speed/web_player.py omg4_demo/scene_M.omg4 --data omg4_demo/scene --forged 60000 --name demo

Each run is recorded (:func:`environment.save_record`: commit, date, machine) in
``benchmarks/results/web_player_<name>.json``.
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

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"

from omg4.testing.browser import Browser, open_player, served

# time paused, the camera orbiting the focus a degree a frame: each frame drawn and read back (a finished frame)
ORBIT = """import('./camera.js').then(({ lookAt }) => {
  const p = window.omg4Player, gl = p.gl, cam = p.state.camera, pixel = new Uint8Array(4);
  const v = cam.viewmat, focus = [0, 1, 2].map((k) => cam.center[k] + p.state.distance * v[8 + k]);
  const ms = [];
  for (let i = 1; i <= FRAMES; i++) {
    const a = (i * Math.PI) / 180, o = [0, 1, 2].map((k) => cam.center[k] - focus[k]);
    const eye = [focus[0] + o[0] * Math.cos(a) - o[1] * Math.sin(a), focus[1] + o[0] * Math.sin(a) + o[1] * Math.cos(a), cam.center[2]];
    const view = { ...cam, viewmat: lookAt(eye, focus), center: eye };
    const start = performance.now();
    p.playback.frame(p.state.time, view, [0, 0, 0]);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
    ms.push(performance.now() - start);
  }
  return ms;
})"""

TRANSFERRED = """[performance.getEntriesByType('navigation'), performance.getEntriesByType('resource')].flat()
  .reduce((sum, e) => sum + (e.encodedBodySize || 0), 0)"""


def measure(browser: Browser, folder: Path, width: int, height: int, seconds: float) -> dict:
    with served(folder) as url:
        result = open_player(browser, f"{url}/index.html?ui=0&width={width}&height={height}", timeout=600)
        if "error" in result:
            raise SystemExit(f"{folder}: the page failed: {result['message']}")
        ready_ms = browser.evaluate("performance.now()")
        load_ms = browser.evaluate("window.omg4Ready.then(() => window.omg4FirstFrameMs)")
        frames0 = browser.evaluate("window.omg4Player.frames")
        time.sleep(seconds)
        frames1 = browser.evaluate("window.omg4Player.frames")
        transferred = browser.evaluate(TRANSFERRED)
        browser.evaluate("window.omg4Player.state.playing = false")
        time.sleep(1.0)
        orbit = browser.evaluate(ORBIT.replace("FRAMES", "12"), timeout=600)[2:]  # after the first new views
        ready = result["ready"]
    return {"num_gaussians": ready["gaussians"], "file_bytes": ready["bytes"], "bytes_transferred": transferred,
            "load_to_first_frame_ms": load_ms, "measured_at_ms": ready_ms, "size": [width, height],
            "fps": (frames1 - frames0) / seconds, "orbit_ms_per_frame": statistics.median(orbit),
            "orbit_fps": 1000 / statistics.median(orbit), "camera": ready["camera"]}


def fidelity(browser: Browser, folder: Path, model: Path, data: Path, tmp: Path) -> dict:
    """PSNR of the page's frame against ``omg4 render`` of the same test camera and time (mid-clip)."""
    import base64
    import io
    import subprocess

    import numpy as np
    from PIL import Image

    from omg4.metrics import psnr
    from omg4.models import load_model

    t0, t1 = load_model(model).config.time_range
    time_ = round((t0 + t1) / 2, 3)
    subprocess.run([sys.executable, "-m", "omg4", "render", "--model", str(model), "--data", str(data), "--time",
                    str(time_), "--out", str(tmp / "reference.png")], check=True, capture_output=True)
    reference = np.asarray(Image.open(tmp / "reference.png").convert("RGB"), np.float64)
    with served(folder) as url:
        height, width = reference.shape[:2]
        open_player(browser, f"{url}/index.html?ui=0&width={width}&height={height}&time={time_}")
        png = browser.evaluate("document.querySelector('omg4-player').canvas.toDataURL('image/png')")
    page = np.asarray(Image.open(io.BytesIO(base64.b64decode(png.split(",", 1)[1]))).convert("RGB"), np.float64)
    return {"psnr_vs_omg4_render_db": psnr(page / 255.0, reference / 255.0), "psnr_time": time_,
            "psnr_size": list(reference.shape[1::-1])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", type=Path, help=".omg4 files")
    ap.add_argument("--data", type=Path, help="dataset folder whose cameras the export takes (test camera first)")
    ap.add_argument("--forged", type=int, nargs="*", default=[], help="add files of this many random Gaussians")
    ap.add_argument("--size", default="640x360", help="canvas WIDTHxHEIGHT (default 640x360)")
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds of playback to count frames over")
    ap.add_argument("--name", default="demo", help="record name: benchmarks/results/web_player_<name>.json")
    args = ap.parse_args()
    from omg4.io.web_player import export_web

    width, height = (int(v) for v in args.size.split("x"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        models = [(str(m), m) for m in args.models]
        for n in args.forged:
            from omg4.testing import forge

            forge.valid_file(tmp / f"forged_{n}.omg4", n, codec="compact", seed=n)
            models.append((f"forged, {n:,} random Gaussians", tmp / f"forged_{n}.omg4"))
        cameras, held_out = None, 0
        if args.data is not None:
            from omg4.data import load_scene

            scene = load_scene(args.data, decode=False, progress=False)
            cameras, held_out = scene.cameras(), len(scene.test_cameras())
        browser = Browser(tmp / "profile")
        try:
            for label, path in models:
                folder = tmp / f"web_{len(rows)}"
                export_web(folder, path, cameras if not label.startswith("forged") else None, held_out)
                row = {"model": label, **measure(browser, folder, width, height, args.seconds)}
                if cameras is not None and not label.startswith("forged"):
                    row.update(fidelity(browser, folder, path, args.data, tmp))
                    print(f"{label}: {row['psnr_vs_omg4_render_db']:.1f} dB PSNR against omg4 render", flush=True)
                print(f"{label}: {row['num_gaussians']:,} Gaussians, {row['file_bytes']:,} B file, "
                      f"{row['bytes_transferred']:,} B transferred, first frame after {row['load_to_first_frame_ms']:.0f} ms, "
                      f"playing {row['fps']:.1f} FPS, orbiting a paused frame {row['orbit_fps']:.1f} FPS at "
                      f"{width}x{height}", flush=True)
                rows.append(row)
        finally:
            browser.close()
    save_record(RESULTS / f"web_player_{args.name}.json", {
        "command": "python benchmarks/speed/web_player.py " + shlex.join(sys.argv[1:]),
        "browser": "headless Chromium, software WebGL2 (SwiftShader)", "rows": rows})


if __name__ == "__main__":
    main()
