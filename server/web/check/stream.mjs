// Checks the JavaScript client's binary decoders (v1 and wire v2), jitter buffer and clock estimator
// (server/sdk/frames.js, frames2.js, jitter.js, clock.js) against vectors from their Rust twins
// (posecast_proto::frame::FrameDecoder, posecast_proto::frame2::Frame2Decoder, posecast_client::net::jitter / clock), written by
// tests/web/stream.rs: `node stream.mjs FILE`; and joint subsets (server/sdk/subset.js against
// posecast_proto::subset). Prints a report and exits 1 on a mismatch.

import { readFileSync } from "node:fs";
import { FrameDecoder } from "../../sdk/frames.js";
import { Frame2Decoder } from "../../sdk/frames2.js";
import { JitterBuffer } from "../../sdk/jitter.js";
import { ClockEstimator } from "../../sdk/clock.js";
import { quatAngleDegrees } from "../../sdk/math.js";
import { expandPose, selectJoints } from "../../sdk/subset.js";

// The two decoders read the same bits (f64 here, f32 in Rust): float rounding only.
const SAME_BITS_DEGREES = 5e-4;
// Blends in f64 against glam's f32 slerp, extrapolated up to 6 ticks.
const BLEND_DEGREES = 5e-3;
const LENGTH = 1e-4;

const vectors = JSON.parse(readFileSync(process.argv[2], "utf8"));
/** @type {string[]} */
const failures = [];
let worstRotation = 0;
let worstBlend = 0;

/**
 * @param {number[][]} got
 * @param {number[][]} want
 * @param {string} what
 * @param {number} bound
 * @returns {number} The largest difference, degrees.
 */
function rotations(got, want, what, bound) {
  if (got.length !== want.length) {
    failures.push(`${what}: ${got.length} rotations, expected ${want.length}`);
    return 0;
  }
  let worst = 0;
  got.forEach((q, j) => {
    const a = quatAngleDegrees(q, want[j]);
    worst = Math.max(worst, a);
    if (!(a <= bound)) failures.push(`${what} joint ${j}: ${q} vs ${want[j]} (${a}°)`);
  });
  return worst;
}

/**
 * @param {number[]} got
 * @param {number[]} want
 * @param {string} what
 * @param {number} [bound]
 */
function numbers(got, want, what, bound = LENGTH) {
  const g = got.flat(2);
  const w = want.flat(2);
  // JSON has no NaN: serde writes it as null (random bytes decode to NaN floats).
  const same = (/** @type {number} */ x, /** @type {number | null} */ y) => (y === null ? Number.isNaN(x) : Math.abs(x - y) <= bound);
  if (g.length !== w.length || g.some((x, i) => !same(x, w[i]))) failures.push(`${what}: ${JSON.stringify(got)} vs ${JSON.stringify(want)}`);
}

/**
 * Decodes one vector's bytes and compares with what the Rust decoder made of them (`null`: it
 * refused them, so this decoder must throw `bad_message`).
 * @param {{decode: (b: Uint8Array) => any}} decoder
 * @param {any} f
 * @param {string} label
 * @returns {"frame" | "refused" | "failed"}
 */
function check(decoder, f, label) {
  /** @type {any} */
  let got;
  try {
    got = decoder.decode(new Uint8Array(f.bytes));
  } catch (e) {
    if (f.expect !== null || !(e instanceof Error && /** @type {any} */ (e).code === "bad_message")) {
      failures.push(`${label}: threw ${e}`);
      return "failed";
    }
    return "refused";
  }
  if (f.expect === null) {
    failures.push(`${label}: decoded, but the Rust decoder refuses it`);
    return "failed";
  }
  const want = f.expect;
  const before = failures.length;
  for (const k of ["key", "scene_num", "seq", "server_time_us", "base_seq"]) {
    if (got[k] !== want[k]) failures.push(`${label} ${k}: ${got[k]} vs ${want[k]}`);
  }
  if (got.avatars.length !== want.avatars.length) {
    failures.push(`${label}: ${got.avatars.length} avatars, expected ${want.avatars.length}`);
    return "failed";
  }
  got.avatars.forEach((/** @type {any} */ a, k) => {
    const w = want.avatars[k];
    const what = `${label} (seq ${want.seq}) avatar ${w.num}`;
    if (a.num !== w.num || a.hash !== w.hash) failures.push(`${what}: num/hash ${a.num} ${a.hash} vs ${w.num} ${w.hash}`);
    worstRotation = Math.max(worstRotation, rotations(a.rotations, w.rotations, what, SAME_BITS_DEGREES));
    numbers(a.translations, w.translations, `${what} translations`, 0);
    numbers(a.scales, w.scales, `${what} scales`, 0);
    numbers(a.placement.position, w.placement.position, `${what} placement`, 0);
    numbers(a.placement.rotation, w.placement.rotation, `${what} placement`, 0);
    numbers(a.weights, w.weights ?? [], `${what} morph weights`, 0);
  });
  return failures.length === before ? "frame" : "failed";
}

// v1 frames, in order through one decoder: refused ones must throw and change nothing.
const decoder = new FrameDecoder();
let frames = 0;
let refused = 0;
vectors.frames.forEach((/** @type {any} */ f, /** @type {number} */ i) => {
  const r = check(decoder, f, `frame ${i}`);
  if (r === "frame") frames++;
  if (r === "refused") refused++;
});

