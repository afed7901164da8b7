// @ts-check
// Joint subsets (proto/src/subset.rs): a subscription may ask for only some joints of every
// avatar (`{depth: 3}` or `{names: [...]}`, each joint with its ancestors, every root always).
// Server and client derive the same selection from the avatar's description, so binary frames
// carry no joint list; JSON frames list the joints (`joints`). The client puts every joint not
// sent at its rest transform, so a pose it hands on always has every joint.

/** @typedef {import("./posecast.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./posecast.js").JointSet} JointSet */
/** @typedef {import("./posecast.js").Quat} Quat */
/** @typedef {import("./posecast.js").Vec3} Vec3 */

/**
 * The joints of `description` a joint set selects, ascending (as the server selects them).
 * @param {JointSet} set
 * @param {AvatarDescription} description
 * @returns {number[]}
 */
export function selectJoints(set, description) {
  const parents = description.parents;
  const n = parents.length;
  /** @param {number} j */
  const parent = (j) => {
    const p = parents[j];
    return p >= 0 && p < n && p !== j ? p : -1;
  };
  const keep = new Array(n).fill(false);
  if ("depth" in set) {
    for (let j = 0; j < n; j++) {
      let at = j;
      let depth = 0;
      while (parent(at) >= 0) {
        depth++;
        if (depth > set.depth) break;
        at = parent(at);
      }
      keep[j] = depth <= set.depth;
    }
  } else {
    const names = new Set(set.names);
    for (let j = 0; j < n; j++) {
      if (parent(j) >= 0 && !names.has(description.joint_names[j])) continue;
      let at = j;
      for (let step = 0; step < n; step++) {
        keep[at] = true;
        const p = parent(at);
        if (p < 0 || keep[p]) break;
        at = p;
      }
    }
  }
  /** @type {number[]} */
  const joints = [];
  keep.forEach((k, j) => k && joints.push(j));
  return joints;
}

/**
 * A pose of only `joints` (ascending) made whole: every other joint at its rest transform.
 * `null` when the pose's lengths do not fit the description and the joints.
 * @param {{rotations: Quat[], translations: Vec3[], scales: Vec3[]}} pose
 * @param {AvatarDescription} description
 * @param {number[]} joints
 * @returns {{rotations: Quat[], translations: Vec3[], scales: Vec3[]} | null}
 */
export function expandPose(pose, description, joints) {
  const n = description.parents.length;
  const selected = new Set(joints);
  const translated = description.translated_joints.filter((j) => selected.has(j));
  const scaled = description.scaled_joints.filter((j) => selected.has(j));
  if (
    joints.some((j) => j >= n) ||
    pose.rotations.length !== joints.length ||
    pose.translations.length !== translated.length ||
    pose.scales.length !== scaled.length
  ) {
    return null;
  }
  /** @type {Quat[]} */
  const rotations = description.rest_rotations.map((q) => [q[0], q[1], q[2], q[3]]);
  joints.forEach((j, k) => (rotations[j] = pose.rotations[k]));
  /** @type {Map<number, Vec3>} */
  const sentT = new Map(translated.map((j, k) => [j, pose.translations[k]]));
  /** @type {Map<number, Vec3>} */
  const sentS = new Map(scaled.map((j, k) => [j, pose.scales[k]]));
  /** @param {number[]} j3 @returns {Vec3} */
  const v3 = (j3) => [j3[0], j3[1], j3[2]];
  return {
    rotations,
    translations: description.translated_joints.map((j) => sentT.get(j) ?? v3(description.rest_translations[j])),
    scales: description.scaled_joints.map((j) => sentS.get(j) ?? v3(description.rest_scales[j])),
  };
}
