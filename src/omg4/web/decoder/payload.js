// The .omg4 container and payload (docs/file-format.md §1, §2, §5; omg4/codec/container.py, payload.py): the
// checks a reader makes before decoding anything — magic, version, checksums, bounded header inflation, the
// section table, the header's limits and its declared values against the file's size — then every section.

import { CODERS, ENCODINGS } from "./codecs.js";
import { decodeIndices, MAX_SYMBOLS } from "./entropy.js";
import {
  decodeFirstUseIndices, decodeFloats, decodeMorton, decodePositions, decodeQuaternions, decodeSortedCodebook, decodeTimes,
  decodeWeightChange, decodeWeights, quaternionBits,
} from "./sections.js";
import { CorruptFileError, crc32, inflateRaw } from "./streams.js";

const MAGIC = [0x89, 0x4f, 0x4d, 0x47, 0x34, 0x0d, 0x0a, 0x1a];
const READABLE_VERSIONS = [1, 2, 3, 4, 5, 6, 7];
export const SEQUENCE_VERSION = 6;
const MAX_JSON_BYTES = 16 * 1024 * 1024;
const MAX_SECTION_NAME = 200;
const KIND = "omg4-compressed-model";
// A decoder for each encoding of the table (omg4/codec/encodings.py ENCODINGS, whose rules — the names, the section
// kinds, the codec capability needed — come with codecs.js). "paper" index streams have none here: an export
// rewrites them as "ans" (omg4/codec/browser.py).
const DECODERS = {
  reference: (s) => referenced(s.name, s.data, s.shape, s.reference),
  "delta-weights": (s) => decodeWeightChange(s.data, referenceValues(s.name, s.shape, s.reference), s.shape[0], s.shape[1],
    s.encoding),
  ans: (s) => decodeIndices(s.data, s.numSymbols, s.count),
  ranks: (s) => decodeIndices(s.data, s.numSymbols, s.count),
  "first-use": (s) => decodeFirstUseIndices(s.data, s.numSymbols, s.count),
  quaternions: (s) => decodeQuaternions(s.data, s.count, quaternionBits(s.encoding)),
  sorted: (s) => decodeSortedCodebook(s.data, s.shape[0], s.shape[1]),
  weights: (s) => decodeWeights(s.data, s.shape[0], s.shape[1], s.encoding),
  morton: (s) => decodeMorton(s.data, s.count),
  "grid-positions": (s) => decodePositions(s.data, s.count, s.encoding === "grid-morton-exact"),
  "grid-times": (s) => decodeTimes(s.data, s.count),
  f16: (s) => decodeFloats(s.data, s.encoding, s.count),
};
const MATCHES = Object.fromEntries(Object.entries(ENCODINGS).map(([family, e]) => [family, new RegExp(`^(?:${e.pattern})$`)]));

/** The kind of section `name` (omg4/codec/encodings.py section_kind). */
function sectionKind(name, shape, numSymbols) {
  if (numSymbols) return "index";
  const head = name.split(".")[0];
  if (head === "mlp") return shape !== null && shape.length === 2 ? "matrix" : "mlp";
  return { svq: "codebook", quat: "quat" }[head] ?? head;
}

/** The values of section `s` ({data, encoding, count, shape, numSymbols, name, reference}) in a file of `coder`'s
 * codec, by its encoding's entry of the table (omg4/codec/encodings.py decode_section). */
