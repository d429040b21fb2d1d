// The WebGL2 renderer of one model: static per-Gaussian textures and weight blocks at load; per new time the slice
// pass (transform feedback, read back); per frame the view's colours and a depth sort on the CPU, the splat pass
// onto a float image cleared to the background, and the present pass. Matches omg4's CPU renderer
// (omg4/render/view.py render_view) up to float rounding and its early stop at transmittance 1e-4.

import { timeTerm } from "../model.js";
import {
  FULL_VIEWPORT, NOTHING, PRESENT_FRAGMENT, SPLAT_FRAGMENT, SPLAT_VERTEX, sliceShader, weightLayout,
} from "./shaders.js";

const TEXTURE_WIDTH = 2048;
export const SLICED = 52; // floats the slice pass writes per Gaussian
const PRESENT_UNIT = 14; // the present pass's two texture units, above every renderer's own

// real spherical harmonics up to degree 3 (3DGS eval_sh; omg4/gaussians/sh.py)
const C0 = 0.28209479177387814;
const C1 = 0.4886025119029199;
const C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396];
const C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
  1.445305721320277, -0.5900435899266435];

/** Y_0..Y_15 of the unit direction (x, y, z), zero beyond the active degree's (degree + 1)² terms. */
function basis(x, y, z, degree, out) {
  const xx = x * x;
  const yy = y * y;
  const zz = z * z;
  out.fill(0);
  out[0] = C0;
  if (degree >= 1) {
    out[1] = -C1 * y; out[2] = C1 * z; out[3] = -C1 * x;
  }
  if (degree >= 2) {
    out[4] = C2[0] * x * y; out[5] = C2[1] * y * z; out[6] = C2[2] * (2 * zz - xx - yy); out[7] = C2[3] * x * z;
    out[8] = C2[4] * (xx - yy);
  }
  if (degree >= 3) {
    out[9] = C3[0] * y * (3 * xx - yy); out[10] = C3[1] * x * y * z; out[11] = C3[2] * y * (4 * zz - xx - yy);
    out[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy); out[13] = C3[4] * x * (4 * zz - xx - yy);
    out[14] = C3[5] * z * (xx - yy); out[15] = C3[6] * x * (xx - 3 * yy);
  }
  return out;
}

/** The same Y_0..Y_{(degree + 1)² − 1} as GLSL expressions of the unit direction's x, y, z and their squares xx, yy,
 * zz (a shader's own evaluation of the colour). */
export function basisGlsl(degree) {
  const terms = [`${C0}`, `${-C1} * y`, `${C1} * z`, `${-C1} * x`,
    `${C2[0]} * x * y`, `${C2[1]} * y * z`, `${C2[2]} * (2.0 * zz - xx - yy)`, `${C2[3]} * x * z`,
    `${C2[4]} * (xx - yy)`,
    `${C3[0]} * y * (3.0 * xx - yy)`, `${C3[1]} * x * y * z`, `${C3[2]} * y * (4.0 * zz - xx - yy)`,
    `${C3[3]} * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)`, `${C3[4]} * x * (4.0 * zz - xx - yy)`,
    `${C3[5]} * z * (xx - yy)`, `${C3[6]} * x * (xx - 3.0 * yy)`];
  return terms.slice(0, (degree + 1) ** 2);
}

/** One vertex per point of `count` through the program in use, with `vao`'s inputs, its varyings captured into
 * `buffer` by transform feedback, nothing rasterized (a per-Gaussian pass). */
export function feedbackPass(gl, vao, buffer, count) {
  gl.bindVertexArray(vao);
  gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 0, buffer);
  gl.enable(gl.RASTERIZER_DISCARD);
  gl.beginTransformFeedback(gl.POINTS);
  gl.drawArrays(gl.POINTS, 0, count);
  gl.endTransformFeedback();
  gl.disable(gl.RASTERIZER_DISCARD);
  gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 0, null);
  gl.bindVertexArray(null);
}

