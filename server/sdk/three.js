// @ts-check
// posecast in three.js: a streamed avatar bound to a three.js skeleton, or to a three-vrm
// humanoid. It touches only the objects a page hands it (bones' `quaternion`, `position` and
// `scale`, a placement target) and imports nothing from three, so it works with the page's own
// copy of three, whatever its version.
//
//   import * as THREE from "three";
//   import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
//   import { Client } from "http://host:8080/sdk/posecast.js";
//   import { meshUrl, SkeletonBinding } from "http://host:8080/sdk/three.js";
//
//   const desc = … client.avatar("avatar").description …;
//   const gltf = await new GLTFLoader().loadAsync(meshUrl(client, desc));
//   scene.add(gltf.scene);
//   const binding = new SkeletonBinding(desc, gltf.scene);
//   renderer.setAnimationLoop(() => { binding.update(client); renderer.render(scene, camera); });
//
// - `SkeletonBinding`: the server's `mesh.glb` (joints as nodes named as the description's
//   joints, at their rest transforms), or any model whose bones carry those names: every
//   joint's local rotation, translation and scale from the stream, the placement on the root,
//   and the face: each streamed morph weight on the mesh targets of its name.
// - `VRMBinding`: a three-vrm `VRM` (or a `VRMHumanoid`) through its normalised humanoid bones,
//   so any VRM follows a posecast avatar whatever its own joint frames: each humanoid bone is
//   given the rotation the avatar's joint has turned through from its bind pose (the rotation
//   of its skinning matrix W_j · B_j⁻¹), and the hips their position. Faces: three-vrm's
//   `vrm.update()` resets the morph targets its expressions bind, so a page sets the streamed
//   weights after it (`applyMorphWeights(morphMeshes(vrm.scene), pose.weights)`).
// - `poseAtBind`, `vrmHumanBones`: put a posecast mesh in its bind pose and name its humanoid
//   bones, to build a `VRMHumanoid` for a model that is not a VRM file.

import { forwardKinematics, skinningMatrices } from "./fk.js";
import { quatMul } from "./math.js";

/** @typedef {import("./posecast.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./posecast.js").FramePose} FramePose */
/** @typedef {import("./posecast.js").Quat} Quat */
/** @typedef {import("./posecast.js").Vec3} Vec3 */

/**
 * What the bindings need of a three.js `Object3D`.
 * @typedef {object} Object3DLike
 * @property {string} name
 * @property {{ set(x: number, y: number, z: number, w: number): unknown }} quaternion
 * @property {{ set(x: number, y: number, z: number): unknown }} position
 * @property {{ set(x: number, y: number, z: number): unknown }} scale
 * @property {(callback: (object: any) => void) => void} traverse
 */

/**
 * What `VRMBinding` needs of a three-vrm `VRMHumanoid`.
 * @typedef {object} HumanoidLike
 * @property {(name: string) => Object3DLike | null | undefined} getNormalizedBoneNode
 */

/**
 * The client calls the bindings make (`Client.pose`, the jitter buffer's played-out pose).
 * @typedef {object} PoseSource
 * @property {(id: string, nowUs?: number) => FramePose | null} pose
 */

/**
 * A node name as three's GLTFLoader gives it (`PropertyBinding.sanitizeNodeName`: white space
 * to `_`, the characters `[ ] . : /` removed).
 * @param {string} name
 * @returns {string}
 */
export function sanitizeNodeName(name) {
  return name.replace(/\s/g, "_").replace(/[[\].:/]/g, "");
}

/**
 * The URL of an avatar's skinned mesh (`mesh.glb`) on the server a client is connected to.
 * @param {{ url: string }} client
 * @param {AvatarDescription} desc
 * @returns {string}
 */
export function meshUrl(client, desc) {
  if (!desc.mesh_url) throw new Error(`avatar ${desc.id} has no mesh`);
  const http = client.url.replace(/^ws(s?):/, "http$1:");
  return new URL(desc.mesh_url, http).toString();
}

/**
 * The description's joints found under `root` by name (the name as written, or as three's
 * GLTFLoader sanitises it); `null` where the model has no such node.
 * @param {AvatarDescription} desc
 * @param {Object3DLike} root
 * @returns {(Object3DLike | null)[]}
 */
