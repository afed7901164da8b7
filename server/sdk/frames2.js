// @ts-check
// Wire v2 binary pose frames (proto/PROTOCOL.md "Pose frames, wire v2"; Rust: posecast-proto
// `frame2.rs`, `Frame2Decoder`): magic 0x51, varint header; keyframe chunks carry 48-bit
// smallest-three rotations and zigzag-varint translation levels (1/8192 m); delta chunks refer
// to the receiver's last ≤ 8 decoded frames of the avatar and carry Rice-coded residuals of
// predicted levels (or a joint's 47 bits in full, flagged in an escape mask). Protocol version
// 4 adds morph weights (chunk flag bit 3): a keyframe lists every channel's 10-bit level, a
// delta a change mask and the new levels of the changed channels. Protocol version 5 adds
// precision per subscription (keyframe chunk flag bit 4): grid steps per joint and for the
// translations follow the flags, and the chunk's levels (and the deltas after it) are grid
// values that integer arithmetic turns back into levels (Rust: `posecast_proto::precision`).
// Protocol version 6 adds near-axis steps (keyframe chunk flag bit 5, after the steps): each
// rotation's bit 47 says which of its joint's two grids it is on; a joint's history runs while
// its dropped component and tier stay the same, and an escaped joint goes in 48 bits.
// Protocol version 7 adds packed deltas (frame kind 3; Rust: `PackedDeltas`, `FrameClock`):
// every chunk in one bit stream padded once at the end — an avatar number as 1 bit "the
// previous + 1" or 5 bits n − 1 and n bits, a head bit for the usual depth 8 without flags
// (else 3 bits depth − 1 and 4 flag bits), kind 2's body, scales and placement as raw f32
// bits, kind 2's weights — and the server time as a zigzag difference from the base frame's,
// which must be the scene's last decoded frame (this decoder keeps each scene's last seq and
// time; a packed delta against another frame is refused).
// Protocol version 8 sends v2 frames over WebTransport as datagrams, any of which may be lost
// or come out of order (Rust: `write_referenced_header`, `encode_referenced_delta`,
// `Frame2Decoder::for_datagrams`): deltas of kind 4 name the frames they refer to — after the
// server time, d (1…8) and d distances seq − refᵢ, strictly increasing; each chunk is its
// length in bytes and a kind 2 chunk of exactly that length, whose depth k ≤ d refers to
// ref₀ … refₖ₋₁. A decoder for datagrams (`Frame2Decoder.forDatagrams()`) keeps each avatar's
// last 64 frames in the order they came, finds a named frame by its tick (the newest that came
// of it), and a keyframe of the rig an avatar has does not drop the frames before it.
// Protocol version 9's deltas of kind 5 are kind 4's, but each chunk predicts over the ticks
// from its newest named frame, `ahead = seq − ref₀`, at the pace of `apart = ref₀ − ref₁` ticks:
// still, constant velocity or constant acceleration, whichever its history says errs least
// that far ahead (`spacingOf`, `predictSpaced`).
//
// Numbers: rotations (≤ 48 bits), levels and Rice sums (< 2⁴⁴) are exact JS numbers. Varints
// are read as BigInt (up to 64 bits, as the Rust reader); the header's seq and server time must
// also fit a JS number exactly (< 2⁵³ — 4.7 million years of 60 Hz ticks, µs until the year
// 2255): a frame beyond that is refused (`bad_message`) rather than decoded with a rounded seq.
// A packed delta's time is summed in BigInt (base time + the signed difference) and refused
// likewise when the sum is negative or beyond 2⁵³. A Rice residual of 53 bits or more cannot
// give a level in range (its magnitude is ≥ 2⁵²), so it is refused as the Rust decoder refuses
// it, without BigInt.

import { PosecastError } from "./errors.js";
import { decodeQuat } from "./frames.js";

/** @typedef {import("./posecast.js").Vec3} Vec3 */
/** @typedef {import("./posecast.js").Placement} Placement */
/** @typedef {import("./posecast.js").BinaryFrame} BinaryFrame */

/** First byte of every v2 frame (v1's is 0x50). */
export const MAGIC2 = 0x51;
/** Frame kind of a packed delta (protocol version 7). */
const KIND_PACKED = 3;
/** Frame kind of a delta naming the frames it refers to (protocol version 8, datagrams). */
const KIND_REFERENCED = 4;
/** Frame kind of a delta naming the frames it refers to, predicted over the ticks between (protocol version 9). */
const KIND_SPACED = 5;
/** Most frames a delta chunk may refer to. */
export const MAX_DEPTH = 8;
/**
 * Frames a decoder for datagrams keeps per avatar (`frame2::DATAGRAM_RETENTION`): the 48
 * ticks a kind 4 delta may name and 16 more of older ticks that came late.
 */
