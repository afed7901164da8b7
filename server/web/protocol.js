// @ts-check
// The websocket protocol's JSON shapes (proto/PROTOCOL.md; Rust: posecast-proto `msg.rs`,
// `command.rs`, `description.rs`), as JSDoc types for the dashboard's type check. Types only:
// nothing imports this file at run time, so the server does not serve it.
//
// Kept honest by check/samples.js: `tests/web/` writes there what the Rust types serialise,
// each sample `@satisfies` its type here, so tsc fails when a field is missing, extra or of
// another type on either side.

export {};

/** @typedef {[number, number, number]} Vec3 */
/** @typedef {[number, number, number, number]} Quat `[x, y, z, w]` */
/** @typedef {"binary" | "json"} Encoding */

/**
 * @typedef {object} Access What the hello's token allows (`welcome.access`).
 * @property {boolean} view
 * @property {boolean} control
 * @property {string} [name] The token's name, when one was accepted.
 * @property {string[]} [scenes] Only these scenes.
 * @property {string[]} [avatars] Only these avatars.
 */

/**
 * @typedef {object} Placement Where an avatar stands: `P = T(position) · R(rotation)`.
 * @property {Vec3} position Metres, Y up.
 * @property {Quat} rotation
 */

/**
 * @typedef {object} FadeState A cross-fade in progress.
 * @property {string} from The clip fading out.
 * @property {string} [from_asset] Its rig, when retargeted.
 * @property {number} elapsed Seconds done at the state's tick.
 * @property {number} duration Seconds.
 */

/** @typedef {"in_place" | "accumulate"} RootMotion */

/**
 * @typedef {object} AvatarState An avatar as `get_avatar`, `list_scenes` and `avatar_changed` report it.
 * @property {string} avatar
 * @property {string} scene
 * @property {string} asset The rig.
 * @property {string | null} clip
 * @property {string | null} clip_asset The rig the clip was retargeted from.
 * @property {number} time Clip time, seconds (at the scene's tick `seq` for `avatar_changed`).
 * @property {number} speed
 * @property {boolean} looping
 * @property {boolean} paused
 * @property {string[]} overrides Joints with an override.
 * @property {Placement} placement
 * @property {RootMotion} [root_motion]
 * @property {boolean} [driven]
 * @property {string} [recording]
 * @property {Record<string, number>} [blend_shapes]
 * @property {FadeState} [fade]
 */

/**
 * @typedef {object} SceneInfo
 * @property {string} scene
 * @property {AvatarState[]} avatars
 * @property {number} subscribers
 */

/**
 * @typedef {object} ClipInfo
 * @property {string} name
 * @property {number} duration Seconds.
 */

/**
 * @typedef {object} AssetInfo A loaded rig (`list_assets`).
 * @property {string} name
 * @property {number} joints
 * @property {ClipInfo[]} clips
 * @property {string[]} pipeline
 * @property {boolean} humanoid Whether it has the H-Anim neutral pose and takes humanoid clips.
 * @property {number} mapped Joints with an H-Anim name.
 * @property {string[]} [notes] What the importer skipped or approximated.
 */

/**
 * @typedef {object} DofInfo
 * @property {number} value Radians (metres for translational DOFs).
 * @property {number | null} min
 * @property {number | null} max
 */

/**
 * @typedef {object} JointInfo `get_joint`'s answer.
 * @property {string} joint
 * @property {string | null} parent
 * @property {string | null} joint_type
 * @property {DofInfo[]} dofs
 * @property {Quat} rotation
 * @property {boolean} overridden
 */

/**
 * @typedef {object} AvatarDescription An avatar's rig (`description.avatar`).
 * @property {string} id
 * @property {number} num
 * @property {string} name
 * @property {string[]} joint_names
 * @property {number[]} parents Parent index per joint, -1 for a root.
 * @property {Vec3[]} rest_translations
 * @property {Quat[]} rest_rotations
 * @property {Vec3[]} rest_scales
 * @property {number[][]} inverse_binds 16 floats per joint, column-major.
 * @property {number[]} translated_joints
 * @property {number[]} scaled_joints
 * @property {string | null} mesh_url
 * @property {string} [clip]
 * @property {string} hash
 */

