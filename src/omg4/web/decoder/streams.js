// Byte-level streams of the .omg4 format (docs/file-format.md §4): LEB128 varints, joined streams,
// bounded raw-DEFLATE inflation, CRC-32 and fp16 rounding. Every failure is a CorruptFileError.

export class CorruptFileError extends Error {
  constructor(message) {
    super(message);
    this.name = "CorruptFileError";
  }
}

/** The first `count` LEB128 integers of `bytes` from `offset`: {values, used}. At most 10 bytes each (a
 * longer one is "overlong"); values past 2^53 lose precision and then fail every range check. */
export function unpackVarints(bytes, offset, count, what = "varints") {
  const values = new Array(count);
  let pos = offset;
  for (let i = 0; i < count; i++) {
    let value = 0;
    let scale = 1;
    for (let k = 0; ; k++) {
      if (pos >= bytes.length) throw new CorruptFileError(`truncated ${what}`);
      if (k >= 10) throw new CorruptFileError(`overlong varint in ${what}`);
      const b = bytes[pos++];
      value += (b & 0x7f) * scale;
      scale *= 128;
      if (b < 0x80) break;
    }
    values[i] = value;
  }
  return { values, used: pos - offset };
}

/** Inverse of the writer's join_streams: [head, tail] of `bytes` (a varint length, then the head). */
export function splitStreams(bytes, what) {
  const { values: [size], used } = unpackVarints(bytes, 0, 1, `${what} size`);
  if (size > bytes.length - used) throw new CorruptFileError(`truncated ${what}`);
  return [bytes.subarray(used, used + size), bytes.subarray(used + size)];
}

/** Raw-DEFLATE `bytes` into at most `limit` bytes (the browser's DecompressionStream); a stream that is
 * damaged, does not end, has trailing bytes or inflates past `limit` is a CorruptFileError. */
export async function inflateRaw(bytes, limit, what) {
  const chunks = [];
  let total = 0;
  try {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate-raw"));
    const reader = stream.getReader();
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      total += value.length;
      if (total > limit) {
        await reader.cancel();
        throw new CorruptFileError(`damaged ${what} (over ${limit} bytes inflated)`);
      }
      chunks.push(value);
    }
  } catch (err) {
    if (err instanceof CorruptFileError) throw err;
    throw new CorruptFileError(`damaged ${what}`);
  }
  const out = new Uint8Array(total);
  let pos = 0;
  for (const c of chunks) {
    out.set(c, pos);
    pos += c.length;
  }
  return out;
}

const CRC_TABLE = (() => {
  const table = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    table[n] = c >>> 0;
  }
  return table;
})();

/** zlib's CRC-32 (unsigned), as the container stores it for the JSON and each section. */
export function crc32(bytes) {
  let c = 0xffffffff;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

function roundHalfEven(v) {
  const f = Math.floor(v);
  const d = v - f;
  if (d > 0.5) return f + 1;
  if (d < 0.5) return f;
  return f % 2 === 0 ? f : f + 1;
}

/** The fp16 bit pattern nearest to the double `x` (ties to even), as numpy's float64 → float16 cast. */
export function toHalfBits(x) {
  if (Number.isNaN(x)) return 0x7e00;
  const sign = x < 0 || Object.is(x, -0) ? 0x8000 : 0;
  const a = Math.abs(x);
  if (a >= 65520) return sign | 0x7c00; // halfway to 2^16 and beyond round to infinity
  if (a < 2 ** -14) return sign | roundHalfEven(a * 2 ** 24); // subnormals (1024 is the smallest normal)
  let e = Math.floor(Math.log2(a));
  if (2 ** e > a) e -= 1;
  else if (2 ** (e + 1) <= a) e += 1;
  let mantissa = roundHalfEven((a / 2 ** e - 1) * 1024);
  let exponent = e + 15;
  if (mantissa === 1024) {
    mantissa = 0;
    exponent += 1;
  }
  return exponent >= 31 ? sign | 0x7c00 : sign | (exponent << 10) | mantissa;
}

/** The double value of fp16 bits `h`. */
export function halfToFloat(h) {
  const exponent = (h >> 10) & 0x1f;
  const mantissa = h & 0x3ff;
  const sign = h & 0x8000 ? -1 : 1;
  if (exponent === 0) return sign * mantissa * 2 ** -24;
  if (exponent === 31) return mantissa ? NaN : sign * Infinity;
  return sign * (1 + mantissa / 1024) * 2 ** (exponent - 15);
}

/** Whether fp16 bits `h` are a finite value. */
export function halfIsFinite(h) {
  return (h & 0x7c00) !== 0x7c00;
}

/** fp16 → uint16 key whose unsigned order is the float order (the sign-flip trick), and its inverse. */
export function orderedKey(h) {
  return h & 0x8000 ? ~h & 0xffff : h | 0x8000;
}

export function keyToHalf(key) {
  return key & 0x8000 ? key ^ 0x8000 : ~key & 0xffff;
}

/** Little-endian uint32 words of `bytes` (a multiple of 4 long). */
export function wordsLE(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const out = new Uint32Array(bytes.length / 4);
  for (let i = 0; i < out.length; i++) out[i] = view.getUint32(4 * i, true);
  return out;
}