export function findJoints(desc, root) {
  /** @type {Map<string, Object3DLike>} */
  const byName = new Map();
  root.traverse((object) => {
    if (typeof object.name === "string" && object.name && !byName.has(object.name)) byName.set(object.name, object);
  });
  return desc.joint_names.map((name) => byName.get(name) ?? byName.get(sanitizeNodeName(name)) ?? null);
}

/**
 * A posecast avatar bound to a three.js skeleton whose bones carry the description's joint
 * names — the server's `mesh.glb` loaded with GLTFLoader, or the page's own model exported
 * from the same rig. `apply` gives each bone its local transform: W_j = W_parent(j) · T R S,
 * the same forward kinematics as posecast's, so three's world matrices are posecast's.
 */
export class SkeletonBinding {
  /**
   * @param {AvatarDescription} desc
   * @param {Object3DLike} root the loaded model (e.g. `gltf.scene`)
   * @param {{ placementTarget?: Object3DLike | null }} [options] where the avatar's placement
   *   in the scene goes (default `root`; `null` leaves placement to the page)
   */
  constructor(desc, root, options = {}) {
    this.desc = desc;
    this.root = root;
    this.placementTarget = options.placementTarget === undefined ? root : options.placementTarget;
    this.bones = findJoints(desc, root);
    /** Joint names the model has no node for (their bones are not posed). */
    this.missing = desc.joint_names.filter((_, j) => this.bones[j] === null);
    this.translated = new Map(desc.translated_joints.map((j, i) => [j, i]));
    this.scaled = new Map(desc.scaled_joints.map((j, i) => [j, i]));
    /** The model's meshes with morph targets (three's `morphTargetDictionary`). */
    this.morphMeshes = morphMeshes(root);
  }

  /**
   * Poses the model: rotations of every joint (rest where the pose has none), translations of
   * the description's `translated_joints`, scales of its `scaled_joints` (rest otherwise), and
   * the placement on the placement target.
   * @param {FramePose} pose
   */
  apply(pose) {
    const d = this.desc;
    for (let j = 0; j < this.bones.length; j++) {
      const bone = this.bones[j];
      if (!bone) continue;
      const q = pose.rotations?.[j] ?? d.rest_rotations[j];
      bone.quaternion.set(q[0], q[1], q[2], q[3]);
      const ti = this.translated.get(j);
      const t = (ti !== undefined && pose.translations?.[ti]) || d.rest_translations[j];
      bone.position.set(t[0], t[1], t[2]);
      const si = this.scaled.get(j);
      const s = (si !== undefined && pose.scales?.[si]) || d.rest_scales[j];
      bone.scale.set(s[0], s[1], s[2]);
    }
    place(this.placementTarget, pose, [0, 0, 0, 1]);
    if (pose.weights) applyMorphWeights(this.morphMeshes, pose.weights);
  }

  /**
   * Applies the client's played-out pose of the avatar (its jitter buffer, at `nowUs`).
   * @param {PoseSource} client
   * @param {number} [nowUs]
   * @returns {FramePose | null} the pose applied, or `null` when the client has none yet
   */
  update(client, nowUs) {
    const pose = client.pose(this.desc.id, nowUs);
    if (pose) this.apply(pose);
    return pose;
  }
}

/**
 * What the face needs of a three.js mesh with morph targets.
 * @typedef {object} MorphMeshLike
 * @property {Record<string, number>} morphTargetDictionary target name → index
 * @property {number[]} morphTargetInfluences weight per target
 */

/**
 * The meshes under `root` that have morph targets (three's GLTFLoader names them from
 * `mesh.extras.targetNames`; the server's `mesh.glb` carries one target per morph channel).
 * @param {Object3DLike} root
 * @returns {MorphMeshLike[]}
 */
export function morphMeshes(root) {
  /** @type {MorphMeshLike[]} */
  const out = [];
  root.traverse((o) => {
    if (o.morphTargetDictionary && Array.isArray(o.morphTargetInfluences)) out.push(o);
  });
  return out;
}

