// <omg4-player>: a custom element that plays an .omg4 file — or a long capture's sequence — in any page, decoded and
// rendered in the browser (plain ES modules, WebGL2, no build step). One module import and one element:
//
//   <script type="module" src="omg4/element.js"></script>
//   <omg4-player src="omg4/model.omg4" controls autoplay loop style="width: 640px; height: 360px"></omg4-player>
//
// Attributes: src (an .omg4 file, a sequence's sequence.json, or the folder holding it, ending in "/"); cameras (a
// cameras.json of presets, as `omg4 export --format web --data` writes; else the file's camera rig); camera (a
// preset's name; default: the first test camera); time (seconds: shows that time, paused); autoplay; loop;
// controls (the panel: camera, play, time, speed, loop, statistics); width and height (the image in pixels; default:
// the camera's view framed in the element's box); background ("r,g,b" in [0, 1]).
// Events: "ready" after the first complete frame (detail: {gaussians, bytes, segments, loadMs, camera}),
// "timechange" whenever the time shown changes (detail: {time}), "error" (detail: {name, message}: one line; the
// element shows it and the page stays alive). API: play(), pause(), seek(t), time, playing, timeRange, cameraNames,
// camera (get; set a preset's name or a camera {K, viewmat, width, height}), ready (a promise), canvas, stats, frames.

import { boundsCamera, cameraFromJson, chosenPreset, framed, orbitControls, resized, rigCameras } from "./camera.js";
import { decodePayload } from "./decoder/payload.js";
import { buildModel } from "./model.js";
import { Compositor, context } from "./render/renderer.js";
import { Playback, checkChain } from "./sequence.js";

const STYLE = `
:host { display: block; position: relative; overflow: hidden; background: #111; color: #ddd;
  font: 13px system-ui, sans-serif; }
canvas { display: block; position: absolute; left: 0; top: 0; touch-action: none; }
.panel { position: absolute; top: 8px; right: 8px; width: 280px; padding: 8px 10px; background: rgba(20, 20, 20, 0.85);
  border-radius: 6px; display: flex; flex-direction: column; gap: 6px; }
.panel[hidden], .message[hidden] { display: none; }
.title { font-weight: 600; }
.row { display: flex; align-items: center; gap: 6px; }
.time { flex: 1; }
.stats { font-variant-numeric: tabular-nums; white-space: pre; }
.hint { color: #888; font-size: 11px; }
.message { position: absolute; left: 8px; bottom: 8px; padding: 6px 10px; background: #5a1d1d; color: #fff;
  border-radius: 4px; }`;

const PANEL = `
<div class="title">omg4 player</div>
<label>camera <select class="camera"></select></label>
<div class="row"><button class="play" type="button">pause</button>
  <input class="time" type="range" min="0" max="1" step="any" value="0"><span class="clock">0.00 s</span></div>
<div class="row"><label>speed <select class="speed"><option>0.25</option><option>0.5</option><option selected>1</option>
  <option>2</option></select></label><label><input class="loop" type="checkbox"> loop</label></div>
<div class="stats"></div>
<div class="hint">drag: orbit · right-drag or shift-drag: pan · wheel: zoom</div>`;

async function fetchBytes(url) {
  const response = await fetch(url, { cache: "no-store" });  // a re-export replaces the file at the same URL
  if (!response.ok) throw new Error(`${url}: ${response.status} ${response.statusText}`);
  return new Uint8Array(await response.arrayBuffer());
}

function pixels(value, name) {
  if (value === null) return null;
  const n = Number(value);
  if (!(Number.isInteger(n) && n >= 16 && n <= 8192)) throw new Error(`${name} must be a whole number of pixels in 16–8192`);
  return n;
}

export class Omg4Player extends HTMLElement {
  static observedAttributes = ["src", "cameras", "camera", "time", "controls", "loop", "width", "height", "background"];

