// The JSON messages of the posecast websocket protocol (version 5) and of its REST answers, as
// TypeScript types. GENERATED from the Rust types of posecast-proto (`proto/src/ts.rs`): do not
// edit; run `cargo run -p posecast-tools --bin gen-ts` after changing them. proto/PROTOCOL.md
// explains every message. Served at /sdk/protocol.d.ts; the SDK's posecast.d.ts builds on it.

/**
 * Everything a client may send.
 */
export type ClientMsg = { "type": "hello", 
/**
 * One of `SUPPORTED_VERSIONS` (1: binary frames are `crate::frame`; 2 and 3:
 * `crate::frame2`; 3: command results tagged with their kind, `ServerMsg::Ack`).
 */
version: number, 
/**
 * The encoding of pose frames the client wants.
 */
encoding: Encoding, 
/**
 * A view or control token, when the server requires one.
 */
token?: string | null, 
/**
 * Free text naming the client, for logs.
 */
client?: string | null, } | { "type": "subscribe", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * Only these avatars, or all.
 */
avatars?: Array<AvatarId> | null, 
/**
 * Frames per second wanted (e.g. 30, 20, 15 or 10 for a distant or small view);
 * absent: every tick. The server sends every `round(tick_rate / rate)`-th tick (at
 * least every tick) and says the rate it chose in `subscribed`.
 */
rate?: number | null, 
/**
 * Only these joints of every avatar (`crate::subset`: `{"depth": 3}` or
 * `{"names": […]}`, with their ancestors); absent: all of them.
 */
joints?: JointSet | null, 
/**
 * Morph weights in the frames (binary frames from protocol version 4, and JSON);
 * `false` leaves them out, for a view that shows no faces (a distant or body-only
 * one). Default `true`.
 */
morph_weights?: boolean | null, 
/**
 * How finely binary frames code each joint (protocol version 5;
 * `crate::precision`): a worst angle, a world-space bound, a translation bound —
 * so a distant view, a crowd or a thin link pays less. Absent: the finest.
 */
precision?: Precision | null, } | { "type": "unsubscribe", 
/**
 * The scene.
 */
scene: SceneId, } | { "type": "ping", 
/**
 * Chosen by the client, echoed back.
 */
id: number, 
/**
 * The client's clock when sending, in microseconds (any epoch).
 */
client_time_us: number, } | { "type": "command", 
/**
 * Chosen by the client, echoed back.
 */
id: number, 
/**
 * What to do.
 */
command: Command, 
/**
 * Chosen by the client (1–128 visible ASCII characters, unique per command, e.g. a
 * UUID): a command sent again with the same key after an unknown outcome (a timeout,
 * a dropped connection) is answered with the first one's result and applied at most
 * once, on whichever server of a cluster it reaches (PROTOCOL.md, "Idempotency").
 */
idempotency_key?: string | null, } | { "type": "watch_scenes" } | { "type": "unwatch_scenes" } | { "type": "pose", 
/**
 * The driven avatar.
 */
avatar: AvatarId, 
/**
 * Local rotations `[x, y, z, w]` of the source rig's joints, by joint name; joints not
 * listed keep their last value. Absent (or empty) for a tracker drive.
 */
rotations?: { [key in string]: [number, number, number, number] }, 
/**
 * The source root joint's local translation, metres.
 */
root_position?: [number, number, number] | null, 
/**
 * The driver's clock when the pose was captured, µs (any epoch).
 */
time_us?: number | null, 
/**
 * Morph weights by name (a morph channel of the driven avatar or a standard
 * expression name, as `set_morph_weights` takes them), each in `[0, 1]`; channels not
 * named keep their weights.
 */
weights?: { [key in string]: number }, 
/**
 * A tracker drive's tracker transforms in the scene's space, by tracker name (of the
 * `drive`'s `trackers`); trackers not named keep their last transform.
 */
trackers?: { [key in string]: TrackerTransform }, };

/**
 * Everything the server may send as a text message.
 */
export type ServerMsg = { "type": "welcome", 
/**
 * The protocol version in use.
 */
version: number, 
/**
 * The encoding of pose frames on this connection.
 */
encoding: Encoding, 
/**
 * Server name and version, for logs.
 */
server: string, 
/**
 * Ticks (pose frames) per second of every scene.
 */
tick_rate: number, 
/**
 * The server clock when sending, microseconds since the Unix epoch.
 */
server_time_us: number, 
/**
 * What the hello's token (or its absence) allows on this connection.
 */
access: Access, } | { "type": "subscribed", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * The scene's number in binary frames.
 */
scene_num: number, 
/**
 * Frames per second this subscription gets (the tick rate divided by a whole number).
 */
rate?: number | null, 
/**
 * The joint set its frames carry (as subscribed; absent: every joint).
 */
joints?: JointSet | null, 
/**
 * The precision its frames are coded at (as subscribed; absent: the finest).
 */
precision?: Precision | null, } | { "type": "unsubscribed", 
/**
 * The scene.
 */
scene: SceneId, } | { "type": "description", 
/**
 * The scene the avatar is in.
 */
scene: SceneId, 
/**
 * The rig.
 */
avatar: AvatarDescription, } | { "type": "avatar_removed", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "type": "scenes", 
/**
 * The scenes.
 */
scenes: Array<SceneInfo>, } | { "type": "scene_created", 
/**
 * The scene.
 */
scene: SceneId, } | { "type": "scene_deleted", 
/**
 * The scene.
 */
scene: SceneId, } | { "type": "avatar_changed", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * The scene's tick at which `avatar.time` (and a fade's `elapsed`) hold: at tick
 * `s` the clip time is `time + (s − seq) / tick_rate · speed` (wrapped or clamped
 * to the clip) while playing.
 */
seq: number, 
/**
 * The avatar's state, as `get_avatar` answers.
 */
