// A decoded .omg4 payload as the per-Gaussian values the renderer needs (omg4/models/compact.py CompactModel):
// SVQ attributes reconstructed and split by backbone (gaussians/backbone.py svq_widths), the time-independent
// 3D covariance, velocity ("gain") and time variance of each Gaussian (Real-Time4DGS: the 4D Gaussian conditioned on
// time, rt4dgs §3.2, covariance.py; FreeTimeGS: a Gaussian moving at constant velocity, freetime.py), the
// appearance MLP weights (paper §4.4, appearance.py) and the position half of the shared network's first layer.

import { CorruptFileError, halfToFloat } from "./decoder/streams.js";

const CONFIG_DEFAULTS = {
  sh_degree: 3, sh_degree_t: 2, rotation_convention: "flip", time_cull: 0.05, sh_direction: "conditioned",
  backbone: "rt4dgs",
};

// SVQ group → the parameters it holds, in order, with their widths (backbone.py BACKBONES)
const SVQ_WIDTHS = {
  rt4dgs: {
    scale: [["scaling", 3]], rotation: [["rotation", 4]], app: [["f_static", 3], ["f_view", 3]],
    scale_t: [["scaling_t", 1]], rotation_r: [["rotation_r", 4]],
  },
  freetimegs: {
    scale: [["scaling", 3]], rotation: [["rotation", 4]], app: [["f_static", 3], ["f_view", 3]],
    duration: [["duration", 1]], velocity: [["velocity", 3]],
  },
};
const MLP_INPUTS = { rt4dgs: 4, freetimegs: 3 };
const MLP_KEYS = ["shared.0.weight", "shared.2.weight", "dc.0.weight", "dc.2.weight", "opacity.0.weight",
  "opacity.2.weight", "rest.0.weight", "rest.2.weight"];
export const MAX_HIDDEN = 128; // what the player's shaders are sized for (the paper's networks: 64)
export const MAX_FREQS = 24;

function floats(bits) {
  const out = new Float32Array(bits.length);
  for (let i = 0; i < bits.length; i++) out[i] = halfToFloat(bits[i]);
  return out;
}

/** Per-Gaussian parameters {name: Float32Array [N·width]} from the decoded SVQ attributes and quaternions. */
function parameters(payload, backbone) {
  const n = payload.numGaussians;
  const out = {};
  const groups = SVQ_WIDTHS[backbone];
  for (const [attr, params] of Object.entries(groups)) {
    const width = params.reduce((sum, [, w]) => sum + w, 0);
    const rows = new Float32Array(n * width);
    if (payload.quaternions[attr]) {
      if (width !== 4) throw new CorruptFileError(`attribute ${attr} is stored as quaternions but is ${width} wide`);
      rows.set(floats(payload.quaternions[attr]));
    } else if (payload.attributes[attr]) {
      const { codebooks, indices } = payload.attributes[attr];
      const total = codebooks.reduce((sum, c) => sum + c.sub, 0);
      if (total !== width) throw new CorruptFileError(`attribute ${attr} is ${total} wide, the backbone needs ${width}`);
      let column = 0;
      codebooks.forEach((cb, j) => {
        const values = floats(cb.values);
        for (let g = 0; g < n; g++) {
          for (let c = 0; c < cb.sub; c++) rows[g * width + column + c] = values[indices[j][g] * cb.sub + c];
        }
        column += cb.sub;
      });
    } else {
      throw new CorruptFileError(`the ${backbone} model lacks the attribute ${attr}`);
    }
    let offset = 0;
    for (const [name, w] of params) {
      const values = new Float32Array(n * w);
      for (let g = 0; g < n; g++) {
        for (let c = 0; c < w; c++) values[g * w + c] = rows[g * width + offset + c];
      }
      out[name] = values;
      offset += w;
    }
  }
  return out;
}

function unit(q, g) {
  const [a, b, c, d] = [q[4 * g], q[4 * g + 1], q[4 * g + 2], q[4 * g + 3]];
  const norm = Math.max(Math.hypot(a, b, c, d), 1e-12);
  return [a / norm, b / norm, c / norm, d / norm];
}

/** The 4D rotation of two unit quaternions (rotation.py build_rotation_4d), "flip" or "legacy" convention. */
function rotation4d([a, b, c, d], [p, q, r, s], convention) {
  const ml = [[a, -b, -c, -d], [b, a, -d, c], [c, d, a, -b], [d, -c, b, a]];
  const mr = [[p, q, r, s], [-q, p, -s, r], [-r, s, p, -q], [-s, -r, q, p]];
  const m = [0, 1, 2, 3].map((i) => [0, 1, 2, 3].map((j) => ml[i].reduce((sum, v, k) => sum + v * mr[k][j], 0)));
  return convention === "legacy" ? m : m.map((_, i) => m[3 - i].map((__, j) => m[3 - i][3 - j]));
}

