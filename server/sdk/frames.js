// @ts-check
// Binary pose frames (proto/PROTOCOL.md "Pose frames"; Rust: posecast-proto `frame.rs` and
// `quant.rs`): a 32-byte header, then one chunk per avatar; keyframes carry every rotation as
// 48-bit smallest-three, deltas a 2-bit tag per joint against the scene's last keyframe
// (0 unchanged, 1 three i8 differences of the stored 15-bit levels, 2 a full rotation); with
// bit 7 of the kind set, every chunk ends with its morph weights (a u16 count, u16 levels).
// A 48-bit rotation fits a JS number exactly (integers up to 2⁵³), so the bits are kept as
// numbers.

import { PosecastError } from "./errors.js";

/** @typedef {import("./posecast.js").Quat} Quat */
/** @typedef {import("./posecast.js").Vec3} Vec3 */
/** @typedef {import("./posecast.js").Placement} Placement */
/** @typedef {import("./posecast.js").BinaryFrame} BinaryFrame */

const MAGIC = 0x50;
const HEADER_BYTES = 32;
const PLACEMENT_FLAG = 0x8000;
const WEIGHTS_FLAG = 0x80;
// Morph weight levels (morph.rs: `WEIGHT_LEVELS`).
const WEIGHT_LEVELS = 1023;
const LEVEL_MASK = 0x7fff;
// 2¹⁵ − 2 steps over [−1/√2, 1/√2] (quant.rs: an even count, so zero is exact).
const LEVELS = 32766;
const RANGE = Math.SQRT1_2;
const TWO_32 = 2 ** 32;
const TWO_15 = 2 ** 15;

/**
 * The dropped component's index and the three stored 15-bit levels of a 48-bit rotation.
 * @param {number} bits
 * @returns {[number, number, number, number]}
 */
function levels(bits) {
  const hi = Math.floor(bits / TWO_32); // bits 32–47
  const lo = bits % TWO_32; // bits 0–31
  return [
    (hi >>> 13) & 3, // bits 45–46
    ((lo >>> 30) | (hi << 2)) & LEVEL_MASK, // bits 30–44
    (lo >>> 15) & LEVEL_MASK, // bits 15–29
    lo & LEVEL_MASK, // bits 0–14
  ];
}

/**
 * Decodes a 48-bit smallest-three rotation: `v = level / 32766 · √2 − 1/√2`, the dropped
 * (largest, positive) component `√(1 − a² − b² − c²)`, then normalised — as `quant::decode`.
 * @param {number} bits
 * @returns {Quat}
 */
export function decodeQuat(bits) {
  const [largest, l0, l1, l2] = levels(bits);
  const small = [l0, l1, l2].map((l) => (l / LEVELS) * 2 * RANGE - RANGE);
  const sum = small[0] * small[0] + small[1] * small[1] + small[2] * small[2];
  /** @type {Quat} */
  const q = [0, 0, 0, 0];
  let k = 0;
  for (let i = 0; i < 4; i++) q[i] = i === largest ? Math.sqrt(Math.max(0, 1 - sum)) : small[k++];
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
}

/**
 * A keyframe's rotation moved by three level differences (tag 1), each level clamped to 15
 * bits — as `frame.rs`'s `apply_difference`.
 * @param {number} key
 * @param {[number, number, number]} d
 * @returns {number}
 */
function applyDifference(key, d) {
  const [index, ...l] = levels(key);
  let bits = index;
  for (let k = 0; k < 3; k++) bits = bits * TWO_15 + Math.min(LEVEL_MASK, Math.max(0, l[k] + d[k]));
  return bits;
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
    if (this.at + n > this.view.byteLength) {
      throw new PosecastError("bad_message", `binary frame truncated at byte ${this.at} (${n} more needed)`);
    }
    const at = this.at;
    this.at += n;
    return at;
  }
  u8() {
    return this.view.getUint8(this.need(1));
  }
  i8() {
    return this.view.getInt8(this.need(1));
  }
  u16() {
    return this.view.getUint16(this.need(2), true);
  }
  u32() {
    return this.view.getUint32(this.need(4), true);
  }
  /** A u64 as a number (exact below 2⁵³: ticks and µs timestamps). */
  u64() {
    const at = this.need(8);
    return this.view.getUint32(at + 4, true) * TWO_32 + this.view.getUint32(at, true);
  }
  /** A u64 as 16 hex digits (description hashes). */
  hex64() {
    const at = this.need(8);
    const hi = this.view.getUint32(at + 4, true).toString(16).padStart(8, "0");
    return hi + this.view.getUint32(at, true).toString(16).padStart(8, "0");
  }
  /** Six bytes: a 48-bit rotation. */
  quatBits() {
    const at = this.need(6);
    return this.view.getUint16(at + 4, true) * TWO_32 + this.view.getUint32(at, true);
  }
  f32() {
    return this.view.getFloat32(this.need(4), true);
  }
  /** @returns {Vec3} */
  vec3() {
    return [this.f32(), this.f32(), this.f32()];
  }
}