export const DATAGRAM_RETENTION = 64;
/** Translation quantisation step, metres. */
export const TRANSLATION_STEP = 1 / 8192;
const K_WITHOUT_HISTORY = 5;
const RICE_ESCAPE = 20;
const MAX_COUNT = 1 << 16;
const FLAG_PLACEMENT = 1;
const FLAG_SCALES = 2;
const FLAG_ESCAPES = 4;
/** Chunk flag (key and delta, protocol version 4): morph weights follow the placement. */
const FLAG_WEIGHTS = 8;
/** Keyframe chunk flag (protocol version 5): grid steps follow the flags byte. */
const FLAG_STEPS = 16;
/** Keyframe chunk flag (protocol version 6, with FLAG_STEPS): near-axis steps follow. */
const FLAG_NEAR = 32;
/** The level of a zero rotation component. */
const ZERO_LEVEL = 16383;
/** Bits of a streamed morph weight level; levels run 0…WEIGHT_LEVELS (weight = level / 1023). */
const WEIGHT_BITS = 10;
export const WEIGHT_LEVELS = 1023;
const LEVEL_MAX = 2 ** 15 - 2;
const LEVEL_MASK = 2 ** 15 - 1;
const CAP = 2 ** 40;
const TWO_15 = 2 ** 15;
const TWO_32 = 2 ** 32;
const TWO_45 = 2 ** 45;
const TWO_47 = 2 ** 47;
const I32_MIN = -(2 ** 31);
const I32_MAX = 2 ** 31 - 1;
const U32_MAX = 2n ** 32n - 1n;
const U32_MAX_NUMBER = 2 ** 32 - 1;
const SAFE = BigInt(Number.MAX_SAFE_INTEGER);
/** Scratch space turning a packed delta's 32 bits into an f32. */
const F32 = new DataView(new ArrayBuffer(4));

/** An f32 from its bits (a packed delta's scales and placement). @param {number} bits */
function f32FromBits(bits) {
  F32.setUint32(0, bits);
  return F32.getFloat32(0);
}

/**
 * One avatar's pose as levels: what v2 codes losslessly (`frame2::QuantPose`).
 * @typedef {{rotations: number[], translations: [number, number, number][], scales: Vec3[], placement: Placement, weights: number[], steps: Steps | null}} QuantPose
 */

/**
 * Grid steps of a subscription's precision (`precision::Steps`): levels per grid step of each
 * joint's rotation components, and of the translations; from protocol version 6 each joint's
 * step for a rotation near an axis (`near`, empty when the grid has none).
 * @typedef {{rotations: number[], translation: number, near: number[]}} Steps
 */

/**
 * Joint `j`'s rotation bits on the finest grid.
 * @param {QuantPose} levels
 * @param {number} j
 */
function fineRotation(levels, j) {
  const tiered = levels.rotations[j];
  const near = tiered >= TWO_47;
  const bits = near ? tiered - TWO_47 : tiered;
  const m = levels.steps ? (near ? levels.steps.near[j] : levels.steps.rotations[j]) : 1;
  if (m === 1) return bits;
  const zm = Math.floor((ZERO_LEVEL + m - 1) / m);
  let out = Math.floor(bits / TWO_45);
  for (let c = 0; c < 3; c++) {
    const fine = Math.min(Math.max(ZERO_LEVEL + (level(bits, c) - zm) * m, 0), 2 * ZERO_LEVEL);
    out = out * TWO_15 + fine;
  }
  return out;
}

/**
 * A translation level on the finest grid (clamped to i32, as the Rust decoder does).
 * @param {QuantPose} levels
 * @param {number} l
 */
function fineTranslation(levels, l) {
  const m = levels.steps ? levels.steps.translation : 1;
  return m === 1 ? l : Math.min(Math.max(l * m, I32_MIN), I32_MAX);
}

/** @param {Steps | null} a @param {Steps | null} b */
function sameSteps(a, b) {
  if (a === b) return true;
  if (!a || !b) return false;
  const same = (/** @type {number[]} */ x, /** @type {number[]} */ y) => x.length === y.length && x.every((m, j) => m === y[j]);
  return a.translation === b.translation && same(a.rotations, b.rotations) && same(a.near, b.near);
}

/** @param {string} message */
function bad(message) {
  return new PosecastError("bad_message", `v2 frame: ${message}`);
}

/** @param {number} r an integer @returns {number} */
function zigzag(r) {
  return r >= 0 ? 2 * r : -2 * r - 1;
}

/** @param {number} u a non-negative integer @returns {number} */
function unzigzag(u) {
  return u % 2 === 0 ? u / 2 : -(u + 1) / 2;
}

/** The dropped component's index (bits 45–46) and grid tier (bit 47). @param {number} bits */
function tag(bits) {
  return Math.floor(bits / TWO_45) % 8;
}

/** The dropped component's index (bits 45–46). @param {number} bits */
function index(bits) {
  return Math.floor(bits / TWO_45) % 4;
}

/** The step of joint `j`'s rotation `bits` (its tier, bit 47, names the grid). @param {Steps} steps @param {number} j @param {number} bits */
function rotationStep(steps, j, bits) {
  return bits >= TWO_47 ? steps.near[j] : steps.rotations[j];
}

/** The level a grid value `c` of step `m` stands for (`precision::fine_rotation_level`). @param {number} c @param {number} m */
function fineLevel(c, m) {
  const zm = Math.floor((ZERO_LEVEL + m - 1) / m);
  return Math.min(Math.max(ZERO_LEVEL + (c - zm) * m, 0), 2 * ZERO_LEVEL);
}

