"""omg4 in a three.js scene through Spark (web/spark.js; the export's spark.html): the model at a time, fed into a
Spark SplatMesh and drawn by Spark, against ``omg4 render``. Spark draws with its own quantized splats (16-bit
centres, 8-bit scales, rotations and colours) and its own sort, so the bar is what Spark reaches on the same time
slice read by its own loader from omg4's ``.ply`` export, measured here: the feed must come within 1 dB of it.
three.js and Spark come from the npm packages of package.json (``npm ci``), nothing from the network."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omg4.testing.browser import data_url_image, open_player, served
from PIL import Image

from omg4.app.cli import main
from omg4.metrics import psnr
from omg4.testing import forge

ROOT = Path(__file__).resolve().parents[2]
MODULES = ROOT / "node_modules"
pytestmark = pytest.mark.skipif(not (MODULES / "@sparkjsdev" / "spark").is_dir() or not (MODULES / "three").is_dir(),
                                reason="needs the npm packages of package.json (npm ci)")

# a test page's head: three.js and Spark from package.json's npm packages, a module script follows
PAGE_HEAD = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<script type="importmap">{"imports": {"three": "./node_modules/three/build/three.module.js",
  "three/addons/": "./node_modules/three/examples/jsm/",
  "@sparkjsdev/spark": "./node_modules/@sparkjsdev/spark/dist/spark.module.js"}}</script></head>
<body style="margin: 0"><script type="module">
import * as THREE from "three";
"""

# Spark's own loader drawing a .ply, from the camera the spark page uses (same conventions, same camera code)
PLY_PAGE = PAGE_HEAD + """import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import { cameraFromJson, resized } from "./camera.js";
import { OMG4_CONVENTIONS, Omg4Splats } from "./spark.js";
window.omg4Ready = (async () => {
  const preset = (await (await fetch("cameras.json")).json()).cameras.map(cameraFromJson)[0];
  const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
  renderer.setSize(WIDTH, HEIGHT);
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.add(new SparkRenderer({ renderer, ...OMG4_CONVENTIONS }));
  const mesh = new SplatMesh({ url: "slice.ply" });
  await mesh.initialized;
  const turn = TURN;  // the .ply's from_omg4_world (its header): the mesh turned back into omg4's world
  mesh.quaternion.setFromRotationMatrix(new THREE.Matrix4().set(...turn.slice(0, 3), 0, ...turn.slice(3, 6), 0,
                                                                ...turn.slice(6), 0, 0, 0, 0, 1).transpose());
  scene.add(mesh);
  const camera = Omg4Splats.threeCamera(resized(preset, WIDTH, HEIGHT));
  let frames = 0;
  window.omg4Spark = { scene, get frames() { return frames; } };
  await new Promise((done) => renderer.setAnimationLoop(() => { renderer.render(scene, camera); if (++frames === 3) done(); }));
  return { frames };
})();
</script></body></html>"""

# the model fed by Omg4Splats into a SparkRenderer with Spark's own splat shaders or with leanSplatShaders' (LEAN)
FED_PAGE = PAGE_HEAD + """import { SparkRenderer } from "@sparkjsdev/spark";
import { cameraFromJson, resized } from "./camera.js";
import { OMG4_CONVENTIONS, Omg4Splats, leanSplatShaders } from "./spark.js";
window.omg4Ready = (async () => {
  const preset = (await (await fetch("cameras.json")).json()).cameras.map(cameraFromJson)[0];
  const splats = await Omg4Splats.load("model.omg4");
  const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
  renderer.setSize(WIDTH, HEIGHT);
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  const spark = new SparkRenderer({ renderer, ...OMG4_CONVENTIONS });
  scene.add(LEAN ? leanSplatShaders(spark) : spark);
  scene.add(splats.mesh);
  const camera = Omg4Splats.threeCamera(resized(preset, WIDTH, HEIGHT));
  let frames = 0;
  window.omg4Spark = { scene, get frames() { return frames; } };
  await new Promise((done) => renderer.setAnimationLoop(() => {
    splats.update(TIME, camera); renderer.render(scene, camera); if (++frames === 3) done(); }));
  return { lean: spark.material.vertexShader.includes("gl_VertexID") };
})();
</script></body></html>"""

# Spark sorts on a worker, frames after the first: wait until its SparkRenderer (Spark 2.2.0, package.json) has sorted
# and has nothing left to sort, then for two frames drawn in that order
SETTLE = """(async () => {
  const spark = window.omg4Spark.scene.children.find((c) => "sortDirty" in c);
  const sorted = () => spark.lastSortTime > 0 && !spark.sorting && !spark.sortDirty;
  const frame = () => new Promise((r) => requestAnimationFrame(r));
  for (let i = 0; i < 3000 && !sorted(); i++) await frame();
  if (!sorted()) throw new Error("Spark never finished sorting");
  const drawn = window.omg4Spark.frames;
  while (window.omg4Spark.frames < drawn + 2) await frame();
  return true; })()"""
CANVAS = "document.querySelector('canvas').toDataURL('image/png')"