avatar: AvatarState, } | { "type": "viewers", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * Its subscribers by token name.
 */
viewers: Array<Viewer>, } | { "type": "pong", 
/**
 * The ping's id.
 */
id: number, 
/**
 * The ping's client time, echoed.
 */
client_time_us: number, 
/**
 * The server clock when answering, microseconds since the Unix epoch.
 */
server_time_us: number, } | { "type": "ack", 
/**
 * The command's id.
 */
id: number, } & ({ "kind": "scenes", "result": Array<SceneInfo> } | { "kind": "assets", "result": Array<AssetInfo> } | { "kind": "avatar", "result": AvatarState } | { "kind": "joint", "result": JointInfo } | { "kind": "drive", "result": DriveInfo } | { "kind": "recorded", "result": RecordingInfo } | { "kind": "asset", "result": AssetDetail } | { "kind": "pose", "result": AvatarPoseJson } | { "kind": "calibration", "result": CalibrationInfo } | { "kind": "takes", "result": Array<TakeInfo> } | { "kind": "take", "result": TakeInfo } | { "kind": "replay", "result": ReplayState } | { "kind": "scene_created", "result": { 
/**
 * The new scene.
 */
scene: SceneId, } } | { "kind": "avatar_added", "result": { 
/**
 * The new avatar's id (chosen by the server when the command named none).
 */
avatar: AvatarId, } } | { "kind": "dofs", "result": { 
/**
 * The joint's new local rotation.
 */
rotation: [number, number, number, number], 
/**
 * Its DOF values, in the joint's order, after limits.
 */
values: Array<number>, } } | { "kind": "rotation", "result": { 
/**
 * The joint's new local rotation.
 */
rotation: [number, number, number, number], } } | { "kind": "done", "result": null }) | { "type": "frame" } & FrameJson | { "type": "error" } & ProtocolError;

/**
 * Something a dashboard or application asks the server to do.
 */