  constructor() {
    super();
    const root = this.attachShadow({ mode: "open" });
    root.innerHTML = `<style>${STYLE}</style><canvas part="canvas"></canvas><div class="panel" part="controls" hidden>`
      + `${PANEL}</div><div class="message" role="alert" part="message" hidden></div>`;
    this.canvas = root.querySelector("canvas");
    this.$ = (name) => root.querySelector(`.${name}`);
    this.frames = 0;
    this.stats = "";
    this.state = null;  // {camera, distance, time, playing, dirty}: with playback and gl, what benchmarks drive
    this._generation = 0;
    this._connected = false;
    this._newReady();
    this._wireControls();
    new ResizeObserver(() => this._refit()).observe(this);
  }

  connectedCallback() {
    this._connected = true;
    if (this.hasAttribute("src")) this._load();
  }

  disconnectedCallback() {
    this._connected = false;
    this._generation += 1;  // stops the frame loop and any load under way
  }

  attributeChangedCallback(name, old, value) {
    if (old === value) return;
    if (name === "src" || name === "cameras") {
      if (this._connected && this.hasAttribute("src")) this._load();
    } else if (name === "controls") {
      this.$("panel").hidden = value === null;
    } else if (name === "loop") {
      this.$("loop").checked = value !== null;
    } else if (this.state) {
      if (name === "time" && value !== null) this.seek(Number(value));
      else if (name === "camera" && value !== null) this.camera = value;
      else if (name === "width" || name === "height") this._refit();
      this.state.dirty = true;
    }
  }

  /** Resolves after the first complete frame (the "ready" event's detail); rejects with the error. */
  get ready() { return this._ready; }

  get time() { return this.state?.time ?? null; }

  get playing() { return !!this.state?.playing; }

  get timeRange() { return this._range ?? null; }

  get cameraNames() { return (this._cameras ?? []).map((c) => c.name); }

  get camera() { return this.state?.camera ?? null; }

  set camera(value) {
    if (!this.state) throw new Error("the player has not loaded its file yet");
    this._preset = typeof value === "string" ? chosenPreset(this._cameras, value, this._first.xyz).camera
      : cameraFromJson(value);
    this._refit();
    this.state.distance = this._focusDistance();
  }

  play() {
    if (!this.state) return;
    if (this.state.time >= this._range[1]) this.state.time = this._range[0];
    this.state.playing = true;
  }

  pause() { if (this.state) this.state.playing = false; }

  /** Show time `t` (seconds, within timeRange). */
  seek(t) {
    if (!this.state) throw new Error("the player has not loaded its file yet");
    const [t0, t1] = this._range;
    if (!(Number.isFinite(t) && t >= t0 && t <= t1)) throw new Error(`time ${t} lies outside the model's time range [${t0}, ${t1}]`);
    this.state.time = t;
    this.state.dirty = true;
  }

  _newReady() {
    this._ready = new Promise((resolve, reject) => { this._settle = { resolve, reject }; });
    this._ready.catch(() => {});
  }

  _wireControls() {
    this.$("camera").addEventListener("change", () => { this.camera = this._cameras[Number(this.$("camera").value)]?.name ?? this._preset.name; });
    this.$("time").addEventListener("input", () => this.seek(Number(this.$("time").value)));
    this.$("play").addEventListener("click", () => (this.playing ? this.pause() : this.play()));
    this.$("loop").addEventListener("change", () => this.toggleAttribute("loop", this.$("loop").checked));
    const player = this;
    const idle = { camera: boundsCamera(new Float32Array(3), 64, 64), distance: 1 };  // moves before a file is shown
    const view = {  // what the controls move: the state of the file shown
      get camera() { return (player.state ?? idle).camera; },
      set camera(c) { if (player.state) player.state.camera = c; },
      get distance() { return (player.state ?? idle).distance; },
      set distance(d) { if (player.state) player.state.distance = d; },
    };
    orbitControls(this.canvas, view, () => { if (this.state) this.state.dirty = true; });
  }

