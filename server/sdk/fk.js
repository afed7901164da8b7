// @ts-check
// Forward kinematics and skinning matrices of a streamed pose, as posecast-proto's
// `fk::forward_kinematics` and `fk::skinning_matrices` do it (tests/web/ checks they agree on
// shared vectors, through ../web/check/fk.mjs).

import { multiply, fromTRS } from "./math.js";

/** @typedef {import("./posecast.js").AvatarDescription} AvatarDescription */

/**
 * The pose parts `forwardKinematics` reads (a frame's `FramePose`, or less).
 * @typedef {object} PoseLike
 * @property {import("./posecast.js").Quat[]} [rotations]
 * @property {import("./posecast.js").Vec3[]} [translations]
 * @property {import("./posecast.js").Vec3[]} [scales]
 * @property {import("./posecast.js").Placement} [placement]
 */

/**
 * World matrices of every joint, column-major, 16 floats each: W_j = W_parent(j) · T(t_j) R_j S_j,
 * and for roots W_root = P · D_root with P = T(position) · R(rotation) the pose's `placement`
 * (identity when absent), so the avatar is drawn where it stands in the scene. Rotations come
 * from the pose (rest when absent); translations and scales from the pose for the description's
 * `translated_joints` / `scaled_joints`, rest otherwise.
 * @param {AvatarDescription} desc
 * @param {PoseLike | null} pose
 * @returns {Float32Array}
 */
export function forwardKinematics(desc, pose) {
  const n = desc.joint_names.length;
  const worlds = new Float32Array(16 * n);
  const local = new Float32Array(16);
  const tmp = new Float32Array(16);
  const placement = pose?.placement;
  const place = placement
    ? fromTRS(new Float32Array(16), placement.position, placement.rotation, [1, 1, 1])
    : null;
  const translated = new Map(desc.translated_joints.map((j, i) => [j, i]));
  const scaled = new Map(desc.scaled_joints.map((j, i) => [j, i]));
  for (let j = 0; j < n; j++) {
    const q = pose?.rotations?.[j] ?? desc.rest_rotations[j];
    const ti = translated.get(j);
    const t = (ti !== undefined && pose?.translations?.[ti]) || desc.rest_translations[j];
    const si = scaled.get(j);
    const s = (si !== undefined && pose?.scales?.[si]) || desc.rest_scales[j];
    fromTRS(local, t, q, s);
    const p = desc.parents[j];
    if (p >= 0) {
      multiply(tmp, worlds.subarray(16 * p, 16 * p + 16), local);
      worlds.set(tmp, 16 * j);
    } else if (place) {
      multiply(tmp, place, local);
      worlds.set(tmp, 16 * j);
    } else {
      worlds.set(local, 16 * j);
    }
  }
  return worlds;
}

/**
 * The translation column of each world matrix: joint positions in world space.
 * @param {Float32Array} worlds
 * @returns {import("./posecast.js").Vec3[]}
 */
export function jointPositions(worlds) {
  const n = worlds.length / 16;
  /** @type {import("./posecast.js").Vec3[]} */
  const out = [];
  for (let j = 0; j < n; j++) out.push([worlds[16 * j + 12], worlds[16 * j + 13], worlds[16 * j + 14]]);
  return out;
}

/**
 * Skinning matrices M_j = W_j · B_j⁻¹ (seed 001's T_j), 16 floats each, from the world matrices
 * `forwardKinematics` gives and the description's inverse binds.
 * @param {AvatarDescription} desc
 * @param {Float32Array} worlds
 * @returns {Float32Array}
 */
export function skinningMatrices(desc, worlds) {
  const n = desc.joint_names.length;
  const out = new Float32Array(16 * n);
  const m = new Float32Array(16);
  for (let j = 0; j < n; j++) {
    multiply(m, worlds.subarray(16 * j, 16 * j + 16), desc.inverse_binds[j]);
    out.set(m, 16 * j);
  }
  return out;
}