/** A level `l` on the grid of step `m` (`precision::coarse_rotation_level`). @param {number} l @param {number} m */
function coarseLevel(l, m) {
  const zm = Math.floor((ZERO_LEVEL + m - 1) / m);
  const d = l - ZERO_LEVEL;
  const q = Math.floor((Math.abs(d) + Math.floor(m / 2)) / m);
  return Math.min(Math.max(Math.sign(d) * q + zm, 0), 2 * zm);
}

/** The stored level `c` (0: bits 30–44, 1: 15–29, 2: 0–14). @param {number} bits @param {number} c */
function level(bits, c) {
  return Math.floor(bits / TWO_15 ** (2 - c)) % TWO_15;
}

/** ⌊log₂ x⌋ of an integer x ≥ 1 (exact; `Math.log2` may round near powers of two). @param {number} x */
function ilog2(x) {
  let k = 0;
  while (2 ** (k + 1) <= x) k++;
  return k;
}

/** The most ticks a spacing counts (`frame2.rs`'s `MAX_SPACING`). */
const MAX_SPACING = 255;

/**
 * @typedef {{ahead: number, apart: number}} Spacing How far apart in ticks a kind 5 delta's
 * frame and the two newest frames it names are (`frame2.rs`'s `Spacing`).
 */

/**
 * The spacing of a kind 5 delta of tick `seq` naming `refs` (newest first): `seq − refs[0]`
 * and `refs[0] − refs[1]` (the first again when it names one frame), each clamped to
 * 1 … 255.
 * @param {number} seq
 * @param {number[]} refs
 * @returns {Spacing}
 */
export function spacingOf(seq, refs) {
  /** @param {number} d */
  const clamp = (d) => Math.min(MAX_SPACING, Math.max(1, d));
  const ahead = clamp(seq - refs[0]);
  return { ahead, apart: refs.length >= 2 ? clamp(refs[0] - refs[1]) : ahead };
}

/**
 * The prediction and Rice parameter of a component of a kind 5 chunk over the ticks to its
 * frame (`Spacing::predict`): of holding still, constant velocity and constant acceleration,
 * the model of least expected error (its history residuals' mean zigzag times its growth over
 * `ahead / apart` steps, in doubles in the Rust order), its motion carried over those steps.
 * Exact in doubles: every numerator is an integer below 2⁵¹ (levels are 15-bit or i32), so
 * `Math.floor` of the quotient is the integer floor.
 * @param {number[]} h
 * @param {boolean} rotation
 * @param {Spacing} s
 * @returns {[number, number]}
 */
function predictSpaced(h, rotation, s) {
  const n = h.length;
  if (n < 2) return [h[0], K_WITHOUT_HISTORY];
  const { ahead: a, apart: b } = s;
  /** @param {number} i */
  const d = (i) => h[i] - h[i + 1];
  let still = 0;
  for (let i = 0; i < n - 1; i++) still += Math.min(zigzag(d(i)), CAP);
  let velocity = 0;
  for (let i = 0; i + 2 < n; i++) velocity += Math.min(zigzag(d(i) - d(i + 1)), CAP);
  let acceleration = 0;
  for (let i = 0; i + 3 < n; i++) acceleration += Math.min(zigzag(d(i) - 2 * d(i + 1) + d(i + 2)), CAP);
  let model = 0;
  let error = (still / (n - 1)) * (a / b);
  if (n >= 3) {
    const e = (velocity / (n - 2)) * ((a * (a + b)) / (2 * b * b));
    if (e < error) [model, error] = [1, e];
  }
  if (n >= 4) {
    const e = (acceleration / (n - 3)) * ((a * (a + b) * (a + 2 * b)) / (6 * b * b * b));
    if (e < error) [model, error] = [2, e];
  }
  const d0 = d(0);
  let pred = h[0];
  if (model === 1) pred += Math.floor((2 * d0 * a + b) / (2 * b));
  if (model === 2) pred += Math.floor((2 * d0 * a * b + (d0 - d(1)) * a * (a + b) + b * b) / (2 * b * b));
  if (rotation) pred = Math.min(LEVEL_MAX, Math.max(0, pred));
  return [pred, Math.min(ilog2(Math.floor(error) + 1), 32)];
}

/**
 * The prediction and Rice parameter of a component from its history `h` (newest first, at
 * least one value) — as `frame2.rs`'s `predict`; `spacing` is a kind 5 delta's (`null`:
 * a frame at a time, kinds 2 to 4).
 * @param {number[]} h
 * @param {boolean} rotation
 * @param {Spacing | null} [spacing]
 * @returns {[number, number]}
 */