  _fail(err) {
    const message = String(err.message ?? err).split("\n")[0];
    this.$("message").textContent = message;
    this.$("message").hidden = false;
    this._settle?.reject(Object.assign(err instanceof Error ? err : new Error(message), { message }));
    this._settle = null;
    this.dispatchEvent(new CustomEvent("error", { detail: { name: err.name ?? "Error", message } }));
  }

  _fitted(camera) {
    const width = pixels(this.getAttribute("width"), "width");
    const height = pixels(this.getAttribute("height"), "height");
    if (width && height) return resized(camera, width, height);
    if (width || height) {
      const aspect = camera.height / camera.width;
      return resized(camera, width ?? Math.round(height / aspect), height ?? Math.round(width * aspect));
    }
    return framed(camera, Math.max(16, this.clientWidth), Math.max(16, this.clientHeight));
  }

  _refit() {
    if (!this.state || !this._preset) return;
    this.state.camera = this._fitted(this._preset);
    this.state.dirty = true;
  }

  _focusDistance() {
    const v = this.state.camera.viewmat, xyz = this._first.xyz, n = this._first.numGaussians;
    let sum = 0;
    for (let g = 0; g < n; g++) sum += v[8] * xyz[3 * g] + v[9] * xyz[3 * g + 1] + v[10] * xyz[3 * g + 2] + v[11];
    return Math.max(sum / Math.max(n, 1), 0.1);
  }

  async _segments(src) {
    const listingUrl = src.endsWith("/") ? new URL("sequence.json", src) : src.endsWith(".json") ? new URL(src) : null;
    if (listingUrl === null) return { segments: [{ url: src, range: null, bytes: null, reference: null }], keyInterval: 1 };
    const listing = JSON.parse(new TextDecoder().decode(await fetchBytes(listingUrl)));
    const segments = listing.segments.map((s) => ({ url: new URL(s.file, listingUrl).href, range: s.time_range,
      bytes: s.bytes, reference: s.reference ?? null }));
    return { segments, keyInterval: listing.key_interval ?? 1 };
  }

  async _presets(payload) {
    const url = this.getAttribute("cameras");
    if (url === null) return rigCameras(payload.meta);  // the file's rig
    const response = await fetch(new URL(url, document.baseURI), { cache: "no-store" });
    if (!response.ok) throw new Error(`${url}: ${response.status} ${response.statusText}`);
    return (await response.json()).cameras.map(cameraFromJson);
  }

  _load() {
    const generation = ++this._generation;
    if (!this._settle) this._newReady();  // a settled promise is replaced; a pending one still waits
    for (const { renderer } of this.playback?.loaded.values() ?? []) renderer.dispose();  // the file shown before
    this.playback = null;
    this.state = null;
    this.$("message").hidden = true;
    this._start(generation).catch((err) => { if (generation === this._generation) this._fail(err); });
  }

  async _start(generation) {
    const started = performance.now();
    const src = new URL(this.getAttribute("src"), document.baseURI).href;
    const { segments, keyInterval } = await this._segments(src);
    checkChain(segments, keyInterval);
    const bytes = await fetchBytes(segments[0].url);
    const fileBytes = segments.length > 1 ? segments.reduce((sum, s) => sum + s.bytes, 0) : bytes.length;
    const payload = await decodePayload(bytes);
    const model = buildModel(payload);  // the first segment: its cameras, and where to look
    const presets = await this._presets(payload);
    if (generation !== this._generation) return;  // a newer src, or the element left the page
    segments[0].range ??= model.timeRange;
    this._range = [segments[0].range[0], segments.at(-1).range[1]];
    this._cameras = presets;
    this._first = model;
    const { preset, camera } = chosenPreset(presets, this.getAttribute("camera"), model.xyz);
    this._preset = camera;
    this.gl ??= context(this.canvas);
    this.playback = new Playback(this.gl, this._compositor ??= new Compositor(this.gl), segments, model, fetchBytes, payload);
    this.background = (this.getAttribute("background") ?? "0,0,0").split(",").map(Number);
    this.state = { camera: this._fitted(this._preset), distance: 1, time: this._range[0], playing: this.hasAttribute("autoplay"), dirty: true };
    if (this.hasAttribute("time")) {
      this.seek(Number(this.getAttribute("time")));
      this.state.playing = false;
    }
    this.state.distance = this._focusDistance();
    const select = this.$("camera");
    select.replaceChildren(...presets.map((c, i) => new Option(`${c.name}${c.test ? " (test)" : ""}`, String(i))));
    if (!presets.length) select.add(new Option("overview", "-1"));
    select.value = String(presets.indexOf(preset));
    Object.assign(this.$("time"), { min: String(this._range[0]), max: String(this._range[1]) });
    this._loop(generation, { started, fileBytes, segments: segments.length });
  }

