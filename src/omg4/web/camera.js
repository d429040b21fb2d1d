// Cameras of the player, in omg4's conventions (omg4/data/scene.py Camera): K in pixels, viewmat world → camera
// (OpenCV: x right, y down, z forward), both row-major; the normalized world's up is +z. Orbit controls move a
// camera around a focus point: drag to orbit, right- or shift-drag to pan, wheel to zoom.

const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const normalize = (a) => scale(a, 1 / Math.hypot(...a));
const UP = [0, 0, 1];

/** A camera from its JSON form ({name, K 3×3, viewmat 4×4, width, height}) with its centre −Rᵀt. */
export function cameraFromJson(c) {
  const K = c.K.flat();
  const viewmat = c.viewmat.flat();
  if (K.length !== 9 || viewmat.length !== 16 || ![...K, ...viewmat].every(Number.isFinite)
      || !(Number.isInteger(c.width) && Number.isInteger(c.height) && c.width > 0 && c.height > 0)) {
    throw new Error(`camera ${c.name ?? ""} is not a valid camera`);
  }
  return withCenter({ name: String(c.name ?? ""), K, viewmat, width: c.width, height: c.height, test: !!c.test });
}

function withCenter(camera) {
  const v = camera.viewmat;
  const t = [v[3], v[7], v[11]];
  camera.center = [0, 1, 2].map((j) => -(v[j] * t[0] + v[4 + j] * t[1] + v[8 + j] * t[2]));
  return camera;
}

/** The cameras of a file's camera rig (meta.rig, validated by the decoder; test cameras first), or []. */
export function rigCameras(meta) {
  const rig = meta.rig;
  if (!rig) return [];
  return rig.cameras.map((c, i) => withCenter({
    name: c.name, width: c.width, height: c.height, test: i < rig.test,
    K: [c.K[0], 0, c.K[2], 0, c.K[1], c.K[3], 0, 0, 1], viewmat: [...c.pose, 0, 0, 0, 1],
  }));
}

/** The same camera at another resolution: K's first row scaled by the width ratio, its second by the height's
 * (Camera.resized). */
export function resized(camera, width, height) {
  const sx = width / camera.width;
  const sy = height / camera.height;
  const K = camera.K.slice();
  for (let j = 0; j < 3; j++) {
    K[j] *= sx;
    K[3 + j] *= sy;
  }
  return withCenter({ ...camera, K, viewmat: camera.viewmat.slice(), width, height });
}

/** The camera's view centred in a width × height image: both focal lengths scaled by the largest factor that keeps
 * its whole image inside, the principal point moved with the margins, so the image shows what the camera shows and
 * more at two of its sides, undistorted (resized instead scales each axis by its own ratio). */
export function framed(camera, width, height) {
  const s = Math.min(width / camera.width, height / camera.height);
  const K = camera.K.slice();
  K[0] *= s;
  K[1] *= s;
  K[4] *= s;
  K[2] = K[2] * s + (width - camera.width * s) / 2;
  K[5] = K[5] * s + (height - camera.height * s) / 2;
  return withCenter({ ...camera, K, viewmat: camera.viewmat.slice(), width, height });
}

/** The world → camera matrix of a camera at `eye` looking at `target` (look_at_viewmat). */
export function lookAt(eye, target, up = UP) {
  const forward = normalize(sub(target, eye));
  const right = normalize(cross(forward, up));
  const down = cross(forward, right);
  const rows = [right, down, forward];
  const viewmat = [];
  for (const r of rows) viewmat.push(...r, -dot(r, eye));
  viewmat.push(0, 0, 0, 1);
  return viewmat;
}

/** A camera framing points `xyz` (flat [N·3]) from −y, slightly above, with a 50° horizontal field of view
 * (omg4/render/paths.py bounds_camera), for files without a camera rig. */
