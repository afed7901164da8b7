// @ts-check
// Jitter buffer (the JavaScript twin of posecast-client's `net/jitter.rs`): an avatar's recent
// poses by server time, played out a little in the past so irregular arrival does not show as
// stutter.
//
// Playout point: a frame stamped s (server clock) arriving at a (client clock) has raw transit
// a − s, the one-way delay plus the constant clock offset. At client time `now` the buffer shows
// server time now − D, D = q(a − s) + one frame interval, q the 99.5th percentile of the last
// 600 raw transits and the interval the longest gap between the stamps of the last 16 frames
// (one tick at full rate; more when the server paces the connection): every frame stamped up to
// now − D + interval has then arrived with 99.5 % probability, so the point lies between two
// received frames and is interpolated. The offset cancels out.
// Past the newest frame the pose is extrapolated from the last two for at most 100 ms, then held.

import { quatSlerp } from "./math.js";

/** @typedef {import("./posecast.js").FramePose} FramePose */
/** @typedef {import("./posecast.js").Sampled} Sampled */
/** @typedef {import("./posecast.js").Vec3} Vec3 */

/** Frames kept (about a second at 60 Hz). */
export const CAPACITY = 64;
/** Raw transits kept for the delay estimate (10 s at 60 Hz). */
export const WINDOW = 600;
/** Stamp gaps the frame interval is the longest of. */
export const GAPS = 16;
/** The share of recent frames the playout delay waits for. */
export const QUANTILE = 0.995;
/** Longest extrapolation past the newest frame, µs. */
export const MAX_EXTRAPOLATION_US = 100_000;
/** Longest playout delay above the fastest transit, µs. */
export const MAX_DELAY_US = 1_000_000;

/**
 * @param {ArrayLike<number>} a
 * @param {ArrayLike<number>} b
 * @param {number} w
 * @returns {Vec3}
 */
function lerp3(a, b, w) {
  return [a[0] + (b[0] - a[0]) * w, a[1] + (b[1] - a[1]) * w, a[2] + (b[2] - a[2]) * w];
}

/**
 * `a` blended towards `b` by `w` (0: a, 1: b; beyond 1 extrapolates): rotations by shortest-arc
 * slerp, translations, scales and position by lerp — `Transform::blend`, joint by joint; morph
 * weights by lerp, kept in [0, 1]. Poses
 * of different shapes (a rig changed between them) give `b`.
 * @param {FramePose} a
 * @param {FramePose} b
 * @param {number} w
 * @returns {FramePose}
 */
export function blendPoses(a, b, w) {
  if (a.rotations.length !== b.rotations.length || a.translations.length !== b.translations.length || a.scales.length !== b.scales.length) {
    return b;
  }
  /** @type {FramePose} */
  const blended = {
    avatar: b.avatar,
    hash: b.hash,
    rotations: a.rotations.map((q, j) => quatSlerp(q, b.rotations[j], w)),
    translations: a.translations.map((t, i) => lerp3(t, b.translations[i], w)),
    scales: a.scales.map((s, i) => lerp3(s, b.scales[i], w)),
    placement: {
      position: lerp3(a.placement.position, b.placement.position, w),
      rotation: quatSlerp(a.placement.rotation, b.placement.rotation, w),
    },
  };
  // No `weights` key at all for a pose without them.
  const weights = blendWeights(a.weights, b.weights, w);
  if (weights) blended.weights = weights;
  return blended;
}

/**
 * Morph weights blended linearly channel by channel and kept in [0, 1] (an extrapolated blend
 * cannot leave the range weights have); a channel only `b` has takes `b`'s weight.
 * @param {Record<string, number> | undefined} a
 * @param {Record<string, number> | undefined} b
 * @param {number} w
 * @returns {Record<string, number> | undefined}
 */
function blendWeights(a, b, w) {
  if (!a || !b) return b;
  /** @type {Record<string, number>} */
  const out = {};
  for (const [name, to] of Object.entries(b)) {
    const from = a[name] ?? to;
    out[name] = Math.min(1, Math.max(0, from + (to - from) * w));
  }
  return out;
}