  _loop(generation, facts) {
    const stamps = [];
    let previous = null;
    let shownTime = null;
    const frame = (now) => {
      if (generation !== this._generation) return;
      const state = this.state;
      try {
        if (state.playing && previous !== null) {
          state.time += ((now - previous) / 1000) * Number(this.$("speed").value);
          const [t0, t1] = this._range;
          if (state.time > t1) {
            if (this.hasAttribute("loop")) state.time = t0 + ((state.time - t0) % (t1 - t0));
            else { state.time = t1; state.playing = false; }
          }
          state.dirty = true;
        }
        previous = now;
        if (state.dirty && this.playback.ready(state.time)) this._draw(now, stamps, facts);
        if (state.time !== shownTime && !state.dirty) {
          shownTime = state.time;
          this.dispatchEvent(new CustomEvent("timechange", { detail: { time: state.time } }));
        }
      } catch (err) {
        this._fail(err);
        return;
      }
      this.$("play").textContent = state.playing ? "pause" : "play";
      requestAnimationFrame(frame);
    };
    requestAnimationFrame(frame);
  }

  _draw(now, stamps, facts) {
    const state = this.state;
    const { width, height } = state.camera;
    if (this.canvas.width !== width || this.canvas.height !== height) {
      Object.assign(this.canvas, { width, height });
      Object.assign(this.canvas.style, { width: `${width}px`, height: `${height}px` });
    }
    const drawn = this.playback.frame(state.time, state.camera, this.background);
    this.frames += 1;
    // the measured rate: frames drawn in the last two seconds of drawing (not the first, which compiles shaders)
    if (!this._settle) stamps.push(now);
    while (stamps.length && stamps[0] < now - 2000) stamps.shift();
    state.dirty = false;
    this.$("time").value = String(state.time);
    this.$("clock").textContent = `${state.time.toFixed(2)} s`;
    const span = stamps.length > 1 ? stamps.at(-1) - stamps[0] : 0;  // no rate until the clock has advanced
    const rate = span > 0 ? `${((1000 * (stamps.length - 1)) / span).toFixed(1)} FPS` : "– FPS";
    const shown = facts.segments > 1 ? ` (segment ${this.playback.shown.map((k) => k + 1).join(" + ")} of ${facts.segments})` : "";
    this.stats = `${(facts.fileBytes / 1024).toFixed(1)} KB · ${this.playback.gaussians.toLocaleString()} Gaussians${shown}\n`
      + `${drawn.toLocaleString()} drawn · ${rate}`;
    this.$("stats").textContent = this.stats;
    if (this._settle) {
      this.gl.finish();
      const detail = { gaussians: this.playback.gaussians, bytes: facts.fileBytes, segments: facts.segments,
        loadMs: performance.now() - facts.started, camera: state.camera.name };
      this._settle.resolve(detail);
      this._settle = null;
      this.dispatchEvent(new CustomEvent("ready", { detail }));
    }
  }
}

customElements.define("omg4-player", Omg4Player);
