// GLSL ES 3.00 sources of the player, generated for one model's network sizes.
//
// slice: one vertex per Gaussian, run with transform feedback: the Gaussian at the frame's time (conditional mean
//   and temporal opacity, Real-Time4DGS §3.2 / FreeTimeGS motion; omg4/gaussians/covariance.py, freetime.py), its
//   appearance from the time-conditioned MLPs (paper §4.4, omg4/gaussians/appearance.py; weights in uniform
//   blocks) and its 4D spherical harmonics summed over the temporal bands at that time (omg4/gaussians/sh.py): 16
//   RGB coefficients, so any view's colour is one dot product with the view's basis (renderer.js), and a camera
//   that moves while time stands still needs no new slice.
// splat: one quad per visible Gaussian (two triangles), back to front: EWA projection with the 0.3 px² dilation, the
//   opacity-aware box and α = min(0.999, o·e^{−σ}) ≥ 1/255 of omg4/render/projection.py and cpu_kernels.py.
// present: the float image (or two, crossfaded) clamped to [0, 1] on the canvas.


/** The weights of every network as one vec4 store split over uniform blocks of at most `blockVec4` vec4s. */
export function weightLayout(net, blockVec4) {
  const order = net.inputs === 3 ? ["shared.0.weight"] : [];
  order.push("shared.2.weight", "dc.0.weight", "dc.2.weight", "opacity.0.weight", "opacity.2.weight",
    "rest.0.weight", "rest.2.weight");
  const offsets = {};
  let total = 0;
  for (const name of order) {
    const [rows, cols] = net.weights[name].shape;
    const stride = Math.ceil(cols / 4);
    offsets[name] = { offset: total, stride, rows, cols };
    total += rows * stride;
  }
  const data = new Float32Array(total * 4);
  for (const name of order) {
    const { offset, stride, rows, cols } = offsets[name];
    const values = net.weights[name].values;
    for (let r = 0; r < rows; r++) {
      for (let c = 0; c < cols; c++) data[(offset + r * stride) * 4 + c] = values[r * cols + c];
    }
  }
  const blocks = Math.ceil(total / blockVec4);
  return { offsets, data, total, blocks, blockVec4 };
}

function weightStore(layout) {
  const decl = [];
  const pick = [];
  for (let b = 0; b < layout.blocks; b++) {
    const size = Math.min(layout.blockVec4, layout.total - b * layout.blockVec4);
    decl.push(`layout(std140) uniform Weights${b} { vec4 w${b}[${size}]; };`);
    pick.push(b === layout.blocks - 1 ? `return w${b}[i - ${b * layout.blockVec4}];`
      : `if (i < ${(b + 1) * layout.blockVec4}) return w${b}[i - ${b * layout.blockVec4}];`);
  }
  return `${decl.join("\n")}\nvec4 W(int i) {\n  ${pick.join("\n  ")}\n}`;
}

/** The slice pass (one vertex per Gaussian, with transform feedback): out v_mean = (μ at τ, opacity; 0 when
 * culled) and v_q, the colour's coefficients at τ for any view (the view's colour is Σ_k Y_k(d)·Q_k + 0.5). */