export class JitterBuffer {
  /** @param {number} tickRate Frames per second of the stream. */
  constructor(tickRate) {
    const rate = Number.isFinite(tickRate) && tickRate > 0 ? tickRate : 60;
    this.tickUs = 1e6 / rate;
    /** @type {{t: number, pose: FramePose}[]} */
    this.frames = [];
    /** @type {number[]} Raw transits of the last frames, µs. */
    this.transits = [];
    this.transitQuantile = 0;
    this.sinceSort = 0;
    this.jitter = 0;
    /** @type {number | null} */
    this.lastTransit = null;
    /** @type {number[]} Gaps between the stamps of the last frames, µs (a paced connection gets fewer frames than ticks). */
    this.gaps = [];
  }

  get length() {
    return this.frames.length;
  }

  /**
   * Adds a pose stamped `serverTimeUs`, received at `arrivalUs` (any epoch: only differences
   * matter). Out-of-order or duplicate stamps are ignored.
   * @param {number} serverTimeUs
   * @param {number} arrivalUs
   * @param {FramePose} pose
   */
  push(serverTimeUs, arrivalUs, pose) {
    const last = this.frames[this.frames.length - 1];
    if (last && last.t >= serverTimeUs) return;
    const transit = arrivalUs - serverTimeUs;
    // RFC 3550's jitter estimator, for people (the delay uses the percentile).
    if (this.lastTransit !== null) this.jitter += (Math.abs(transit - this.lastTransit) - this.jitter) / 16;
    this.lastTransit = transit;
    if (this.transits.length === WINDOW) this.transits.shift();
    this.transits.push(transit);
    // The quantile moves slowly: sorted every 16 frames, and at once for a later frame.
    this.sinceSort++;
    if (this.sinceSort >= 16 || transit > this.transitQuantile) {
      this.sinceSort = 0;
      const sorted = [...this.transits].sort((x, y) => x - y);
      const rank = Math.min(sorted.length, Math.max(1, Math.ceil(sorted.length * QUANTILE)));
      this.transitQuantile = sorted[rank - 1];
    }
    if (last) {
      if (this.gaps.length === GAPS) this.gaps.shift();
      this.gaps.push(serverTimeUs - last.t);
    }
    if (this.frames.length === CAPACITY) this.frames.shift();
    this.frames.push({ t: serverTimeUs, pose });
  }

  /** @returns {number} Arrival jitter (RFC 3550), µs. */
  jitterUs() {
    return this.jitter;
  }

  /** @returns {number} The playout delay, µs: the transits' 99.5th percentile + one frame interval. */
  delayUs() {
    let floor = Infinity;
    for (const t of this.transits) floor = Math.min(floor, t);
    return Math.min(this.transitQuantile + this.intervalUs(), floor + MAX_DELAY_US);
  }

  /** @returns {number} The frames' interval, µs: the longest recent stamp gap, at least one tick. */
  intervalUs() {
    return this.gaps.reduce((a, b) => Math.max(a, b), this.tickUs);
  }

  /**
   * The pose at server time `timeUs`: the two frames around it blended; past the newest,
   * carried on from the last two for up to 100 ms, then held; before the oldest, the oldest.
   * @param {number} timeUs
   * @returns {{pose: FramePose, kind: Sampled} | null}
   */
  sample(timeUs) {
    const frames = this.frames;
    const first = frames[0];
    if (!first) return null;
    if (timeUs <= first.t) return { pose: first.pose, kind: "held" };
    const i = frames.findIndex((f) => f.t >= timeUs);
    if (i < 0) {
      const n = frames.length;
      const f1 = frames[n - 1];
      if (n < 2 || timeUs - f1.t > MAX_EXTRAPOLATION_US) return { pose: f1.pose, kind: "held" };
      const f0 = frames[n - 2];
      return { pose: blendPoses(f0.pose, f1.pose, (timeUs - f0.t) / (f1.t - f0.t)), kind: "extrapolated" };
    }
    const f0 = frames[i - 1];
    const f1 = frames[i];
    return { pose: blendPoses(f0.pose, f1.pose, (timeUs - f0.t) / (f1.t - f0.t)), kind: "interpolated" };
  }

  /**
   * @param {number} nowUs Client time, µs (the epoch of the arrivals).
   * @returns {number} The server time shown then.
   */
  playoutTime(nowUs) {
    return nowUs - this.delayUs();
  }

  /**
   * @param {number} nowUs
   * @returns {FramePose | null} The pose to show at client time `nowUs`.
   */
  playout(nowUs) {
    return this.sample(this.playoutTime(nowUs))?.pose ?? null;
  }
}