async function decodeSection(s, coder) {
  const kind = sectionKind(s.name, s.shape, s.numSymbols);
  const name = s.encoding;
  for (const [family, rule] of Object.entries(ENCODINGS)) {
    if (!rule.sections.includes(kind) || !MATCHES[family].test(name)) continue;
    const allowed = rule.needs === null ? true : rule.needs === "index_encodings" ? coder.index_encodings.includes(name)
      : Boolean(coder[rule.needs]);
    if (!allowed) continue;
    if (!Object.hasOwn(DECODERS, family)) {
      throw new CorruptFileError(`the '${name}' sections are not decoded in the browser (re-export with omg4 export --format web)`);
    }
    return await DECODERS[family](s);
  }
  if (kind === "index") throw new CorruptFileError(`encoding '${name}' is not an index encoding of the codec '${coder.name}'`);
  if (kind === "quat") throw new CorruptFileError(`encoding '${name}' is not a quaternion encoding`);
  throw new CorruptFileError(`unknown encoding '${name}'`);
}
const MAX_GAUSSIANS = 2 ** 27;
const MAX_SUB_LEN = 64;
const MAX_MLP_ELEMENTS = 2 ** 24;
const MAX_MLP_DIMS = 4;
const MAX_MLP_WEIGHTS = 64;
const MAX_ATTRIBUTES = 32;
const MAX_SLOTS = 64;
const MIN_BYTES_PER_GAUSSIAN = 4;
const GAUSSIANS_ALWAYS_ALLOWED = 4096;
const MAX_VALUES_PER_BYTE = 64;
const VALUES_SLACK = 2 ** 20;
const NAME = /^[A-Za-z0-9_]{1,64}$/;
const MLP_NAME = /^[A-Za-z0-9_.]{1,128}$/;

const isInt = (v, lo, hi) => Number.isInteger(v) && v >= lo && v <= hi;
const isObject = (v) => v !== null && typeof v === "object" && !Array.isArray(v);

/** Verify a container (bytes: Uint8Array): {version, header, sections: Map name → Uint8Array}. */
export async function readContainer(bytes) {
  if (bytes.length < 20) {
    const start = bytes.subarray(0, 8);
    if (!start.every((b, i) => b === MAGIC[i])) throw new CorruptFileError("not an .omg4 file (wrong magic bytes)");
    throw new CorruptFileError(`truncated (${bytes.length} bytes, shorter than the fixed header)`);
  }
  if (!MAGIC.every((b, i) => bytes[i] === b)) throw new CorruptFileError("not an .omg4 file (wrong magic bytes)");
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint16(8, true);
  const flags = view.getUint16(10, true);
  const jsonLength = view.getUint32(12, true);
  const jsonCrc = view.getUint32(16, true);
  if (!READABLE_VERSIONS.includes(version)) {
    throw new CorruptFileError(`.omg4 format version ${version} is not one this player reads (${READABLE_VERSIONS.join(", ")})`);
  }
  if (flags !== 0) throw new CorruptFileError(`unknown container flags 0x${flags.toString(16).padStart(4, "0")}`);
  if (jsonLength > MAX_JSON_BYTES || jsonLength > bytes.length - 20) {
    throw new CorruptFileError(`header length ${jsonLength} exceeds the file size or limit (truncated or damaged)`);
  }
  let blob = bytes.subarray(20, 20 + jsonLength);
  if (crc32(blob) !== jsonCrc) throw new CorruptFileError("header checksum mismatch (file is damaged)");
  if (version >= 2) blob = await inflateRaw(blob, Math.min(MAX_JSON_BYTES, 65536 + 32 * jsonLength), "compressed header");
  let doc;
  try {
    doc = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(blob));
  } catch (err) {
    throw new CorruptFileError(`header is not valid JSON (${err.name})`);
  }
  if (!(isObject(doc) && isObject(doc.header) && Array.isArray(doc.sections))) {
    throw new CorruptFileError("container header is not an object with 'header' and 'sections'");
  }
  const sections = new Map();
  let offset = 20 + jsonLength;
  const table = [];
  for (const entry of doc.sections) {
    const ok = Array.isArray(entry) && entry.length === 3 && typeof entry[0] === "string" && entry[0].length > 0
      && entry[0].length <= MAX_SECTION_NAME && isInt(entry[1], 0, Number.MAX_SAFE_INTEGER)
      && isInt(entry[2], 0, 0xffffffff);
    if (!ok) throw new CorruptFileError("malformed section table entry");
    if (table.some((e) => e[0] === entry[0])) throw new CorruptFileError(`duplicate section '${entry[0]}'`);
    table.push(entry);
  }
  const expected = table.reduce((sum, e) => sum + e[1], offset);
  if (expected !== bytes.length) {
    const state = expected > bytes.length ? "truncated" : "has trailing bytes";
    throw new CorruptFileError(`file ${state} (${bytes.length} bytes, the section table needs ${expected})`);
  }
  for (const [name, size, crc] of table) {
    const data = bytes.subarray(offset, offset + size);
    if (crc32(data) !== crc) throw new CorruptFileError(`checksum mismatch in section '${name}' (file is damaged)`);
    sections.set(name, data);
    offset += size;
  }
  return { version, header: doc.header, sections };
}