export function predict(h, rotation, spacing = null) {
  if (spacing) return predictSpaced(h, rotation, spacing);
  const n = h.length;
  if (n < 2) return [h[0], K_WITHOUT_HISTORY];
  let still = 0;
  for (let i = 0; i < n - 1; i++) still += Math.min(zigzag(h[i] - h[i + 1]), CAP);
  let velocity = 0;
  for (let i = 0; i + 2 < n; i++) velocity += Math.min(zigzag(h[i] - 2 * h[i + 1] + h[i + 2]), CAP);
  let pred;
  let mean;
  if (n >= 3 && velocity * (n - 1) < still * (n - 2)) {
    pred = 2 * h[0] - h[1];
    mean = Math.floor(velocity / (n - 2));
  } else {
    pred = h[0];
    mean = Math.floor(still / (n - 1));
  }
  if (rotation) pred = Math.min(LEVEL_MAX, Math.max(0, pred));
  return [pred, ilog2(mean + 1)];
}

/** A bounds-checked little-endian reader: running past the end is a `bad_message`. */
class Reader {
  /** @param {DataView} view */
  constructor(view) {
    this.view = view;
    this.at = 0;
  }

  /** @param {number} n */
  need(n) {
    if (this.at + n > this.view.byteLength) throw bad(`truncated at byte ${this.at}`);
    const at = this.at;
    this.at += n;
    return at;
  }
  u8() {
    return this.view.getUint8(this.need(1));
  }
  /** A u64 as 16 hex digits (description hashes). */
  hex64() {
    const at = this.need(8);
    const hi = this.view.getUint32(at + 4, true).toString(16).padStart(8, "0");
    return hi + this.view.getUint32(at, true).toString(16).padStart(8, "0");
  }
  f32() {
    return this.view.getFloat32(this.need(4), true);
  }
  /** @returns {Vec3} */
  vec3() {
    return [this.f32(), this.f32(), this.f32()];
  }
  /** @returns {Placement} */
  placement() {
    return { position: this.vec3(), rotation: [this.f32(), this.f32(), this.f32(), this.f32()] };
  }
  /** A LEB128 u64 (at most 10 bytes, no bits above 64), as BigInt. */
  varint() {
    const start = this.at;
    let v = 0n;
    for (let shift = 0n; shift < 70n; shift += 7n) {
      const b = this.u8();
      const part = BigInt(b & 0x7f);
      if (shift === 63n && part > 1n) break;
      v |= part << shift;
      if ((b & 0x80) === 0) return v;
    }
    throw bad(`number out of range at byte ${start}`);
  }
  /** A varint that must fit a u32. */
  varintU32() {
    const at = this.at;
    const v = this.varint();
    if (v > U32_MAX) throw bad(`number out of range at byte ${at}`);
    return Number(v);
  }
  /** A varint that must fit a JS number exactly (seq, server time). @param {string} what */
  varintSafe(what) {
    const at = this.at;
    const v = this.varint();
    if (v > SAFE) throw bad(`${what} ${v} at byte ${at} is beyond 2^53, which this client cannot hold exactly`);
    return Number(v);
  }
  /** A count of joints, translations or scales. @param {number} avatar */
  count(avatar) {
    const v = this.varint();
    if (v > BigInt(MAX_COUNT)) throw bad(`avatar ${avatar}: ${v} items exceed the limit of ${MAX_COUNT}`);
    return Number(v);
  }
}

/** Reads bits least significant first, as `frame2.rs`'s `BitReader`. */
class BitReader {
  /** @param {Reader} r */
  constructor(r) {
    this.r = r;
    this.acc = 0; // < 2⁴⁰: at most 39 pending bits
    this.bits = 0;
  }

  /**
   * The next `n` bits (n ≤ 64) as a number: exact below 2⁵³, a rounded value (still ≥ 2⁵²)
   * above — only ever compared with a range it cannot be in.
   * @param {number} n
   * @returns {number}
   */
  get(n) {
    if (n > 32) {
      const low = this.get(32);
      return low + this.get(n - 32) * TWO_32;
    }
    while (this.bits < n) {
      this.acc += this.r.u8() * 2 ** this.bits;
      this.bits += 8;
    }
    const unit = 2 ** n;
    const v = this.acc % unit;
    this.acc = (this.acc - v) / unit;
    this.bits -= n;
    return v;
  }

  /** A Rice-coded value of parameter `k`. @param {number} k */
  rice(k) {
    let q = 0;
    while (q < RICE_ESCAPE && this.get(1) === 1) q++;
    if (q < RICE_ESCAPE) return q * 2 ** k + this.get(k);
    const n = this.get(6) + 1;
    return this.get(n);
  }
}

/**
 * @param {QuantPose} a
 * @param {QuantPose} b
 */
function sameShape(a, b) {
  return (
    a.rotations.length === b.rotations.length &&
    a.translations.length === b.translations.length &&
    a.scales.length === b.scales.length &&
    a.weights.length === b.weights.length &&
    sameSteps(a.steps, b.steps)
  );
}

/** @returns {Placement} */
function identityPlacement() {
  return { position: [0, 0, 0], rotation: [0, 0, 0, 1] };
}

/**
 * One morph weight level, checked against {@link WEIGHT_LEVELS}.
 * @param {BitReader} b
 * @param {number} num
 */
function weightLevel(b, num) {
  const at = b.r.at;
  const l = b.get(WEIGHT_BITS);
  if (l > WEIGHT_LEVELS) throw bad(`avatar ${num}: morph weight level ${l} out of range at byte ${at}`);
  return l;
}

