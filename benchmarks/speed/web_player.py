"""Benchmark: the .omg4 web player (``omg4 export --format web``) in headless Chromium with software WebGL2.

For each model: the export folder served by a local static server, the page opened at ``--size`` (default
640×360) from the first test camera (``--data``) or the file's camera rig, playing. Measured: load to first frame
(navigation start to ``window.omg4Ready``, which includes fetching, decoding, the per-Gaussian set-up and the
first frame), the bytes transferred (every file the page fetched), frames per second while playing (frames the
page drew in ``--seconds`` of playback: each a new time, so a new slice through the MLPs) and while the camera
orbits a paused frame (the median of finished frames, each drawn and read back: a new view of the same time), and
the time of each of the renderer's passes (the slice through the MLPs, the sort, the splats, the present pass), each
drained before the next is timed. ``--forged N`` adds a file of N random Gaussians (:mod:`omg4.testing.forge`) to
measure the player at that size. The page is the export's ``index.html``: one ``<omg4-player>`` element.

Where the npm packages of ``package.json`` are installed (``npm ci``), each model is also played by the export's
``spark.html`` (three.js drawing through Spark, fed by ``web/spark.js``): first frame, frames per second playing,
and its PSNR against ``omg4 render``. Each model's glTF slice (``omg4 export --out X.glb``) is written and checked by
Khronos's glTF-Validator: its bytes and the validator's counts and issue codes.

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

import numpy as np

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"

from omg4.testing.browser import Browser, data_url_image, open_player, served

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

# each pass of the renderer at a new time, drained (a one-pixel read) before the next is timed; medians of 6 times
PASSES = """(() => {
  const p = window.omg4Player; p.pause(); const gl = p.gl; const cam = p.state.camera;
  const r = p.playback.loaded.get(0).renderer; const pixel = new Uint8Array(4); const value = new Float32Array(4);
  const drain = () => { gl.bindFramebuffer(gl.FRAMEBUFFER, null); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel); };
  const ms = { slice: [], sort: [], splats: [], present: [] };
  for (let i = 0; i < 6; i++) {
    const tau = p.timeRange[0] + (p.timeRange[1] - p.timeRange[0]) * (0.1 + 0.13 * i);
    drain();
    let start = performance.now(); r.sliceAt(tau); ms.slice.push(performance.now() - start);
    start = performance.now(); r._sort(cam); ms.sort.push(performance.now() - start);
    drain();
    start = performance.now(); const image = r.draw(tau, cam, [0, 0, 0]);
    gl.bindFramebuffer(gl.FRAMEBUFFER, r.target.framebuffer); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.FLOAT, value);
    ms.splats.push(performance.now() - start);
    start = performance.now(); p.playback.compositor.present([[image, 1]], cam.width, cam.height); drain();
    ms.present.push(performance.now() - start);
  }
  const median = (a) => a.slice().sort((x, y) => x - y)[a.length >> 1];
  return Object.fromEntries(Object.entries(ms).map(([k, v]) => [k, median(v)]));
})()"""

TRANSFERRED = """[performance.getEntriesByType('navigation'), performance.getEntriesByType('resource')].flat()
  .reduce((sum, e) => sum + (e.encodedBodySize || 0), 0)"""


def opened(browser: Browser, url: str) -> dict:
    """The page at ``url`` after its first frame (``open_player``'s ``ready``); a page that fails ends the run."""
    result = open_player(browser, url, timeout=600)
    if "error" in result:
        raise SystemExit(f"{url}: the page failed: {result['message']}")
    return result


def frame_rate(browser: Browser, frames: str, seconds: float) -> float:
    """Frames per second over ``seconds``, from the page's frame counter (the expression ``frames``)."""
    before = browser.evaluate(frames)
    time.sleep(seconds)
    return (browser.evaluate(frames) - before) / seconds


def measure(browser: Browser, folder: Path, width: int, height: int, seconds: float) -> dict:
    with served(folder) as url:
        result = opened(browser, f"{url}/index.html?ui=0&width={width}&height={height}")
        ready_ms = browser.evaluate("performance.now()")
        load_ms = browser.evaluate("window.omg4Ready.then(() => window.omg4FirstFrameMs)")
        fps = frame_rate(browser, "window.omg4Player.frames", seconds)
        transferred = browser.evaluate(TRANSFERRED)
        browser.evaluate("window.omg4Player.state.playing = false")
        time.sleep(1.0)
        orbit = browser.evaluate(ORBIT.replace("FRAMES", "12"), timeout=600)[2:]  # after the first new views
        passes = browser.evaluate(PASSES, timeout=600)
        ready = result["ready"]
    return {"num_gaussians": ready["gaussians"], "file_bytes": ready["bytes"], "bytes_transferred": transferred,
            "load_to_first_frame_ms": load_ms, "measured_at_ms": ready_ms, "size": [width, height],
            "fps": fps, "orbit_ms_per_frame": statistics.median(orbit),
            "orbit_fps": 1000 / statistics.median(orbit), "camera": ready["camera"], "pass_ms": passes}


def reference_frame(model: Path, data: Path, tmp: Path) -> tuple[float, np.ndarray]:
    """(time, image): ``omg4 render`` of the dataset's first test camera at mid-clip, the frame each page is
    compared with."""
    import subprocess

    from PIL import Image

    from omg4.models import load_model

    t0, t1 = load_model(model).config.time_range
    time_ = round((t0 + t1) / 2, 3)
    subprocess.run([sys.executable, "-m", "omg4", "render", "--model", str(model), "--data", str(data), "--time",
                    str(time_), "--out", str(tmp / "reference.png")], check=True, capture_output=True)
    return time_, np.asarray(Image.open(tmp / "reference.png").convert("RGB"), np.float64)


def page_psnr(browser: Browser, url: str, canvas: str, reference: np.ndarray, settle_s: float = 0.0) -> float:
    """PSNR of the page at ``url`` (its first frame, ``settle_s`` later) against ``reference``; ``canvas``: the
    expression of the page's canvas."""
    from omg4.metrics import psnr

    open_player(browser, url, timeout=600)
    time.sleep(settle_s)
    png = browser.evaluate(f"{canvas}.toDataURL('image/png')")
    page = data_url_image(png)
    return psnr(page / 255.0, reference / 255.0)


def fidelity(browser: Browser, folder: Path, reference: tuple[float, np.ndarray]) -> dict:
    """PSNR of the page's frame against ``omg4 render`` of the same test camera and time (:func:`reference_frame`)."""
    time_, image = reference
    height, width = image.shape[:2]
    with served(folder) as url:
        db = page_psnr(browser, f"{url}/index.html?ui=0&width={width}&height={height}&time={time_}",
                       "document.querySelector('omg4-player').canvas", image)
    return {"psnr_vs_omg4_render_db": db, "psnr_time": time_, "psnr_size": [width, height]}


def spark(browser: Browser, folder: Path, reference: tuple[float, np.ndarray] | None, width: int, height: int,
          seconds: float) -> dict:
    """The export's spark.html (three.js + Spark, the npm packages linked into the folder): first frame, frames per
    second playing, and with a ``reference`` frame (:func:`reference_frame`) its PSNR against it."""
    (folder / "node_modules").symlink_to(REPO / "node_modules")
    with served(folder) as url:
        opened(browser, f"{url}/spark.html?width={width}&height={height}")
        row = {"spark_first_frame_ms": browser.evaluate("window.omg4FirstFrameMs"),
               "spark_fps": frame_rate(browser, "window.omg4Spark.frames", seconds)}
        if reference is not None:
            time_, image = reference
            h, w = image.shape[:2]
            row["spark_psnr_vs_omg4_render_db"] = page_psnr(  # Spark sorts on a worker: a moment after its frame
                browser, f"{url}/spark.html?width={w}&height={h}&time={time_}", "document.querySelector('canvas')",
                image, settle_s=1.5)
    return row


def gltf_slice(model: Path, tmp: Path) -> dict:
    """The model's glTF slice at mid-clip: its bytes, and Khronos's glTF-Validator's counts and issue codes."""
    import json
    import subprocess

    from omg4.models import load_model

    t0, t1 = load_model(model).config.time_range
    out = tmp / "slice.glb"
    subprocess.run([sys.executable, "-m", "omg4", "export", str(model), "--time", str((t0 + t1) / 2), "--out",
                    str(out), "--force"], check=True, capture_output=True)
    row = {"gltf_bytes": out.stat().st_size}
    if (REPO / "node_modules" / "gltf-validator").is_dir():
        report = json.loads(subprocess.run(["node", str(REPO / "tools" / "validate_gltf.mjs"), str(out)], cwd=REPO,
                                           check=True, capture_output=True, text=True).stdout)
        issues = report["issues"]
        row["gltf_validator"] = {"errors": issues["numErrors"], "warnings": issues["numWarnings"],
                                 "infos": issues["numInfos"],
                                 "codes": sorted({m["code"] for m in issues["messages"]})}
    return row


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
    # Chromium's child processes may still write its profile in there as it closes: a finished run keeps its record
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:
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
                own = cameras is not None and not label.startswith("forged")
                reference = reference_frame(path, args.data, tmp) if own else None
                if own:
                    row.update(fidelity(browser, folder, reference))
                    print(f"{label}: {row['psnr_vs_omg4_render_db']:.1f} dB PSNR against omg4 render", flush=True)
                if (REPO / "node_modules" / "@sparkjsdev" / "spark").is_dir():
                    row.update(spark(browser, folder, reference, width, height, args.seconds))
                row.update(gltf_slice(path, tmp))
                print(f"{label}: passes {row['pass_ms']} ms; Spark page "
                      f"{row.get('spark_fps', float('nan')):.1f} FPS playing, first frame after "
                      f"{row.get('spark_first_frame_ms', float('nan')):.0f} ms"
                      + (f", {row['spark_psnr_vs_omg4_render_db']:.1f} dB" if "spark_psnr_vs_omg4_render_db" in row else "")
                      + f"; glTF slice {row['gltf_bytes']:,} B, validator {row.get('gltf_validator')}", flush=True)
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
