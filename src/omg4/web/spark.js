// omg4 in a three.js scene of one's own, drawn by Spark (@sparkjsdev/spark: it sorts and rasterizes the splats):
// Omg4Splats decodes an .omg4 file and keeps a Spark SplatMesh holding its Gaussians at the time it plays.
//
//   import { OMG4_CONVENTIONS, Omg4Splats, leanSplatShaders } from "./omg4/spark.js";  // three, Spark: import map
//   const splats = await Omg4Splats.load("omg4/model.omg4");
//   scene.add(leanSplatShaders(new SparkRenderer({ renderer, ...OMG4_CONVENTIONS })));
//   scene.add(splats.mesh);                                   // the model's world, +z up: rotate the mesh to taste
//   renderer.setAnimationLoop((ms) => { splats.update(t, camera); renderer.render(scene, camera); });
//
// Per new time the slice pass of the player's renderer (render/renderer.js, in a WebGL2 context of its own) gives
// each Gaussian's mean and opacity at τ and its colour coefficients, left on the GPU; per new time or camera position
// the pack pass (packShader) evaluates each colour for the camera's position (the 4D SH and the appearance MLPs'
// view-dependent terms, as the player does) and writes every Gaussian's four 32-bit words of Spark 2.2.0's packed
// layout (setPackedSplat's: RGBA bytes; centre x, y halves; centre z half and two quaternion bytes; three scale bytes
// and one quaternion byte), which one read-back copies into the SplatMesh's PackedSplats — no loop over the
// Gaussians in JavaScript. Covariances do not change with time (the conditional Σ_3D of Real-Time4DGS, FreeTimeGS's
// Σ): their scales and rotations are packed once, at load, and the pack pass copies those words through.
// leanSplatShaders draws the same picture with less work per splat and per pixel, which decides the frame rate where
// WebGL runs in software (SwiftShader).

import * as THREE from "three";
import { PackedSplats, SplatMesh } from "@sparkjsdev/spark";
import { decodePayload } from "./decoder/payload.js";
import { buildModel } from "./model.js";
import { Renderer, SLICED, basisGlsl, compile, context, feedbackPass, readBack } from "./render/renderer.js";
import { NOTHING } from "./render/shaders.js";

/** Eigen-decomposition of the symmetric 3×3 matrix (xx, xy, xz, yy, yz, zz) by Jacobi rotations: the standard
 * deviations along its axes and the rotation whose columns are those axes (a proper rotation). */
export function principalAxes(c) {
  const a = [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]];
  const v = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  for (let sweep = 0; sweep < 32; sweep++) {
    const off = Math.abs(a[0][1]) + Math.abs(a[0][2]) + Math.abs(a[1][2]);
    if (off <= 1e-30 * (Math.abs(a[0][0]) + Math.abs(a[1][1]) + Math.abs(a[2][2]) + 1e-300)) break;
    for (const [p, q] of [[0, 1], [0, 2], [1, 2]]) {
      if (a[p][q] === 0) continue;
      const theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
      const t = Math.sign(theta || 1) / (Math.abs(theta) + Math.sqrt(theta * theta + 1));
      const cs = 1 / Math.sqrt(t * t + 1);
      const sn = t * cs;
      for (let k = 0; k < 3; k++) {  // a ← Jᵀ a J, v ← v J
        const akp = a[k][p], akq = a[k][q];
        a[k][p] = cs * akp - sn * akq;
        a[k][q] = sn * akp + cs * akq;
      }
      for (let k = 0; k < 3; k++) {
        const apk = a[p][k], aqk = a[q][k];
        a[p][k] = cs * apk - sn * aqk;
        a[q][k] = sn * apk + cs * aqk;
      }
      for (let k = 0; k < 3; k++) {
        const vkp = v[k][p], vkq = v[k][q];
        v[k][p] = cs * vkp - sn * vkq;
        v[k][q] = sn * vkp + cs * vkq;
      }
    }
  }
  const det = v[0][0] * (v[1][1] * v[2][2] - v[1][2] * v[2][1]) - v[0][1] * (v[1][0] * v[2][2] - v[1][2] * v[2][0])
    + v[0][2] * (v[1][0] * v[2][1] - v[1][1] * v[2][0]);
  if (det < 0) for (let k = 0; k < 3; k++) v[k][2] = -v[k][2];
  const sigma = [0, 1, 2].map((i) => Math.sqrt(Math.max(a[i][i], 1e-24)));
  return { sigma, axes: v };
}

const MIN_ALPHA = 1 / 255;  // Spark's minAlpha here: a splat of lower opacity draws no pixel