export type Command = { "op": "list_scenes" } | { "op": "list_assets" } | { "op": "get_asset", 
/**
 * The rig's asset name.
 */
asset: string, } | { "op": "configure_asset", 
/**
 * The upload's name (a multi-skin glTF's `name`, not `name#skin`).
 */
asset: string, 
/**
 * The options, replacing the asset's (absent fields take their defaults).
 */
options: PipelineOptions, } | { "op": "get_avatar", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "get_joint", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The joint's name.
 */
joint: string, } | { "op": "sample_pose", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The clip (of the avatar's rig, or of `from_asset`'s, retargeted); absent: the
 * avatar's current clip.
 */
clip?: string | null, 
/**
 * The rig `clip` belongs to, when another (as in `play`).
 */
from_asset?: string | null, 
/**
 * Seconds from the clip's start (wrapped for a looping clip, clamped otherwise).
 */
time: number, } | { "op": "create_scene", 
/**
 * Its id (letters, digits, `-`, `_`; at most 64).
 */
scene: SceneId, } | { "op": "delete_scene", 
/**
 * The scene.
 */
scene: SceneId, } | { "op": "add_avatar", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * The rig's asset name.
 */
asset: string, 
/**
 * The avatar's id; chosen by the server when absent.
 */
avatar?: AvatarId | null, 
/**
 * The clip to start playing, if any.
 */
clip?: string | null, 
/**
 * World position `[x, y, z]` in metres; default the origin.
 */
position?: [number, number, number] | null, 
/**
 * World rotation `[x, y, z, w]`; default none.
 */
rotation?: [number, number, number, number] | null, } | { "op": "remove_avatar", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "play", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The clip's name.
 */
clip: string, 
/**
 * Take the clip from another loaded rig and retarget it; absent: the avatar's own rig.
 */
from_asset?: string | null, 
/**
 * Playback speed (1 = authored; negative plays backwards). Default 1.
 */
speed?: number | null, 
/**
 * Loop (default) or hold the last pose.
 */
looping?: boolean | null, 
/**
 * Start offset into the clip, seconds from its start. Default 0.
 */
start?: number | null, 
/**
 * Cross-fade duration in seconds. Default 0.25.
 */
fade?: number | null, 
/**
 * What the clip's root translation does; default in place for looping clips,
 * accumulate (as authored) otherwise.
 */
root_motion?: RootMotion | null, } | { "op": "pause", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "resume", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "seek", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Clip time.
 */
time: number, } | { "op": "set_speed", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * New speed.
 */
speed: number, } | { "op": "stop", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "play_layer", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The layer's name (e.g. `upper`, `breathing`).
 */
layer: string, 
/**
 * The clip's name.
 */
clip: string, 
/**
 * Take the clip from another loaded rig and retarget it; absent: the avatar's own rig.
 */
from_asset?: string | null, 
/**
 * The joints the layer owns; absent: all.
 */
mask?: JointMask | null, 
/**
 * Add the clip's rotations (away from the reference pose) on top instead of replacing.
 */
additive?: boolean, 
/**
 * What an additive layer's rotations are taken away from: the rig's rest pose
 * (default) or the clip's first frame (a clip authored as whole poses, such as an
 * idle, then adds only its motion).
 */
reference?: AdditiveReference, 
/**
 * How much of the layer shows, 0 to 1 (default 1).
 */
weight?: number | null, 
/**
 * Playback speed (default 1).
 */
speed?: number | null, 
/**
 * Loop (default) or hold the last pose.
 */
looping?: boolean | null, 
/**
 * Start offset into the clip, seconds. Default 0.
 */
start?: number | null, 
/**
 * Fade-in (or cross-fade) seconds. Default 0.25.
 */
fade?: number | null, } | { "op": "stop_layer", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The layer's name.
 */
layer: string, 
/**
 * Fade-out seconds. Default 0.25.
 */
fade?: number | null, } | { "op": "set_joint_rotation", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Joint name.
 */
joint: string, 
/**
 * Local rotation `[x, y, z, w]`.
 */
rotation: [number, number, number, number], } | { "op": "set_joint_dofs", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Joint name.
 */
joint: string, 
/**
 * One value per DOF of the joint's type.
 */
values: Array<number>, } | { "op": "rotate_joint_local", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Joint name.
 */
joint: string, 
/**
 * The increment `[x, y, z, w]`.
 */
rotation: [number, number, number, number], } | { "op": "rotate_joint_world", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Joint name.
 */
joint: string, 
/**
 * The world-space rotation `[x, y, z, w]`.
 */
rotation: [number, number, number, number], } | { "op": "release", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Joint name, or all.
 */
joint?: string | null, } | { "op": "set_ik_goal", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The chain's end joint.
 */
effector: string, 
/**
 * Where it goes `[x, y, z]`, metres (each within ±10⁶).
 */
position: [number, number, number], 
/**
 * Its rotation `[x, y, z, w]` in the same frame (finite, non-zero; normalised).
 */
rotation?: [number, number, number, number] | null, 
/**
 * How much of the solve applies, 0 to 1 (default 1).
 */
weight?: number | null, 
/**
 * A point the limb's middle joint (elbow, knee) bends toward, in the same frame.
 */
pole?: [number, number, number] | null, 
/**
 * The joint (of this avatar or another of its scene) whose frame the values are in.
 */
relative_to?: JointRef | null, 
/**
 * Joints in the chain, the effector included (2 to 32): solved by FABRIK; absent for a
 * limb end, its limb in closed form.
 */
chain?: number | null, } | { "op": "clear_ik_goal", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The effector whose goal ends.
 */
effector?: string | null, 
/**
 * Seconds to let go over (finite, ≥ 0; default 0.25, `play`'s default fade; 0: at once).
 */
fade?: number | null, } | { "op": "look_at", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The point looked at `[x, y, z]`, metres.
 */
target: [number, number, number], 
/**
 * How much of the turn applies, 0 to 1 (default 1; 0 lets the gaze go).
 */
weight?: number | null, 
/**
 * The joint whose frame `target` is in.
 */
relative_to?: JointRef | null, } | { "op": "set_morph_weights", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Name → weight.
 */
weights: { [key in string]: number }, 
/**
 * Every channel not named goes to 0 first (default: they keep their weights).
 */
reset?: boolean, } | { "op": "set_expression", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * A standard expression (`happy`, `blink`, `aa`, `jawOpen`, `viseme_PP`, …) or one of
 * the avatar's morph channels.
 */
expression: string, 
/**
 * How much, 0 to 1 (default 1).
 */
weight?: number | null, } | { "op": "place_avatar", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * World position `[x, y, z]`, metres (each within ±`crate::placement::MAX_PLACEMENT_METRES`).
 */
position: [number, number, number], 
/**
 * World rotation `[x, y, z, w]` (normalised; must be finite and non-zero).
 */
rotation: [number, number, number, number], 
/**
 * Seconds to get there (finite, ≥ 0).
 */
duration?: number | null, } | { "op": "drive", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The rig (asset) whose joints the poses name; absent: the avatar's own rig.
 */
source?: string | null, 
/**
 * What the avatar does when the driver leaves, goes silent or releases: return to
 * its clip (default) or hold the last pose.
 */
on_release?: OnRelease | null, 
/**
 * The joints the driver owns (`{"joints": ["r_sternoclavicular"]}`: the right arm):
 * its poses set only these, and the avatar's clip and layers keep the rest; absent:
 * every joint. The root's translation follows the driver only when it owns the root.
 */
joints?: JointMask | null, 
/**
 * Tracker driving: the trackers this driver's poses give, in the order binary poses
 * index them — `head`, `l_hand` and `r_hand` always; `hips`, `l_foot`, `r_foot` and
 * joints of the avatar's rig (by its own or H-Anim name) optionally; at most
 * `crate::trackers::MAX_TRACKERS`, no name twice. Poses then carry tracker
 * transforms in the scene's space (`trackers`), not rotations, and the server solves
 * the avatar's whole body from them every tick. Only on the avatar's own rig (no
 * `source`). Absent: poses carry local rotations.
 */
trackers?: Array<string> | null, 
/**
 * With `trackers`: what moves the legs (default `planted`: feet stand where they are
 * planted and step when the hips move away, or follow foot trackers).
 */
legs?: Legs | null, 
/**
 * With `legs: "locomotion"`: the avatar's clips the legs play, each with the speed
 * (m/s) its walk covers; the server picks the one nearest the hips' speed and plays it
 * at the matching rate on a `@locomotion` layer over the legs.
 */
locomotion?: Array<LocomotionClip> | null, } | { "op": "calibrate_trackers", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The pose the user holds (default `neutral`: standing, arms at the sides).
 */
pose?: CalibrationPose | null, } | { "op": "release_drive", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "record", 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The new clip's name (an id: 1–64 letters, digits, `-`, `_`, `.`), not yet a clip of
 * the avatar's rig.
 */
clip: string, 
/**
 * Longest recording, seconds of scene time (default and most: the server's limit).
 */
max_seconds?: number | null, } | { "op": "stop_recording", 
/**
 * The avatar.
 */
avatar: AvatarId, } | { "op": "delete_clip", 
/**
 * The rig.
 */
asset: string, 
/**
 * The recorded clip.
 */
clip: string, } | { "op": "delete_asset", 
/**
 * The upload's name.
 */
asset: string, } | { "op": "record_scene", 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * The take's name (an id: 1–64 letters, digits, `-`, `_`, `.`), not yet a take.
 */
take: string, 
/**
 * Longest take, seconds of scene time.
 */
max_seconds?: number | null, } | { "op": "stop_recording_scene", 
/**
 * The scene.
 */
scene: SceneId, } | { "op": "list_takes" } | { "op": "get_take", 
/**
 * The take.
 */
take: string, } | { "op": "delete_take", 
/**
 * The take.
 */
take: string, } | { "op": "replay", 
/**
 * The take.
 */
take: string, 
/**
 * The new scene's id.
 */
scene: SceneId, 
/**
 * Take seconds per scene second (default 1; 0.01–100).
 */
speed?: number | null, 
/**
 * Start again at the beginning after the end (default: hold the last frame).
 */
loop?: boolean | null, 
/**
 * Where to start, seconds into the take (default 0).
 */
from?: number | null, } | { "op": "control_replay", 
/**
 * The replay's scene.
 */
scene: SceneId, 
/**
 * Seek to this time, seconds into the take (clamped to it).
 */
time?: number | null, 
/**
 * Pause (`true`) or resume (`false`).
 */
paused?: boolean | null, 
/**
 * Take seconds per scene second (0.01–100).
 */
speed?: number | null, 
/**
 * Loop at the end.
 */
loop?: boolean | null, };

/**
 * What a successful command returns, one variant per shape. Tagged: `kind` names the shape
 * (snake_case, e.g. `avatar_added`) and `result` holds the value — an array or an object;
 * `null` in an `ack` or a REST answer for `CommandResult::Done` (these write
 * `CommandResult::to_tagged_value`), absent in serde's own form (cluster messages, stored
 * answers). An `ack` of protocol version 1 or 2 carries the bare value alone
 * (`CommandResult::to_value`), which `CommandResult::from_bare` reads back by its shape.
 */