export function boundsCamera(xyz, width, height) {
  const n = xyz.length / 3;
  const median = [0, 1, 2].map((k) => {
    const column = Array.from({ length: n }, (_, i) => xyz[3 * i + k]).sort((a, b) => a - b);
    return column[Math.floor(n / 2)];
  });
  const radii = Array.from({ length: n }, (_, i) => Math.hypot(xyz[3 * i] - median[0], xyz[3 * i + 1] - median[1],
    xyz[3 * i + 2] - median[2])).sort((a, b) => a - b);
  const radius = Math.max(radii[Math.floor(0.9 * (n - 1))], 1e-3);
  const half = Math.tan((50 * Math.PI) / 360);
  const focal = (0.5 * width) / half;
  const eye = add(median, scale([0, -Math.cos(0.3), Math.sin(0.3)], (1.2 * radius) / half));
  return withCenter({ name: "bounds", K: [focal, 0, width / 2, 0, focal, height / 2, 0, 0, 1],
    viewmat: lookAt(eye, median), width, height, test: false });
}

/** The camera to show first: the preset named `named` (a one-line error when there is none such), else the first
 * test camera, else the first preset; with no presets at all, one framing the points `xyz` (the preset is then
 * null). Returns {preset, camera}. */
export function chosenPreset(cameras, named, xyz) {
  const preset = named !== null ? cameras.find((c) => c.name === named) : cameras.find((c) => c.test) ?? cameras[0];
  if (named !== null && !preset) {
    throw new Error(`no camera named '${named}' (the cameras: ${cameras.map((c) => c.name).join(", ") || "none"})`);
  }
  return { preset: preset ?? null, camera: preset ?? boundsCamera(xyz, 960, 540) };
}

/** Orbit/pan/zoom of `state.camera` by pointer and wheel on `element`; calls `changed()` after each move. */
export function orbitControls(element, state, changed) {
  let last = null;
  let mode = null;
  const focusOf = (camera) => {
    const v = camera.viewmat;
    const forward = [v[8], v[9], v[10]];
    return add(camera.center, scale(forward, state.distance));
  };
  const place = (eye, focus) => {
    state.camera = withCenter({ ...state.camera, viewmat: lookAt(eye, focus) });
    changed();
  };
  element.addEventListener("contextmenu", (e) => e.preventDefault());
  element.addEventListener("pointerdown", (e) => {
    last = [e.clientX, e.clientY];
    mode = e.button === 2 || e.shiftKey ? "pan" : "orbit";
    element.setPointerCapture(e.pointerId);
  });
  element.addEventListener("pointerup", () => { last = null; });
  element.addEventListener("pointermove", (e) => {
    if (!last) return;
    const dx = e.clientX - last[0];
    const dy = e.clientY - last[1];
    last = [e.clientX, e.clientY];
    const focus = focusOf(state.camera);
    const v = state.camera.viewmat;
    const right = [v[0], v[1], v[2]];
    const down = [v[4], v[5], v[6]];
    if (mode === "pan") {
      const step = state.distance / state.camera.K[0];
      const shift = add(scale(right, -dx * step), scale(down, -dy * step));
      place(add(state.camera.center, shift), add(focus, shift));
      return;
    }
    let offset = sub(state.camera.center, focus);
    const yaw = -dx * 0.005;
    offset = [offset[0] * Math.cos(yaw) - offset[1] * Math.sin(yaw), offset[0] * Math.sin(yaw) + offset[1] * Math.cos(yaw), offset[2]];
    const elevation = Math.asin(Math.max(-0.99, Math.min(0.99, offset[2] / Math.hypot(...offset))));
    const pitch = Math.max(-1.5, Math.min(1.5, elevation + dy * 0.005)) - elevation;
    const axis = normalize(cross(offset, UP));
    const c = Math.cos(pitch);
    const s = Math.sin(pitch);
    offset = add(add(scale(offset, c), scale(cross(axis, offset), s)), scale(axis, dot(axis, offset) * (1 - c)));
    place(add(focus, offset), focus);
  });
  element.addEventListener("wheel", (e) => {
    e.preventDefault();
    const focus = focusOf(state.camera);
    state.distance *= Math.exp(e.deltaY * 0.001);
    const v = state.camera.viewmat;
    place(sub(focus, scale([v[8], v[9], v[10]], state.distance)), focus);
  }, { passive: false });
}