/** The highest opacity byte a splat is given. Spark's accumulator keeps half the opacity in 8 bits and doubles it to
 * draw, so a byte of 255 (opacity ≥ 0.998) comes back as 128 / 127.5 > 1: Spark's LOD opacity, drawn with another
 * kernel (and a wider cut-off); 254 comes back as 0.996 ≤ 1, drawn as every other splat (omg4 caps α at 0.999). */
const MAX_OPACITY_BYTE = 254;

/** The pack pass for `model` (GLSL ES 3.00, one vertex per Gaussian, its output captured by transform feedback): from
 * the slice pass's floats (μ at τ, opacity, Q_0..Q_15 in 13 vec4s) and the Gaussian's constant shape words, its four
 * words of Spark's layout — the colour from u_center, max(Σ_k Y_k(d)·Q_k + 0.5, 0) with d from the camera to the
 * mean at τ (or the canonical mean) as Renderer.color has it, and the opacity, as Spark's floatToUint8 rounds them
 * (the opacity byte at most MAX_OPACITY_BYTE); the centre as halves. A Gaussian below MIN_ALPHA gets four zero
 * words: zero scales, an empty slot to Spark, which leaves it out of its sort and its draw as if it were not there. */
function packShader(model) {
  // Q_k's rgb: floats 3k, 3k + 1, 3k + 2 of the 48 in a_q0..a_q11
  const q = (k) => `vec3(${[0, 1, 2].map((c) => `a_q${(3 * k + c) >> 2}.${"xyzw"[(3 * k + c) & 3]}`).join(", ")})`;
  const terms = basisGlsl(model.activeSh[0]).map((y, k) => `\n      + (${y}) * ${q(k)}`).join("");
  const canonical = model.config.sh_direction === "canonical";
  const inputs = [
    "layout(location = 0) in vec4 a_mean;  // μ at τ, opacity (0: culled)",
    ...Array.from({ length: 12 }, (_, i) => `layout(location = ${i + 1}) in vec4 a_q${i};`),
    "layout(location = 13) in uvec2 a_shape;  // word 2's quaternion bytes (its high half), word 3",
    ...(canonical ? ["layout(location = 14) in vec3 a_xyz;  // the canonical mean"] : []),
  ];
  return `#version 300 es
precision highp float;
precision highp int;
${inputs.join("\n")}
uniform vec3 u_center;  // the camera, in the model's world
flat out uvec4 v_words;

uint toByte(float v) { return uint(floor(clamp(v, 0.0, 1.0) * 255.0 + 0.5)); }

void main() {
  float opacity = a_mean.w;
  if (!(opacity >= ${MIN_ALPHA})) {
    v_words = uvec4(0u);
    return;
  }
  vec3 d = ${canonical ? "a_xyz" : "a_mean.xyz"} - u_center;
  d /= max(length(d), 1e-12);
  float x = d.x, y = d.y, z = d.z, xx = x * x, yy = y * y, zz = z * z;
  vec3 rgb = max(vec3(0.5)${terms}, 0.0);
  uint alpha = min(toByte(opacity), ${MAX_OPACITY_BYTE}u);
  v_words = uvec4(toByte(rgb.r) | toByte(rgb.g) << 8 | toByte(rgb.b) << 16 | alpha << 24, packHalf2x16(a_mean.xy),
                  packHalf2x16(vec2(a_mean.z, 0.0)) | a_shape.x, a_shape.y);
}
`;
}

/** The pack pass (packShader) of `slicer`'s model in its context: its input, the slice pass's output buffer, and its
 * output, a buffer of four words a Gaussian. `shape`: each Gaussian's two constant words (word 2's quaternion bytes,
 * word 3). */
class PackPass {
  constructor(slicer, shape) {
    const gl = slicer.gl;
    const { model } = slicer;
    this.gl = gl;
    this.slicer = slicer;
    this.program = compile(gl, packShader(model), NOTHING, ["v_words"]);
    this.uCenter = gl.getUniformLocation(this.program, "u_center");
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, slicer.feedback);
    for (let location = 0; location < 13; location++) {
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 4, gl.FLOAT, false, 4 * SLICED, 16 * location);
    }
    gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer());
    gl.bufferData(gl.ARRAY_BUFFER, shape, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(13);
    gl.vertexAttribIPointer(13, 2, gl.UNSIGNED_INT, 8, 0);
    if (model.config.sh_direction === "canonical") {
      gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer());
      gl.bufferData(gl.ARRAY_BUFFER, model.xyz, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(14);
      gl.vertexAttribPointer(14, 3, gl.FLOAT, false, 12, 0);
    }
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    this.words = gl.createBuffer();
    gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, this.words);
    gl.bufferData(gl.TRANSFORM_FEEDBACK_BUFFER, 16 * model.numGaussians, gl.DYNAMIC_READ);
    gl.bindBuffer(gl.TRANSFORM_FEEDBACK_BUFFER, null);
  }

  /** Every Gaussian's words at time `tau` seen from `center` ([x, y, z], the model's world) into `out` (a
   * Uint32Array of four words a Gaussian or more: Spark's packed array). */
  run(tau, center, out) {
    const gl = this.gl;
    const n = this.slicer.model.numGaussians;
    this.slicer.sliceOnGpu(tau);
    gl.useProgram(this.program);
    gl.uniform3f(this.uCenter, center[0], center[1], center[2]);
    feedbackPass(gl, this.vao, this.words, n);
    readBack(gl, this.words, out, 4 * n);
  }
}