export type CommandResult = { "kind": "scenes", "result": Array<SceneInfo> } | { "kind": "assets", "result": Array<AssetInfo> } | { "kind": "avatar", "result": AvatarState } | { "kind": "joint", "result": JointInfo } | { "kind": "drive", "result": DriveInfo } | { "kind": "recorded", "result": RecordingInfo } | { "kind": "asset", "result": AssetDetail } | { "kind": "pose", "result": AvatarPoseJson } | { "kind": "calibration", "result": CalibrationInfo } | { "kind": "takes", "result": Array<TakeInfo> } | { "kind": "take", "result": TakeInfo } | { "kind": "replay", "result": ReplayState } | { "kind": "scene_created", "result": { 
/**
 * The new scene.
 */
scene: SceneId, } } | { "kind": "avatar_added", "result": { 
/**
 * The new avatar's id (chosen by the server when the command named none).
 */
avatar: AvatarId, } } | { "kind": "dofs", "result": { 
/**
 * The joint's new local rotation.
 */
rotation: [number, number, number, number], 
/**
 * Its DOF values, in the joint's order, after limits.
 */
values: Array<number>, } } | { "kind": "rotation", "result": { 
/**
 * The joint's new local rotation.
 */
rotation: [number, number, number, number], } } | { "kind": "done", "result": null };

/**
 * A typed error: a stable machine-readable code and a human message.
 */
export type ProtocolError = { 
/**
 * What kind of error.
 */
code: ErrorCode, 
/**
 * What happened, for people.
 */
message: string, 
/**
 * The id of the command that failed, if a command failed.
 */
id?: number | null, 
/**
 * With `rate_limited`: milliseconds until a command would be accepted again.
 */
retry_after_ms?: number | null, 
/**
 * What the error is about, in fields a client can act on (the scene, avatar, rig, clip,
 * joint, expression or take it could not find; the quota that refused): absent when the
 * message is all there is.
 */
details?: ErrorDetails | null, };

/**
 * The subject of an error (`ProtocolError::details`): each field present only when the
 * error is about it.
 */
export type ErrorDetails = { 
/**
 * The scene (`unknown_scene`; `unknown_avatar` for an avatar not in it).
 */
scene?: SceneId | null, 
/**
 * The avatar (`unknown_avatar`).
 */
avatar?: AvatarId | null, 
/**
 * The rig (asset): `unknown_asset`, `no_mesh`, and the rig of `unknown_clip`.
 */
asset?: string | null, 
/**
 * The clip (`unknown_clip`).
 */
clip?: string | null, 
/**
 * The joint asked for (`unknown_joint`).
 */
joint?: string | null, 
/**
 * The morph target or expression asked for (`unknown_expression`).
 */
expression?: string | null, 
/**
 * The take (`unknown_take`).
 */
take?: string | null, 
/**
 * The command's field whose value is refused (`invalid_value`), when the refusal is
 * about one: its name in the command (`speed`, `weight`, `time`).
 */
field?: string | null, 
/**
 * The limit that refused (`quota_exceeded`): its name, as in `/metrics`.
 */
quota?: string | null, 
/**
 * That limit's value, as people read it.
 */
limit?: string | null, };

/**
 * Stable error codes. New codes may be added in later versions; clients treat an unknown code
 * as a generic failure.
 */
export type ErrorCode = "bad_message" | "unexpected_binary" | "message_too_large" | "unsupported_version" | "not_allowed_now" | "unknown_scene" | "unknown_avatar" | "unknown_clip" | "unknown_joint" | "invalid_value" | "unauthorized" | "forbidden" | "conflict" | "import_failed" | "too_large" | "internal" | "unknown_asset" | "quota_exceeded" | "rate_limited" | "method_not_allowed" | "not_found" | "timeout" | "unavailable" | "not_humanoid" | "no_mesh" | "storage_full" | "outcome_unknown" | "unknown_expression" | "unknown_take";

/**
 * How pose frames reach a client.
 */
export type Encoding = "binary" | "json";

/**
 * What precision a subscription asks for (`subscribe`'s `precision`). Absent fields take the
 * finest precision (what a subscription without `precision` gets).
 */
export type Precision = { 
/**
 * Worst angle of any joint's rotation, degrees (at least `finest_degrees`, at most
 * 45). Absent: the finest, unless `millimetres` is given.
 */
degrees?: number, 
/**
 * Worst world-space movement, millimetres, of a point `shell` metres from any joint
 * caused by the rotations' coding (0.01–10,000).
 */
millimetres?: number, 
/**
 * The shell distance of `millimetres`, metres (0–10; default 0.03).
 */
shell?: number, 
/**
 * Worst error of a streamed translation, metres (at least half of
 * `TRANSLATION_STEP`, at most 1).
 */
translation?: number, };

/**
 * What a connection (or a REST request) may do, as decided from its token.
 *
 * `scenes` / `avatars` are `None` when the token is not limited that way. A token limited
 * to avatars commands only those avatars; one limited to scenes commands those scenes and
 * every avatar in them; a token with both limits may do either.
 */
export type Access = { 
/**
 * May subscribe and read (list, get) — within `scenes` when that is set.
 */
view: boolean, 
/**
 * May run commands that change state, within the limits.
 */
control: boolean, 
/**
 * The token's name (never the token itself), when one was accepted.
 */
name?: string | null, 
/**
 * Only these scenes.
 */
scenes?: Array<SceneId> | null, 
/**
 * Only these avatars.
 */
avatars?: Array<AvatarId> | null, 
/**
 * Everything the token may do, in detail (empty without a token). `control` above is
 * `rights` holding `control`.
 */
rights?: Array<Right>, 
/**
 * Unix time (seconds) from which the token is refused: minted tokens only.
 */
expires_at?: number | null, };

/**
 * One thing a token may do.
 */
export type Right = "view" | "control" | "drive" | "upload" | "record";

/**
 * `POST /api/tokens`: a token for one user of an app. Only an unlimited control token the
 * operator configured (an *admin* token) may mint; a minted token never mints.
 */
export type MintRequest = { 
/**
 * Who holds it: logs, presence and the owner of what it uploads or records (tokens
 * minted with one name share that name's quota). 1–64 characters, none of them control
 * characters; not the name of a configured token.
 */
name: string, 
/**
 * What it may do (default: `["view"]`).
 */
rights?: Array<Right>, 
/**
 * Only these scenes (and every avatar in them).
 */
scenes?: Array<SceneId>, 
/**
 * Only these avatars.
 */
avatars?: Array<AvatarId>, 
/**
 * Lifetime in seconds (default 3600; at most `MAX_TTL_S`).
 */
ttl_s?: number, 
/**
 * Bytes its name may store (uploads and recordings), within the server's own limit.
 */
max_bytes?: number, 
/**
 * Objects its name may store.
 */
max_objects?: number, };

