// The omg4 player page: reads the export's list of its files (omg4-web.json), fetches model.omg4 — or, for a long
// capture, sequence.json and its segments one by one — (and cameras.json when the export had a dataset), decodes and
// renders it with WebGL2, and plays it. URL parameters: ?camera=<name>&time=<T>&width=<W>&height=<H>&ui=0 (a
// reproducible view: no camera → the first test camera, as `omg4 render --data` picks; a time → paused there; ui=0 →
// only the canvas, filling the window unless a size is given). window.omg4Ready resolves after the first complete
// frame (rejects with the one-line message a damaged file gets).

import { boundsCamera, cameraFromJson, framed, orbitControls, resized, rigCameras } from "./camera.js";
import { decodePayload } from "./decoder/payload.js";
import { buildModel } from "./model.js";
import { Compositor, context } from "./render/renderer.js";
import { Playback, checkChain } from "./sequence.js";

const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
let settle;
window.omg4Ready = new Promise((resolve, reject) => { settle = { resolve, reject }; });
window.omg4Ready.catch(() => {});

function show(message) {
  $("message").textContent = message.split("\n")[0];
  $("message").hidden = false;
}

async function fetchBytes(url) {
  const response = await fetch(url, { cache: "no-store" });  // a re-export replaces the file at the same URL
  if (!response.ok) throw new Error(`${url}: ${response.status} ${response.statusText}`);
  return new Uint8Array(await response.arrayBuffer());
}

async function exportedFiles() {
  // what the export wrote, so the page asks for no file that is not there
  const response = await fetch("omg4-web.json", { cache: "no-store" });
  return new Set(response.ok ? (await response.json()).files : []);
}

async function presets(files) {
  if (!files.has("cameras.json")) return [];
  const response = await fetch("cameras.json", { cache: "no-store" });
  if (!response.ok) return [];
  return (await response.json()).cameras.map(cameraFromJson);
}

function positiveInt(name) {
  const value = params.get(name);
  if (value === null) return null;
  const n = Number(value);
  if (!(Number.isInteger(n) && n >= 16 && n <= 8192)) throw new Error(`?${name}= must be a whole number of pixels in 16–8192`);
  return n;
}

function fitted(camera, bare) {
  const width = positiveInt("width");
  const height = positiveInt("height");
  if (width && height) return resized(camera, width, height);
  if (width || height) {
    const aspect = camera.height / camera.width;
    return resized(camera, width ?? Math.round(height / aspect), height ?? Math.round(width * aspect));
  }
  if (bare) return framed(camera, Math.max(16, window.innerWidth), Math.max(16, window.innerHeight));
  const fit = Math.min((window.innerWidth - 16) / camera.width, (window.innerHeight - 16) / camera.height);
  return resized(camera, Math.max(16, Math.round(camera.width * fit)), Math.max(16, Math.round(camera.height * fit)));
}