/**
 * Sets the streamed morph weights (a pose's `weights`: channel name → weight, what the server
 * evaluated, VRM expressions included) on every mesh target of that name. A three-vrm `VRM`
 * resets the targets its expressions bind in `vrm.update()`: call this after it.
 * @param {MorphMeshLike[]} meshes from {@link morphMeshes}
 * @param {Record<string, number>} weights
 */
export function applyMorphWeights(meshes, weights) {
  for (const mesh of meshes) {
    for (const [name, w] of Object.entries(weights)) {
      const k = mesh.morphTargetDictionary[name];
      if (k !== undefined) mesh.morphTargetInfluences[k] = w;
    }
  }
}

/**
 * VRM 1.0 humanoid bone names in three-vrm's order (parents before children), each with the
 * bone it hangs from in the humanoid hierarchy.
 * @type {[string, string | null][]}
 */
export const VRM_HUMAN_BONES = (() => {
  /** @type {[string, string | null][]} */
  const bones = [
    ["hips", null],
    ["spine", "hips"],
    ["chest", "spine"],
    ["upperChest", "chest"],
    ["neck", "upperChest"],
    ["head", "neck"],
    ["leftEye", "head"],
    ["rightEye", "head"],
    ["jaw", "head"],
  ];
  for (const side of ["left", "right"]) {
    bones.push(
      [`${side}UpperLeg`, "hips"],
      [`${side}LowerLeg`, `${side}UpperLeg`],
      [`${side}Foot`, `${side}LowerLeg`],
      [`${side}Toes`, `${side}Foot`],
    );
  }
  for (const side of ["left", "right"]) {
    bones.push(
      [`${side}Shoulder`, "upperChest"],
      [`${side}UpperArm`, `${side}Shoulder`],
      [`${side}LowerArm`, `${side}UpperArm`],
      [`${side}Hand`, `${side}LowerArm`],
    );
  }
  for (const side of ["left", "right"]) {
    bones.push(
      [`${side}ThumbMetacarpal`, `${side}Hand`],
      [`${side}ThumbProximal`, `${side}ThumbMetacarpal`],
      [`${side}ThumbDistal`, `${side}ThumbProximal`],
    );
    for (const finger of ["Index", "Middle", "Ring", "Little"]) {
      bones.push(
        [`${side}${finger}Proximal`, `${side}Hand`],
        [`${side}${finger}Intermediate`, `${side}${finger}Proximal`],
        [`${side}${finger}Distal`, `${side}${finger}Intermediate`],
      );
    }
  }
  return bones;
})();

/**
 * The VRM humanoid bone of each of a description's joints that has one, by posecast's
 * normalised (H-Anim) names — the inverse of the server's VRM import: `humanoid_root` is the
 * hips, `vl5` the spine, `vt10` the chest and `vt1` the upper chest (`vt1` is the chest when
 * there is no `vt10`), `vc4` the neck, `skullbase` the head, `l_sternoclavicular` …
 * `l_midtarsal` the left limbs, `l_thumb1..3` the thumb's metacarpal, proximal and distal,
 * `l_index1..3` (middle, ring, pinky) a finger's proximal, intermediate and distal.
 * @param {AvatarDescription} desc
 * @returns {Map<string, number>} VRM bone name → joint index
 */
export function vrmBoneJoints(desc) {
  const names = desc.joint_names;
  const hasVt10 = names.includes("vt10");
  /** @type {Record<string, string>} */
  const fixed = {
    humanoid_root: "hips",
    vl5: "spine",
    vt10: "chest",
    vt1: hasVt10 ? "upperChest" : "chest",
    vc4: "neck",
    skullbase: "head",
  };
  /** @type {Record<string, string>} */
  const limbs = {
    sternoclavicular: "Shoulder",
    shoulder: "UpperArm",
    elbow: "LowerArm",
    wrist: "Hand",
    hip: "UpperLeg",
    knee: "LowerLeg",
    ankle: "Foot",
    midtarsal: "Toes",
  };
  /** @type {Record<string, string>} */
  const fingers = { thumb: "Thumb", index: "Index", middle: "Middle", ring: "Ring", pinky: "Little" };
  /** @type {Map<string, number>} */
  const out = new Map();
  names.forEach((name, j) => {
    let bone = fixed[name];
    const m = /^([lr])_([a-z]+?)([123])?$/.exec(name);
    if (!bone && m) {
      const side = m[1] === "l" ? "left" : "right";
      if (!m[3] && limbs[m[2]]) bone = side + limbs[m[2]];
      else if (m[3] && fingers[m[2]]) {
        const k = Number(m[3]);
        const segment =
          m[2] === "thumb" ? ["Metacarpal", "Proximal", "Distal"][k - 1] : ["Proximal", "Intermediate", "Distal"][k - 1];
        bone = side + fingers[m[2]] + segment;
      }
    }
    if (bone && !out.has(bone)) out.set(bone, j);
  });
  return out;
}

