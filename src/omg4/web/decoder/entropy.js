// Index streams of the .omg4 format (docs/file-format.md §4, omg4/codec/entropy.py): the "ans" coder — a
// categorical model quantized as constriction's Categorical(perfect=False) and its stack AnsCoder (32-bit words,
// 64-bit state, 24-bit precision) — and the hybrid-uint coder built on it. Values equal the Python decoder's.

import { CorruptFileError, inflateRaw, splitStreams, unpackVarints, wordsLE } from "./streams.js";

export const MAX_SYMBOLS = 1 << 16;
const MAX_COUNT = 2 ** 31 - 1;
const TAG_ANS = 0xa1;
const STEPS = [1, 2, 4, 8];
// round(2^15 · 2^(j/8)), j = 0..7: the integer symbol weights 2^(e/8)
const MANTISSA = [32768, 35734, 38968, 42495, 46341, 50535, 55109, 60097];
const PRECISION = 2 ** 24;
const WORD = 2 ** 32;

/** constriction's fast quantization of the weights 2^((q−1)/steps) (ContiguousCategoricalEntropyModel::
 * from_floating_point_probabilities_fast): cdf[i] = ⌊Σ_{j<i} w_j · (2^24 − K) / Σ w⌋ + i, cdf[K] = 2^24. */
function quantizedCdf(q, steps) {
  const k = q.length;
  const weights = new Float64Array(k);
  for (let i = 0; i < k; i++) {
    if (q[i] > 0) {
      const e = (q[i] - 1) * (8 / steps);
      weights[i] = MANTISSA[e % 8] * 2 ** Math.floor(e / 8);
    }
  }
  let norm = 0;
  for (let i = 0; i < k; i++) norm += weights[i];
  const scale = (PRECISION - k) / norm;
  const cdf = new Float64Array(k + 1);
  let cumulative = 0;
  for (let i = 0; i < k; i++) {
    cdf[i] = Math.min(Math.floor(cumulative * scale), WORD - 1) + i;
    cumulative += weights[i];
  }
  cdf[k] = PRECISION;
  return cdf;
}

/** `count` symbols of an ANS body (uint32 LE words, popped from the end as constriction's stack coder does). */
function decodeAnsBody(body, cdf, q, count) {
  const words = wordsLE(body);
  let pos = words.length;
  if (words[pos - 1] === 0) throw new CorruptFileError("damaged ANS stream (ends in a zero word)");
  let hi = 0;
  let lo = words[--pos];
  if (pos > 0) {
    hi = lo;
    lo = words[--pos];
  }
  const k = q.length;
  const out = new Int32Array(count);
  for (let n = 0; n < count; n++) {
    const quantile = lo % PRECISION;
    let a = 0;
    let b = k; // the last cdf entry among cdf[0..k) that is ≤ quantile
    while (b - a > 1) {
      const mid = (a + b) >>> 1;
      if (cdf[mid] <= quantile) a = mid;
      else b = mid;
    }
    const left = cdf[a];
    const probability = cdf[a + 1] - left;
    if (probability <= 0) throw new CorruptFileError("damaged ANS stream (empty symbol)");
    // state = (state >> 24) · probability + (quantile − left), in exact pieces below 2^53
    const shifted = hi * 256 + Math.floor(lo / PRECISION);
    const top = Math.floor(shifted / 65536);
    const high = top * probability;
    const low = (shifted - top * 65536) * probability + (quantile - left);
    const highTop = Math.floor(high / 65536);
    const sum = (high - highTop * 65536) * 65536 + low;
    const carry = Math.floor(sum / WORD);
    hi = highTop + carry;
    lo = sum - carry * WORD;
    if (hi === 0 && pos > 0) {
      hi = lo;
      lo = words[--pos];
    }
    out[n] = a;
  }
  if (hi !== 0 || lo !== 0) throw new CorruptFileError("damaged ANS stream (does not decode to the stored count)");
  for (let n = 0; n < count; n++) {
    if (q[out[n]] === 0) throw new CorruptFileError("damaged ANS stream (does not decode to the stored count)");
  }
  return out;
}