// Spark 2.2.0's splat shaders (SparkRenderer's material), where leanSplatShaders edits them
const VERTEX_MAIN = "void main() {\n";
const VERTEX_COLOUR = "    vRgba = rgba;\n";
const FRAGMENT_TO_LINEAR = "    if (encodeLinear) {\n        rgba.rgb = srgbToLinear(rgba.rgb);\n    }\n";
const FRAGMENT_KERNELS = [
  "        if (rgba.a <= 1.0) {",
  "            rgba.a = mix(rgba.a, rgba.a * exp(-0.5 * z2), falloff);",
  "        } else {",
  "            float a = exp((rgba.a*rgba.a - 1.0) / 2.718281828459045);",
  "            float alpha = 1.0 - pow(1.0 - exp(-0.5 * z2), a);",
  "            rgba.a = mix(1.0, alpha, falloff);",
  "        }\n"].join("\n");
const FRAGMENT_KERNEL = "        rgba.a = mix(rgba.a, rgba.a * exp(-0.5 * z2), falloff);\n";
// a splat's two triangles from gl_VertexID, six vertices a splat: Spark's quad (corners ±1), triangles 0 1 2, 0 2 3
const SIX_VERTICES = `
    int splatInstance = gl_VertexID / 6;
    int corner = gl_VertexID - 6 * splatInstance;
    vec3 position = vec3((corner == 1 || corner == 2 || corner == 4) ? 1.0 : -1.0,
                         (corner == 2 || corner == 4 || corner == 5) ? 1.0 : -1.0, 0.0);
`;

/** A SparkRenderer's geometry for the vertex shader of leanSplatShaders: no attributes (the shader makes each
 * corner); the splat count Spark sets each frame (as an instance count) sets the draw's range, six vertices a splat. */
class SplatQuads extends THREE.BufferGeometry {
  get instanceCount() { return this.drawRange.count / 6; }

  set instanceCount(count) { this.setDrawRange(0, 6 * count); }
}

/** `spark` (a SparkRenderer of Spark 2.2.0) drawing the same picture for less: its splats in one draw of six vertices
 * each rather than one instance each (software WebGL pays for each instance as for a draw: about 4,000 splats cost
 * more than the pixels), and its fragment shader without the branches that no Omg4Splats pixel takes — a shader runs
 * both sides of a branch in software — the sRGB → linear conversion (for linear render targets only) moved to the
 * vertex shader, where a splat's colour is constant (the same up to rounding), and the kernel of Spark's LOD
 * opacities (> 1; Omg4Splats gives none, see MAX_OPACITY_BYTE) left out: meant for a SparkRenderer drawing
 * Omg4Splats, not Spark's LOD splats. Another Spark version's shaders are left as they are (with a warning).
 * Returns `spark`. */
export function leanSplatShaders(spark) {
  const material = spark.material;
  const vertex = material.vertexShader, fragment = material.fragmentShader;
  if (!(vertex.includes(VERTEX_MAIN) && vertex.includes(VERTEX_COLOUR) && vertex.includes("gl_InstanceID")
        && fragment.includes(FRAGMENT_TO_LINEAR) && fragment.includes(FRAGMENT_KERNELS))) {
    console.warn("leanSplatShaders: not Spark 2.2.0's splat shaders; left as they are");
    return spark;
  }
  material.vertexShader = vertex.replace(VERTEX_MAIN, `uniform bool encodeLinear;\n\n${VERTEX_MAIN}${SIX_VERTICES}`)
    .replaceAll("gl_InstanceID", "splatInstance")
    .replace(VERTEX_COLOUR, `${VERTEX_COLOUR}    if (encodeLinear) vRgba.rgb = srgbToLinear(vRgba.rgb);\n`);
  material.fragmentShader = fragment.replace(FRAGMENT_TO_LINEAR, "").replace(FRAGMENT_KERNELS, FRAGMENT_KERNEL);
  material.needsUpdate = true;
  spark.geometry.dispose();
  spark.geometry = new SplatQuads();
  return spark;
}

/** SparkRenderer options that draw as omg4's renderer does (gsplat's conventions): the 0.3 px² dilation without
 * opacity compensation, splats cut at 3.33σ and α ≥ 1/255, sorted by view depth. */