/** `buffer`'s contents into the typed array `out` (its first `length` elements; all of them by default). */
export function readBack(gl, buffer, out, length = out.length) {
  gl.bindBuffer(gl.COPY_READ_BUFFER, buffer);
  gl.getBufferSubData(gl.COPY_READ_BUFFER, 0, out, 0, length);
  gl.bindBuffer(gl.COPY_READ_BUFFER, null);
}

export function compile(gl, vertex, fragment, varyings = null) {
  const program = gl.createProgram();
  for (const [type, source] of [[gl.VERTEX_SHADER, vertex], [gl.FRAGMENT_SHADER, fragment]]) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
      throw new Error(`shader does not compile: ${gl.getShaderInfoLog(shader)}`);
    }
    gl.attachShader(program, shader);
  }
  if (varyings) gl.transformFeedbackVaryings(program, varyings, gl.INTERLEAVED_ATTRIBS);
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(`shaders do not link: ${gl.getProgramInfoLog(program)}`);
  return program;
}

/** An RGBA32F texture of `texelsPerItem` texels per item from `values` (`channels` floats per item). */
function floatTexture(gl, values, count, channels, texelsPerItem = 1) {
  const texels = count * texelsPerItem;
  const rows = Math.max(1, Math.ceil(texels / TEXTURE_WIDTH));
  const data = new Float32Array(TEXTURE_WIDTH * rows * 4);
  const perItem = 4 * texelsPerItem;
  for (let i = 0; i < count; i++) {
    for (let c = 0; c < channels; c++) data[i * perItem + c] = values[i * channels + c];
  }
  const texture = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, texture);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, TEXTURE_WIDTH, rows, 0, gl.RGBA, gl.FLOAT, data);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  return texture;
}

/** `parts` ([[array, width]]) side by side: one array of Σ width floats per item. */
function interleave(n, parts) {
  const width = parts.reduce((sum, [, w]) => sum + w, 0);
  const out = new Float32Array(n * width);
  for (let i = 0; i < n; i++) {
    let o = 0;
    for (const [a, w] of parts) {
      for (let c = 0; c < w; c++) out[i * width + o + c] = a[i * w + c];
      o += w;
    }
  }
  return out;
}

/** The canvas's WebGL2 context with float render targets (one per page: every renderer and the compositor use it). */
export function context(canvas) {
  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true, alpha: false });
  if (!gl) throw new Error("this browser has no WebGL2");
  if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("this browser cannot render to float images");
  return gl;
}

export class Renderer {
  constructor(gl, model) {
    this.floatBlend = !!gl.getExtension("EXT_float_blend");
    this.gl = gl;
    this.model = model;
    const n = model.numGaussians;
    const blockVec4 = Math.floor(gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE) / 16);
    this.layout = weightLayout(model.net, blockVec4);
    if (this.layout.blocks > gl.getParameter(gl.MAX_VERTEX_UNIFORM_BLOCKS)) {
      throw new Error("the model's networks do not fit this browser's uniform blocks");
    }
    this.slice = compile(gl, sliceShader(model, this.layout), NOTHING, ["v_mean", ...Array.from({ length: 12 }, (_, i) => `v_q${i}`)]);
    this.splat = compile(gl, SPLAT_VERTEX, SPLAT_FRAGMENT);