/**
 * The `humanBones` a three-vrm `VRMHumanoid` takes, for a model whose nodes carry the
 * description's joint names (the server's `mesh.glb`): `{ hips: { node }, … }`.
 * @param {AvatarDescription} desc
 * @param {Object3DLike} root
 * @returns {Record<string, { node: Object3DLike }>}
 */
export function vrmHumanBones(desc, root) {
  const bones = findJoints(desc, root);
  /** @type {Record<string, { node: Object3DLike }>} */
  const out = {};
  for (const [bone, j] of vrmBoneJoints(desc)) {
    const node = bones[j];
    if (node) out[bone] = { node };
  }
  return out;
}

/**
 * Puts a model whose nodes carry the description's joint names in the avatar's bind pose (the
 * world matrices B_j its inverse bind matrices undo), as a VRM file's nodes are at rest.
 * three-vrm takes a humanoid's pose at construction as its rest, and `VRMBinding` turns bones
 * from the bind pose, so call this before `new VRMHumanoid(…)` on such a model.
 * @param {AvatarDescription} desc
 * @param {Object3DLike} root
 */
export function poseAtBind(desc, root) {
  const bones = findJoints(desc, root);
  const binds = desc.inverse_binds.map((m) => affineInverse(Float32Array.from(m)));
  for (let j = 0; j < bones.length; j++) {
    const bone = bones[j];
    if (!bone) continue;
    const p = desc.parents[j];
    const local = p >= 0 ? multiplyAffine(affineInverse(binds[p]), binds[j]) : binds[j];
    const { t, q, s } = decompose(local);
    bone.position.set(t[0], t[1], t[2]);
    bone.quaternion.set(q[0], q[1], q[2], q[3]);
    bone.scale.set(s[0], s[1], s[2]);
  }
}

/**
 * A posecast avatar bound to a three-vrm VRM through its normalised humanoid bones. Each tick
 * every humanoid bone the avatar has is turned through the rotation its joint turned through
 * from the avatar's bind pose — G_b = F · rot(W_j · B_j⁻¹) · F⁻¹, F the frame the model is in
 * (posecast faces +Z; a VRM 0.x model faces −Z) — given to three-vrm as the normalised bone's
 * local rotation G_parent(b)⁻¹ · G_b, and the hips are put where the avatar's root joint is.
 * three-vrm's `vrm.update(dt)` (or `humanoid.update()`) then turns the model's own bones; a VRM's
 * rest is its T-pose, which must be the pose of the avatar's bind (the server imports a VRM's
 * bind pose from the same file). Humanoid bones the avatar lacks follow their parent; joints
 * the avatar has and the VRM lacks are left out.
 */