/**
 * @typedef {object} AvatarPose One avatar's pose in a JSON frame.
 * @property {string} avatar
 * @property {string} hash
 * @property {Quat[]} rotations
 * @property {Vec3[]} translations
 * @property {Vec3[]} scales
 * @property {Placement} placement
 * @property {number[]} [joints] With a joint set: the joints `rotations` are of.
 */

/**
 * @typedef {object} ProtocolError
 * @property {string} code
 * @property {string} message
 * @property {number} [id]
 * @property {number} [retry_after_ms]
 */

/** @typedef {{type: "welcome", version: number, encoding: Encoding, server: string, tick_rate: number, server_time_us: number, access: Access}} WelcomeMsg */
/** @typedef {{depth: number} | {names: string[]}} JointSet */
/** @typedef {{type: "subscribed", scene: string, scene_num: number, rate?: number, joints?: JointSet}} SubscribedMsg */
/** @typedef {{type: "unsubscribed", scene: string}} UnsubscribedMsg */
/** @typedef {{type: "description", scene: string, avatar: AvatarDescription}} DescriptionMsg */
/** @typedef {{type: "avatar_removed", scene: string, avatar: string}} AvatarRemovedMsg */
/** @typedef {{type: "scenes", scenes: SceneInfo[]}} ScenesMsg */
/** @typedef {{type: "scene_created", scene: string}} SceneCreatedMsg */
/** @typedef {{type: "scene_deleted", scene: string}} SceneDeletedMsg */
/** @typedef {{type: "avatar_changed", scene: string, seq: number, avatar: AvatarState}} AvatarChangedMsg */
/** @typedef {{type: "pong", id: number, client_time_us: number, server_time_us: number}} PongMsg */
/** @typedef {{type: "ack", id: number, result: unknown}} AckMsg */
/** @typedef {{type: "frame", scene: string, seq: number, server_time_us: number, avatars: AvatarPose[]}} FrameMsg */
/** @typedef {{type: "error"} & ProtocolError} ErrorMsg */

/**
 * @typedef {WelcomeMsg | SubscribedMsg | UnsubscribedMsg | DescriptionMsg | AvatarRemovedMsg
 *   | ScenesMsg | SceneCreatedMsg | SceneDeletedMsg | AvatarChangedMsg | PongMsg | AckMsg
 *   | FrameMsg | ErrorMsg} ServerMsg Every text message the server sends.
 */

/**
 * @typedef {{op: "list_scenes"} | {op: "list_assets"} | {op: "get_avatar", avatar: string}
 *   | {op: "get_joint", avatar: string, joint: string}
 *   | {op: "create_scene", scene: string} | {op: "delete_scene", scene: string}
 *   | {op: "add_avatar", scene: string, asset: string, avatar?: string, clip?: string, position?: Vec3, rotation?: Quat}
 *   | {op: "remove_avatar", avatar: string}
 *   | {op: "place_avatar", avatar: string, position: Vec3, rotation: Quat, duration?: number}
 *   | {op: "play", avatar: string, clip: string, from_asset?: string, speed?: number, looping?: boolean, start?: number, fade?: number, root_motion?: RootMotion}
 *   | {op: "pause" | "resume" | "stop", avatar: string}
 *   | {op: "seek", avatar: string, time: number}
 *   | {op: "set_speed", avatar: string, speed: number}
 *   | {op: "set_joint_rotation" | "rotate_joint_local" | "rotate_joint_world", avatar: string, joint: string, rotation: Quat}
 *   | {op: "set_joint_dofs", avatar: string, joint: string, values: number[]}
 *   | {op: "release", avatar: string, joint?: string}} Command The commands the dashboard sends.
 */

/**
 * @typedef {{type: "hello", version: number, encoding: Encoding, token?: string, client?: string}
 *   | {type: "subscribe", scene: string, avatars?: string[], rate?: number, joints?: JointSet}
 *   | {type: "unsubscribe", scene: string}
 *   | {type: "ping", id: number, client_time_us: number}
 *   | {type: "command", id: number, command: Command}
 *   | {type: "watch_scenes"} | {type: "unwatch_scenes"}} ClientMsg What the dashboard sends.
 */
