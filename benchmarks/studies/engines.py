"""Benchmark: an omg4 model's time slice in other engines, against ``omg4 render`` (:mod:`omg4.testing.engines`).

For each model (an ``.omg4`` file with ``--data``: the dataset's test camera; ``--forged N``: a file of N random
Gaussians and a camera framing it): the slice at ``--time`` exported as ``.glb`` and drawn by PlayCanvas and by
Babylon.js, and exported as ``.ply``, turned into glTF by PlayCanvas's ``splat-transform`` (as SuperSplat reads a
``.ply``) and drawn by PlayCanvas — each from the camera turned into glTF's world: PSNR against ``omg4 render`` of
that camera, PSNR of the picture turned (180°, upside down, mirrored) and whether it is upright. Also the player's npm
package (``npm pack`` of ``src/omg4/web``): the tarball's bytes and files. The npm packages of ``package.json``
(``npm ci``) and Debian's ``chromium`` are needed.

    python benchmarks/studies/engines.py omg4_demo/scene_M.omg4 --data omg4_demo/scene --width 512 --forged 1200 \
        --name demo

Each run is recorded (commit, date, machine) in ``benchmarks/results/engines_<name>.json``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from omg4.testing.records import save_record

REPO = Path(__file__).resolve().parents[2]
MODULES = REPO / "node_modules"
RESULTS = REPO / "benchmarks" / "results"


def view_of(path: Path, data: Path | None, tau: float | None, width: int | None):
    """(model, its camera, the slice's time): the dataset's first test camera (``width`` pixels wide, if given), or
    one framing a forged model."""
    from omg4.models import load_model
    from omg4.render.paths import bounds_camera

    model = load_model(path)
    t0, t1 = model.config.time_range
    tau = 0.5 * (t0 + t1) if tau is None else tau
    if data is None:
        return model, bounds_camera(model.values["xyz"].numpy(), 96, 64), tau
    from omg4.data import load_scene

    camera = load_scene(data, decode=False, progress=False).test_cameras()[0]
    if width is not None:
        camera = camera.resized(width, round(width * camera.height / camera.width))
    return model, camera, tau


def engine_rows(browser, path: Path, data: Path | None, tau: float | None, width: int | None, folder: Path) -> dict:
    from omg4.app.cli import main
    from omg4.testing import engines

    model, camera, tau = view_of(path, data, tau, width)
    folder.mkdir(parents=True)
    for suffix in ("glb", "ply"):
        if main(["export", str(path), "--out", str(folder / f"slice.{suffix}"), "--time", repr(tau)]) != 0:
            raise SystemExit(f"omg4 export {path} --out slice.{suffix} failed")
    engines.ply_to_glb(folder / "slice.ply", folder / "from_ply.glb", MODULES)
    camera_to_world, fov, reference = engines.glb_view(model, camera, tau)
    size = (int(camera.width), int(camera.height))
    pages = {"glb in PlayCanvas": engines.playcanvas_page("slice.glb", camera_to_world, fov, *size),
             "glb in Babylon.js": engines.babylon_page("slice.glb", camera_to_world, fov, *size),
             "ply through splat-transform in PlayCanvas": engines.playcanvas_page("from_ply.glb", camera_to_world, fov,
                                                                                  *size)}
    rows = {name: engines.uprightness(engines.drawn_by(browser, folder, page, MODULES), reference)
            for name, page in pages.items()}
    return {"time": tau, "camera": camera.name, "size": list(size), "engines": rows}


def npm_package() -> dict:
    """``npm pack --dry-run`` of the player's package: its name, version, tarball bytes and files."""
    packed = json.loads(subprocess.run(["npm", "pack", "--dry-run", "--json", str(REPO / "src" / "omg4" / "web")],
                                       cwd=REPO, check=True, capture_output=True, text=True).stdout)[0]
    return {"name": packed["name"], "version": packed["version"], "tarball_bytes": packed["size"],
            "unpacked_bytes": packed["unpackedSize"], "files": sorted(f["path"] for f in packed["files"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="*", type=Path, help=".omg4 files (seen from --data's test camera)")
    ap.add_argument("--data", type=Path, help="the models' dataset folder")
    ap.add_argument("--forged", type=int, nargs="*", default=[], help="add files of this many random Gaussians")
    ap.add_argument("--time", type=float, help="the slice's time (default: the middle of the time range)")
    ap.add_argument("--width", type=int, help="the dataset camera's width in pixels (default: the dataset's)")
    ap.add_argument("--name", default="demo", help="record name: benchmarks/results/engines_<name>.json")
    args = ap.parse_args()
    from omg4.testing import forge
    from omg4.testing.browser import Browser

    rows = []
    # Chromium's child processes may still write its profile in there as it closes: a finished run keeps its record
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:
        tmp = Path(tmp)
        models = [(str(m), m, args.data) for m in args.models]
        for n in args.forged:
            forge.valid_file(tmp / f"forged_{n}.omg4", n, codec="compact", seed=7, codebook_scale=0.25)
            models.append((f"forged, {n:,} random Gaussians", tmp / f"forged_{n}.omg4", None))
        browser = Browser(tmp / "profile")
        try:
            for label, path, data in models:
                row = {"model": label, **engine_rows(browser, path, data, args.time, args.width, tmp / f"m{len(rows)}")}
                for engine, r in row["engines"].items():
                    print(f"{label}: {engine}: {r['db']:.2f} dB ({'upright' if r['upright'] else 'NOT upright'}; "
                          f"turned {', '.join(f'{x:.2f}' for x in r['turned_db'])})", flush=True)
                rows.append(row)
        finally:
            browser.close()
    package = npm_package()
    print(f"npm package {package['name']} {package['version']}: {package['tarball_bytes']:,} B tarball, "
          f"{len(package['files'])} files", flush=True)
    save_record(RESULTS / f"engines_{args.name}.json", {
        "command": "python benchmarks/studies/engines.py " + shlex.join(sys.argv[1:]),
        "browser": "headless Chromium, software WebGL2 (SwiftShader)",
        "packages": json.loads((REPO / "package.json").read_text())["devDependencies"],
        "rows": rows, "npm_package": package})
    if not all(r["upright"] for row in rows for r in row["engines"].values()):
        print("a slice was not upright", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