/** @returns {Placement} */
function identityPlacement() {
  return { position: [0, 0, 0], rotation: [0, 0, 0, 1] };
}

/**
 * Decodes binary frames, keeping the last keyframe of every (scene, avatar) for deltas — the
 * JavaScript twin of posecast-proto's `FrameDecoder`. One decoder per connection.
 */
export class FrameDecoder {
  constructor() {
    /** @type {Map<string, {seq: number, bits: number[], placement: Placement}>} "scene:avatar" → keyframe. */
    this.keys = new Map();
  }

  /**
   * Decodes one frame. A keyframe's rotations become the reference of later deltas; on error
   * (malformed bytes, a delta whose keyframe is not held) nothing changes.
   * @param {ArrayBuffer | Uint8Array} bytes
   * @returns {BinaryFrame}
   */
  decode(bytes) {
    const view =
      bytes instanceof Uint8Array ? new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength) : new DataView(bytes);
    const r = new Reader(view);
    if (view.byteLength < HEADER_BYTES) throw new PosecastError("bad_message", `binary frame of ${view.byteLength} bytes, shorter than its header`);
    const magic = r.u8();
    if (magic !== MAGIC) throw new PosecastError("bad_message", `binary frame magic ${magic}, expected ${MAGIC}`);
    const rawKind = r.u8();
    // Bit 7: every chunk ends with its morph weights (WebTransport sessions, version ≥ 4).
    const withWeights = (rawKind & WEIGHTS_FLAG) !== 0;
    const kind = rawKind & ~WEIGHTS_FLAG;
    if (kind !== 1 && kind !== 2) throw new PosecastError("bad_message", `binary frame kind ${rawKind}`);
    const key = kind === 1;
    const count = r.u16();
    const sceneNum = r.u32();
    const seq = r.u64();
    const serverTimeUs = r.u64();
    const baseSeq = r.u64();
    /** @type {BinaryFrame["avatars"]} */
    const avatars = [];
    /** @type {[string, {seq: number, bits: number[], placement: Placement}][]} */
    const newKeys = [];
    for (let c = 0; c < count; c++) {
      const num = r.u32();
      const hash = r.hex64();
      const joints = r.u16();
      const translations = r.u16();
      const scalesField = r.u16();
      const scales = scalesField & ~PLACEMENT_FLAG;
      const slot = `${sceneNum}:${num}`;
      /** @type {number[]} */
      const bits = [];
      let placement = identityPlacement();
      if (key) {
        for (let j = 0; j < joints; j++) bits.push(r.quatBits());
      } else {
        const held = this.keys.get(slot);
        if (!held || held.seq !== baseSeq) {
          throw new PosecastError("bad_message", `delta of avatar ${num} refers to keyframe ${baseSeq}, which is not held`);
        }
        if (held.bits.length !== joints) {
          throw new PosecastError("bad_message", `delta of avatar ${num} has ${joints} joints, its keyframe ${held.bits.length}`);
        }
        placement = held.placement;
        const tagsAt = r.need(Math.ceil(joints / 4));
        for (let j = 0; j < joints; j++) {
          const tag = (view.getUint8(tagsAt + (j >> 2)) >> (2 * (j & 3))) & 3;
          if (tag === 0) bits.push(held.bits[j]);
          else if (tag === 1) bits.push(applyDifference(held.bits[j], [r.i8(), r.i8(), r.i8()]));
          else if (tag === 2) bits.push(r.quatBits());
          else throw new PosecastError("bad_message", `delta of avatar ${num}: invalid tag 3 for joint ${j}`);
        }
      }
      /** @type {Vec3[]} */
      const ts = [];
      for (let i = 0; i < translations; i++) ts.push(r.vec3());
      /** @type {Vec3[]} */
      const ss = [];
      for (let i = 0; i < scales; i++) ss.push(r.vec3());
      if (scalesField & PLACEMENT_FLAG) {
        placement = { position: r.vec3(), rotation: [r.f32(), r.f32(), r.f32(), r.f32()] };
      }
      /** @type {number[]} */
      const weights = [];
      if (withWeights) {
        const n = r.u16();
        for (let i = 0; i < n; i++) weights.push(Math.min(r.u16(), WEIGHT_LEVELS) / WEIGHT_LEVELS);
      }
      if (key) newKeys.push([slot, { seq, bits, placement }]);
      avatars.push({ num, hash, rotations: bits.map(decodeQuat), translations: ts, scales: ss, placement, weights });
    }
    if (r.at !== view.byteLength) {
      throw new PosecastError("bad_message", `binary frame has ${view.byteLength - r.at} bytes after its last chunk`);
    }
    for (const [slot, k] of newKeys) this.keys.set(slot, k);
    return { key, scene_num: sceneNum, seq, server_time_us: serverTimeUs, base_seq: baseSeq, avatars };
  }
}