export function sliceShader(model, layout) {
  const { net, config } = model;
  const h4 = Math.ceil(net.hidden / 4);
  const s4 = Math.ceil((net.shared + 3) / 4);
  const band = (config.sh_degree + 1) ** 2;
  const o = layout.offsets;
  const rt = net.inputs === 4;
  return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D u_base;    // xyz, t
uniform sampler2D u_motion;  // gain (mean shift per unit time), time variance
uniform sampler2D u_feat;    // f_static, f_view.x | f_view.yz: two texels per Gaussian
uniform sampler2D u_pos;     // position term of the first layer, ${h4} texels per Gaussian
uniform int u_width;
uniform float u_tau;
uniform float u_period;
uniform float u_timeCull;
uniform int u_degree;
uniform int u_degreeT;
uniform vec4 u_timeTerm[${h4}];
out vec4 v_mean;
${Array.from({ length: 12 }, (_, i) => `out vec4 v_q${i};`).join("\n")}  // Q_0..Q_15 (rgb each), four floats a vec4
${weightStore(layout)}
const int H4 = ${h4};
const int S4 = ${s4};
const int SHARED = ${net.shared};

ivec2 texel(int i) { return ivec2(i % u_width, i / u_width); }
vec4 lrelu(vec4 x) { return max(x, 0.01 * x); }

// one output of a layer: row r of the matrix at offset (stride S4 or H4) times the input vec4s
float rowS(int offset, int r, vec4 x[S4]) {
  float sum = 0.0;
  for (int j = 0; j < S4; j++) sum += dot(W(offset + r * S4 + j), x[j]);
  return sum;
}
float rowH(int offset, int r, vec4 x[H4]) {
  float sum = 0.0;
  for (int j = 0; j < H4; j++) sum += dot(W(offset + r * H4 + j), x[j]);
  return sum;
}
void hidden(int offset, vec4 x[S4], out vec4 h[H4]) {
  for (int i = 0; i < H4; i++) {
    vec4 v = vec4(0.0);
    for (int c = 0; c < 4; c++) if (4 * i + c < ${net.hidden}) v[c] = rowS(offset, 4 * i + c, x);
    h[i] = lrelu(v);
  }
}
vec3 contract(vec3 x) {
  float m = length(x);
  return (m > 1.0 ? (2.0 - 1.0 / m) * (x / m) : x) / 4.0 + 0.5;
}
// sin or cos of 2^k·π·v with the phase reduced exactly: 2^k·v is exact, so is its remainder modulo 2
float harmonic(float v, int k, bool cosine) {
  float m = v * exp2(float(k));
  float r = m - 2.0 * floor(m * 0.5);
  return cosine ? cos(3.141592653589793 * r) : sin(3.141592653589793 * r);
}

void main() {
  int g = gl_VertexID;
  vec4 base = texelFetch(u_base, texel(g), 0);
  vec4 motion = texelFetch(u_motion, texel(g), 0);
  float delta = u_tau - base.w;
  float pt = exp(-0.5 * delta * delta / motion.w);
  vec3 mean = base.xyz + motion.xyz * delta;
${Array.from({ length: 12 }, (_, i) => `  v_q${i} = vec4(0.0);`).join("\n")}
  if (!(pt > u_timeCull)) {
    v_mean = vec4(mean, 0.0);
    return;
  }
  vec4 h[H4];
${rt ? `  for (int i = 0; i < H4; i++) h[i] = max(texelFetch(u_pos, texel(g * H4 + i), 0) + u_timeTerm[i], 0.0);`
    : `  vec3 c = contract(mean);
  const int F = ${net.freqs};
  for (int i = 0; i < H4; i++) {
    vec4 v = vec4(0.0);
    for (int q = 0; q < 4; q++) {
      if (4 * i + q >= ${net.hidden}) continue;
      int row = ${o["shared.0.weight"].offset} + (4 * i + q) * ${o["shared.0.weight"].stride};
      float sum = 0.0;
      for (int j = 0; j < 6 * F; j += 4) {
        vec4 e;
        for (int u = 0; u < 4; u++) {
          int col = j + u;
          e[u] = harmonic(c[col / (2 * F)], (col % (2 * F)) / 2, col % 2 == 1);
        }
        sum += dot(W(row + j / 4), e);
      }
      v[q] = sum;
    }
    h[i] = max(v, 0.0);
  }`}
  vec4 s[S4];
  vec4 sv[S4];
  for (int i = 0; i < S4; i++) { s[i] = vec4(0.0); sv[i] = vec4(0.0); }
  for (int r = 0; r < SHARED; r++) {
    float x = rowH(${o["shared.2.weight"].offset}, r, h);
    s[r / 4][r % 4] = x;
    sv[r / 4][r % 4] = x;
  }
  vec4 f0 = texelFetch(u_feat, texel(2 * g), 0);
  vec4 f1 = texelFetch(u_feat, texel(2 * g + 1), 0);
  vec3 fs = f0.xyz;
  vec3 fv = vec3(f0.w, f1.xy);
  for (int c = 0; c < 3; c++) {
    s[(SHARED + c) / 4][(SHARED + c) % 4] = fs[c];
    sv[(SHARED + c) / 4][(SHARED + c) % 4] = fv[c];
  }
  vec4 a[H4];
  hidden(${o["dc.0.weight"].offset}, s, a);
  vec3 dc = vec3(rowH(${o["dc.2.weight"].offset}, 0, a), rowH(${o["dc.2.weight"].offset}, 1, a),
                 rowH(${o["dc.2.weight"].offset}, 2, a));
  hidden(${o["opacity.0.weight"].offset}, s, a);
  float logit = rowH(${o["opacity.2.weight"].offset}, 0, a);
  hidden(${o["rest.0.weight"].offset}, sv, a);

  // Q_k = Σ_n cos(2πn·(t − τ)/T)·(the rest head's coefficient band·n + k), Q_0 with the dc term
  float q[48];
  for (int i = 0; i < 48; i++) q[i] = 0.0;
  q[0] = dc.r; q[1] = dc.g; q[2] = dc.b;
  int spatial = (u_degree + 1) * (u_degree + 1);
  for (int n = 0; n <= u_degreeT; n++) {
    float tw = cos(6.283185307179586 * float(n) * (base.w - u_tau) / u_period);
    for (int k = 0; k < spatial; k++) {
      if (n == 0 && k == 0) continue;
      // coefficient band·n + k is the rest head's rows 3·(coefficient − 1) + channel
      int row = ${o["rest.2.weight"].offset} + 3 * (${band} * n + k - 1) * H4;
      vec3 sum = vec3(0.0);
      for (int j = 0; j < H4; j++) {
        vec4 x = a[j];
        sum += vec3(dot(W(row + j), x), dot(W(row + H4 + j), x), dot(W(row + 2 * H4 + j), x));
      }
      q[3 * k] += tw * sum.r;
      q[3 * k + 1] += tw * sum.g;
      q[3 * k + 2] += tw * sum.b;
    }
  }
${Array.from({ length: 12 }, (_, i) => `  v_q${i} = vec4(q[${4 * i}], q[${4 * i + 1}], q[${4 * i + 2}], q[${4 * i + 3}]);`).join("\n")}
  v_mean = vec4(mean, pt / (1.0 + exp(-logit)));
}
`;
}

export const SPLAT_VERTEX = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
layout(location = 0) in vec4 a_mean;    // μ at τ, opacity (the same at the quad's four corners)
layout(location = 1) in vec4 a_color;   // rgb
layout(location = 2) in int a_index;    // the Gaussian (its covariance in u_cov)
uniform sampler2D u_cov;   // xx, xy, xz, yy | yz, zz: two texels per Gaussian
uniform int u_width;
uniform mat4 u_view;       // world → camera (OpenCV: x right, y down, z forward)
uniform vec4 u_K;          // fx, fy, cx, cy in pixels
uniform vec2 u_size;       // image width, height
flat out vec2 v_center;
flat out vec3 v_conic;
flat out vec4 v_rgba;
void cull() { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); }
void main() {
  float opacity = a_mean.w;
  vec3 m = (u_view * vec4(a_mean.xyz, 1.0)).xyz;
  if (opacity < 1.0 / 255.0 || m.z < 0.2 || m.z > 1e10) { cull(); return; }
  int first = 2 * a_index;
  vec4 ca = texelFetch(u_cov, ivec2(first % u_width, first / u_width), 0);
  vec2 cb = texelFetch(u_cov, ivec2((first + 1) % u_width, (first + 1) / u_width), 0).xy;
  mat3 sigma = mat3(ca.x, ca.y, ca.z, ca.y, ca.w, cb.x, ca.z, cb.x, cb.y);
  float fx = u_K.x, fy = u_K.y, cx = u_K.z, cy = u_K.w;
  float tanx = 0.5 * u_size.x / fx, tany = 0.5 * u_size.y / fy;
  float tx = m.z * clamp(m.x / m.z, -(cx / fx + 0.3 * tanx), (u_size.x - cx) / fx + 0.3 * tanx);
  float ty = m.z * clamp(m.y / m.z, -(cy / fy + 0.3 * tany), (u_size.y - cy) / fy + 0.3 * tany);
  vec3 j0 = vec3(fx / m.z, 0.0, -fx * tx / (m.z * m.z));
  vec3 j1 = vec3(0.0, fy / m.z, -fy * ty / (m.z * m.z));
  mat3 rot = mat3(u_view);
  vec3 a0 = transpose(rot) * j0;
  vec3 a1 = transpose(rot) * j1;
  float c00 = dot(a0, sigma * a0) + 0.3;
  float c01 = dot(a0, sigma * a1);
  float c11 = dot(a1, sigma * a1) + 0.3;
  float det = c00 * c11 - c01 * c01;
  if (!(det > 0.0) || !(c00 > 0.0) || !(c11 > 0.0)) { cull(); return; }
  vec2 center = vec2(fx * m.x / m.z + cx, fy * m.y / m.z + cy);
  float extend = min(3.33, sqrt(2.0 * log(opacity * 255.0)));
  vec2 radius = ceil(extend * sqrt(vec2(c00, c11)));
  if (center.x + radius.x <= 0.0 || center.x - radius.x >= u_size.x || center.y + radius.y <= 0.0
      || center.y - radius.y >= u_size.y) { cull(); return; }
  // the quad: the ellipse σ ≤ ln(255·o) outside which α < 1/255, along its principal axes (inside the box above,
  // but far fewer fragments for a thin, tilted Gaussian)
  float mid = 0.5 * (c00 + c11);
  float spread = sqrt(max(mid * mid - det, 0.0));
  vec2 axis = abs(c01) > 1e-12 ? normalize(vec2(c01, mid + spread - c00)) : (c00 >= c11 ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 half_axes = sqrt(2.0 * log(opacity * 255.0) * vec2(mid + spread, max(mid - spread, 0.0))) + 0.01;
  vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1)) * 2.0 - 1.0;
  vec2 pixel = center + corner.x * half_axes.x * axis + corner.y * half_axes.y * vec2(-axis.y, axis.x);
  gl_Position = vec4(pixel.x / u_size.x * 2.0 - 1.0, 1.0 - pixel.y / u_size.y * 2.0, 0.0, 1.0);
  v_center = center;
  v_conic = vec3(c11 / det, -c01 / det, c00 / det);
  v_rgba = vec4(a_color.rgb, opacity);
}
`;

export const SPLAT_FRAGMENT = `#version 300 es
precision highp float;
uniform vec2 u_size;
flat in vec2 v_center;
flat in vec3 v_conic;
flat in vec4 v_rgba;
out vec4 color;
void main() {
  vec2 d = v_center - vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  float sigma = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
  if (sigma < 0.0) discard;
  float alpha = min(0.999, v_rgba.a * exp(-sigma));
  if (alpha < 1.0 / 255.0) discard;
  color = vec4(v_rgba.rgb, alpha);
}
`;

/** A fragment shader for a pass that draws nothing (the slice pass, with the rasterizer discarding). */
export const NOTHING = `#version 300 es
precision highp float;
out vec4 color;
void main() { color = vec4(0.0); }
`;

/** A triangle covering the viewport (the present pass). */
export const FULL_VIEWPORT = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
`;

/** The frame: one float image, or two crossfaded (the two segments of a sequence across their shared frames,
 * (1 − w)·first + w·second, as omg4/render/view.py blends them), clamped to [0, 1]. */
export const PRESENT_FRAGMENT = `#version 300 es
precision highp float;
uniform sampler2D u_first;
uniform sampler2D u_second;
uniform float u_weight;
out vec4 color;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec3 rgb = (1.0 - u_weight) * texelFetch(u_first, p, 0).rgb + u_weight * texelFetch(u_second, p, 0).rgb;
  color = vec4(clamp(rgb, 0.0, 1.0), 1.0);
}
`;