export const OMG4_CONVENTIONS = { preBlurAmount: 0.3, blurAmount: 0, maxStdDev: 3.33, minAlpha: MIN_ALPHA, sortRadial: false };

export class Omg4Splats {
  /** Fetch and decode the .omg4 file at `url` (a single model). */
  static async load(url) {
    const response = await fetch(url);
    if (!response.ok) throw new Error(`${url}: ${response.status} ${response.statusText}`);
    const payload = await decodePayload(new Uint8Array(await response.arrayBuffer()));
    return new Omg4Splats(buildModel(payload), payload.meta);
  }

  /** `model`: a decoded model (model.js buildModel); `meta`: its file's metadata (its camera rig). */
  constructor(model, meta = {}) {
    this.model = model;
    this.meta = meta;
    this.timeRange = model.timeRange;
    this.slicer = new Renderer(context(document.createElement("canvas")), model);
    const n = model.numGaussians;
    this.packed = new PackedSplats({ maxSplats: Math.max(n, 1) });
    const basis = new THREE.Matrix4();
    const scale = new THREE.Vector3();
    const rotation = new THREE.Quaternion();
    const zero = new THREE.Vector3();
    const black = new THREE.Color(0, 0, 0);
    for (let g = 0; g < n; g++) {  // the scales and rotations, packed once (update writes the rest)
      const { sigma, axes } = principalAxes(model.cov.subarray(6 * g, 6 * g + 6));
      basis.set(axes[0][0], axes[0][1], axes[0][2], 0, axes[1][0], axes[1][1], axes[1][2], 0, axes[2][0], axes[2][1],
        axes[2][2], 0, 0, 0, 0, 1);
      this.packed.pushSplat(zero, scale.set(...sigma), rotation.setFromRotationMatrix(basis), 0, black);
    }
    const words = this.packed.packedArray;
    const shape = new Uint32Array(2 * n);  // each Gaussian's constant words: quaternion bytes, scales
    for (let g = 0; g < n; g++) {
      shape[2 * g] = words[4 * g + 2] & 0xffff0000;
      shape[2 * g + 1] = words[4 * g + 3];
    }
    this.packer = new PackPass(this.slicer, shape);
    this.mesh = new SplatMesh({ packedSplats: this.packed });
    this.time = null;
    this._seenFrom = null;
    this._center = new THREE.Vector3();
    this._inverse = new THREE.Matrix4();
  }

  /** The Gaussians at `time` (seconds, clamped to the model's time range) as seen by `camera` (a three.js camera:
   * its position gives the view-dependent colours): writes them into the mesh's splats. */
  update(time, camera) {
    const [t0, t1] = this.timeRange;
    const tau = Math.min(Math.max(time, t0), t1);
    this.mesh.updateMatrixWorld();
    camera.getWorldPosition(this._center).applyMatrix4(this._inverse.copy(this.mesh.matrixWorld).invert());
    const center = [this._center.x, this._center.y, this._center.z];
    if (tau === this.time && center.every((v, k) => v === this._seenFrom?.[k])) return;  // the splats hold this view
    this.packer.run(tau, center, this.packed.packedArray);  // every Gaussian: those culled at τ are empty slots
    this.packed.needsUpdate = true;  // the packed array to upload
    this.mesh.needsUpdate = true;  // and its splats to generate again: Spark does not see a changed packed array
    this.time = tau;
    this._seenFrom = center;
  }

  /** A three.js camera looking as an omg4 camera ({K, viewmat, width, height}, OpenCV axes, row-major) looks: its
   * pose from the view matrix, its projection from K (principal point included), for a mesh left in place. */
  static threeCamera(camera, near = 0.01, far = 1000) {
    const three = new THREE.PerspectiveCamera();
    const v = camera.viewmat;
    const world = new THREE.Matrix4().set(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9], v[10], v[11], 0, 0,
      0, 1).invert().multiply(new THREE.Matrix4().makeScale(1, -1, -1));  // OpenCV camera → three's (y up, −z ahead)
    world.decompose(three.position, three.quaternion, three.scale);
    three.updateMatrixWorld(true);
    const [fx, , cx, , fy, cy] = camera.K;
    const { width: w, height: h } = camera;
    three.projectionMatrix.set(2 * fx / w, 0, 1 - 2 * cx / w, 0, 0, 2 * fy / h, 2 * cy / h - 1, 0, 0, 0,
      -(far + near) / (far - near), -2 * far * near / (far - near), 0, 0, -1, 0);
    three.projectionMatrixInverse.copy(three.projectionMatrix).invert();
    three.near = near;
    three.far = far;
    three.aspect = w / h;
    three.fov = (2 * Math.atan(h / (2 * fy)) * 180) / Math.PI;
    return three;
  }
}