/**
 * A keyframe chunk.
 * @param {Reader} r
 * @returns {{num: number, hash: string, levels: QuantPose}}
 */
function keyChunk(r) {
  const num = r.varintU32();
  const hash = r.hex64();
  const joints = r.count(num);
  const translations = r.count(num);
  const scales = r.count(num);
  const flags = r.u8();
  if (flags & ~(FLAG_PLACEMENT | FLAG_WEIGHTS | FLAG_STEPS | FLAG_NEAR) || (flags & FLAG_NEAR && !(flags & FLAG_STEPS))) {
    throw bad(`avatar ${num}: invalid chunk flags ${flags}`);
  }
  /** @type {Steps | null} */
  let steps = null;
  if (flags & FLAG_STEPS) {
    const at = r.at;
    const translation = r.varint();
    if (translation < 1n || translation > 65535n) throw bad(`number out of range at byte ${at}`);
    const rotations = [];
    for (let j = 0; j < joints; j++) {
      const m = r.u8();
      if (m === 0) throw bad(`number out of range at byte ${r.at - 1}`);
      rotations.push(m);
    }
    const near = [];
    if (flags & FLAG_NEAR) {
      for (let j = 0; j < joints; j++) {
        const m = r.u8();
        if (m === 0) throw bad(`number out of range at byte ${r.at - 1}`);
        near.push(m);
      }
    }
    steps = { rotations, translation: Number(translation), near };
  }
  // Bit 47 is a tier only on a grid with near-axis steps; elsewhere it is dropped.
  const tiered = steps !== null && steps.near.length > 0;
  if (r.view.byteLength - r.at < joints * 6 + translations * 3 + scales * 12) throw bad(`truncated at byte ${r.view.byteLength}`);
  /** @type {QuantPose} */
  const levels = { rotations: [], translations: [], scales: [], placement: identityPlacement(), weights: [], steps };
  for (let j = 0; j < joints; j++) {
    const at = r.need(6);
    const bits = r.view.getUint16(at + 4, true) * TWO_32 + r.view.getUint32(at, true);
    levels.rotations.push(tiered || bits < TWO_47 ? bits : bits - TWO_47);
  }
  for (let t = 0; t < translations; t++) {
    /** @type {[number, number, number]} */
    const v = [0, 0, 0];
    for (let c = 0; c < 3; c++) {
      const at = r.at;
      const u = r.varint();
      const x = (u >> 1n) ^ -(u & 1n);
      if (x < BigInt(I32_MIN) || x > BigInt(I32_MAX)) throw bad(`number out of range at byte ${at}`);
      v[c] = Number(x);
    }
    levels.translations.push(v);
  }
  for (let s = 0; s < scales; s++) levels.scales.push(r.vec3());
  if (flags & FLAG_PLACEMENT) levels.placement = r.placement();
  if (flags & FLAG_WEIGHTS) {
    const count = r.count(num);
    if ((r.view.byteLength - r.at) * 8 < count * WEIGHT_BITS) throw bad(`truncated at byte ${r.view.byteLength}`);
    const b = new BitReader(r);
    for (let c = 0; c < count; c++) levels.weights.push(weightLevel(b, num));
  }
  return { num, hash, levels };
}

/**
 * Decodes v2 frames, keeping each (scene, avatar)'s last 8 decoded frames (64 for datagrams)
 * and each scene's last (seq, server time) — the JavaScript twin of posecast-proto's
 * `Frame2Decoder`. One decoder per connection.
 */
export class Frame2Decoder {
  /**
   * @param {{datagrams?: boolean}} [options] `datagrams`: frames come as datagrams (protocol
   * version 8 over WebTransport), as {@link Frame2Decoder.forDatagrams}.
   */
  constructor(options = {}) {
    /** @type {Map<string, {hash: string, frames: {seq: number, levels: QuantPose}[]}>} "scene:avatar" → newest first (for datagrams: in the order they came, the last first). */
    this.history = new Map();
    /** @type {Map<number, {seq: number, time: number}>} Scene number → its last decoded frame's seq and server time (`FrameClock`). */
    this.clock = new Map();
    /** Frames come as datagrams: each avatar's last {@link DATAGRAM_RETENTION} frames are kept, and a keyframe of its rig keeps them. */
    this.datagrams = options.datagrams === true;
  }

  /**
   * A decoder of frames that come as datagrams (protocol version 8 over WebTransport), any of
   * which may be lost or come out of order (`Frame2Decoder::for_datagrams`): its deltas (kind
   * 4) name the frames they refer to, so it keeps each avatar's last
   * {@link DATAGRAM_RETENTION} frames in the order they came, and a keyframe of the rig it
   * holds does not drop the frames before it (a keyframe that comes late must not drop the
   * newer frames a delta names).
   * @returns {Frame2Decoder}
   */
  static forDatagrams() {
    return new Frame2Decoder({ datagrams: true });
  }