// Wire v2: the reader of every frame and the slow reader, each through its own decoder.
/** @type {Record<string, {frames: number, refused: number, keys: number}>} */
const v2 = {};
for (const stream of ["fast", "slow"]) {
  const d = new Frame2Decoder();
  const count = (v2[stream] = { frames: 0, refused: 0, keys: 0 });
  vectors.frames2[stream].forEach((/** @type {any} */ f, /** @type {number} */ i) => {
    const r = check(d, f, `v2 ${stream} frame ${i}`);
    if (r === "frame") count.frames++;
    if (r === "frame" && f.expect.key) count.keys++;
    if (r === "refused") count.refused++;
  });
}
// Odd frames after three good ones, each through a fresh decoder; one beyond 2⁵³ the Rust
// decoder takes and this one refuses.
const odd = { decoded: 0, refused: 0, beyond: 0 };
vectors.frames2.odd.forEach((/** @type {any} */ c, /** @type {number} */ i) => {
  const d = new Frame2Decoder();
  for (const p of c.prefix) d.decode(new Uint8Array(p));
  const r = check(d, c.beyond_js ? { bytes: c.bytes, expect: null } : c, `v2 odd case ${i}`);
  if (c.beyond_js && r === "refused") odd.beyond++;
  else if (r === "frame") odd.decoded++;
  else if (r === "refused") odd.refused++;
});

// Random bytes (after a v2 magic and kind, or not) through a decoder holding frames: each
// decodes or throws bad_message — never another exception — and in bounded time.
let seed = 0x2545f491;
const random = () => {
  seed ^= seed << 13;
  seed ^= seed >>> 17;
  seed ^= seed << 5;
  return (seed >>> 0) / 2 ** 32;
};
const fuzzed = new Frame2Decoder();
for (const p of vectors.frames2.odd[0].prefix) fuzzed.decode(new Uint8Array(p));
const fuzzStart = Date.now();
let fuzz = 0;
for (let i = 0; i < 3000; i++) {
  const bytes = new Uint8Array(Math.floor(random() * 400));
  for (let k = 0; k < bytes.length; k++) bytes[k] = random() * 256;
  if (i % 3 !== 0 && bytes.length >= 2) [bytes[0], bytes[1]] = [0x51, 1 + (i % 2)];
  try {
    fuzzed.decode(bytes);
  } catch (e) {
    if (!(e instanceof Error && /** @type {any} */ (e).code === "bad_message")) failures.push(`random bytes ${i}: threw ${e}`);
  }
  fuzz++;
}
const fuzzMs = Date.now() - fuzzStart;
if (fuzzMs > 20000) failures.push(`3000 random frames took ${fuzzMs} ms`);

// The jitter buffer: the same pushes, the same delay, the same samples.
const buffer = new JitterBuffer(60);
let samples = 0;
/** @type {Record<string, number>} */
const kinds = {};
const placement = { position: [0, 0, 0], rotation: [0, 0, 0, 1] };
for (const step of vectors.jitter) {
  buffer.push(step.stamp, step.arrival, { avatar: "a", hash: "", rotations: step.rotations, translations: step.translations, scales: [], placement });
  if (Math.abs(buffer.delayUs() - step.delay) > 1e-6) failures.push(`after stamp ${step.stamp}: delay ${buffer.delayUs()} vs ${step.delay}`);
  for (const q of step.queries) {
    samples++;
    kinds[q.kind] = (kinds[q.kind] ?? 0) + 1;
    const time = buffer.playoutTime(q.now);
    if (Math.abs(time - q.time) > 1e-6) failures.push(`at ${q.now}: playout time ${time} vs ${q.time}`);
    const s = buffer.sample(time);
    if (!s || s.kind !== q.kind) {
      failures.push(`at ${q.now}: ${s?.kind} vs ${q.kind}`);
      continue;
    }
    worstBlend = Math.max(worstBlend, rotations(s.pose.rotations, q.rotations, `sample at ${q.now}`, BLEND_DEGREES));
    numbers(s.pose.translations, q.translations, `sample at ${q.now} translations`);
  }
}

// The clock: the fastest exchange's offset and round trip.
const clock = new ClockEstimator();
for (const c of vectors.clock) {
  clock.add(c.t0, c.server, c.t1);
  if (Math.abs(clock.offsetUs() - c.offset) > 1e-6 || clock.rttUs() !== c.rtt) {
    failures.push(`clock after ${c.t0}: ${clock.offsetUs()} / ${clock.rttUs()} vs ${c.offset} / ${c.rtt}`);
  }
}

// Joint subsets: the same joints selected, the same whole pose (exact: copies, no arithmetic).
let subsets = 0;
for (const c of vectors.subsets) {
  const joints = selectJoints(c.set, c.description);
  if (JSON.stringify(joints) !== JSON.stringify(c.joints)) {
    failures.push(`subset ${JSON.stringify(c.set)} of ${c.description.parents}: ${joints} vs ${c.joints}`);
    continue;
  }
  const whole = expandPose(c.sent, c.description, joints);
  const same = (/** @type {string} */ k) => JSON.stringify(whole?.[k]) === JSON.stringify(c.whole[k]);
  if (!same("rotations") || !same("translations") || !same("scales")) {
    failures.push(`subset ${c.description.id}: whole pose differs`);
    continue;
  }
  if (expandPose({ ...c.sent, rotations: [...c.sent.rotations, [0, 0, 0, 1]] }, c.description, joints) !== null) {
    failures.push(`subset ${c.description.id}: a pose of the wrong length was accepted`);
    continue;
  }
  subsets++;
}

console.log(JSON.stringify({ frames, refused, v2, odd, fuzz, samples, subsets, kinds, worst_rotation_degrees: worstRotation, worst_blend_degrees: worstBlend, failures: failures.slice(0, 20) }));
process.exit(failures.length ? 1 : 0);