/**
 * What a minted token says of itself (its claims): the answer to `GET /api/tokens` lists
 * these, and `POST /api/tokens` returns them with the token.
 */
export type TokenInfo = { 
/**
 * Its id: `DELETE /api/tokens/{id}` revokes it.
 */
id: string, 
/**
 * Who holds it.
 */
name: string, 
/**
 * What it may do.
 */
rights: Array<Right>, 
/**
 * Only these scenes.
 */
scenes?: Array<SceneId>, 
/**
 * Only these avatars.
 */
avatars?: Array<AvatarId>, 
/**
 * Unix time (seconds) it was minted.
 */
issued_at: number, 
/**
 * Unix time (seconds) from which it is refused.
 */
expires_at: number, 
/**
 * Bytes its name may store.
 */
max_bytes?: number, 
/**
 * Objects its name may store.
 */
max_objects?: number, };

/**
 * The answer to `POST /api/tokens` (201).
 */
export type MintedToken = { 
/**
 * The token to hand to the user (`Authorization: Bearer …`, the websocket `hello`'s
 * `token`, or the dashboard's `?token=`). Shown once: the server keeps only its claims.
 */
token: string, 
/**
 * What it allows.
 */
info: TokenInfo, };

/**
 * A scene's id, chosen by whoever creates the scene (`"default"` for the built-in one).
 */
export type SceneId = string;

/**
 * An avatar's id, unique on the server.
 */
export type AvatarId = string;

/**
 * Position and rotation of an avatar in its scene.
 */
export type Placement = { 
/**
 * World position of the avatar's origin, metres `[x, y, z]`.
 */
position: [number, number, number], 
/**
 * World rotation of the avatar `[x, y, z, w]` (unit).
 */
rotation: [number, number, number, number], };

/**
 * Which joints of every avatar a subscription gets.
 */
export type JointSet = { "depth": number } | { "names": Array<string> };

/**
 * An avatar's normalised rig, sent once per subscription.
 *
 * Joints are in parent-before-child order. A joint's local transform is
 * `D_j = T(t_j) · R_j · S_j` where `R_j` comes from every frame, `t_j` from the frame when
 * `j ∈ translated_joints` and from `rest_translations` otherwise, and likewise `S_j` with
 * `scaled_joints` / `rest_scales`.
 */
export type AvatarDescription = { 
/**
 * The avatar.
 */
id: AvatarId, 
/**
 * The avatar's number in binary frames (unique on the server).
 */
num: number, 
/**
 * Display name (e.g. the asset's name).
 */
name: string, 
/**
 * Joint names, in order.
 */
joint_names: Array<string>, 
/**
 * Parent index of each joint, `-1` for a root.
 */
parents: Array<number>, 
/**
 * Rest local translation `t'_j` of each joint (metres, parent space).
 */
rest_translations: Array<[number, number, number]>, 
/**
 * Rest local rotation of each joint `[x, y, z, w]` (the neutral pose; identity after
 * normalisation).
 */
rest_rotations: Array<[number, number, number, number]>, 
/**
 * Rest local scale of each joint.
 */
rest_scales: Array<[number, number, number]>, 
/**
 * Inverse bind matrix `B'_j⁻¹` of each joint, column-major.
 */
inverse_binds: Array<[number, number, number, number, number, number, number, number, number, number, number, number, number, number, number, number]>, 
/**
 * Joints whose translation every frame carries (always includes the roots).
 */
translated_joints: Array<number>, 
/**
 * Joints whose scale every frame carries.
 */
scaled_joints: Array<number>, 
/**
 * Where to fetch the skinned mesh (a .glb), relative to the server's HTTP root.
 */
mesh_url: string | null, 
/**
 * Morph channels: the distinct morph target names over the avatar's meshes (every mesh
 * target of that name follows one weight), in the order weights are streamed. Absent for
 * a rig without morph targets.
 */
morph_targets?: Array<string>, 
/**
 * Standard expression names (ARKit's 52, VRM presets, Oculus visemes: see
 * `crate::expressions`) → the morph channel that plays each, found by name.
 */
expressions?: { [key in string]: string }, 
/**
 * Expressions the file defines (VRM 0.x `blendShapeMaster`, VRM 1.0 `expressions`): each
 * moves weighted channels together and may hold back the blink, look-at and mouth
 * expressions while it shows (`crate::expressions::Expression`). A name set by a client
 * resolves to one of these before `morph_targets` and `expressions`. Absent for other rigs.
 */
expression_binds?: Array<Expression>, 
/**
 * The name of the clip playing when the description was sent, for display only.
 */
clip?: string | null, 
/**
 * `AvatarDescription::compute_hash` of all the fields above except `clip` and `hash`,
 * as 16 hex digits. Every frame carries it; a client whose description has another hash is
 * holding a stale rig.
 */
hash: string, };

/**
 * An expression a file defines (VRM 0.x `blendShapeMaster.blendShapeGroups`, VRM 1.0
 * `expressions.preset` and `expressions.custom`): weighted morph channels shown together, and
 * how it holds back the blink, look-at and mouth expressions while it shows.
 */
export type Expression = { 
/**
 * Its name: the VRM 1.0 preset (`happy`, `aa`, `blinkLeft`, …; a VRM 0.x preset converted
 * with `vrm0_preset`) or the file's custom name.
 */
name: string, 
/**
 * The channels it moves.
 */
binds: Array<ExpressionBind>, 
/**
 * Shown only fully or not at all (weight > 0.5 is 1, else 0).
 */
is_binary?: boolean, 
/**
 * Its effect on `blink`, `blinkLeft`, `blinkRight`.
 */
override_blink?: Override, 
/**
 * Its effect on `lookUp`, `lookDown`, `lookLeft`, `lookRight`.
 */
override_look_at?: Override, 
/**
 * Its effect on `aa`, `ih`, `ou`, `ee`, `oh`.
 */
override_mouth?: Override, };

/**
 * One morph channel an expression moves, and how far at expression weight 1.
 */
export type ExpressionBind = { 
/**
 * The morph channel (one of the description's `morph_targets`).
 */
channel: string, 
/**
 * The channel's weight when the expression's weight is 1 (VRM 0.x `weight / 100`).
 */
weight: number, };

/**
 * How an expression holds back a group of others while it shows (VRM 1.0 `overrideBlink`,
 * `overrideLookAt`, `overrideMouth`).
 */
export type Override = "none" | "block" | "blend";