  /**
   * Decodes one v2 frame, remembering it for the deltas after it. On error (malformed bytes, a
   * delta whose base frame this decoder does not hold) it throws `bad_message` and nothing
   * changes.
   * @param {ArrayBuffer | Uint8Array} bytes
   * @returns {BinaryFrame}
   */
  decode(bytes) {
    const view =
      bytes instanceof Uint8Array ? new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength) : new DataView(bytes);
    const r = new Reader(view);
    const magic = r.u8();
    if (magic !== MAGIC2) throw bad(`bad magic byte ${magic} (a v2 frame starts with ${MAGIC2})`);
    const kind = r.u8();
    if (kind < 1 || kind > KIND_SPACED) throw bad(`unknown frame kind ${kind}`);
    const key = kind === 1;
    const packed = kind === KIND_PACKED;
    const referenced = kind === KIND_REFERENCED || kind === KIND_SPACED;
    const count = r.varint();
    const sceneNum = r.varintU32();
    const seq = r.varintSafe("seq");
    // A packed delta's time comes after its base gap, as a difference from its base frame's.
    let serverTimeUs = packed ? 0 : r.varintSafe("server time");
    let baseSeq = seq;
    /** @type {number[] | null} The ticks a kind 4 or 5 delta names, newest first. */
    let refs = null;
    if (referenced) {
      const at = r.at;
      const n = r.varint();
      if (n === 0n || n > BigInt(MAX_DEPTH)) throw bad(`number out of range at byte ${at}`);
      refs = [];
      let lastGap = 0n;
      for (let i = 0n; i < n; i++) {
        const gap = r.varint();
        if (gap <= lastGap || gap > BigInt(seq)) throw bad(`delta reference gap ${gap} invalid for seq ${seq}`);
        lastGap = gap;
        refs.push(seq - Number(gap));
      }
      baseSeq = refs[0];
    } else if (!key) {
      const gap = r.varint();
      if (gap === 0n || gap > BigInt(seq)) throw bad(`delta base gap ${gap} invalid for seq ${seq}`);
      baseSeq = seq - Number(gap);
    }
    if (packed) {
      const at = r.at;
      const u = r.varint();
      const last = this.clock.get(sceneNum);
      if (!last || last.seq !== baseSeq) {
        throw bad(`scene ${sceneNum}: packed delta against frame ${baseSeq}, which this decoder does not hold`);
      }
      // Exact in BigInt: the base time (< 2⁵³) plus the signed difference.
      const time = BigInt(last.time) + ((u >> 1n) ^ -(u & 1n));
      if (time < 0n || time > SAFE) throw bad(`server time ${time} at byte ${at} is negative or beyond 2^53, which this client cannot hold exactly`);
      serverTimeUs = Number(time);
    }
    /** @type {{num: number, hash: string, levels: QuantPose}[]} */
    const decoded = [];
    /** @param {{num: number, hash: string, levels: QuantPose}} a */
    const push = (a) => {
      if (decoded.some((b) => b.num === a.num)) throw bad(`avatar ${a.num} appears twice in one frame`);
      decoded.push(a);
    };
    if (packed) {
      // One bit stream for every chunk (each takes at least 2 bits, so a count beyond the
      // bytes fails on them first).
      const b = new BitReader(r);
      /** @type {number | null} */
      let prev = null;
      for (let c = 0n; c < count; c++) {
        const a = this.packedChunk(b, sceneNum, baseSeq, prev);
        prev = a.num;
        push(a);
      }
    } else if (refs) {
      // Each chunk its length, then a kind 2 chunk of exactly that many bytes (at least 1 byte
      // each, so a count beyond the bytes fails on them first).
      for (let c = 0n; c < count; c++) {
        const at = r.at;
        const len = r.varint();
        if (len > BigInt(view.byteLength - r.at)) throw bad(`truncated at byte ${at}`);
        const end = r.at + Number(len);
        // Read within its bytes, at their offsets in the frame.
        const chunk = new Reader(new DataView(view.buffer, view.byteOffset, end));
        chunk.at = r.at;
        push(this.deltaChunk(chunk, sceneNum, baseSeq, refs, kind === KIND_SPACED ? seq : null));
        if (chunk.at !== end) throw bad(`${end - chunk.at} trailing bytes in avatar chunk at byte ${at}`);
        r.at = end;
      }
    } else {
      // Every chunk takes at least 2 bytes, so a count beyond the bytes fails on them first.
      for (let c = 0n; c < count; c++) push(key ? keyChunk(r) : this.deltaChunk(r, sceneNum, baseSeq));
    }
    if (r.at !== view.byteLength) throw bad(`${view.byteLength - r.at} trailing bytes after the last avatar chunk`);
    const retained = this.datagrams ? DATAGRAM_RETENTION : MAX_DEPTH;
    for (const a of decoded) {
      const slot = `${sceneNum}:${a.num}`;
      let h = this.history.get(slot);
      if (!h) this.history.set(slot, (h = { hash: a.hash, frames: [] }));
      // Over datagrams a keyframe of the rig held keeps the frames before it: one that comes
      // late must not drop newer frames a delta names.
      const newRig = h.frames.length === 0 || h.hash !== a.hash;
      if (key && (newRig || !this.datagrams)) {
        h.frames = [];
        h.hash = a.hash;
      }
      // In the order frames came: a kind 4 delta finds the frames it names by tick (the
      // newest that came of each).
      h.frames.unshift({ seq, levels: a.levels });
      if (h.frames.length > retained) h.frames.length = retained;
    }
    this.clock.set(sceneNum, { seq, time: serverTimeUs });
    return {
      key,
      scene_num: sceneNum,
      seq,
      server_time_us: serverTimeUs,
      base_seq: baseSeq,
      avatars: decoded.map(({ num, hash, levels }) => ({
        num,
        hash,
        rotations: levels.rotations.map((_, j) => decodeQuat(fineRotation(levels, j))),
        translations: levels.translations.map(
          (t) => /** @type {Vec3} */ (t.map((l) => Math.fround(fineTranslation(levels, l) * TRANSLATION_STEP))),
        ),
        scales: levels.scales.map((s) => /** @type {Vec3} */ ([...s])),
        placement: { position: [...levels.placement.position], rotation: [...levels.placement.rotation] },
        weights: levels.weights.map((l) => Math.fround(l / WEIGHT_LEVELS)),
      })),
    };
  }

  /**
   * Forgets a scene's frames and its last (seq, time) (the client left it).
   * @param {number} sceneNum
   */
  forgetScene(sceneNum) {
    for (const slot of [...this.history.keys()]) if (slot.startsWith(`${sceneNum}:`)) this.history.delete(slot);
    this.clock.delete(sceneNum);
  }

  /**
   * Forgets one avatar's frames (it left the scene), so a long-lived decoder holds only
   * avatars still there.
   * @param {number} sceneNum
   * @param {number} avatarNum
   */
  forgetAvatar(sceneNum, avatarNum) {
    this.history.delete(`${sceneNum}:${avatarNum}`);
  }

  /**
   * The description hash and the frames (newest first, the depth in `flags`) a delta chunk of
   * avatar `num` refers to, checked against what this decoder holds (`history_for`): its
   * newest frames, or those of `refs` (a kind 4 delta), wherever they are among those it holds.
   * @param {number} sceneNum
   * @param {number} num
   * @param {number} baseSeq
   * @param {number} flags
   * @param {number[] | null} [refs]
   * @returns {{hash: string, history: QuantPose[]}}
   */
  historyFor(sceneNum, num, baseSeq, flags, refs = null) {
    const depth = (flags >> 4) + 1;
    const held = this.history.get(`${sceneNum}:${num}`);
    const missing = () => bad(`avatar ${num}: delta against frame ${baseSeq} (depth ${depth}), which this decoder does not hold`);
    /** @type {QuantPose[]} */
    let history;
    if (refs) {
      if (!held) throw missing();
      if (depth > refs.length) throw bad(`avatar ${num}: invalid chunk flags ${flags}`);
      history = refs.slice(0, depth).map((seq) => {
        // The newest frame that came of that tick.
        const f = held.frames.find((f) => f.seq === seq);
        if (!f) throw missing();
        return f.levels;
      });
    } else {
      if (!held || depth > MAX_DEPTH || held.frames.length < depth || held.frames[0].seq !== baseSeq) throw missing();
      history = held.frames.slice(0, depth).map((f) => f.levels);
    }
    const base = history[0];
    if (history.some((h) => !sameShape(h, base))) throw missing();
    if (flags & FLAG_WEIGHTS && base.weights.length === 0) throw bad(`avatar ${num}: invalid chunk flags ${flags}`);
    return { hash: held.hash, history };
  }

  /**
   * A delta chunk of a frame of kind 2 or 4 (byte-aligned) against the held frames of its
   * avatar (`refs`: those a kind 4 delta names).
   * @param {Reader} r
   * @param {number} sceneNum
   * @param {number} baseSeq
   * @param {number[] | null} [refs]
   * @param {number | null} [seq] a kind 5 delta's tick (it predicts over the ticks to it)
   * @returns {{num: number, hash: string, levels: QuantPose}}
   */
  deltaChunk(r, sceneNum, baseSeq, refs = null, seq = null) {
    const num = r.varintU32();
    const flags = r.u8();
    const { hash, history } = this.historyFor(sceneNum, num, baseSeq, flags, refs);
    const spacing = refs && seq !== null ? spacingOf(seq, refs) : null;
    const pose = deltaLevels(new BitReader(r), history, flags, num, spacing);
    if (flags & FLAG_SCALES) pose.scales = history[0].scales.map(() => r.vec3());
    if (flags & FLAG_PLACEMENT) pose.placement = r.placement();
    if (flags & FLAG_WEIGHTS) pose.weights = readWeights(new BitReader(r), history[0].weights, num);
    return { num, hash, levels: pose };
  }

  /**
   * A chunk of a packed delta (kind 3), read from the frame's one bit stream; `prev` is the
   * previous chunk's avatar number (`packed_chunk`).
   * @param {BitReader} b
   * @param {number} sceneNum
   * @param {number} baseSeq
   * @param {number | null} prev
   * @returns {{num: number, hash: string, levels: QuantPose}}
   */
  packedChunk(b, sceneNum, baseSeq, prev) {
    const at = b.r.at;
    let num;
    if (prev !== null && b.get(1) === 1) {
      // The previous chunk's number + 1.
      if (prev >= U32_MAX_NUMBER) throw bad(`number out of range at byte ${at}`);
      num = prev + 1;
    } else {
      const n = b.get(5) + 1;
      num = b.get(n);
    }
    // 1: depth 8 and no flag (a steady stream's usual chunk); 0: depth − 1 and the flags.
    let flags = (MAX_DEPTH - 1) << 4;
    if (b.get(1) === 0) {
      const depth = b.get(3);
      flags = (depth << 4) | b.get(4);
    }
    const { hash, history } = this.historyFor(sceneNum, num, baseSeq, flags);
    const pose = deltaLevels(b, history, flags, num);
    /** @returns {Vec3} */
    const vec3 = () => [f32FromBits(b.get(32)), f32FromBits(b.get(32)), f32FromBits(b.get(32))];
    if (flags & FLAG_SCALES) pose.scales = history[0].scales.map(() => vec3());
    if (flags & FLAG_PLACEMENT) {
      const position = vec3();
      pose.placement = { position, rotation: [...vec3(), f32FromBits(b.get(32))] };
    }
    if (flags & FLAG_WEIGHTS) pose.weights = readWeights(b, history[0].weights, num);
    return { num, hash, levels: pose };
  }
}