def image(browser) -> np.ndarray:
    assert browser.evaluate(SETTLE, timeout=120)
    url = browser.evaluate(CANVAS)
    return data_url_image(url)


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_spark_draws_the_model_as_close_to_omg4_render_as_it_draws_omg4s_ply(chromium, tmp_path, tiny_scene_dir,
                                                                              backbone):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=7, codebook_scale=0.25, backbone=backbone)
    web = tmp_path / "web"
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out", str(web)]) == 0
    (web / "node_modules").symlink_to(MODULES)
    time = 0.45
    assert main(["export", str(model), "--time", str(time), "--out", str(web / "slice.ply")]) == 0
    header = (web / "slice.ply").read_bytes().split(b"end_header")[0].decode().splitlines()
    turn = [float(x) for x in next(ln for ln in header if ln.startswith("comment from_omg4_world")).split()[2:]]
    (web / "ply.html").write_text(PLY_PAGE.replace("WIDTH", "64").replace("HEIGHT", "48").replace("TURN",
                                                                                                   json.dumps(turn)))
    assert main(["render", "--model", str(model), "--data", str(tiny_scene_dir), "--time", str(time), "--out",
                 str(tmp_path / "ref.png")]) == 0
    reference = np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64)
    with served(web) as url:
        result = open_player(chromium, f"{url}/spark.html?width=64&height=48&time={time}")
        assert result["ready"]["camera"] == "cam00" and result["ready"]["gaussians"] == 1200, result
        fed = image(chromium)
        chromium.call("Page.navigate", url=f"{url}/ply.html")
        assert chromium.evaluate("new Promise((done) => { const wait = () => window.omg4Ready ? "
                                 "window.omg4Ready.then(done) : setTimeout(wait, 50); wait(); })", timeout=120)
        own = image(chromium)
    assert fed.shape == own.shape == reference.shape and reference.std() > 10
    fed_db, own_db = psnr(fed / 255, reference / 255), psnr(own / 255, reference / 255)
    print(json.dumps({"backbone": backbone, "spark_fed_db": fed_db, "spark_own_ply_db": own_db}))
    assert own_db > 20, own_db  # Spark itself draws omg4's slice recognizably
    assert fed_db >= own_db - 1.0, (fed_db, own_db)


def test_the_lean_splat_shaders_draw_what_sparks_own_draw(chromium, tmp_path, tiny_scene_dir):
    """leanSplatShaders (one draw of six vertices a splat, the branches an omg4 splat never takes left out) against
    Spark 2.2.0's own shaders on the same feed: the same picture, and the edit took (the warning path would keep Spark's
    shaders and pass the picture check alone)."""
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=11, codebook_scale=0.25)
    web = tmp_path / "web"
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out", str(web)]) == 0
    (web / "node_modules").symlink_to(MODULES)
    pictures, ready = {}, {}
    with served(web) as url:
        for lean in (False, True):
            page = FED_PAGE.replace("WIDTH", "160").replace("HEIGHT", "120").replace("TIME", "0.45")
            (web / f"fed_{lean}.html").write_text(page.replace("LEAN", json.dumps(lean)))
            chromium.call("Page.navigate", url=f"{url}/fed_{lean}.html")
            ready[lean] = chromium.evaluate("new Promise((done) => { const wait = () => window.omg4Ready ? "
                                            "window.omg4Ready.then(done) : setTimeout(wait, 50); wait(); })",
                                            timeout=120)
            pictures[lean] = image(chromium).astype(np.int64)
            ready[lean]["vertices"] = chromium.evaluate(
                "window.omg4Spark.scene.children.find((c) => 'sortDirty' in c).geometry.drawRange.count")
    assert ready[True]["lean"] and not ready[False]["lean"], ready
    assert ready[True]["vertices"] > 0 and ready[True]["vertices"] % 6 == 0, ready  # splats drawn, six vertices each
    assert pictures[False].std() > 10
    assert np.abs(pictures[True] - pictures[False]).max() <= 1


def test_the_spark_page_shows_a_new_time_seen_from_the_same_camera(chromium, tmp_path, tiny_scene_dir):
    """The page paused at one time, then fed another with its camera still: Spark generates its splats again (it does
    not see a changed packed array by itself; a FreeTimeGS model culls no Gaussian at either time, so their count does
    not change either) and draws the picture a page opened at that time draws."""
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 3000, codec="compact", seed=5, codebook_scale=0.25, backbone="freetimegs")
    web = tmp_path / "web"
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out", str(web)]) == 0
    (web / "node_modules").symlink_to(MODULES)
    # the page's frames from now on at time 0.6, until Spark has sorted again (a sort that starts later; at most 300
    # frames), when image() waits for that sort
    later = """(async () => {
      const page = window.omg4Spark;
      const spark = page.scene.children.find((c) => "sortDirty" in c);
      const start = performance.now();
      let frames = 0;
      page.renderer.setAnimationLoop(() => {
        page.splats.update(0.6, page.camera); page.renderer.render(page.scene, page.camera); frames += 1; });
      window.omg4Spark = { scene: page.scene, get frames() { return frames; } };
      while (frames < 300 && !(spark.lastSortTime > start)) await new Promise((r) => requestAnimationFrame(r));
      return true; })()"""
    with served(web) as url:
        assert "ready" in open_player(chromium, f"{url}/spark.html?width=64&height=48&time=0.3")
        earlier = image(chromium).astype(np.int64)
        assert chromium.evaluate(later)
        fed_later = image(chromium).astype(np.int64)
        assert "ready" in open_player(chromium, f"{url}/spark.html?width=64&height=48&time=0.6")
        opened_later = image(chromium).astype(np.int64)
    assert np.abs(opened_later - earlier).mean() > 1  # the two times look different
    assert np.abs(fed_later - opened_later).max() <= 1


def test_the_spark_page_says_what_is_missing_without_three_and_spark(chromium, tmp_path):
    forge.valid_file(tmp_path / "m.omg4", 300, codec="compact", seed=4)
    assert main(["export", str(tmp_path / "m.omg4"), "--format", "web", "--out", str(tmp_path / "web")]) == 0
    with served(tmp_path / "web") as url:
        result = open_player(chromium, f"{url}/spark.html")
    assert "error" in result and "npm install three@0.187.0 @sparkjsdev/spark@2.2.0" in result["message"]
    assert "\n" not in result["message"]