const MAX_CAMERAS = 1024;
const MAX_IMAGE_SIDE = 16384;

/** The capture's camera rig, meta.rig (omg4/codec/rig.py check_rig). */
function checkRig(rig) {
  const cameras = isObject(rig) ? rig.cameras : null;
  if (!(Array.isArray(cameras) && cameras.length >= 1 && cameras.length <= MAX_CAMERAS
    && isInt(rig.test, 0, cameras.length))) {
    throw new CorruptFileError(`invalid camera rig (1 to ${MAX_CAMERAS} cameras and a test count)`);
  }
  cameras.forEach((c, i) => {
    const ok = isObject(c) && typeof c.name === "string" && c.name.length <= 64
      && isInt(c.width, 1, MAX_IMAGE_SIDE) && isInt(c.height, 1, MAX_IMAGE_SIDE)
      && Array.isArray(c.K) && c.K.length === 4 && c.K.every(Number.isFinite) && c.K[0] > 0 && c.K[1] > 0
      && Array.isArray(c.pose) && c.pose.length === 12 && c.pose.every(Number.isFinite);
    if (!ok) throw new CorruptFileError(`invalid camera ${i} in the camera rig`);
    for (let a = 0; a < 3; a++) {
      for (let b = 0; b < 3; b++) {
        let dot = 0;
        for (let k = 0; k < 3; k++) dot += c.pose[4 * a + k] * c.pose[4 * b + k];
        if (Math.abs(dot - (a === b)) > 1e-3 + 1e-5 * (a === b)) {  // numpy.allclose(atol=1e-3)
          throw new CorruptFileError(`camera ${i} of the camera rig has no rotation in its pose`);
        }
      }
    }
  });
}

/** The payload header's structure and limits (payload.py: _check_header), given the file's section bytes; returns the
 * section names it implies, sorted. */