/**
 * A pose frame in the JSON encoding: the same content as a binary keyframe, with float
 * quaternions `[x, y, z, w]` (unquantised).
 */
export type FrameJson = { 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * Tick number of the scene, +1 per tick (ticks skipped under load leave gaps).
 */
seq: number, 
/**
 * The server clock at the tick, microseconds since the Unix epoch.
 */
server_time_us: number, 
/**
 * One entry per avatar the subscription covers.
 */
avatars: Array<AvatarPoseJson>, };

/**
 * One avatar's pose in a `FrameJson`.
 */
export type AvatarPoseJson = { 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The description hash the pose belongs to (16 hex digits).
 */
hash: string, 
/**
 * Local rotation of every joint, `[x, y, z, w]`, in description order (with a joint
 * subset: of the joints in `joints`, in that order).
 */
rotations: Array<[number, number, number, number]>, 
/**
 * Local translation of every joint in the description's `translated_joints`, in order.
 */
translations: Array<[number, number, number]>, 
/**
 * Local scale of every joint in the description's `scaled_joints`, in order.
 */
scales: Array<[number, number, number]>, 
/**
 * The avatar's world placement at this tick (every JSON frame carries it; absent from a
 * server that predates placement: the identity).
 */
placement: Placement, 
/**
 * With a joint subset (`crate::subset`): the joints `rotations` are of, ascending; the
 * translations and scales are then those of these joints only. Absent: every joint.
 */
joints?: Array<number> | null, 
/**
 * Morph weights by channel name (every channel of the description's `morph_targets`,
 * zeros included), each within 1/2046 of the weight set; absent for a rig without
 * morph targets.
 */
weights?: { [key in string]: number }, };

/**
 * A scene as listed.
 */
export type SceneInfo = { 
/**
 * The scene.
 */
scene: SceneId, 
/**
 * Its avatars.
 */
avatars: Array<AvatarState>, 
/**
 * Current subscriber count.
 */
subscribers: number, 
/**
 * The server ticking it, when servers form a cluster (`--nats`); absent otherwise.
 */
owner?: string | null, 
/**
 * Who watches it (presence): its subscribers by token name, the most connections first
 * (at most `MAX_VIEWER_NAMES` names; the rest count under `name: null` with the
 * anonymous ones). Changes follow as `viewers` messages to the scene list's watchers.
 */
viewers?: Array<Viewer>, };

/**
 * An avatar's playback state.
 */
export type AvatarState = { 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Its scene.
 */
scene: SceneId, 
/**
 * The rig it uses.
 */
asset: string, 
/**
 * The clip playing, if any.
 */
clip: string | null, 
/**
 * The asset the clip came from when retargeted.
 */
clip_asset: string | null, 
/**
 * Clip time in seconds from the clip's start.
 */
time: number, 
/**
 * Playback speed.
 */
speed: number, 
/**
 * Whether it loops.
 */
looping: boolean, 
/**
 * Whether paused.
 */
paused: boolean, 
/**
 * Joints with an override.
 */
overrides: Array<string>, 
/**
 * Where it stands now (mid-move: the interpolated placement).
 */
placement: Placement, 
/**
 * The current clip's root motion, if a clip plays.
 */
root_motion?: RootMotion | null, 
/**
 * Whether a live driver sets its pose (a held pose counts: `drive … on_release hold`).
 */
driven?: boolean, 
/**
 * Who drives it live and how, while a driver is connected (presence).
 */
driver?: Driver | null, 
/**
 * The clip being recorded, if any.
 */
recording?: string | null, 
/**
 * Blend shape (expression) values its live driver applied, by name (VMC
 * `/VMC/Ext/Blend/Val` + `Apply`), as sent; those naming a morph channel or a standard
 * expression of the avatar also set `morph_weights`.
 */
blend_shapes?: { [key in string]: number }, 
/**
 * Morph weights by channel name as shown (streamed), those above 0 (issue 30): per
 * channel the larger of the weight set (`set_morph_weights`, a live driver, VMC) and the
 * playing clip's; absent when all are 0.
 */
morph_weights?: { [key in string]: number }, 
/**
 * The cross-fade in progress (after `play … fade`), if any.
 */
fade?: FadeState | null, 
/**
 * The effectors with an IK goal (`set_ik_goal`), in the order they are solved.
 */
ik_goals?: Array<string>, 
/**
 * Whether a gaze (`look_at`) is set.
 */
looking?: boolean, 
/**
 * Clip layers over the clip (`play_layer`), in the order they apply.
 */
layers?: Array<LayerState>, };

/**
 * A cross-fade in progress: the clip fading out and how far the fade is.
 */
export type FadeState = { 
/**
 * The clip fading out.
 */
from: string, 
/**
 * The rig that clip came from when it was retargeted.
 */
from_asset?: string | null, 
/**
 * Seconds of the fade done at the state's tick (scene time; the new clip's weight is
 * `elapsed / duration`).
 */
elapsed: number, 
/**
 * The fade's length, seconds.
 */
duration: number, };

/**
 * The joints a clip layer owns: each joint of `joints` and everything below it, less each
 * joint of `except` and everything below it. Names are the rig's own or H-Anim names
 * (`{"joints": ["vl5"], "except": ["l_sternoclavicular"]}`: the upper body but the left arm).
 */
export type JointMask = { 
/**
 * Subtrees the layer owns.
 */
joints: Array<string>, 
/**
 * Subtrees taken out of them.
 */
except?: Array<string>, };

/**
 * A clip layer as `get_avatar` reports it.
 */
export type LayerState = { 
/**
 * The layer's name.
 */
layer: string, 
/**
 * The clip it plays.
 */
clip: string, 
/**
 * Clip time, seconds.
 */
time: number, 
/**
 * Clip seconds per second (what `play_layer … speed` set, or a tracker drive's
 * locomotion rate).
 */
speed: number, 
/**
 * Whether it adds to the pose below rather than replacing it.
 */
additive: boolean, 
/**
 * The weight it shows now (fades included).
 */
weight: number, 
/**
 * How many joints it owns.
 */
joints: number, };

/**
 * What an additive clip layer's rotations are measured from.
 */
export type AdditiveReference = "rest" | "first_frame";

/**
 * A joint of an avatar, whose frame an IK goal is given in.
 */
export type JointRef = { 
/**
 * The avatar (this one, or another of the same scene).
 */
avatar: AvatarId, 
/**
 * The joint's name on its rig.
 */
joint: string, };

/**
 * What a clip's root translation does to the avatar (`play`'s `root_motion`).
 */