async function decodeAns(data, numSymbols, count) {
  if (data.length < 1) throw new CorruptFileError("truncated ANS stream");
  const mode = data[0];
  const rest = data.subarray(1);
  if (mode === 0) {
    if (count !== 0 || rest.length) throw new CorruptFileError("damaged ANS stream (empty stream with data)");
    return new Int32Array(0);
  }
  if (mode === 1) {
    const { values: [symbol], used } = unpackVarints(rest, 0, 1, "ANS constant symbol");
    if (symbol >= numSymbols || used !== rest.length) {
      throw new CorruptFileError("damaged ANS stream (constant symbol out of range)");
    }
    return new Int32Array(count).fill(symbol);
  }
  if (mode !== 2 || rest.length < 1 || !STEPS.includes(rest[0])) {
    throw new CorruptFileError("damaged ANS stream (unknown mode)");
  }
  const steps = rest[0];
  const { values: [tableLength], used } = unpackVarints(rest, 1, 1, "ANS model size");
  const start = 1 + used;
  if (tableLength > rest.length - start) throw new CorruptFileError("truncated ANS model");
  const q = await inflateRaw(rest.subarray(start, start + tableLength), numSymbols, "ANS model");
  if (q.length !== numSymbols) throw new CorruptFileError("damaged ANS model (wrong length)");
  const body = rest.subarray(start + tableLength);
  let nonzero = 0;
  let largest = 0;
  for (const v of q) {
    nonzero += v > 0;
    largest = Math.max(largest, v);
  }
  if (nonzero < 2 || largest > 1 + 31 * steps || body.length % 4 || !body.length) {
    throw new CorruptFileError("damaged ANS stream (invalid model or body)");
  }
  return decodeAnsBody(body, quantizedCdf(q, steps), q, count);
}

/** Inverse of the writer's encode_indices(..., "ans"): Int32Array [count] with values in [0, numSymbols). */
export async function decodeIndices(data, numSymbols, count) {
  if (!(numSymbols >= 1 && numSymbols <= MAX_SYMBOLS)) throw new CorruptFileError(`invalid alphabet ${numSymbols}`);
  if (!(Number.isInteger(count) && count >= 0 && count <= MAX_COUNT)) {
    throw new CorruptFileError(`invalid index count ${count}`);
  }
  if (!data.length || data[0] !== TAG_ANS) throw new CorruptFileError("not an 'ans' index stream (wrong tag)");
  const { values: [stored], used } = unpackVarints(data, 1, 1, "ANS count");
  if (stored !== count) throw new CorruptFileError(`index stream holds ${stored} symbols, expected ${count}`);
  return decodeAns(data.subarray(1 + used), numSymbols, count);
}

const SPLIT = 16; // hybrid uints: values below this are their own token
const TOKENS = 256;

/** Inverse of encode_uints: `count` values of at most `maxBits` bits — a Float64Array when maxBits ≤ 52, else a
 * BigUint64Array. Tokens carry the bit length and the two bits below the leading one; the rest are raw bits. */
export async function decodeUints(data, count, maxBits = 64) {
  const [tokenStream, raw] = splitStreams(data, "uint stream");
  const tokens = await decodeIndices(tokenStream, TOKENS, count);
  const nraw = new Int32Array(count);
  let total = 0;
  for (let i = 0; i < count; i++) {
    if (tokens[i] >= SPLIT) {
      const length = ((tokens[i] - SPLIT) >> 2) + 5;
      if (length > maxBits) throw new CorruptFileError(`damaged uint stream (a value longer than ${maxBits} bits)`);
      nraw[i] = length - 3;
      total += nraw[i];
    }
  }
  if (raw.length !== Math.ceil(total / 8)) throw new CorruptFileError("damaged uint stream (raw bits have the wrong length)");
  const big = maxBits > 52;
  const out = big ? new BigUint64Array(count) : new Float64Array(count);
  let bit = 0;
  for (let i = 0; i < count; i++) {
    const t = tokens[i];
    if (t < SPLIT) {
      out[i] = big ? BigInt(t) : t;
      continue;
    }
    let value = big ? BigInt(4 + ((t - SPLIT) & 3)) : 4 + ((t - SPLIT) & 3);
    for (let j = 0; j < nraw[i]; j++, bit++) {
      const b = (raw[bit >> 3] >> (7 - (bit & 7))) & 1;
      value = big ? (value << 1n) | BigInt(b) : value * 2 + b;
    }
    out[i] = value;
  }
  return out;
}

/** Inverse of encode_sorted_codes: `count` cumulative sums of the gaps, each below 2^bits, non-decreasing
 * (strictly increasing with `strict`); a Float64Array for bits ≤ 52, else a BigUint64Array. */
export async function decodeSortedCodes(data, count, bits, strict, damaged) {
  const gaps = await decodeUints(data, count, bits);
  const big = bits > 52;
  const limit = big ? 1n << BigInt(bits) : 2 ** bits;
  const codes = big ? new BigUint64Array(count) : new Float64Array(count);
  let sum = big ? 0n : 0;
  for (let i = 0; i < count; i++) {
    const gap = gaps[i];
    if (strict && i > 0 && (big ? gap === 0n : gap === 0)) throw new CorruptFileError(`damaged ${damaged}`);
    sum += gap;
    if (sum >= limit) throw new CorruptFileError(`damaged ${damaged}`);
    codes[i] = sum;
  }
  return codes;
}