export function checkHeader(h, sectionBytes) {
  const n = h.num_gaussians;
  if (!(h.kind === KIND && Object.hasOwn(CODERS, h.codec) && isObject(h.meta) && isObject(h.attributes)
    && isObject(h.mlp) && isObject(h.encodings) && isInt(n, 1, MAX_GAUSSIANS))) {
    throw new CorruptFileError("not an OMG4 compressed model (header fields missing or invalid)");
  }
  if ("rig" in h.meta) checkRig(h.meta.rig);
  const rotations = h.quaternions ?? [];
  if (("quaternions" in h) !== CODERS[h.codec].quaternion_sections || !Array.isArray(rotations) || rotations.length > MAX_ATTRIBUTES
    || new Set(rotations.map(String)).size !== rotations.length
    || !rotations.every((a) => typeof a === "string" && NAME.test(a) && !(a in h.attributes))) {
    throw new CorruptFileError("invalid list of quaternion attributes");
  }
  const named = h.rotations ?? [];
  if (!(Array.isArray(named) && named.length <= MAX_ATTRIBUTES
    && named.every((a) => typeof a === "string" && (a in h.attributes || rotations.includes(a)))
    && rotations.every((a) => named.includes(a)))) {  // an attribute stored as quaternions is a rotation
    throw new CorruptFileError("invalid list of rotation attributes");
  }
  if ("carried" in h && !isInt(h.carried, 1, MAX_GAUSSIANS)) throw new CorruptFileError("invalid count of carried Gaussians");
  if (n > GAUSSIANS_ALWAYS_ALLOWED && n * MIN_BYTES_PER_GAUSSIAN > sectionBytes) {
    throw new CorruptFileError(`header claims ${n} Gaussians, more than the file's ${sectionBytes} data bytes can hold`);
  }
  const attributes = Object.entries(h.attributes);
  const mlp = Object.entries(h.mlp);
  if (attributes.length > MAX_ATTRIBUTES || mlp.length > MAX_MLP_WEIGHTS) {
    throw new CorruptFileError(`header lists ${attributes.length} attributes and ${mlp.length} MLP weights `
      + `(limits ${MAX_ATTRIBUTES} and ${MAX_MLP_WEIGHTS})`);
  }
  let values = 8 * n + 8 * n * rotations.length;
  for (const [attr, shapes] of attributes) {
    if (!(NAME.test(attr) && Array.isArray(shapes) && shapes.length >= 1 && shapes.length <= MAX_SLOTS
      && shapes.every((s) => Array.isArray(s) && s.length === 2 && isInt(s[0], 1, MAX_SYMBOLS) && isInt(s[1], 1, MAX_SUB_LEN)))) {
      throw new CorruptFileError(`invalid codebook shapes for attribute '${attr}'`);
    }
    for (const [k, d] of shapes) values += k * d + n + n * d;
  }
  const logs = h.log_scaled ?? [];
  if (!(Array.isArray(logs) && logs.length <= MAX_ATTRIBUTES && logs.every((a) => typeof a === "string" && a in h.attributes))) {
    throw new CorruptFileError("invalid list of log-scale attributes");
  }
  for (const [name, shape] of mlp) {
    const ok = MLP_NAME.test(name) && Array.isArray(shape) && shape.length <= MAX_MLP_DIMS
      && shape.every((s) => isInt(s, 0, MAX_MLP_ELEMENTS)) && shape.reduce((a, b) => a * b, 1) <= MAX_MLP_ELEMENTS;
    if (!ok) throw new CorruptFileError(`invalid shape for MLP weight '${name}'`);
    values += shape.reduce((a, b) => a * b, 1);
  }
  if (values > MAX_VALUES_PER_BYTE * sectionBytes + VALUES_SLACK) {
    throw new CorruptFileError(`header declares ${values} values, more than ${sectionBytes} data bytes can encode`);
  }
  const expected = ["xyz", "t"];
  for (const [attr, shapes] of attributes) {
    for (const kind of ["codebook", "index"]) shapes.forEach((_, j) => expected.push(`svq.${attr}.${kind}${j}`));
  }
  for (const [name] of mlp) expected.push(`mlp.${name}`);
  for (const attr of rotations) expected.push(`quat.${attr}`);
  if ("carried" in h) expected.push(CARRY);
  return expected.sort();
}

/** The encoding of a section a predicted segment takes from the segment before (omg4/codec/types.py REFERENCE). */
const REFERENCE = "reference";

/** The section that names a predicted segment's carried Gaussians, and its encoding (omg4/codec/carry.py). */
const CARRY = "carry";
const CARRY_ENCODING = "mask";

/** One quaternion per Gaussian (fp16 bits, [4N]) of rotation attribute `attr` of a decoded payload. */
function rotationValues(payload, attr) {
  if (payload.quaternions[attr]) return payload.quaternions[attr];
  const { codebooks, indices } = payload.attributes[attr];
  const width = codebooks.reduce((sum, cb) => sum + cb.sub, 0);
  if (width !== 4) throw new CorruptFileError(`rotation ${attr} is ${width} wide, not 4`);
  const out = new Uint16Array(4 * payload.numGaussians);
  let column = 0;
  codebooks.forEach((cb, j) => {
    for (let g = 0; g < payload.numGaussians; g++) {
      for (let c = 0; c < cb.sub; c++) out[4 * g + column + c] = cb.values[indices[j][g] * cb.sub + c];
    }
    column += cb.sub;
  });
  return out;
}

/** The decoded arrays of `payload` a segment predicted from it may take, by section name, with their shapes
 * (omg4/codec/references.py reference_sections): every MLP weight, every codebook of a non-rotation attribute, and the
 * per-Gaussian arrays it may carry (omg4/codec/carry.py gaussian_sections). */