export type RootMotion = "in_place" | "accumulate";

/**
 * A loaded rig as listed.
 */
export type AssetInfo = { 
/**
 * The asset's name (what `add_avatar` and `from_asset` take).
 */
name: string, 
/**
 * Joint count.
 */
joints: number, 
/**
 * Its clips.
 */
clips: Array<ClipInfo>, 
/**
 * What the import pipeline did to the rig, in order.
 */
pipeline: Array<string>, 
/**
 * Whether the rig is a humanoid: it has the H-Anim neutral pose and takes (and gives)
 * humanoid clips; rigs that are not keep their own neutral pose.
 */
humanoid: boolean, 
/**
 * Joints with an H-Anim name (of `joints`).
 */
mapped: number, 
/**
 * What the importer skipped, defaulted or approximated (a material not imported, a
 * repeated name suffixed, a channel skipped, a clip with fewer channels than the rig).
 */
notes?: Array<string>, };

/**
 * A clip as listed.
 */
export type ClipInfo = { 
/**
 * Its name.
 */
name: string, 
/**
 * Duration in seconds.
 */
duration: number, };

/**
 * One rig in full, as `get_asset` reports it.
 */
export type AssetDetail = { 
/**
 * Every joint, in order, with its parent and H-Anim name: the effective mapping.
 */
mapping: Array<JointMapping>, 
/**
 * The pipeline options it was normalised with (change them with `configure_asset`).
 */
options: PipelineOptions, 
/**
 * Metres per file unit the normalisation used, and how it was decided.
 */
units: Units, 
/**
 * Whether `configure_asset` can normalise it again (uploaded assets can).
 */
configurable: boolean, 
/**
 * The asset's name (what `add_avatar` and `from_asset` take).
 */
name: string, 
/**
 * Joint count.
 */
joints: number, 
/**
 * Its clips.
 */
clips: Array<ClipInfo>, 
/**
 * What the import pipeline did to the rig, in order.
 */
pipeline: Array<string>, 
/**
 * Whether the rig is a humanoid: it has the H-Anim neutral pose and takes (and gives)
 * humanoid clips; rigs that are not keep their own neutral pose.
 */
humanoid: boolean, 
/**
 * Joints with an H-Anim name (of `joints`).
 */
mapped: number, 
/**
 * What the importer skipped, defaulted or approximated (a material not imported, a
 * repeated name suffixed, a channel skipped, a clip with fewer channels than the rig).
 */
notes?: Array<string>, };

/**
 * A joint and its H-Anim name.
 */
export type JointMapping = { 
/**
 * The joint's name in the rig.
 */
joint: string, 
/**
 * Its parent's name (none for a root).
 */
parent: string | null, 
/**
 * Its H-Anim name, if mapped.
 */
hanim: string | null, };

/**
 * The unit conversion a rig went through.
 */
export type Units = { 
/**
 * Metres per file unit (applied to translations and the mesh).
 */
metres_per_unit: number, 
/**
 * `configured`, `file` (the format or file says) or `guessed` (from the rig's height).
 */
source: string, 
/**
 * The rig's height at rest in file units (joints and mesh, along its up axis).
 */
height: number, };

/**
 * One joint as `get_joint` reports it.
 */
export type JointInfo = { 
/**
 * The joint's name.
 */
joint: string, 
/**
 * Its parent's name (none for a root).
 */
parent: string | null, 
/**
 * Its joint type (`hinge`, `universal`, `ball_euler`, `ball_quaternion`, `prismatic`,
 * `translational`) when the rig defines joint types (e.g. `.skel`), else none: set it by
 * rotation.
 */
joint_type: string | null, 
/**
 * Its DOFs, in `set_joint_dofs` order: the current value (radians; the current local
 * rotation projected onto the DOFs) and the limits (none: unlimited).
 */
dofs: Array<DofInfo>, 
/**
 * Its current local rotation `[x, y, z, w]` (clip plus override).
 */
rotation: [number, number, number, number], 
/**
 * Whether an override holds it.
 */
overridden: boolean, };

/**
 * One DOF of a joint.
 */
export type DofInfo = { 
/**
 * Current value (radians, or metres for translational DOFs).
 */
value: number, 
/**
 * Lower limit, if any.
 */
min: number | null, 
/**
 * Upper limit, if any.
 */
max: number | null, };

/**
 * The answer to `drive`: how to address poses.
 */
export type DriveInfo = { 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * Its number (what binary pose messages carry).
 */
avatar_num: number, 
/**
 * The source rig's name.
 */
source: string, 
/**
 * The source rig's joints, in order: binary pose messages index this list.
 */
joints: Array<string>, 
/**
 * The source rig's root joint (what `root_position` moves).
 */
root: string, 
/**
 * Seconds of silence after which the driver is released.
 */
timeout: number, 
/**
 * Most poses per second accepted from the driver.
 */
max_rate_hz: number, 
/**
 * The avatar's morph channels (its description's `morph_targets`): binary pose messages
 * give weights by index into this list. Absent for a rig without morph targets.
 */
morph_targets?: Array<string>, 
/**
 * Standard expression names → channel (its description's `expressions`), which JSON
 * poses may name weights by.
 */
expressions?: { [key in string]: string }, 
/**
 * A tracker drive's trackers (`drive … trackers`), in order: binary poses index this
 * list. Absent for a drive by rotations.
 */
trackers?: Array<string>, };

/**
 * Who drives an avatar live, and how.
 */
export type Driver = { 
/**
 * The driving connection's token name (`anonymous` without one); for a VMC input
 * `vmc ADDRESS` (the UDP address it listens on).
 */
name: string, 
/**
 * How the poses arrive.
 */
via: DriveVia, };

/**
 * How a live driver's poses arrive.
 */
export type DriveVia = "websocket" | "vmc" | "cluster";

/**
 * Connections watching a scene under one token name.
 */
export type Viewer = { 
/**
 * The token's name; `null`: anonymous (and the names beyond the list's limit).
 */
name: string | null, 
/**
 * Its subscribed connections.
 */
connections: number, };

/**
 * What a live-driven avatar does when its driver goes.
 */
export type OnRelease = "clip" | "hold";

/**
 * One tracker's transform in a JSON `pose` message.
 */
export type TrackerTransform = { 
/**
 * Position `[x, y, z]` in the scene's space, metres.
 */
position: [number, number, number], 
/**
 * Rotation `[x, y, z, w]` in the scene's space (normalised; finite and non-zero).
 */
rotation: [number, number, number, number], };

