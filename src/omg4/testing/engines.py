"""A time slice in the engines users have, against ``omg4 render``: the ``.glb`` export in PlayCanvas and Babylon.js
(their own ``KHR_gaussian_splatting`` readers) and the ``.ply`` export turned into glTF by PlayCanvas's
``splat-transform`` (as SuperSplat reads a ``.ply``), each drawn in headless Chromium from an omg4 camera turned into
glTF's world the way the export says (:mod:`omg4.io.worlds`), and how upright the picture is. The npm packages come
from the repository's ``node_modules`` (``npm ci``). Used by ``tests/web/test_gltf_engines.py`` and
``benchmarks/studies/engines.py``.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import torch

from omg4.data.scene import Camera
from omg4.io import worlds
from omg4.metrics import psnr
from omg4.render.view import render_view
from omg4.testing.browser import Browser, data_url_image, served

PLAYCANVAS = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,"></head>
<body style="margin: 0"><script type="module">
import * as pc from "./node_modules/playcanvas/build/playcanvas.mjs";
const canvas = document.createElement("canvas");
canvas.width = WIDTH; canvas.height = HEIGHT;
document.body.appendChild(canvas);
const app = new pc.Application(canvas, { graphicsDeviceOptions: { preserveDrawingBuffer: true, antialias: false } });
app.setCanvasFillMode(pc.FILLMODE_NONE);
app.setCanvasResolution(pc.RESOLUTION_FIXED, WIDTH, HEIGHT);
app.start();
const camera = new pc.Entity("camera");
camera.addComponent("camera", { clearColor: new pc.Color(0, 0, 0, 1), fov: FOV, nearClip: 0.01, farClip: 1000 });
const pose = new pc.Mat4().set(POSE);  // camera-to-world in glTF's world, PlayCanvas's camera axes
camera.setPosition(pose.getTranslation());
camera.setRotation(new pc.Quat().setFromMat4(pose));
app.root.addChild(camera);
window.drawn = 0;
app.on("frameend", () => window.drawn++);
const asset = new pc.Asset("slice", "container", { url: "GLB" });
window.loaded = new Promise((done, fail) => {
  asset.ready(() => { app.root.addChild(asset.resource.instantiateRenderEntity()); done(asset.resource.gsplats.length); });
  asset.on("error", (err) => fail(String(err)));
});
app.assets.add(asset);
app.assets.load(asset);
</script></body></html>"""

BABYLON = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<script type="importmap">{"imports": {"@babylonjs/core/": "./node_modules/@babylonjs/core/",
                                      "@babylonjs/loaders/": "./node_modules/@babylonjs/loaders/"}}</script>
</head><body style="margin: 0"><script type="module">
window.loaded = (async () => {  // imported here, so that a module that fails says why (the caller reads the promise)
  const core = "@babylonjs/core/";
  const [{ Engine }, { Scene }, { UniversalCamera }, { Vector3 }, { Color4 }, { ImportMeshAsync }] = await Promise.all([
    import(core + "Engines/engine.js"), import(core + "scene.js"), import(core + "Cameras/universalCamera.js"),
    import(core + "Maths/math.vector.js"), import(core + "Maths/math.color.js"), import(core + "Loading/sceneLoader.js")]);
  await import(core + "Meshes/GaussianSplatting/gaussianSplattingMesh.js");  // not the .pure module: it registers
  await import("@babylonjs/loaders/glTF/glTFFileLoader.js");
  await import("@babylonjs/loaders/glTF/2.0/index.js");  // the glTF 2.0 loader with its extensions
  const canvas = document.createElement("canvas");
  canvas.width = WIDTH; canvas.height = HEIGHT;
  document.body.appendChild(canvas);
  const engine = new Engine(canvas, false, { preserveDrawingBuffer: true, antialias: false });
  const scene = new Scene(engine);
  scene.useRightHandedSystem = true;  // glTF's world as it is (no handedness root)
  scene.clearColor = new Color4(0, 0, 0, 1);
  const [position, target, up] = CAMERA;  // in glTF's world
  const camera = new UniversalCamera("camera", new Vector3(...position), scene);
  camera.upVector = new Vector3(...up);
  camera.setTarget(new Vector3(...target));
  Object.assign(camera, { fov: FOV, minZ: 0.01, maxZ: 1000 });
  window.drawn = 0;
  engine.runRenderLoop(() => { scene.render(); window.drawn++; });
  return (await ImportMeshAsync("GLB", scene)).meshes.length;
})();
</script></body></html>"""

# frames drawn, then the same picture twice (PlayCanvas sorts splats on a worker: the first frames may precede it)
SETTLED = """(async () => {
  const grab = () => document.querySelector("canvas").toDataURL("image/png");
  const frame = () => new Promise((r) => requestAnimationFrame(r));
  await window.loaded;
  while (window.drawn < 30) await frame();
  let last = grab();
  for (let i = 0; i < 300; i++) { for (let k = 0; k < 10; k++) await frame(); const now = grab(); if (now === last) return now; last = now; }
  throw new Error("the picture never settled");
})()"""

UPRIGHT_MARGIN_DB = 3.0
"""A picture is upright when it is this much closer to omg4's than any turn of it (180°, upside down, mirrored)."""