/**
 * The changed morph weights of a delta chunk: a change mask over `base`'s channels, then the
 * new level of each changed one (`read_weights`).
 * @param {BitReader} b
 * @param {number[]} base
 * @param {number} num
 * @returns {number[]}
 */
function readWeights(b, base, num) {
  const changed = base.map(() => b.get(1) === 1);
  return base.map((l, c) => (changed[c] ? weightLevel(b, num) : l));
}

/**
 * A delta chunk's escape mask, rotations and translations, read against `history` (newest
 * first, the chunk's depth); scales, placement and weights are the base's (`delta_levels`).
 * @param {BitReader} b
 * @param {QuantPose[]} history
 * @param {number} flags
 * @param {number} num
 * @param {Spacing | null} [spacing] a kind 5 delta's
 * @returns {QuantPose}
 */
function deltaLevels(b, history, flags, num, spacing = null) {
  const r = b.r;
  const base = history[0];
  /** @type {QuantPose} */
  const pose = { rotations: [], translations: [], scales: base.scales, placement: base.placement, weights: base.weights, steps: base.steps };
  const joints = base.rotations.length;
  const escaped = new Array(joints).fill(false);
  // An escaped joint's bits: with near-axis steps, its tier too.
  const steps = base.steps && base.steps.near.length > 0 ? base.steps : null;
  const full = steps ? 48 : 47;
  if (flags & FLAG_ESCAPES) for (let j = 0; j < joints; j++) escaped[j] = b.get(1) === 1;
  for (let j = 0; j < joints; j++) {
    if (escaped[j]) {
      if (steps && b.get(1) === 1) {
        // Only the tier changed: residuals against the history put on the new grid.
        const was = base.rotations[j];
        const flipped = was >= TWO_47 ? was - TWO_47 : was + TWO_47;
        const i = index(was);
        let n = 0;
        while (n < history.length && index(history[n].rotations[j]) === i) n++;
        const to = rotationStep(steps, j, flipped);
        let bits = tag(flipped);
        for (let c = 0; c < 3; c++) {
          const h = history.slice(0, n).map((f) => {
            const from = f.rotations[j];
            return coarseLevel(fineLevel(level(from, c), rotationStep(steps, j, from)), to);
          });
          const [pred, k] = predict(h, true, spacing);
          const value = pred + unzigzag(b.rice(k));
          if (!(value >= 0 && value <= LEVEL_MASK)) throw bad(`avatar ${num}: rotation level out of range at byte ${r.at}`);
          bits = bits * TWO_15 + value;
        }
        pose.rotations.push(bits);
        continue;
      }
      pose.rotations.push(b.get(full));
      continue;
    }
    const i = tag(base.rotations[j]);
    let n = 0;
    while (n < history.length && tag(history[n].rotations[j]) === i) n++;
    let bits = i;
    for (let c = 0; c < 3; c++) {
      const h = history.slice(0, n).map((f) => level(f.rotations[j], c));
      const [pred, k] = predict(h, true, spacing);
      const value = pred + unzigzag(b.rice(k));
      if (!(value >= 0 && value <= LEVEL_MASK)) throw bad(`avatar ${num}: rotation level out of range at byte ${r.at}`);
      bits = bits * TWO_15 + value;
    }
    pose.rotations.push(bits);
  }
  for (let t = 0; t < base.translations.length; t++) {
    /** @type {[number, number, number]} */
    const v = [0, 0, 0];
    for (let c = 0; c < 3; c++) {
      const [pred, k] = predict(
        history.map((f) => f.translations[t][c]),
        false,
        spacing,
      );
      const value = pred + unzigzag(b.rice(k));
      if (!(value >= I32_MIN && value <= I32_MAX)) throw bad(`avatar ${num}: translation level out of range at byte ${r.at}`);
      v[c] = value;
    }
    pose.translations.push(v);
  }
  return pose;
}
