// Section decoders of the .omg4 payload (docs/file-format.md §3, §3a): fp16 float sections, grid positions and
// time centres, "sorted" and "first-use" codebooks, unit quaternions, n-bit MLP weights and their changes from a
// reference segment's. Floats come back as Uint16Array fp16 bit patterns equal to the Python decoder's
// (omg4/codec/{payload,grids,codewords,quaternions,weights}.py), computed in doubles and rounded to fp16 as numpy
// does.

import { decodeIndices, decodeSortedCodes, decodeUints, MAX_SYMBOLS } from "./entropy.js";
import {
  CorruptFileError, halfIsFinite, halfToFloat, keyToHalf, orderedKey, splitStreams, toHalfBits, unpackVarints,
} from "./streams.js";

function checkFinite(bits, what) {
  for (let i = 0; i < bits.length; i++) {
    if (!halfIsFinite(bits[i])) throw new CorruptFileError(what);
  }
  return bits;
}

/** `count` fp16 values of a float section ("f16", "f16-planes"; "f16-lzma" needs an LZMA decoder the browser
 * lacks: `omg4 export --format web` re-encodes such files without it). */
export async function decodeFloats(data, encoding, count) {
  let bits;
  if (encoding === "f16") {
    if (data.length !== 2 * count) throw new CorruptFileError(`${data.length} bytes of fp16 data, expected ${2 * count}`);
    bits = new Uint16Array(count);
    for (let i = 0; i < count; i++) bits[i] = data[2 * i] | (data[2 * i + 1] << 8);
  } else if (encoding === "f16-planes") {
    const [high, low] = splitStreams(data, "byte planes");
    const hi = await decodeIndices(high, 256, count);
    const lo = await decodeIndices(low, 256, count);
    bits = new Uint16Array(count);
    for (let i = 0; i < count; i++) bits[i] = (hi[i] << 8) | lo[i];
  } else if (encoding === "f16-lzma") {
    throw new CorruptFileError("LZMA-coded floats are not decoded in the browser (re-export with omg4 export --format web)");
  } else {
    throw new CorruptFileError(`unknown encoding '${encoding}'`);
  }
  return checkFinite(bits, "non-finite values");
}

/** Inverse of codewords.interleave for one code: its `s` 16-bit keys (bit b of key a at bit b·s + a). */
function deinterleaveInto(code, s, out, offset) {
  let hi;
  let lo;
  if (typeof code === "bigint") {
    hi = Number(code >> 32n);
    lo = Number(code & 0xffffffffn);
  } else {
    hi = Math.floor(code / 2 ** 32);
    lo = code - hi * 2 ** 32;
  }
  for (let a = 0; a < s; a++) out[offset + a] = 0;
  for (let p = 0; p < 16 * s; p++) {
    const bit = p < 32 ? Math.floor(lo / 2 ** p) % 2 : Math.floor(hi / 2 ** (p - 32)) % 2;
    if (bit) out[offset + (p % s)] |= 1 << Math.floor(p / s);
  }
}

/** The "sorted" codebook [K, s] (strictly increasing interleaved keys within 16·s bits). */
export async function decodeSortedCodebook(data, rows, sub) {
  if (!(sub >= 1 && sub <= 4)) throw new CorruptFileError(`sorted codebook with sub-vectors of ${sub} values (limit 4)`);
  const codes = await decodeSortedCodes(data, rows, 16 * sub, true,
    "sorted codebook (codes not strictly increasing or out of range)");
  const keys = new Uint16Array(rows * sub);
  for (let i = 0; i < rows; i++) deinterleaveInto(codes[i], sub, keys, i * sub);
  return checkFinite(keys.map(keyToHalf), "non-finite codebook values");
}

/** The indices of the "first-use" mode into a codebook of `rows` rows. */
export async function decodeFirstUseIndices(data, rows, count) {
  if (rows < 1) throw new CorruptFileError("first-use indices into an empty codebook");
  const [flagStream, repeatStream] = splitStreams(data, "first-use flags");
  const isNew = await decodeIndices(flagStream, 2, count);
  let introduced = 0;
  for (const f of isNew) introduced += f;
  if (introduced !== rows || (count && !isNew[0])) {
    throw new CorruptFileError("damaged first-use flags (new codewords do not match the codebook)");
  }
  const repeats = await decodeIndices(repeatStream, rows, count - rows);
  const labels = new Int32Array(count);
  let seen = 0;
  let r = 0;
  for (let i = 0; i < count; i++) {
    if (isNew[i]) {
      labels[i] = seen++;
    } else {
      if (repeats[r] >= seen) {
        throw new CorruptFileError("damaged first-use indices (a repeat refers to a codeword not yet used)");
      }
      labels[i] = repeats[r++];
    }
  }
  return labels;
}