/**
 * What moves a tracker-driven avatar's legs.
 */
export type Legs = "planted" | "animated" | "locomotion";

/**
 * The pose the user holds while `calibrate_trackers` measures them.
 */
export type CalibrationPose = "neutral" | "t_pose" | "a_pose";

/**
 * What `calibrate_trackers` measured.
 */
export type CalibrationInfo = { 
/**
 * The avatar.
 */
avatar: AvatarId, 
/**
 * The user's head (tracker) height above the scene's floor, metres.
 */
user_height: number, 
/**
 * The avatar's over the user's size: tracker positions are scaled by it about the user's
 * place on the floor.
 */
scale: number, 
/**
 * The same for the arms (from a T- or A-pose's hand span; `scale` otherwise).
 */
arm_scale: number, 
/**
 * The trackers whose offsets were measured.
 */
trackers: Array<string>, };

/**
 * A clip the legs of a tracker drive may play (`drive … legs: "locomotion"`).
 */
export type LocomotionClip = { 
/**
 * One of the avatar's clips (`idle`, `walk`, …).
 */
clip: string, 
/**
 * How fast its walk covers ground played at rate 1, m/s (0 for standing still; finite,
 * 0 to 20).
 */
speed: number, };

/**
 * The answer to `stop_recording`.
 */
export type RecordingInfo = { 
/**
 * The rig the clip was added to.
 */
asset: string, 
/**
 * The clip's name.
 */
clip: string, 
/**
 * Its length, seconds.
 */
duration: number, 
/**
 * Ticks recorded.
 */
frames: number, 
/**
 * Ticks past the recording's limit, not kept.
 */
dropped: number, };

/**
 * A take of a whole scene (`record_scene`), as listed.
 */
export type TakeInfo = { 
/**
 * Its name.
 */
take: string, 
/**
 * The scene it recorded.
 */
scene: SceneId, 
/**
 * Seconds from its first frame to its last.
 */
duration: number, 
/**
 * Frames (ticks) it holds.
 */
frames: number, 
/**
 * Every avatar that appears in it, in order of appearance.
 */
avatars: Array<AvatarId>, 
/**
 * Its size in bytes.
 */
bytes: number, 
/**
 * When recording started, µs since the Unix epoch.
 */
started_us: number, 
/**
 * Whether it is being recorded now.
 */
recording: boolean, 
/**
 * Bytes after its last complete frame that a crash cut short (ignored when read).
 */
torn_bytes?: number, 
/**
 * Who drove which avatar live during the take, each pair once, in order of first drive
 * (listed once the take is stopped).
 */
drivers?: Array<TakeDriver>, };

/**
 * A live driver of an avatar during a take (`TakeInfo::drivers`).
 */
export type TakeDriver = { 
/**
 * The avatar (its id in the take).
 */
avatar: AvatarId, 
/**
 * The driver's name, as the scene list shows it (`Driver::name`).
 */
name: string, 
/**
 * How its poses arrived.
 */
via: DriveVia, };

/**
 * Where a replay (`replay`, `control_replay`) is.
 */
export type ReplayState = { 
/**
 * The replay's scene.
 */
scene: SceneId, 
/**
 * The take it replays.
 */
take: string, 
/**
 * Seconds into the take.
 */
time: number, 
/**
 * The take's duration, seconds.
 */
duration: number, 
/**
 * Whether it is paused.
 */
paused: boolean, 
/**
 * Take seconds per scene second.
 */
speed: number, 
/**
 * Whether it loops.
 */
loop: boolean, };

/**
 * Per-asset pipeline configuration; `Default` is the default pipeline. Deserialises from JSON
 * with every field optional, e.g.
 * `{"up_axis": {"up": "+z", "forward": "-y"}, "metres_per_unit": 0.01, "neutral": "keep",
 *   "name_map": {"Bip01_L_Thigh": "l_hip"}}`.
 */
export type PipelineOptions = { 
/**
 * Simplify bind matrices to translations (default true).
 */
simplify: boolean, 
/**
 * The source's orientation; `None` detects it (glTF `Z_UP` exports; BVH and CSE169 are
 * Y-up by convention).
 */
up_axis: UpAxisOverride | null, 
/**
 * Metres per file unit; `None` takes the file's (glTF: 1) or, where the format does not
 * say (BVH, CSE169), guesses from the rig's height: 1 when it is 0.3–3 units tall,
 * centimetres when 30–300, millimetres when 300–3000, else 1.
 */
metres_per_unit: number | null, 
/**
 * Which neutral pose (default: H-Anim when humanoid).
 */
neutral: NeutralPose, 
/**
 * Joint name → H-Anim name, replacing the guesses for the joints it names (`""` unmaps).
 */
name_map: { [key in string]: string } | null, 
/**
 * Whether the rig is a humanoid; `None` classifies it (humanoid when its mapping covers
 * the H-Anim core chain and its legs hang away from its spine). A non-humanoid keeps its
 * neutral pose and cannot take humanoid clips.
 */
humanoid: boolean | null, 
/**
 * Standard expression name (ARKit, VRM preset, `viseme_*`: `crate::expressions`) → the
 * rig's morph target that plays it, replacing the guess for the names it lists (`""`
 * unmaps). Each name must be a standard one and each target one of the rig's.
 */
expression_map: { [key in string]: string } | null, };

/**
 * Which neutral pose the pipeline gives a rig.
 */
export type NeutralPose = "auto" | "h_anim" | "keep";

/**
 * The source's orientation, as axes or as a rotation.
 */
export type UpAxisOverride = { 
/**
 * The source's up axis (default `+y`).
 */
up: SignedAxis, 
/**
 * The source's forward axis (the way the avatar faces); `None` picks the first of `+z`,
 * `-y`, `+x` perpendicular to `up`.
 */
forward: SignedAxis | null, 
/**
 * A rotation `R` (x, y, z, w) to apply instead of the axes.
 */
rotation: [number, number, number, number] | null, 
/**
 * What to rotate; `None`: `bind` for glTF (whose scene is Y-up by
 * specification), `world` otherwise.
 */
frame: ReorientFrame | null, };

/**
 * A coordinate axis with a sign, as written in a pipeline config: `"+x"` (or `"x"`), `"-z"`, …
 */
export type SignedAxis = "+x" | "-x" | "+y" | "-y" | "+z" | "-z";

/**
 * What a re-orientation rotates.
 */
export type ReorientFrame = "world" | "bind";