function rotation3d([w, x, y, z]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

/** Per Gaussian: covariance [N·6] (xx, xy, xz, yy, yz, zz), gain [N·3] (mean shift per unit time) and time
 * variance [N]. Real-Time4DGS: Σ4 = (R4·S)(R4·S)ᵀ conditioned on t (Σ11 − Σ12Σ12ᵀ/Σtt, gain Σ12/Σtt, var Σtt);
 * FreeTimeGS: Σ = (R·S)(R·S)ᵀ, gain the velocity, var exp(2·duration). */
function motion(params, backbone, convention, n) {
  const cov = new Float32Array(6 * n);
  const gain = new Float32Array(3 * n);
  const varT = new Float32Array(n);
  for (let g = 0; g < n; g++) {
    const s = [0, 1, 2].map((k) => Math.exp(params.scaling[3 * g + k]));
    let c;
    if (backbone === "rt4dgs") {
      s.push(Math.exp(params.scaling_t[g]));
      const rot = rotation4d(unit(params.rotation, g), unit(params.rotation_r, g), convention);
      const l = rot.map((row) => row.map((v, j) => v * s[j]));
      const sig = (i, j) => l[i][0] * l[j][0] + l[i][1] * l[j][1] + l[i][2] * l[j][2] + l[i][3] * l[j][3];
      const tt = sig(3, 3);
      const xt = [sig(0, 3), sig(1, 3), sig(2, 3)];
      c = [sig(0, 0) - (xt[0] * xt[0]) / tt, sig(0, 1) - (xt[0] * xt[1]) / tt, sig(0, 2) - (xt[0] * xt[2]) / tt,
        sig(1, 1) - (xt[1] * xt[1]) / tt, sig(1, 2) - (xt[1] * xt[2]) / tt, sig(2, 2) - (xt[2] * xt[2]) / tt];
      for (let k = 0; k < 3; k++) gain[3 * g + k] = xt[k] / tt;
      varT[g] = tt;
    } else {
      const rot = rotation3d(unit(params.rotation, g));
      const l = rot.map((row) => row.map((v, j) => v * s[j]));
      const sig = (i, j) => l[i][0] * l[j][0] + l[i][1] * l[j][1] + l[i][2] * l[j][2];
      c = [sig(0, 0), sig(0, 1), sig(0, 2), sig(1, 1), sig(1, 2), sig(2, 2)];
      for (let k = 0; k < 3; k++) gain[3 * g + k] = params.velocity[3 * g + k];
      varT[g] = Math.exp(2 * params.duration[g]);
    }
    cov.set(c, 6 * g);
  }
  return { cov, gain, varT };
}

/** The appearance networks' weights (float32, [out, in] row-major) and sizes, checked against each other. */
function networks(payload, backbone) {
  const names = Object.keys(payload.mlp).sort();
  if (JSON.stringify(names) !== JSON.stringify([...MLP_KEYS].sort())) {
    throw new CorruptFileError(`appearance MLP weights: expected keys ${MLP_KEYS.join(", ")}`);
  }
  const w = Object.fromEntries(MLP_KEYS.map((k) => [k, { shape: payload.mlp[k].shape, values: floats(payload.mlp[k].values) }]));
  const [hidden, encoding] = w["shared.0.weight"].shape;
  const shared = w["shared.2.weight"].shape[0];
  const restOut = w["rest.2.weight"].shape[0];
  const inputs = MLP_INPUTS[backbone];
  const freqs = encoding / (2 * inputs);
  const head = shared + 3;
  const expected = {
    "shared.0.weight": [hidden, encoding], "shared.2.weight": [shared, hidden], "dc.0.weight": [hidden, head],
    "dc.2.weight": [3, hidden], "opacity.0.weight": [hidden, head], "opacity.2.weight": [1, hidden],
    "rest.0.weight": [hidden, head], "rest.2.weight": [restOut, hidden],
  };
  const ok = Number.isInteger(freqs) && freqs >= 1 && freqs <= MAX_FREQS && restOut % 3 === 0 && hidden >= 1
    && hidden <= MAX_HIDDEN && shared >= 1 && shared <= MAX_HIDDEN
    && MLP_KEYS.every((k) => JSON.stringify(w[k].shape) === JSON.stringify(expected[k]));
  if (!ok) throw new CorruptFileError("appearance MLP: sizes this player does not render");
  return { weights: w, hidden, shared, freqs, inputs, numRest: restOut / 3 };
}

function contract(x, y, z) {
  const m = Math.hypot(x, y, z);
  const f = m > 1 ? (2 - 1 / m) / m : 1;
  return [Math.fround((x * f) / 4 + 0.5), Math.fround((y * f) / 4 + 0.5), Math.fround((z * f) / 4 + 0.5)];
}

/** sin/cos(2^k·π·v), k < freqs, interleaved per frequency (tiny-cuda-nn's Frequency encoding) into out[offset…]. */
export function frequencies(v, freqs, out, offset) {
  for (let k = 0; k < freqs; k++) {
    const phase = Math.fround(v * Math.fround(Math.PI * 2 ** k));
    out[offset + 2 * k] = Math.sin(phase);
    out[offset + 2 * k + 1] = Math.cos(phase);
  }
}

/** The shared network's first-layer response to each canonical position, [N·hidden] (AppearanceMLP.position_term;
 * Real-Time4DGS only: its input is [contract(xyz), t_norm] and the encoding acts per input). */
function positionTerm(xyz, net, n) {
  const { hidden, freqs } = net;
  const w = net.weights["shared.0.weight"].values;
  const columns = net.weights["shared.0.weight"].shape[1];
  const width = 6 * freqs;
  const enc = new Float64Array(width);
  const out = new Float32Array(n * hidden);
  for (let g = 0; g < n; g++) {
    const c = contract(xyz[3 * g], xyz[3 * g + 1], xyz[3 * g + 2]);
    for (let d = 0; d < 3; d++) frequencies(c[d], freqs, enc, d * 2 * freqs);
    for (let i = 0; i < hidden; i++) {
      let sum = 0;
      const row = i * columns;
      for (let j = 0; j < width; j++) sum += w[row + j] * enc[j];
      out[g * hidden + i] = sum;
    }
  }
  return out;
}

const isInt = (v, lo, hi) => Number.isInteger(v) && v >= lo && v <= hi;
const REQUIRED_SH_DEGREE_T = { freetimegs: 0 };

/** The model config and active SH degrees a payload's meta declares, validated as omg4/models/compact.py
 * model_settings and GaussianConfig do (a CorruptFileError otherwise). */
function settings(meta) {
  const given = meta.gaussian_config;
  const bad = (why) => new CorruptFileError(`compressed model metadata is incomplete or invalid (${why})`);
  if (given === null || typeof given !== "object" || Array.isArray(given)) throw bad("the model config is not an object");
  const unknown = Object.keys(given).filter((k) => !(k in CONFIG_DEFAULTS) && k !== "time_range");
  if (unknown.length || !("time_range" in given)) throw bad(`unknown fields ${unknown.join(", ")} or no time_range`);
  const config = { ...CONFIG_DEFAULTS, ...given };
  const range = config.time_range;
  if (!(Array.isArray(range) && range.length === 2 && range.every(Number.isFinite) && range[1] > range[0])) {
    throw bad("time_range must be two increasing finite numbers");
  }
  if (!(isInt(config.sh_degree, 0, 3) && isInt(config.sh_degree_t, 0, 2))) throw bad("SH degrees");
  if (!["flip", "legacy"].includes(config.rotation_convention)) throw bad("rotation_convention");
  if (!(typeof config.time_cull === "number" && config.time_cull >= 0 && config.time_cull < 1)) throw bad("time_cull");
  if (!["conditioned", "canonical"].includes(config.sh_direction)) throw bad("sh_direction");
  if (!(typeof config.backbone === "string" && config.backbone in SVQ_WIDTHS)) throw bad("unknown backbone");
  const required = REQUIRED_SH_DEGREE_T[config.backbone];
  if (required !== undefined && config.sh_degree_t !== required) throw bad(`the ${config.backbone} backbone's sh_degree_t`);
  const active = [meta.active_sh_degree, meta.active_sh_degree_t];
  if (!(isInt(active[0], 0, config.sh_degree) && isInt(active[1], 0, config.sh_degree_t))) {
    throw new CorruptFileError("compressed model metadata: active SH degrees must be integers within the maximum");
  }
  return { config, active };
}

/** Everything the renderer reads of one model. */
export function buildModel(payload) {
  const { config, active } = settings(payload.meta);
  const backbone = config.backbone;
  const range = config.time_range;
  const n = payload.numGaussians;
  const params = parameters(payload, backbone);
  const net = networks(payload, backbone);
  if (net.numRest + 1 !== (config.sh_degree + 1) ** 2 * (config.sh_degree_t + 1)) {
    throw new CorruptFileError("appearance MLP: its SH coefficients do not match the model's SH degrees");
  }
  const xyz = floats(payload.xyz);
  const t = floats(payload.t);
  const appearance = new Float32Array(6 * n);
  for (let g = 0; g < n; g++) {
    appearance.set(params.f_static.subarray(3 * g, 3 * g + 3), 6 * g);
    appearance.set(params.f_view.subarray(3 * g, 3 * g + 3), 6 * g + 3);
  }
  return {
    numGaussians: n, backbone, config, activeSh: active, timeRange: range, xyz, t, appearance,
    ...motion(params, backbone, config.rotation_convention, n), net,
    positionTerm: backbone === "rt4dgs" ? positionTerm(xyz, net, n) : null,
  };
}

/** The time half of the shared network's first layer at normalized time tn, [hidden] (Real-Time4DGS). */
export function timeTerm(model, tn) {
  const { hidden, freqs } = model.net;
  const w = model.net.weights["shared.0.weight"].values;
  const columns = model.net.weights["shared.0.weight"].shape[1];
  const enc = new Float64Array(2 * freqs);
  frequencies(Math.fround(tn), freqs, enc, 0);
  const out = new Float32Array(hidden);
  for (let i = 0; i < hidden; i++) {
    let sum = 0;
    for (let j = 0; j < 2 * freqs; j++) sum += w[i * columns + 6 * freqs + j] * enc[j];
    out[i] = sum;
  }
  return out;
}