async function main() {
  const bare = params.get("ui") === "0";
  if (bare) document.body.classList.add("bare");
  const started = performance.now();
  const files = await exportedFiles();
  const sequence = files.has("sequence.json") && params.get("model") === null;
  const listing = sequence ? JSON.parse(new TextDecoder().decode(await fetchBytes("sequence.json"))) : null;
  const segments = sequence
    ? listing.segments.map((s) => ({ url: s.file, range: s.time_range, bytes: s.bytes, reference: s.reference ?? null }))
    : [{ url: params.get("model") ?? "model.omg4", range: null, bytes: null, reference: null }];
  checkChain(segments, sequence ? listing.key_interval ?? 1 : 1);
  const bytes = await fetchBytes(segments[0].url);
  const fileBytes = sequence ? segments.reduce((sum, s) => sum + s.bytes, 0) : bytes.length;
  const payload = await decodePayload(bytes);
  const model = buildModel(payload);  // the first segment: its cameras, and where to look
  const exported = await presets(files);
  const cameras = exported.length ? exported : rigCameras(payload.meta);  // the export's dataset, else the file's rig
  segments[0].range ??= model.timeRange;
  const [t0, t1] = [segments[0].range[0], segments.at(-1).range[1]];
  const named = params.get("camera");
  let preset = named !== null ? cameras.find((c) => c.name === named) : cameras.find((c) => c.test) ?? cameras[0];
  if (named !== null && !preset) throw new Error(`no camera named '${named}' (the export's cameras: ${cameras.map((c) => c.name).join(", ") || "none"})`);
  if (!preset) preset = boundsCamera(model.xyz, 960, 540);
  const canvas = $("view");
  const gl = context(canvas);
  const playback = new Playback(gl, new Compositor(gl), segments, model, fetchBytes, payload);
  const background = (params.get("background") ?? "0,0,0").split(",").map(Number);
  const state = { camera: fitted(preset, bare), distance: 1, time: t0, playing: true, dirty: true };
  const time = params.get("time");
  if (time !== null) {
    const tau = Number(time);
    if (!(Number.isFinite(tau) && tau >= t0 && tau <= t1)) throw new Error(`?time=${time} lies outside the model's time range [${t0}, ${t1}]`);
    state.time = tau;
    state.playing = false;
  }
  const focusDistance = () => {
    const v = state.camera.viewmat;
    let sum = 0;
    for (let g = 0; g < model.numGaussians; g++) {
      sum += v[8] * model.xyz[3 * g] + v[9] * model.xyz[3 * g + 1] + v[10] * model.xyz[3 * g + 2] + v[11];
    }
    return Math.max(sum / model.numGaussians, 0.1);
  };
  state.distance = focusDistance();

  const select = $("camera");
  cameras.forEach((c, i) => select.add(new Option(`${c.name}${c.test ? " (test)" : ""}`, String(i))));
  if (!cameras.length) select.add(new Option("overview", "-1"));
  select.value = String(cameras.indexOf(preset));
  select.addEventListener("change", () => {
    state.camera = fitted(cameras[Number(select.value)], bare);
    state.distance = focusDistance();
    state.dirty = true;
  });
  const slider = $("time");
  slider.min = String(t0);
  slider.max = String(t1);
  slider.addEventListener("input", () => { state.time = Number(slider.value); state.dirty = true; });
  const play = $("play");
  play.addEventListener("click", () => { state.playing = !state.playing; });
  orbitControls(canvas, state, () => { state.dirty = true; });

  const stamps = [];
  let previous = null;
  const frame = (now) => {
    if (state.playing && previous !== null) {
      const speed = Number($("speed").value);
      state.time += ((now - previous) / 1000) * speed;
      if (state.time > t1) {
        if ($("loop").checked) state.time = t0 + ((state.time - t0) % (t1 - t0));
        else { state.time = t1; state.playing = false; }
      }
      state.dirty = true;
    }
    previous = now;
    if (state.dirty) {
      const { width, height } = state.camera;
      if (canvas.width !== width || canvas.height !== height) {
        canvas.width = width;
        canvas.height = height;
        canvas.style.width = `${width}px`;
        canvas.style.height = `${height}px`;
      }
      if (!playback.ready(state.time)) {  // a segment still on its way: the last frame stays
        requestAnimationFrame(frame);
        return;
      }
      const drawn = playback.frame(state.time, state.camera, background);
      window.omg4Player.frames += 1;
      // the measured rate: frames drawn in the last two seconds of drawing (not the first, which compiles shaders)
      if (!settle) stamps.push(now);
      while (stamps.length && stamps[0] < now - 2000) stamps.shift();
      state.dirty = false;
      slider.value = String(state.time);
      $("clock").textContent = `${state.time.toFixed(2)} s`;
      const span = stamps.length > 1 ? stamps.at(-1) - stamps[0] : 0;  // no rate until the clock has advanced
      const rate = span > 0 ? `${((1000 * (stamps.length - 1)) / span).toFixed(1)} FPS` : "– FPS";
      const shown = segments.length > 1 ? ` (segment ${playback.shown.map((k) => k + 1).join(" + ")} of ${segments.length})` : "";
      $("stats").textContent = `${(fileBytes / 1024).toFixed(1)} KB · ${playback.gaussians.toLocaleString()} Gaussians${shown}\n`
        + `${drawn.toLocaleString()} drawn · ${rate}`;
      if (settle) {
        gl.finish();
        window.omg4FirstFrameMs = performance.now();  // since navigation started
        settle.resolve({ gaussians: playback.gaussians, bytes: fileBytes, segments: segments.length,
          loadMs: performance.now() - started, camera: state.camera.name });
        settle = null;
      }
    }
    play.textContent = state.playing ? "pause" : "play";
    requestAnimationFrame(frame);
  };
  window.omg4Player = { state, playback, gl, frames: 0 };
  requestAnimationFrame(frame);
}

main().catch((err) => {
  show(err.message);
  document.body.dataset.error = err.name;
  settle?.reject(err);
});