export class VRMBinding {
  /**
   * @param {AvatarDescription} desc
   * @param {HumanoidLike | { humanoid: HumanoidLike, scene?: Object3DLike, meta?: { metaVersion?: string } }} vrm
   *   a three-vrm `VRM` (its `scene` then takes the placement) or a `VRMHumanoid`
   * @param {{ frame?: Quat, placementTarget?: Object3DLike | null }} [options] `frame`: the
   *   rotation from posecast's model frame to the model's (default: a half turn about Y for a
   *   VRM 0.x, whose scene three-vrm's `VRMUtils.rotateVRM0` turns, identity otherwise)
   */
  constructor(desc, vrm, options = {}) {
    this.desc = desc;
    const isVrm = "humanoid" in vrm;
    /** @type {HumanoidLike} */
    this.humanoid = isVrm ? vrm.humanoid : vrm;
    const vrm0 = isVrm && vrm.meta?.metaVersion === "0";
    /** @type {Quat} */
    this.frame = options.frame ?? (vrm0 ? [0, 1, 0, 0] : [0, 0, 0, 1]);
    this.placementTarget = options.placementTarget === undefined ? (isVrm ? vrm.scene ?? null : null) : options.placementTarget;
    const joints = vrmBoneJoints(desc);
    /** @type {{ bone: string, node: Object3DLike, joint: number | undefined, parent: number }[]} */
    this.bones = [];
    /** @type {Map<string, number>} */
    const index = new Map();
    for (const [bone, parentBone] of VRM_HUMAN_BONES) {
      const node = this.humanoid.getNormalizedBoneNode(bone);
      if (!node) continue;
      // The nearest present ancestor, as three-vrm parents normalised bones.
      let parent = -1;
      for (let p = parentBone; p !== null; p = VRM_HUMAN_BONES.find(([b]) => b === p)?.[1] ?? null) {
        const i = index.get(p);
        if (i !== undefined) {
          parent = i;
          break;
        }
      }
      index.set(bone, this.bones.length);
      this.bones.push({ bone, node, joint: joints.get(bone), parent });
    }
    /** Humanoid bones the VRM has and the avatar does not (they follow their parents). */
    this.unmatched = this.bones.filter((b) => b.joint === undefined).map((b) => b.bone);
  }

  /**
   * Poses the normalised humanoid bones (and the placement target) from a pose; three-vrm's
   * update copies them to the model.
   * @param {FramePose} pose
   */
  apply(pose) {
    const d = this.desc;
    const unplaced = { rotations: pose.rotations, translations: pose.translations, scales: pose.scales };
    const worlds = forwardKinematics(d, unplaced);
    const skins = skinningMatrices(d, worlds);
    const f = this.frame;
    const fInv = conjugate(f);
    /** @type {Quat[]} */
    const turned = [];
    for (const b of this.bones) {
      const up = b.parent >= 0 ? turned[b.parent] : /** @type {Quat} */ ([0, 0, 0, 1]);
      const g =
        b.joint === undefined ? up : quatMul(quatMul(f, quatFromMatrix(skins.subarray(16 * b.joint, 16 * b.joint + 16))), fInv);
      turned.push(g);
      const n = normalize(quatMul(conjugate(up), g));
      b.node.quaternion.set(n[0], n[1], n[2], n[3]);
      if (b.bone === "hips" && b.joint !== undefined) {
        const w = worlds.subarray(16 * b.joint, 16 * b.joint + 16);
        const p = rotate(f, [w[12], w[13], w[14]]);
        b.node.position.set(p[0], p[1], p[2]);
      }
    }
    place(this.placementTarget, pose, fInv);
  }

  /**
   * Applies the client's played-out pose of the avatar (its jitter buffer, at `nowUs`).
   * @param {PoseSource} client
   * @param {number} [nowUs]
   * @returns {FramePose | null} the pose applied, or `null` when the client has none yet
   */
  update(client, nowUs) {
    const pose = client.pose(this.desc.id, nowUs);
    if (pose) this.apply(pose);
    return pose;
  }
}

/**
 * The placement P = T(position) · R(rotation) on `target`, after the model's frame turn `fInv`.
 * @param {Object3DLike | null} target
 * @param {FramePose} pose
 * @param {Quat} fInv
 */
function place(target, pose, fInv) {
  if (!target) return;
  const p = pose.placement;
  const position = p?.position ?? [0, 0, 0];
  const rotation = quatMul(p?.rotation ?? [0, 0, 0, 1], fInv);
  target.position.set(position[0], position[1], position[2]);
  target.quaternion.set(rotation[0], rotation[1], rotation[2], rotation[3]);
}

/**
 * @param {Quat} q
 * @returns {Quat}
 */
function conjugate(q) {
  return [-q[0], -q[1], -q[2], q[3]];
}

/**
 * @param {Quat} q
 * @returns {Quat}
 */
function normalize(q) {
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
}

/**
 * `q · v · q⁻¹`.
 * @param {Quat} q
 * @param {Vec3} v
 * @returns {Vec3}
 */
