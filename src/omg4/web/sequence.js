// Playback of a model or of a long capture's sequence of segments (omg4/codec/sequence.py SequenceModel): each
// segment its own .omg4 file, fetched and decoded when first shown (the next one ahead of playback), at most three
// held; at a time inside two segments both are drawn and crossfaded (omg4/data/segments.py blend_weights). A
// predicted segment is decoded after the segment it is predicted from (omg4/codec/sequence.py SegmentDecoder).

import { CorruptFileError } from "./decoder/streams.js";
import { decodePayload, referenceSections } from "./decoder/payload.js";
import { buildModel } from "./model.js";
import { Renderer } from "./render/renderer.js";

const KEEP = 3;

/** (segment, weight) pairs for a frame at `time`, given each segment's time range [t0, t1) in order: in the
 * shared range of segments a and a + 1, [t0(a+1), t1(a)), both, the later one's weight rising linearly from 0 to
 * 1; elsewhere the one segment holding `time`; before the first range or after the last, the nearest segment. */
export function blendWeights(time, ranges) {
  for (let a = 0; a + 1 < ranges.length; a++) {
    const start = ranges[a + 1][0];
    const stop = ranges[a][1];
    if (start <= time && time < stop) {
      const w = (time - start) / (stop - start);
      return w > 0 ? [[a, 1 - w], [a + 1, w]] : [[a, 1]];
    }
  }
  const holding = ranges.map(([t0, t1], a) => (t0 <= time && time < t1 ? a : -1)).filter((a) => a >= 0);
  if (holding.length) return [[holding.at(-1), 1]];
  if (time < ranges[0][0]) return [[0, 1]];
  return [[Math.max(...ranges.map(([t0], a) => (t0 <= time ? a : 0))), 1]];
}

/** Check each segment's `reference` (null: a key segment; else the segment just before it) and that no more than
 * `keyInterval` - 1 predicted segments follow one another (omg4/codec/sequence.py _check_index). */
const MAX_KEY_INTERVAL = 1024;  // omg4/codec/sequence.py MAX_KEY_INTERVAL

export function checkChain(segments, keyInterval) {
  if (!(Number.isInteger(keyInterval) && keyInterval >= 1 && keyInterval <= MAX_KEY_INTERVAL)) {
    throw new CorruptFileError(`the key interval must be an integer from 1 to ${MAX_KEY_INTERVAL}`);
  }
  let inARow = 0;
  segments.forEach((s, k) => {
    if (s.reference !== null && !(k >= 1 && s.reference === k - 1)) {
      throw new CorruptFileError(`segment ${k} is predicted from segment ${s.reference}; a segment may only be predicted from the one just before it`);
    }
    inARow = s.reference === null ? 0 : inARow + 1;
    if (inARow >= keyInterval) throw new CorruptFileError(`segment ${k} makes ${inARow} predicted segments in a row, more than the key interval ${keyInterval} allows`);
  });
}

/** The decoded payloads of a sequence's segments (omg4/codec/sequence.py SegmentDecoder): a predicted segment is
 * decoded after the segment it is predicted from; the KEEP most recently asked for are held, so playing forward decodes each
 * segment once and a seek decodes at most the key interval. `segments`: [{url, reference}]; `firstPayload`: segment
 * 0's, when already decoded. */
export class SegmentPayloads {
  constructor(segments, fetchBytes, firstPayload = null) {
    this.segments = segments;
    this.fetchBytes = fetchBytes;
    this.held = new Map(firstPayload ? [[0, Promise.resolve(firstPayload)]] : []);
  }

  /** Segment `k`'s decoded payload (a promise). */
  payload(k) {
    if (this.held.has(k)) {  // the most recently asked for last
      const held = this.held.get(k);
      this.held.delete(k);
      this.held.set(k, held);
    } else {
      const reference = this.segments[k].reference;
      const sections = reference === null ? Promise.resolve(null) : this.payload(reference).then(referenceSections);
      this.held.set(k, Promise.all([sections, this.fetchBytes(this.segments[k].url)])
        .then(([taken, bytes]) => decodePayload(bytes, taken)));
      for (const old of [...this.held.keys()]) {
        if (this.held.size <= KEEP) break;
        if (old !== k) this.held.delete(old);
      }
    }
    return this.held.get(k);
  }
}

export class Playback {
  /** `segments`: [{url, range: [t0, t1), bytes, reference}] in order (checkChain); `first`: the first segment's
   * model (buildModel) and `firstPayload` its decoded payload. */
  constructor(gl, compositor, segments, first, fetchBytes, firstPayload) {
    this.gl = gl;
    this.compositor = compositor;
    this.segments = segments;
    this.ranges = segments.map((s) => s.range);
    this.loaded = new Map([[0, this._renderer(first)]]);
    this.payloads = new SegmentPayloads(segments, fetchBytes, firstPayload);
    this.loading = new Map();
    this.error = null;
    this.shown = [0];
  }

  _renderer(model) {
    return { model, renderer: new Renderer(this.gl, model) };
  }

  _load(k) {
    if (this.loaded.has(k) || this.loading.has(k) || k >= this.segments.length) return;
    const promise = this.payloads.payload(k)
      .then((payload) => {
        this.loaded.set(k, this._renderer(buildModel(payload)));
        this.loading.delete(k);
        this._evict();
      })
      .catch((err) => { this.error = err; });
    this.loading.set(k, promise);
  }

  _evict() {
    for (const k of [...this.loaded.keys()]) {
      if (this.loaded.size <= KEEP) break;
      if (!this.shown.includes(k) && k !== Math.max(...this.shown) + 1) {
        this.loaded.get(k).renderer.dispose();
        this.loaded.delete(k);
      }
    }
  }

  /** Whether every segment shown at `time` is decoded (loading the missing ones, and the next one, if not). */
  ready(time) {
    if (this.error) throw this.error;
    const parts = blendWeights(time, this.ranges);
    parts.forEach(([k]) => this._load(k));
    this._load(parts.at(-1)[0] + 1);  // ahead of playback
    return parts.every(([k]) => this.loaded.has(k));
  }

  /** Draw the frame at `time` from `camera` on the canvas; the number of Gaussians drawn. */
  frame(time, camera, background) {
    const parts = blendWeights(time, this.ranges);
    this.shown = parts.map(([k]) => k);
    const images = parts.map(([k, w]) => [this.loaded.get(k).renderer.draw(time, camera, background), w]);
    this.compositor.present(images, camera.width, camera.height);
    return parts.reduce((sum, [k]) => sum + this.loaded.get(k).renderer.visible, 0);
  }

  /** Gaussians of the segments shown last. */
  get gaussians() {
    return this.shown.reduce((sum, k) => sum + (this.loaded.get(k)?.model.numGaussians ?? 0), 0);
  }
}
