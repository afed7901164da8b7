// What a TypeScript user of /sdk/three.js writes, type-checked against three.d.ts alone
// (scripts/check-web). three's own objects are stood in for by their shapes.

import { Client, type AvatarDescription } from "../posecast.js";
import { SkeletonBinding, VRMBinding, meshUrl, poseAtBind, vrmHumanBones, type Object3DLike } from "../three.js";

declare const desc: AvatarDescription;
declare const model: Object3DLike;
const client = new Client({ url: "ws://localhost:8080/ws" });
const url: string = meshUrl(client, desc);
const binding = new SkeletonBinding(desc, model);
const missing: string[] = binding.missing;
binding.update(client);
poseAtBind(desc, model);
const bones: Record<string, { node: Object3DLike }> = vrmHumanBones(desc, model);
const vrm = new VRMBinding(desc, { humanoid: { getNormalizedBoneNode: () => null }, scene: model });
vrm.update(client, 0);
// @ts-expect-error a binding needs a description
new SkeletonBinding(model, model);
void url;
void missing;
void bones;
