// The sample page of omg4 in three.js through Spark (spark.html): the exported model in a three.js scene with orbit
// controls, playing. URL parameters as the player's page: ?camera=<name>&time=<T>&width=<W>&height=<H>&model=<file>
// (a time: paused there). window.omg4Ready resolves after the first frame drawn (rejects with a one-line message).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer } from "@sparkjsdev/spark";
import { cameraFromJson, chosenPreset, framed, resized, rigCameras } from "./camera.js";
import { OMG4_CONVENTIONS, Omg4Splats, leanSplatShaders } from "./spark.js";

const params = new URLSearchParams(location.search);

async function presets(model) {
  const listing = await fetch("omg4-web.json", { cache: "no-store" });
  const files = new Set(listing.ok ? (await listing.json()).files : []);
  if (!files.has("cameras.json")) return rigCameras(model.meta);
  return (await (await fetch("cameras.json", { cache: "no-store" })).json()).cameras.map(cameraFromJson);
}

async function main() {
  const splats = await Omg4Splats.load(params.get("model") ?? "model.omg4");
  const cameras = await presets(splats);
  const preset = chosenPreset(cameras, params.get("camera"), splats.model.xyz).camera;
  const width = Number(params.get("width") ?? window.innerWidth);
  const height = Number(params.get("height") ?? window.innerHeight);
  const view = params.has("width") && params.has("height") ? resized(preset, width, height) : framed(preset, width, height);
  const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
  renderer.setSize(width, height);
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.add(leanSplatShaders(new SparkRenderer({ renderer, ...OMG4_CONVENTIONS })));
  scene.add(splats.mesh);
  const camera = Omg4Splats.threeCamera(view);
  const [t0, t1] = splats.timeRange;
  const paused = params.get("time") !== null;
  let time = paused ? Number(params.get("time")) : t0;
  if (!(Number.isFinite(time) && time >= t0 && time <= t1)) throw new Error(`time ${params.get("time")} lies outside [${t0}, ${t1}]`);
  const focus = new THREE.Vector3(...preset.center).addScaledVector(
    new THREE.Vector3(preset.viewmat[8], preset.viewmat[9], preset.viewmat[10]), 2);
  const pose = camera.matrixWorld.clone();
  camera.up.set(0, 0, 1);  // the model's world is +z up
  const controls = new OrbitControls(camera, renderer.domElement);  // it turns the camera to its target: undone below
  controls.target.copy(focus);
  pose.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
  let previous = null;
  let frames = 0;
  window.omg4Spark = { splats, camera, renderer, scene, get frames() { return frames; } };
  renderer.setAnimationLoop((now) => {
    if (!paused && previous !== null) time = t0 + ((time - t0 + (now - previous) / 1000) % (t1 - t0));
    previous = now;
    splats.update(time, camera);
    renderer.render(scene, camera);
    frames += 1;
    if (frames === 1) window.omg4FirstFrameMs = performance.now();  // since navigation started
    if (frames === 3) {  // Spark sorts on a worker: its first frames may show nothing yet
      window.omg4Settle.resolve({ gaussians: splats.model.numGaussians, camera: preset.name, time });
    }
  });
}

main().catch((err) => {
  const message = document.getElementById("message");
  message.textContent = String(err.message).split("\n")[0];
  message.hidden = false;
  window.omg4Settle.reject(err);
});