export function referenceSections(payload) {
  const out = new Map();
  for (const [name, w] of Object.entries(payload.mlp)) out.set(`mlp.${name}`, { shape: w.shape, values: w.values });
  const n = payload.numGaussians;
  out.set("gaussians.xyz", { shape: [n, 3], values: payload.xyz });
  out.set("gaussians.t", { shape: [n], values: payload.t });
  for (const attr of payload.rotations) {
    out.set(`gaussians.rotation.${attr}`, { shape: [n, 4], values: rotationValues(payload, attr) });
  }
  for (const [attr, q] of Object.entries(payload.attributes)) {
    if (payload.rotations.includes(attr)) continue;
    q.codebooks.forEach((cb, j) => out.set(`svq.${attr}.codebook${j}`, { shape: [cb.rows, cb.sub], values: cb.values }));
    q.indices.forEach((ix, j) => out.set(`gaussians.svq.${attr}.index${j}`, { shape: [n], values: ix }));
  }
  return out;
}

/** The carried `rows` of the reference's per-Gaussian array `what`, `width` values per Gaussian. */
function carriedRows(reference, what, rows, width) {
  const taken = reference.get(`gaussians.${what}`);
  if (!taken) throw new CorruptFileError(`the reference segment has no ${what} to carry`);
  if ((taken.shape[1] ?? 1) !== width) throw new CorruptFileError(`the reference's ${what} is not ${width} wide`);
  const out = new taken.values.constructor(rows.length * width);
  rows.forEach((r, i) => out.set(taken.values.subarray(r * width, (r + 1) * width), i * width));
  return out;
}

function joined(head, tail) {
  const out = new head.constructor(head.length + tail.length);
  out.set(head);
  out.set(tail, head.length);
  return out;
}

/** A predicted segment's Gaussians (omg4/codec/payload.py _with_carried): the reference's carried ones as they decoded
 * there, then its own; rotations become one quaternion per Gaussian. */
async function withCarried(own, header, data, reference) {
  const count = reference?.get("gaussians.xyz")?.shape[0];
  if (count === undefined) {
    throw new CorruptFileError("a segment that carries Gaussians takes them from the segment before: decode it through its sequence file");
  }
  if (header.encodings[CARRY] !== CARRY_ENCODING) {
    throw new CorruptFileError(`section ${CARRY}: encoding '${header.encodings[CARRY]}' is not '${CARRY_ENCODING}'`);
  }
  let mask;
  try {
    mask = await decodeIndices(data, 2, count);
  } catch (err) {
    if (err instanceof CorruptFileError) throw new CorruptFileError(`section ${CARRY}: ${err.message}`);
    throw err;
  }
  const rows = [];
  mask.forEach((bit, r) => { if (bit) rows.push(r); });
  if (rows.length !== header.carried) {
    throw new CorruptFileError(`section ${CARRY} marks ${rows.length} carried Gaussians, the header declares ${header.carried}`);
  }
  const attributes = {};
  const quaternions = {};
  for (const attr of own.rotations) {
    const carried = carriedRows(reference, `rotation.${attr}`, rows, 4);
    quaternions[attr] = joined(carried, rotationValues(own, attr));
  }
  for (const [attr, q] of Object.entries(own.attributes)) {
    if (own.rotations.includes(attr)) continue;
    if (q.codebooks.some((_, j) => header.encodings[`svq.${attr}.codebook${j}`] !== REFERENCE)) {
      throw new CorruptFileError(`carried Gaussians index the reference's codebooks, and ${attr} has its own`);
    }
    const indices = q.indices.map((ix, j) => joined(carriedRows(reference, `svq.${attr}.index${j}`, rows, 1), ix));
    attributes[attr] = { codebooks: q.codebooks, indices };
  }
  return {
    ...own, numGaussians: rows.length + own.numGaussians, attributes, quaternions,
    xyz: joined(carriedRows(reference, "xyz", rows, 3), own.xyz), t: joined(carriedRows(reference, "t", rows, 1), own.t),
  };
}

