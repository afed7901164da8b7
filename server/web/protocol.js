// @ts-check
// The websocket protocol's JSON shapes (proto/PROTOCOL.md) for the dashboard's type check:
// names for the types GENERATED from the server's Rust types (../sdk/protocol.d.ts, written by
// `cargo run -p posecast-tools --bin gen-ts`; tools/tests/ts_types.rs fails when it is out of
// date). Types only: nothing imports this file at run time, so the server does not serve it.
//
// Kept honest by check/samples.js as well: `tests/web/` writes there what the Rust types
// serialise, each sample `@satisfies` its type here, so tsc fails when a generated type does
// not accept what the server really sends.

export {};

/** @typedef {[number, number, number]} Vec3 */
/** @typedef {[number, number, number, number]} Quat `[x, y, z, w]` */
/** @typedef {import("../sdk/protocol").Encoding} Encoding */
/** @typedef {import("../sdk/protocol").Access} Access What the hello's token allows (`welcome.access`). */
/** @typedef {import("../sdk/protocol").Placement} Placement Where an avatar stands: `P = T(position) · R(rotation)`. */
/** @typedef {import("../sdk/protocol").FadeState} FadeState A cross-fade in progress. */
/** @typedef {import("../sdk/protocol").RootMotion} RootMotion */
/** @typedef {import("../sdk/protocol").AvatarState} AvatarState An avatar as `get_avatar`, `list_scenes` and `avatar_changed` report it. */
/** @typedef {import("../sdk/protocol").SceneInfo} SceneInfo */
/** @typedef {import("../sdk/protocol").Viewer} Viewer Connections watching a scene under one token name. */
/** @typedef {import("../sdk/protocol").Driver} Driver Who drives an avatar live, and how. */
/** @typedef {import("../sdk/protocol").ClipInfo} ClipInfo */
/** @typedef {import("../sdk/protocol").AssetInfo} AssetInfo A loaded rig (`list_assets`). */
/** @typedef {import("../sdk/protocol").DofInfo} DofInfo */
/** @typedef {import("../sdk/protocol").JointInfo} JointInfo `get_joint`'s answer. */
/** @typedef {import("../sdk/protocol").AvatarDescription} AvatarDescription An avatar's rig (`description.avatar`). */
/** @typedef {import("../sdk/protocol").AvatarPoseJson} AvatarPose One avatar's pose in a JSON frame. */
/** @typedef {import("../sdk/protocol").ProtocolError} ProtocolError */
/** @typedef {import("../sdk/protocol").JointSet} JointSet */
/** @typedef {import("../sdk/protocol").Command} Command Every command (`op` and its fields). */
/** @typedef {import("../sdk/protocol").CommandResult} CommandResult A command's result, tagged with its `kind`. */
/** @typedef {import("../sdk/protocol").ServerMsg} ServerMsg Every text message the server sends. */
/** @typedef {import("../sdk/protocol").ClientMsg} ClientMsg Every message a client sends. */

/** @typedef {Extract<ServerMsg, {type: "welcome"}>} WelcomeMsg */
/** @typedef {Extract<ServerMsg, {type: "subscribed"}>} SubscribedMsg */
/** @typedef {Extract<ServerMsg, {type: "unsubscribed"}>} UnsubscribedMsg */
/** @typedef {Extract<ServerMsg, {type: "description"}>} DescriptionMsg */
/** @typedef {Extract<ServerMsg, {type: "avatar_removed"}>} AvatarRemovedMsg */
/** @typedef {Extract<ServerMsg, {type: "scenes"}>} ScenesMsg */
/** @typedef {Extract<ServerMsg, {type: "scene_created"}>} SceneCreatedMsg */
/** @typedef {Extract<ServerMsg, {type: "viewers"}>} ViewersMsg */
/** @typedef {Extract<ServerMsg, {type: "scene_deleted"}>} SceneDeletedMsg */
/** @typedef {Extract<ServerMsg, {type: "avatar_changed"}>} AvatarChangedMsg */
/** @typedef {Extract<ServerMsg, {type: "pong"}>} PongMsg */
/** @typedef {Extract<ServerMsg, {type: "ack"}>} AckMsg An `ack` of protocol version 3: the result tagged with its `kind`. */
/** @typedef {Extract<ServerMsg, {type: "frame"}>} FrameMsg */
/** @typedef {Extract<ServerMsg, {type: "error"}>} ErrorMsg */

/** @typedef {import("../sdk/protocol").TakeInfo} TakeInfo A take of a whole scene (`record_scene`, `list_takes`, `get_take`). */
/** @typedef {import("../sdk/protocol").ReplayState} ReplayState Where a replay is (`replay`, `control_replay`). */