function rotate(q, v) {
  const r = quatMul(quatMul(q, [v[0], v[1], v[2], 0]), conjugate(q));
  return [r[0], r[1], r[2]];
}

/**
 * The rotation of a column-major affine matrix (its columns' scale taken out), as a unit
 * quaternion (Shepperd's method: the largest of the four squares first, for accuracy).
 * @param {ArrayLike<number>} m
 * @returns {Quat}
 */
export function quatFromMatrix(m) {
  const sx = Math.hypot(m[0], m[1], m[2]) || 1;
  const sy = Math.hypot(m[4], m[5], m[6]) || 1;
  const sz = Math.hypot(m[8], m[9], m[10]) || 1;
  const m00 = m[0] / sx, m10 = m[1] / sx, m20 = m[2] / sx;
  const m01 = m[4] / sy, m11 = m[5] / sy, m21 = m[6] / sy;
  const m02 = m[8] / sz, m12 = m[9] / sz, m22 = m[10] / sz;
  const trace = m00 + m11 + m22;
  /** @type {Quat} */
  let q;
  if (trace > 0) {
    const s = 2 * Math.sqrt(trace + 1);
    q = [(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, s / 4];
  } else if (m00 > m11 && m00 > m22) {
    const s = 2 * Math.sqrt(1 + m00 - m11 - m22);
    q = [s / 4, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s];
  } else if (m11 > m22) {
    const s = 2 * Math.sqrt(1 + m11 - m00 - m22);
    q = [(m01 + m10) / s, s / 4, (m12 + m21) / s, (m02 - m20) / s];
  } else {
    const s = 2 * Math.sqrt(1 + m22 - m00 - m11);
    q = [(m02 + m20) / s, (m12 + m21) / s, s / 4, (m10 - m01) / s];
  }
  return normalize(q);
}

/**
 * The inverse of a column-major affine matrix (last row 0 0 0 1).
 * @param {Float32Array} m
 * @returns {Float32Array}
 */
function affineInverse(m) {
  const [a, b, c, , d, e, f, , g, h, i] = m;
  const det = a * (e * i - f * h) - d * (b * i - c * h) + g * (b * f - c * e);
  const k = det === 0 ? 0 : 1 / det;
  const r = new Float32Array(16);
  r[0] = (e * i - f * h) * k;
  r[1] = (c * h - b * i) * k;
  r[2] = (b * f - c * e) * k;
  r[4] = (f * g - d * i) * k;
  r[5] = (a * i - c * g) * k;
  r[6] = (c * d - a * f) * k;
  r[8] = (d * h - e * g) * k;
  r[9] = (b * g - a * h) * k;
  r[10] = (a * e - b * d) * k;
  const [tx, ty, tz] = [m[12], m[13], m[14]];
  r[12] = -(r[0] * tx + r[4] * ty + r[8] * tz);
  r[13] = -(r[1] * tx + r[5] * ty + r[9] * tz);
  r[14] = -(r[2] * tx + r[6] * ty + r[10] * tz);
  r[15] = 1;
  return r;
}

/**
 * `a · b` of two column-major affine matrices.
 * @param {Float32Array} a
 * @param {Float32Array} b
 * @returns {Float32Array}
 */
function multiplyAffine(a, b) {
  const r = new Float32Array(16);
  for (let col = 0; col < 4; col++) {
    for (let row = 0; row < 3; row++) {
      r[4 * col + row] =
        a[row] * b[4 * col] + a[4 + row] * b[4 * col + 1] + a[8 + row] * b[4 * col + 2] + (col === 3 ? a[12 + row] : 0);
    }
  }
  r[15] = 1;
  return r;
}

/**
 * Translation, rotation and scale of a column-major affine matrix without shear.
 * @param {Float32Array} m
 * @returns {{ t: Vec3, q: Quat, s: Vec3 }}
 */
function decompose(m) {
  return {
    t: [m[12], m[13], m[14]],
    q: quatFromMatrix(m),
    s: [Math.hypot(m[0], m[1], m[2]), Math.hypot(m[4], m[5], m[6]), Math.hypot(m[8], m[9], m[10])],
  };
}