function referenced(name, data, shape, reference) {
  if (data.length) throw new CorruptFileError(`a section taken from the reference holds ${data.length} bytes of its own`);
  return referenceValues(name, shape, reference).slice();
}

/** The reference's decoded values behind section `name` of a predicted segment, of the declared `shape`. */
function referenceValues(name, shape, reference) {
  if (reference === null) {
    throw new CorruptFileError("a predicted segment takes its sections from the segment before: decode it through its sequence file");
  }
  const taken = reference.get(name);
  if (!taken) throw new CorruptFileError("the reference segment has no such section");
  if (shape === null || JSON.stringify(taken.shape) !== JSON.stringify(shape)) {
    throw new CorruptFileError(`the reference's section has shape [${taken.shape}], the header declares [${shape}]`);
  }
  return taken.values;
}

/** Decode a single-model .omg4 file (bytes: Uint8Array) into fp16 bit patterns and int32 indices:
 * {numGaussians, xyz [3N], t [N], attributes: {name: {codebooks: [{rows, sub, values}], indices: [Int32Array]}},
 *  quaternions: {name: Uint16Array [4N]}, mlp: {name: {shape, values}}, meta, rotations, logScaled, codec}.
 * `reference`: a predicted segment's, referenceSections() of the segment before's decoded payload. */
export async function decodePayload(bytes, reference = null) {
  const { version, header, sections } = await readContainer(bytes);
  if (version === SEQUENCE_VERSION || header.layout !== undefined) {
    throw new CorruptFileError("a sequence of segments, not one model (open it as a sequence)");
  }
  const sectionBytes = [...sections.values()].reduce((sum, d) => sum + d.length, 0);
  const expected = checkHeader(header, sectionBytes);
  const names = [...sections.keys()].sort();
  const encodings = header.encodings;
  if (JSON.stringify(expected) !== JSON.stringify(names) || JSON.stringify(expected) !== JSON.stringify(Object.keys(encodings).sort())
    || !Object.values(encodings).every((e) => typeof e === "string")) {
    throw new CorruptFileError("section list does not match the header");
  }
  const n = header.num_gaussians;
  const coder = CODERS[header.codec];

  async function decode(name, count, shape = null, numSymbols = 0) {
    try {
      return await decodeSection({ data: sections.get(name), encoding: encodings[name], count, shape, numSymbols, name,
        reference }, coder);
    } catch (err) {
      if (err instanceof CorruptFileError) throw new CorruptFileError(`section ${name}: ${err.message}`);
      throw err;
    }
  }

  const perGaussian = ["morton", "grid-morton", "grid-morton-exact"].includes(encodings.xyz);
  const xyz = await decode("xyz", perGaussian ? n : 3 * n);
  const t = await decode("t", n);
  const attributes = {};
  for (const [attr, shapes] of Object.entries(header.attributes)) {
    const codebooks = [];
    for (const [j, [k, s]] of shapes.entries()) {
      codebooks.push({ rows: k, sub: s, values: await decode(`svq.${attr}.codebook${j}`, k * s, [k, s]) });
    }
    const indices = [];
    for (const [j, [k]] of shapes.entries()) indices.push(await decode(`svq.${attr}.index${j}`, n, null, k));
    attributes[attr] = { codebooks, indices };
  }
  const quaternions = {};
  for (const attr of header.quaternions ?? []) quaternions[attr] = await decode(`quat.${attr}`, n);
  const mlp = {};
  for (const [name, shape] of Object.entries(header.mlp)) {
    mlp[name] = { shape, values: await decode(`mlp.${name}`, shape.reduce((a, b) => a * b, 1), shape) };
  }
  const own = {
    numGaussians: n, codec: header.codec, xyz, t, attributes, quaternions, mlp, meta: header.meta,
    rotations: header.rotations ?? [], logScaled: header.log_scaled ?? [],
  };
  return "carried" in header ? await withCarried(own, header, sections.get(CARRY), reference) : own;
}