def db(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR of two [H, W, 3] pictures in [0, 1]."""
    return float(psnr(torch.from_numpy(np.ascontiguousarray(a)), torch.from_numpy(np.ascontiguousarray(b))))


def uprightness(image: np.ndarray, reference: np.ndarray) -> dict:
    """``image``'s PSNR against omg4's ``reference`` as drawn and turned, and whether it is upright."""
    drawn = db(image, reference)
    turned = [db(np.rot90(image, 2), reference), db(image[::-1], reference), db(image[:, ::-1], reference)]
    return {"db": drawn, "turned_db": turned, "upright": drawn > max(turned) + UPRIGHT_MARGIN_DB}


def glb_view(model, camera: Camera, tau: float, turn: np.ndarray = worlds.GLTF
             ) -> tuple[np.ndarray, float, np.ndarray]:
    """(camera-to-world of ``camera`` in glTF's world (omg4's turned by ``turn``, a file's ``from_omg4_world``;
    OpenCV's camera axes), its vertical field of view, and ``omg4 render``'s picture of ``model`` at ``tau`` from
    it) — the view every engine is checked from."""
    with torch.no_grad():
        reference = render_view(model, camera, tau, backend="cpu")[0].image.clamp(0, 1).numpy()
    turn = np.block([[np.asarray(turn).T, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    fov = float(2 * np.arctan(camera.height / (2 * camera.K[1, 1])))
    return np.linalg.inv(camera.viewmat @ turn), fov, reference


def playcanvas_page(glb: str, camera_to_world: np.ndarray, fov: float, width: int, height: int) -> str:
    """A page drawing ``glb`` in PlayCanvas from the camera (glTF's world, OpenCV's axes; ``fov`` in radians)."""
    pose = camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV's camera axes to PlayCanvas's
    return (PLAYCANVAS.replace("GLB", glb).replace("FOV", repr(float(np.degrees(fov))))
            .replace("POSE", json.dumps(pose.T.ravel().tolist())).replace("WIDTH", str(width))
            .replace("HEIGHT", str(height)))


def babylon_page(glb: str, camera_to_world: np.ndarray, fov: float, width: int, height: int) -> str:
    """A page drawing ``glb`` in Babylon.js from the camera (glTF's world, OpenCV's axes; ``fov`` in radians)."""
    position, forward, down = camera_to_world[:3, 3], camera_to_world[:3, 2], camera_to_world[:3, 1]
    view = [position.tolist(), (position + forward).tolist(), (-down).tolist()]
    return (BABYLON.replace("GLB", glb).replace("FOV", repr(fov)).replace("CAMERA", json.dumps(view))
            .replace("WIDTH", str(width)).replace("HEIGHT", str(height)))


def drawn_by(browser: Browser, folder: Path, page: str, modules: Path) -> np.ndarray:
    """The settled picture of ``page`` ([H, W, 3] in [0, 1]), written into ``folder`` beside its files, the npm
    packages of ``modules`` linked in."""
    (folder / "page.html").write_text(page)
    if not (folder / "node_modules").exists():
        (folder / "node_modules").symlink_to(modules)
    with served(folder) as url:
        browser.call("Page.navigate", url=f"{url}/page.html")
        for _ in range(600):  # the new page's module has run
            if browser.evaluate(f"location.href === {json.dumps(url + '/page.html')} && !!window.loaded"):
                break
        data_url = browser.evaluate(SETTLED, timeout=120)
    return data_url_image(data_url) / 255


def ply_to_glb(ply: Path, glb: Path, modules: Path) -> None:
    """``splat-transform``'s reading of a ``.ply`` (3DGS's y-down world turned into PlayCanvas's, glTF's, +Y up)
    written as a ``.glb``."""
    cli = modules / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
    done = subprocess.run(["node", str(cli), "--overwrite", str(ply), str(glb)], capture_output=True, text=True,
                          timeout=120)
    if done.returncode != 0:
        raise RuntimeError(f"splat-transform failed: {done.stderr.strip()[-300:]}")


__all__ = ["babylon_page", "db", "drawn_by", "glb_view", "playcanvas_page", "ply_to_glb", "uprightness"]
