// Type declarations of posecast's three.js bindings, served at /sdk/three.d.ts beside the
// module (/sdk/three.js; `posecast/three` in the npm package). The module imports nothing from
// three: it poses the objects a page hands it, so these types name only what it touches.

import type { AvatarDescription, FramePose, Quat } from "./posecast";

/** What the bindings need of a three.js `Object3D` (a `THREE.Object3D` has all of it). */
export interface Object3DLike {
  name: string;
  quaternion: { set(x: number, y: number, z: number, w: number): unknown };
  position: { set(x: number, y: number, z: number): unknown };
  scale: { set(x: number, y: number, z: number): unknown };
  traverse(callback: (object: any) => void): void;
}

/** What `VRMBinding` needs of a three-vrm `VRMHumanoid`. */
export interface HumanoidLike {
  getNormalizedBoneNode(name: string): Object3DLike | null | undefined;
}

/** Where the bindings take poses from: a posecast `Client` (its jitter buffer's playout). */
export interface PoseSource {
  pose(id: string, nowUs?: number): FramePose | null;
}

/** A node name as three's GLTFLoader gives it (white space to `_`, `[ ] . : /` removed). */
export declare function sanitizeNodeName(name: string): string;
/** The URL of an avatar's `mesh.glb` on the server `client` is connected to. */
export declare function meshUrl(client: { url: string }, desc: AvatarDescription): string;
/** The description's joints found under `root` by name; `null` where the model has none. */
export declare function findJoints(desc: AvatarDescription, root: Object3DLike): (Object3DLike | null)[];

/**
 * A posecast avatar bound to a three.js skeleton whose bones carry the description's joint
 * names (the server's `mesh.glb`): every joint's local transform from the stream, the placement
 * on the root, so three's world matrices are posecast's forward kinematics.
 */
export declare class SkeletonBinding {
  constructor(desc: AvatarDescription, root: Object3DLike, options?: { placementTarget?: Object3DLike | null });
  readonly desc: AvatarDescription;
  /** Joint names the model has no node for. */
  readonly missing: string[];
  /** The model's meshes with morph targets, which `apply` sets the streamed weights on. */
  readonly morphMeshes: MorphMeshLike[];
  /** Poses the model from a pose, its face from the pose's morph `weights` (by target name). */
  apply(pose: FramePose): void;
  /** Applies the client's played-out pose of the avatar; the pose, or `null` when none yet. */
  update(client: PoseSource, nowUs?: number): FramePose | null;
}

/** What the face needs of a three.js mesh with morph targets. */
export interface MorphMeshLike {
  morphTargetDictionary: Record<string, number>;
  morphTargetInfluences: number[];
}

/** The meshes under `root` with morph targets. */
export declare function morphMeshes(root: Object3DLike): MorphMeshLike[];

/**
 * Sets streamed morph weights (channel name → weight) on every mesh target of that name. For a
 * three-vrm `VRM`, call it after `vrm.update()`, which resets the targets its expressions bind.
 */
export declare function applyMorphWeights(meshes: MorphMeshLike[], weights: Record<string, number>): void;

/** VRM 1.0 humanoid bones, parents first, each with its humanoid parent. */
export declare const VRM_HUMAN_BONES: [string, string | null][];
/** VRM humanoid bone name → joint index, by posecast's normalised (H-Anim) joint names. */
export declare function vrmBoneJoints(desc: AvatarDescription): Map<string, number>;
/** The `humanBones` for three-vrm's `new VRMHumanoid(…)` on a model named as the description. */
export declare function vrmHumanBones(desc: AvatarDescription, root: Object3DLike): Record<string, { node: Object3DLike }>;
/** Puts a model named as the description in the avatar's bind pose (a VRM's rest is its bind). */
export declare function poseAtBind(desc: AvatarDescription, root: Object3DLike): void;
/** The rotation of a column-major affine matrix, `[x, y, z, w]`. */
export declare function quatFromMatrix(m: ArrayLike<number>): Quat;

/**
 * A posecast avatar bound to a three-vrm VRM through its normalised humanoid bones: each bone
 * turned through the rotation its joint turned through from the avatar's bind pose, the hips
 * where the avatar's root is. Call three-vrm's `vrm.update(dt)` after `update`.
 */
export declare class VRMBinding {
  constructor(
    desc: AvatarDescription,
    vrm: HumanoidLike | { humanoid: HumanoidLike; scene?: Object3DLike; meta?: { metaVersion?: string } },
    options?: { frame?: Quat; placementTarget?: Object3DLike | null },
  );
  readonly desc: AvatarDescription;
  /** Humanoid bones the VRM has and the avatar does not (they follow their parents). */
  readonly unmatched: string[];
  apply(pose: FramePose): void;
  update(client: PoseSource, nowUs?: number): FramePose | null;
}