    const base = interleave(n, [[model.xyz, 3], [model.t, 1]]);
    const motion = interleave(n, [[model.gain, 3], [model.varT, 1]]);
    const h4 = Math.ceil(model.net.hidden / 4);
    this.textures = {
      u_base: floatTexture(gl, base, n, 4), u_motion: floatTexture(gl, motion, n, 4),
      u_feat: floatTexture(gl, model.appearance, n, 6, 2), u_cov: floatTexture(gl, model.cov, n, 6, 2),
      u_pos: model.positionTerm ? floatTexture(gl, model.positionTerm, n, model.net.hidden, h4)
        : floatTexture(gl, new Float32Array(4), 1, 4),
    };
    this.weightBuffers = [];
    for (let b = 0; b < this.layout.blocks; b++) {
      const start = b * this.layout.blockVec4 * 4;
      const end = Math.min(this.layout.data.length, start + this.layout.blockVec4 * 4);
      const buffer = gl.createBuffer();
      gl.bindBuffer(gl.UNIFORM_BUFFER, buffer);
      gl.bufferData(gl.UNIFORM_BUFFER, this.layout.data.subarray(start, end), gl.STATIC_DRAW);
      gl.uniformBlockBinding(this.slice, gl.getUniformBlockIndex(this.slice, `Weights${b}`), b);
      gl.bindBufferBase(gl.UNIFORM_BUFFER, b, buffer);
      this.weightBuffers.push(buffer);
    }
    this._setSamplers();
    this.feedback = gl.createBuffer();
    gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, this.feedback);
    gl.bufferData(gl.TRANSFORM_FEEDBACK_BUFFER, n * 4 * SLICED, gl.DYNAMIC_READ);
    gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, null);
    this.feedbackAt = null;
    this.sliced = new Float32Array(n * SLICED);  // per Gaussian: μ at τ, opacity, then Q_0..Q_15 (rgb each)
    this.slicedAt = null;
    // quads as plain indexed triangles, four vertices per Gaussian (software GL draws instances one by one)
    this.corners = gl.createBuffer();
    this.cornerIndex = gl.createBuffer();
    this.emptyVao = gl.createVertexArray();
    this.splatVao = gl.createVertexArray();
    gl.bindVertexArray(this.splatVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.corners);
    for (const [location, offset] of [[0, 0], [1, 16]]) {
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 4, gl.FLOAT, false, 32, offset);
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, this.cornerIndex);
    gl.enableVertexAttribArray(2);
    gl.vertexAttribIPointer(2, 1, gl.INT, 4, 0);
    const triangles = new Uint32Array(6 * n);
    for (let q = 0; q < n; q++) triangles.set([4 * q, 4 * q + 1, 4 * q + 2, 4 * q + 2, 4 * q + 1, 4 * q + 3], 6 * q);
    this.triangles = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.triangles);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, triangles, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.target = null;
    this.visible = 0;
  }

  /** This model's textures on units 0… and weight blocks on binding points 0… (several renderers share one
   * context: each binds its own before drawing). */
  _bind() {
    const gl = this.gl;
    Object.values(this.textures).forEach((texture, unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, texture);
    });
    this.weightBuffers.forEach((buffer, b) => gl.bindBufferBase(gl.UNIFORM_BUFFER, b, buffer));
  }

  _setSamplers() {
    const gl = this.gl;
    for (const program of [this.slice, this.splat]) {
      gl.useProgram(program);
      Object.keys(this.textures).forEach((name, unit) => {
        const location = gl.getUniformLocation(program, name);
        if (location !== null) gl.uniform1i(location, unit);
      });
      const width = gl.getUniformLocation(program, "u_width");
      if (width !== null) gl.uniform1i(width, TEXTURE_WIDTH);
    }
  }

  _ensureTarget(width, height) {
    const gl = this.gl;
    if (this.target && this.target.width === width && this.target.height === height) return;
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, this.floatBlend ? gl.RGBA32F : gl.RGBA16F, width, height, 0, gl.RGBA,
      this.floatBlend ? gl.FLOAT : gl.HALF_FLOAT, null);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    const framebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, framebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (this.target) {
      gl.deleteFramebuffer(this.target.framebuffer);
      gl.deleteTexture(this.target.texture);
    }
    this.target = { texture, framebuffer, width, height };
  }

  /** The Gaussians at time `tau` into `feedback`: their means, opacities and colour coefficients (for any view). */
  _slicePass(tau) {
    const gl = this.gl;
    const model = this.model;
    const [t0, t1] = model.timeRange;
    gl.useProgram(this.slice);
    const u = (name) => gl.getUniformLocation(this.slice, name);
    gl.uniform1f(u("u_tau"), tau);
    gl.uniform1f(u("u_period"), t1 - t0);
    gl.uniform1f(u("u_timeCull"), model.config.time_cull);
    gl.uniform1i(u("u_degree"), model.activeSh[0]);
    gl.uniform1i(u("u_degreeT"), model.activeSh[1]);
    const h4 = Math.ceil(model.net.hidden / 4);
    const term = new Float32Array(4 * h4);
    if (model.positionTerm) term.set(timeTerm(model, (tau - t0) / (t1 - t0)));
    gl.uniform4fv(u("u_timeTerm"), term);
    feedbackPass(gl, this.emptyVao, this.feedback, model.numGaussians);
  }

  /** Visible Gaussians back to front (descending view depth; ties: descending index, the reverse of the
   * reference's front-to-back order), with their colour for this view, max(Σ_k Y_k(d)·Q_k + 0.5, 0) where d runs
   * from the camera to the mean at τ (or the canonical mean) → the four corner vertices of each. */
  _sort(camera) {
    const n = this.model.numGaussians;
    const v = camera.viewmat;
    const s = this.sliced;
    const depth = new Float32Array(n);
    const order = [];
    for (let g = 0; g < n; g++) {
      const o = SLICED * g;
      if (!(s[o + 3] >= 1 / 255)) continue;
      depth[g] = v[8] * s[o] + v[9] * s[o + 1] + v[10] * s[o + 2] + v[11];
      if (depth[g] >= 0.2) order.push(g);
    }
    order.sort((a, b) => depth[b] - depth[a] || b - a);
    const vertices = new Float32Array(32 * order.length);
    const index = new Int32Array(4 * order.length);
    const rgb = new Float64Array(3);
    const y = new Float64Array(16);
    order.forEach((g, i) => {
      const o = SLICED * g;
      this.color(g, camera.center, rgb, y);
      for (let c = 0; c < 4; c++) {
        const at = 32 * i + 8 * c;
        vertices[at] = s[o];
        vertices[at + 1] = s[o + 1];
        vertices[at + 2] = s[o + 2];
        vertices[at + 3] = s[o + 3];
        vertices[at + 4] = rgb[0];
        vertices[at + 5] = rgb[1];
        vertices[at + 6] = rgb[2];
        index[4 * i + c] = g;
      }
    });
    return { vertices, index, count: order.length };
  }

  /** Gaussian `g`'s colour at the slice's time seen from `center`, max(Σ_k Y_k(d)·Q_k + 0.5, 0) where d runs from
   * the camera to the mean at τ (or the canonical mean), into `rgb` [3] (`y`: scratch [16]). */
  color(g, center, rgb, y) {
    const s = this.sliced;
    const o = SLICED * g;
    const xyz = this.model.xyz;
    const conditioned = this.model.config.sh_direction !== "canonical";
    const dx = (conditioned ? s[o] : xyz[3 * g]) - center[0];
    const dy = (conditioned ? s[o + 1] : xyz[3 * g + 1]) - center[1];
    const dz = (conditioned ? s[o + 2] : xyz[3 * g + 2]) - center[2];
    const length = Math.max(Math.hypot(dx, dy, dz), 1e-12);
    basis(dx / length, dy / length, dz / length, this.model.activeSh[0], y);
    rgb.fill(0.5);
    for (let k = 0; k < 16; k++) {
      if (y[k] === 0) continue;
      for (let c = 0; c < 3; c++) rgb[c] += y[k] * s[o + 4 + 3 * k + c];
    }
    for (let c = 0; c < 3; c++) rgb[c] = Math.max(rgb[c], 0);
    return rgb;
  }

  /** The Gaussians at time `tau` left on the GPU (the slice pass, skipped when `feedback` holds that time already):
   * `feedback`, the SLICED floats a Gaussian of `sliced` (sliceAt) without reading them back. */
  sliceOnGpu(tau) {
    if (this.feedbackAt === tau) return this.feedback;
    this._bind();
    this._slicePass(tau);
    this.feedbackAt = tau;
    return this.feedback;
  }

  /** The Gaussians at time `tau` (the slice pass, skipped when it is the time sliced last): `sliced`, per Gaussian
   * μ at τ, opacity (0: culled), then the colour's coefficients Q_0..Q_15 (rgb each), for any view. */
  sliceAt(tau) {
    if (this.slicedAt === tau) return this.sliced;
    readBack(this.gl, this.sliceOnGpu(tau), this.sliced);
    this.slicedAt = tau;
    return this.sliced;
  }

  /** Draw the model at time `tau` from `camera` into this renderer's float image, over `background` (not yet on
   * the canvas: see Compositor); returns that image. */
  draw(tau, camera, background) {
    const gl = this.gl;
    const { width, height } = camera;
    this.sliceAt(tau);  // a new view alone reuses the slice
    this._bind();
    const { vertices, index, count } = this._sort(camera);
    this.visible = count;
    this._ensureTarget(width, height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.target.framebuffer);
    gl.viewport(0, 0, width, height);
    gl.clearColor(background[0], background[1], background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (count) {
      gl.useProgram(this.splat);
      const u = (name) => gl.getUniformLocation(this.splat, name);
      const v = camera.viewmat;
      // column-major upload of the row-major world → camera matrix
      gl.uniformMatrix4fv(u("u_view"), false, [v[0], v[4], v[8], v[12], v[1], v[5], v[9], v[13], v[2], v[6], v[10],
        v[14], v[3], v[7], v[11], v[15]]);
      const K = camera.K;
      gl.uniform4f(u("u_K"), K[0], K[4], K[2], K[5]);
      gl.uniform2f(u("u_size"), width, height);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.corners);
      gl.bufferData(gl.ARRAY_BUFFER, vertices, gl.STREAM_DRAW);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.cornerIndex);
      gl.bufferData(gl.ARRAY_BUFFER, index, gl.STREAM_DRAW);
      gl.bindVertexArray(this.splatVao);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
      gl.drawElements(gl.TRIANGLES, 6 * count, gl.UNSIGNED_INT, 0);
      gl.disable(gl.BLEND);
      gl.bindVertexArray(null);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return this.target.texture;
  }

  /** Free the model's GL resources (a sequence keeps only the segments it shows). */
  dispose() {
    const gl = this.gl;
    for (const texture of Object.values(this.textures)) gl.deleteTexture(texture);
    const buffers = [...this.weightBuffers, this.feedback, this.corners, this.cornerIndex, this.triangles];
    for (const buffer of buffers) gl.deleteBuffer(buffer);
    for (const program of [this.slice, this.splat]) gl.deleteProgram(program);
    gl.deleteVertexArray(this.splatVao);
    gl.deleteVertexArray(this.emptyVao);
    if (this.target) {
      gl.deleteFramebuffer(this.target.framebuffer);
      gl.deleteTexture(this.target.texture);
    }
  }
}

/** Puts a frame on the canvas: one renderer's float image, or two crossfaded. */
export class Compositor {
  constructor(gl) {
    this.gl = gl;
    this.program = compile(gl, FULL_VIEWPORT, PRESENT_FRAGMENT);
    this.vao = gl.createVertexArray();
  }

  /** `parts`: [[image, weight], …] (one or two, weights summing to 1) of `width` × `height`. */
  present(parts, width, height) {
    const gl = this.gl;
    const [[first], second] = [parts[0], parts[1] ?? [parts[0][0], 0]];
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, width, height);
    gl.useProgram(this.program);
    [first, second[0]].forEach((texture, i) => {
      gl.activeTexture(gl.TEXTURE0 + PRESENT_UNIT + i);
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.uniform1i(gl.getUniformLocation(this.program, i ? "u_second" : "u_first"), PRESENT_UNIT + i);
    });
    gl.uniform1f(gl.getUniformLocation(this.program, "u_weight"), second[1]);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
  }
}