/** fp16 positions stored as their sorted 48-bit Morton codes ("morton": the "ans" codec's positions). */
export async function decodeMorton(data, count) {
  const codes = await decodeSortedCodes(data, count, 48, false, "Morton codes");
  const keys = new Uint16Array(3 * count);
  for (let i = 0; i < count; i++) deinterleaveInto(codes[i], 3, keys, 3 * i);
  return checkFinite(keys.map(keyToHalf), "non-finite positions");
}

/** Positions on the grid ("grid-morton") with, for "grid-morton-exact", the exact fp16 corrections. */
export async function decodePositions(data, count, exact) {
  const [grid, tail] = exact ? splitStreams(data, "position grid") : [data, null];
  if (grid.length < 33) throw new CorruptFileError("truncated position grid");
  const view = new DataView(grid.buffer, grid.byteOffset, grid.byteLength);
  const origin = [view.getFloat64(0, true), view.getFloat64(8, true), view.getFloat64(16, true)];
  const step = view.getFloat64(24, true);
  const bits = view.getUint8(32);
  if (!(bits >= 1 && bits <= 16 && [...origin, step].every(Number.isFinite) && step > 0)) {
    throw new CorruptFileError("invalid position grid");
  }
  const codes = await decodeSortedCodes(grid.subarray(33), count, 3 * bits, false, "Morton codes");
  const cells = new Uint16Array(3 * count);
  for (let i = 0; i < count; i++) deinterleaveInto(codes[i], 3, cells, 3 * i);
  const xyz = new Uint16Array(3 * count);
  for (let i = 0; i < 3 * count; i++) xyz[i] = toHalfBits(origin[i % 3] + cells[i] * step);
  checkFinite(xyz, "positions beyond the fp16 range");
  return exact ? exactPositions(xyz, tail) : xyz;
}

async function exactPositions(xyz, tail) {
  const n = xyz.length / 3;
  const { values: [num], used } = unpackVarints(tail, 0, 1, "exact-position count");
  if (!(num >= 1 && num <= n)) throw new CorruptFileError(`${num} exact positions for ${n} Gaussians`);
  const [rankData, diffData] = splitStreams(tail.subarray(used), "exact-position ranks");
  const rankBits = Math.max(1, (n - 1).toString(2).length * (n > 1));
  const ranks = await decodeSortedCodes(rankData, num, rankBits, true, "exact-position ranks");
  if (ranks[num - 1] >= n) throw new CorruptFileError("damaged exact-position ranks");
  const zigzag = await decodeUints(diffData, 3 * num, 17);
  const out = xyz.slice();
  const keys = new Int32Array(3 * num);
  for (let i = 0; i < 3 * num; i++) {
    const z = zigzag[i];
    const diff = z % 2 ? -(z + 1) / 2 : z / 2;
    keys[i] = orderedKey(xyz[3 * ranks[Math.floor(i / 3)] + (i % 3)]) + diff;
    if (keys[i] < 0 || keys[i] > 0xffff) throw new CorruptFileError("damaged exact positions");
  }
  for (let i = 0; i < 3 * num; i++) out[3 * ranks[Math.floor(i / 3)] + (i % 3)] = keyToHalf(keys[i]);
  return checkFinite(out, "exact positions beyond the fp16 range");
}

/** Time centres on the grid ("grid"): origin + code · step, rounded to fp16. */
export async function decodeTimes(data, count) {
  if (data.length < 20) throw new CorruptFileError("truncated time grid");
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const origin = view.getFloat64(0, true);
  const step = view.getFloat64(8, true);
  const levels = view.getUint32(16, true);
  if (!(Number.isFinite(origin) && Number.isFinite(step) && step > 0 && levels >= 1 && levels <= MAX_SYMBOLS)) {
    throw new CorruptFileError("invalid time grid");
  }
  const codes = await decodeIndices(data.subarray(20), levels, count);
  const t = new Uint16Array(count);
  for (let i = 0; i < count; i++) t[i] = toHalfBits(origin + codes[i] * step);
  return checkFinite(t, "time centres beyond the fp16 range");
}

/** The grid bits of a quaternion encoding name ("smallest-three-b", b in 2–15 without a leading zero), or null. */
export function quaternionBits(name) {
  const m = /^smallest-three-([1-9][0-9]?)$/.exec(name);
  return m && +m[1] >= 2 && +m[1] <= 15 ? +m[1] : null;
}

/** Unit quaternions [count, 4] ("smallest three"): the largest component's index, the other three on the grid
 * −1/√2 + k·√2/(2^b − 2), the largest rebuilt as √(1 − Σ²). */
export async function decodeQuaternions(data, count, bits) {
  const [head, tail] = splitStreams(data, "quaternion stream");
  const levels = 2 ** bits - 1;
  const largest = await decodeIndices(head, 4, count);
  const codes = await decodeIndices(tail, levels, 3 * count);
  const limit = 1 / Math.sqrt(2);
  const step = (2 * limit) / (levels - 1);
  const out = new Uint16Array(4 * count);
  for (let i = 0; i < count; i++) {
    const others = [0, 1, 2].map((j) => codes[3 * i + j] * step - limit);
    const w = Math.sqrt(Math.max(0, 1 - (others[0] * others[0] + others[1] * others[1] + others[2] * others[2])));
    for (let c = 0, o = 0; c < 4; c++) out[4 * i + c] = toHalfBits(c === largest[i] ? w : others[o++]);
  }
  return out;
}

/** (bits, per-column scales) of a weight encoding name ("int2-rows" … "int8-cols"), or null. */
function weightEncoding(name) {
  const m = /^int([2-8])-(rows|cols)$/.exec(name);
  return m ? [+m[1], m[2] === "cols"] : null;
}

/** A 2-D MLP weight [rows, cols] of an int<b>-rows/-cols section: float32 scales, then ANS codes in [−L, L]. */
export async function decodeWeights(data, rows, cols, encoding) {
  const [bits, columns] = weightEncoding(encoding);
  const [r, c] = columns ? [cols, rows] : [rows, cols]; // per-column: the transpose's rows
  const top = 2 ** (bits - 1) - 1;
  if (data.length < 4 * r) throw new CorruptFileError("truncated weight scales");
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const scale = new Float64Array(r);
  for (let i = 0; i < r; i++) {
    scale[i] = view.getFloat32(4 * i, true);
    if (!(Number.isFinite(scale[i]) && scale[i] >= 0 && scale[i] * top <= 65504)) {
      throw new CorruptFileError("invalid weight scales (negative, non-finite or beyond the fp16 range)");
    }
  }
  const codes = await decodeIndices(data.subarray(4 * r), 2 * top + 1, r * c);
  const out = new Uint16Array(rows * cols);
  for (let i = 0; i < r; i++) {
    for (let j = 0; j < c; j++) {
      const value = toHalfBits((codes[i * c + j] - top) * scale[i]);
      out[columns ? j * cols + i : i * cols + j] = value;
    }
  }
  return out;
}

/** The code bits of a weight change's encoding name (`delta-int2-cols` … `delta-int8-cols`), or null
 * (omg4/codec/weights.py parse_delta_encoding). */
function deltaEncoding(name) {
  const m = /^delta-int([2-8])-cols$/.exec(name);
  return m ? +m[1] : null;
}

const DELTA_LEVELS = 15; // omg4/codec/weights.py
const MAX_SHIFT = 31;

/** A predicted segment's 2-D MLP weight [rows, cols] stored as its change from the reference's decoded one
 * (`reference`: fp16 bits): a uint32 byte count, the columns' ANS-coded shifts, then the ANS codes in [−L, L],
 * column by column; each weight is fp16(reference + code · step), step = max(the column's largest |reference|,
 * 2^-14) / 15 · 2^shift (omg4/codec/weights.py decode_delta). */
export async function decodeWeightChange(data, reference, rows, cols, encoding) {
  const top = 2 ** (deltaEncoding(encoding) - 1) - 1;
  const head = data.length < 4 ? -1 : new DataView(data.buffer, data.byteOffset, data.byteLength).getUint32(0, true);
  if (head < 0 || head > data.length - 4) throw new CorruptFileError("truncated change of a weight matrix");
  const shifts = await decodeIndices(data.subarray(4, 4 + head), MAX_SHIFT + 1, cols);
  const codes = await decodeIndices(data.subarray(4 + head), 2 * top + 1, rows * cols);
  const out = new Uint16Array(rows * cols);
  for (let j = 0; j < cols; j++) {
    let largest = 0;
    for (let i = 0; i < rows; i++) largest = Math.max(largest, Math.abs(halfToFloat(reference[i * cols + j])));
    const step = Math.max(largest, 2 ** -14) / DELTA_LEVELS * 2 ** shifts[j];
    for (let i = 0; i < rows; i++) {
      const bits = toHalfBits(halfToFloat(reference[i * cols + j]) + (codes[j * rows + i] - top) * step);
      if (!halfIsFinite(bits)) throw new CorruptFileError("the change takes weights beyond the fp16 range");
      out[i * cols + j] = bits;
    }
  }
  return out;
}
