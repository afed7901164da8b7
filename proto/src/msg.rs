//! The messages of the posecast websocket protocol (version [`PROTOCOL_VERSION`]).
//!
//! Control messages travel as JSON text frames in both encodings: serde enums tagged by
//! `"type"`, snake_case. Pose frames travel as JSON text ([`FrameJson`]) for the `json`
//! encoding and as compact binary frames ([`crate::frame`]) for the `binary` encoding. A client
//! always speaks first with [`ClientMsg::Hello`]; the server answers [`ServerMsg::Welcome`] or an
//! error and a close. See `proto/PROTOCOL.md` for the whole exchange with examples.

use crate::command::{AvatarState, SceneInfo};
use crate::description::AvatarDescription;
use serde::{Deserialize, Serialize};

/// The protocol version clients speak unless they ask for another ([`SUPPORTED_VERSIONS`]).
pub const PROTOCOL_VERSION: u32 = 1;

/// The protocol versions a server accepts; a hello with any other is refused with
/// [`ErrorCode::UnsupportedVersion`]. Version 2 differs from 1 only in binary pose frames
/// ([`crate::frame2`] instead of [`crate::frame`]); version 3 is version 2 with tagged
/// command results in `ack` ([`ServerMsg::Ack`]) and joint subsets served as v2 frames (v1
/// frames on version 2); version 4 is version 3 with morph weights in v2 frames (chunk flag
/// 8, `proto/PROTOCOL.md`); version 5 is version 4 with precision per subscription
/// (`subscribe`'s `precision`, keyframe chunk flag 16: [`crate::precision`]); version 6 is
/// version 5 with near-axis grid steps in a precision's frames (keyframe chunk flag 32, a
/// tier bit per rotation: [`crate::precision::Steps::near`]); version 7 is version 6 with
/// packed deltas (frame kind 3: every avatar's chunk in one bit stream, the time since the base
/// frame's, [`crate::frame2::PackedDeltas`]); version 8 is version 7 with, over WebTransport,
/// wire v2 frames as datagrams: deltas of kind 4 naming the frames they refer to, every frame
/// acknowledged ([`crate::quic`]; on a websocket version 8 is version 7); version 9 is
/// version 8 with deltas of kind 5 over datagrams, predicted over the ticks between the frames
/// they name and their own ([`crate::frame2::ReferencedKind`]). Every other message is the
/// same.
pub const SUPPORTED_VERSIONS: [u32; 9] = [1, 2, 3, 4, 5, 6, 7, 8, 9];

/// Largest message the server accepts from a client, in bytes (hello, subscribe, commands).
/// Uploads of assets go through HTTP, not the websocket.
pub const MAX_CLIENT_MESSAGE_BYTES: usize = 64 * 1024;

pub use crate::ids::{AvatarId, SceneId};

/// How pose frames reach a client.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum Encoding {
    /// Binary websocket frames with smallest-three quantised rotations ([`crate::frame`]).
    Binary,
    /// JSON text frames with float quaternions ([`FrameJson`]), for dashboards and debugging.
    Json,
}

/// Everything a client may send.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ClientMsg {
    /// First message of every connection.
    Hello {
        /// One of [`SUPPORTED_VERSIONS`] (1: binary frames are [`crate::frame`]; 2 and 3:
        /// [`crate::frame2`]; 3: command results tagged with their kind, [`ServerMsg::Ack`]).
        version: u32,
        /// The encoding of pose frames the client wants.
        encoding: Encoding,
        /// A view or control token, when the server requires one.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        token: Option<String>,
        /// Free text naming the client, for logs.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        client: Option<String>,
    },
    /// Start receiving a scene's descriptions and frames. `avatars` limits the frames to the
    /// listed avatars; `None` means every avatar in the scene, including ones added later.
    Subscribe {
        /// The scene.
        scene: SceneId,
        /// Only these avatars, or all.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        avatars: Option<Vec<AvatarId>>,
        /// Frames per second wanted (e.g. 30, 20, 15 or 10 for a distant or small view);
        /// absent: every tick. The server sends every `round(tick_rate / rate)`-th tick (at
        /// least every tick) and says the rate it chose in `subscribed`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rate: Option<f32>,
        /// Only these joints of every avatar ([`crate::subset`]: `{"depth": 3}` or
        /// `{"names": […]}`, with their ancestors); absent: all of them.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        joints: Option<crate::subset::JointSet>,
        /// Morph weights in the frames (binary frames from protocol version 4, and JSON);
        /// `false` leaves them out, for a view that shows no faces (a distant or body-only
        /// one). Default `true`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        morph_weights: Option<bool>,
        /// How finely binary frames code each joint (protocol version 5;
        /// [`crate::precision`]): a worst angle, a world-space bound, a translation bound —
        /// so a distant view, a crowd or a thin link pays less. Absent: the finest.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        precision: Option<crate::precision::Precision>,
    },
    /// Stop receiving a scene.
    Unsubscribe {
        /// The scene.
        scene: SceneId,
    },
    /// Clock probe: the server echoes `client_time_us` in a [`ServerMsg::Pong`].
    Ping {
        /// Chosen by the client, echoed back.
        id: u32,
        /// The client's clock when sending, in microseconds (any epoch).
        client_time_us: u64,
    },
    /// A control command (see [`crate::command`]); answered by [`ServerMsg::Ack`] or
    /// [`ServerMsg::Error`] carrying the same `id`.
    Command {
        /// Chosen by the client, echoed back.
        id: u64,
        /// What to do.
        command: crate::command::Command,
        /// Chosen by the client (1–128 visible ASCII characters, unique per command, e.g. a
        /// UUID): a command sent again with the same key after an unknown outcome (a timeout,
        /// a dropped connection) is answered with the first one's result and applied at most
        /// once, on whichever server of a cluster it reaches (PROTOCOL.md, "Idempotency").
        #[serde(default, skip_serializing_if = "Option::is_none")]
        idempotency_key: Option<String>,
    },
    /// Ask for changes of the scene list: the server answers [`ServerMsg::Scenes`] (every
    /// scene this connection may watch, as `list_scenes` lists them), then pushes
    /// [`ServerMsg::SceneCreated`], [`ServerMsg::SceneDeleted`], [`ServerMsg::AvatarChanged`] and
    /// [`ServerMsg::AvatarRemoved`] for those scenes as commands change them.
    WatchScenes,
    /// Stop the pushes [`ClientMsg::WatchScenes`] asked for (subscriptions keep theirs). No
    /// answer.
    UnwatchScenes,
    /// Live driving: one pose of the avatar this connection drives (after `drive`). Not
    /// acknowledged; a bad pose gets a typed error and changes nothing.
    Pose {
        /// The driven avatar.
        avatar: AvatarId,
        /// Local rotations `[x, y, z, w]` of the source rig's joints, by joint name; joints not
        /// listed keep their last value. Absent (or empty) for a tracker drive.
        #[serde(default)]
        #[cfg_attr(
            feature = "ts",
            ts(as = "Option<std::collections::BTreeMap<String, [f32; 4]>>", optional)
        )]
        rotations: std::collections::BTreeMap<String, [f32; 4]>,
        /// The source root joint's local translation, metres.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        root_position: Option<[f32; 3]>,
        /// The driver's clock when the pose was captured, µs (any epoch).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        time_us: Option<u64>,
        /// Morph weights by name (a morph channel of the driven avatar or a standard
        /// expression name, as `set_morph_weights` takes them), each in `[0, 1]`; channels not
        /// named keep their weights.
        #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
        weights: std::collections::BTreeMap<String, f32>,
        /// A tracker drive's tracker transforms in the scene's space, by tracker name (of the
        /// `drive`'s `trackers`); trackers not named keep their last transform.
        #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
        trackers: std::collections::BTreeMap<String, crate::trackers::TrackerTransform>,
    },
}

/// Everything the server may send as a text message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMsg {
    /// Answer to a valid hello.
    Welcome {
        /// The protocol version in use.
        version: u32,
        /// The encoding of pose frames on this connection.
        encoding: Encoding,
        /// Server name and version, for logs.
        server: String,
        /// Ticks (pose frames) per second of every scene.
        tick_rate: f32,
        /// The server clock when sending, microseconds since the Unix epoch.
        server_time_us: u64,
        /// What the hello's token (or its absence) allows on this connection.
        #[serde(default)]
        access: Access,
    },
    /// Subscription confirmed. Descriptions of the scene's avatars follow, then a keyframe.
    Subscribed {
        /// The scene.
        scene: SceneId,
        /// The scene's number in binary frames.
        scene_num: u32,
        /// Frames per second this subscription gets (the tick rate divided by a whole number).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rate: Option<f32>,
        /// The joint set its frames carry (as subscribed; absent: every joint).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        joints: Option<crate::subset::JointSet>,
        /// The precision its frames are coded at (as subscribed; absent: the finest).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        precision: Option<crate::precision::Precision>,
    },
    /// Subscription ended (on request or because the scene was deleted).
    Unsubscribed {
        /// The scene.
        scene: SceneId,
    },
    /// An avatar's rig, sent once per subscription and again whenever it changes.
    Description {
        /// The scene the avatar is in.
        scene: SceneId,
        /// The rig.
        avatar: Box<AvatarDescription>,
    },
    /// The avatar left the scene; frames no longer carry it. Sent to the scene's subscribers
    /// covering the avatar and to connections watching the scene list.
    AvatarRemoved {
        /// The scene.
        scene: SceneId,
        /// The avatar.
        avatar: AvatarId,
    },
    /// The scene list, answering [`ClientMsg::WatchScenes`]: every scene the connection may
    /// watch, with its avatars' states. Changes follow as the messages below.
    Scenes {
        /// The scenes.
        scenes: Vec<SceneInfo>,
    },
    /// A scene was created (to connections watching the scene list).
    SceneCreated {
        /// The scene.
        scene: SceneId,
    },
    /// A scene was deleted (to connections watching the scene list; its subscribers get
    /// [`ServerMsg::Unsubscribed`]).
    SceneDeleted {
        /// The scene.
        scene: SceneId,
    },
    /// An avatar was added, or a command changed its state (clip, speed, pause, seek, joint
    /// overrides, placement, live driving, recording): its state now. Sent to the scene's
    /// subscribers covering the avatar and to connections watching the scene list, once each.
    AvatarChanged {
        /// The scene.
        scene: SceneId,
        /// The scene's tick at which `avatar.time` (and a fade's `elapsed`) hold: at tick
        /// `s` the clip time is `time + (s − seq) / tick_rate · speed` (wrapped or clamped
        /// to the clip) while playing.
        seq: u64,
        /// The avatar's state, as `get_avatar` answers.
        avatar: Box<AvatarState>,
    },
    /// Who watches a scene changed (presence, to the scene's subscribers and to connections
    /// watching the scene list; at most one a second per scene): its viewers now, as in
    /// [`SceneInfo::viewers`].
    Viewers {
        /// The scene.
        scene: SceneId,
        /// Its subscribers by token name.
        viewers: Vec<crate::command::Viewer>,
    },
    /// Answer to a ping.
    Pong {
        /// The ping's id.
        id: u32,
        /// The ping's client time, echoed.
        client_time_us: u64,
        /// The server clock when answering, microseconds since the Unix epoch.
        server_time_us: u64,
    },
    /// A command succeeded. `"result"` holds the value (`null` for `done`); protocol version
    /// 3 also names its shape in `"kind"` ([`crate::command::CommandResult::kind`]), versions
    /// 1 and 2 do not ([`ServerMsg::ack_bare`]). Both are read.
    Ack {
        /// The command's id.
        id: u64,
        /// What the command returned.
        #[serde(
            flatten,
            serialize_with = "tagged",
            deserialize_with = "tagged_or_bare"
        )]
        result: crate::command::CommandResult,
    },
    /// A pose frame in the JSON encoding.
    Frame(FrameJson),
    /// Something went wrong. `id` is the command's id when a command failed.
    Error(ProtocolError),
}

/// Writes an ack's result as `"kind"` and `"result"`, `null` for `done`.
fn tagged<S: serde::Serializer>(
    result: &crate::command::CommandResult,
    s: S,
) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeMap;
    let mut map = s.serialize_map(Some(2))?;
    map.serialize_entry("kind", result.kind())?;
    map.serialize_entry("result", &result.to_value())?;
    map.end()
}

/// Reads an ack's result tagged (version 3) or bare (versions 1 and 2).
fn tagged_or_bare<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<crate::command::CommandResult, D::Error> {
    #[derive(Deserialize)]
    struct Fields {
        #[serde(default)]
        kind: Option<String>,
        #[serde(default)]
        result: serde_json::Value,
    }
    let Fields { kind, result } = Fields::deserialize(d)?;
    let read = match kind {
        Some(kind) => serde_json::from_value(serde_json::json!({ "kind": kind, "result": result })),
        None => crate::command::CommandResult::from_bare(result),
    };
    read.map_err(serde::de::Error::custom)
}

impl ServerMsg {
    /// The JSON text of an ack as protocol versions 1 and 2 write it: `{"type":"ack","id":…,
    /// "result":…}` with the bare value ([`crate::command::CommandResult::to_value`]).
    #[must_use]
    pub fn ack_bare(id: u64, result: &crate::command::CommandResult) -> String {
        serde_json::json!({ "type": "ack", "id": id, "result": result.to_value() }).to_string()
    }
}

/// Longest scene or avatar id.
pub const MAX_ID_LEN: usize = 64;

/// Checks an id: 1–64 characters from letters, digits, `-`, `_`, `.`.
///
/// # Errors
/// [`ErrorCode::InvalidValue`] naming what is wrong.
pub fn check_id(kind: &str, id: &str) -> Result<(), ProtocolError> {
    let ok = !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
    if ok {
        Ok(())
    } else {
        Err(ProtocolError::new(
            ErrorCode::InvalidValue,
            format!("{kind} id must be 1-{MAX_ID_LEN} letters, digits, '-', '_' or '.'"),
        ))
    }
}

/// A typed error: a stable machine-readable code and a human message.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[error("{code:?}: {message}")]
pub struct ProtocolError {
    /// What kind of error.
    pub code: ErrorCode,
    /// What happened, for people.
    pub message: String,
    /// The id of the command that failed, if a command failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u64>,
    /// With `rate_limited`: milliseconds until a command would be accepted again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retry_after_ms: Option<u64>,
    /// What the error is about, in fields a client can act on (the scene, avatar, rig, clip,
    /// joint, expression or take it could not find; the quota that refused): absent when the
    /// message is all there is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub details: Option<Box<ErrorDetails>>,
}

/// The subject of an error ([`ProtocolError::details`]): each field present only when the
/// error is about it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct ErrorDetails {
    /// The scene (`unknown_scene`; `unknown_avatar` for an avatar not in it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<SceneId>,
    /// The avatar (`unknown_avatar`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub avatar: Option<AvatarId>,
    /// The rig (asset): `unknown_asset`, `no_mesh`, and the rig of `unknown_clip`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub asset: Option<String>,
    /// The clip (`unknown_clip`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clip: Option<String>,
    /// The joint asked for (`unknown_joint`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joint: Option<String>,
    /// The morph target or expression asked for (`unknown_expression`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expression: Option<String>,
    /// The take (`unknown_take`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub take: Option<String>,
    /// The command's field whose value is refused (`invalid_value`), when the refusal is
    /// about one: its name in the command (`speed`, `weight`, `time`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// The limit that refused (`quota_exceeded`): its name, as in `/metrics`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quota: Option<String>,
    /// That limit's value, as people read it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub limit: Option<String>,
}

impl ProtocolError {
    /// An error with no command id.
    #[must_use]
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
            id: None,
            retry_after_ms: None,
            details: None,
        }
    }

    /// The same error, answering command `id`.
    #[must_use]
    pub fn for_command(mut self, id: u64) -> Self {
        self.id = Some(id);
        self
    }
}

/// Stable error codes. New codes may be added in later versions; clients treat an unknown code
/// as a generic failure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// Not valid JSON, or not a known message shape.
    BadMessage,
    /// A binary message from the client that is not a pose (clients send JSON text, and binary
    /// only for live poses).
    UnexpectedBinary,
    /// Larger than [`MAX_CLIENT_MESSAGE_BYTES`].
    MessageTooLarge,
    /// Hello carried a version not in [`SUPPORTED_VERSIONS`].
    UnsupportedVersion,
    /// A message other than hello before the hello, or a second hello.
    NotAllowedNow,
    /// No such scene.
    UnknownScene,
    /// No such avatar.
    UnknownAvatar,
    /// No such clip.
    UnknownClip,
    /// No such joint.
    UnknownJoint,
    /// A value that is out of range or not finite (e.g. a NaN quaternion).
    InvalidValue,
    /// Missing or wrong token.
    Unauthorized,
    /// The token is valid but does not allow this.
    Forbidden,
    /// The thing already exists.
    Conflict,
    /// An uploaded asset could not be imported.
    ImportFailed,
    /// The request is too large.
    TooLarge,
    /// The server failed; the request may be retried.
    Internal,
    /// No such asset (rig).
    UnknownAsset,
    /// A configured quota (scenes, avatars per scene, rig size, clip size, upload bytes) would be
    /// exceeded; the message names it and its limit.
    QuotaExceeded,
    /// Too many commands too fast; `retry_after_ms` says when to try again.
    RateLimited,
    /// HTTP only: the path exists but not with this method (405; `Allow` lists the methods).
    MethodNotAllowed,
    /// HTTP only: no endpoint at this path (404).
    NotFound,
    /// The peer was too slow: no `hello` within the server's hello timeout (then close 1008),
    /// or an HTTP request body not received in time (408).
    Timeout,
    /// The server holds as many connections as it allows (in all, or from this address): try
    /// again later (HTTP 503 with `Retry-After`; websocket upgrades: close 1013).
    Unavailable,
    /// A humanoid clip or driver for a rig that is not a humanoid, or the other way round
    /// (HTTP 422): their neutral poses do not correspond.
    NotHumanoid,
    /// The rig has no mesh (HTTP 404 for `GET /api/assets/{name}/mesh.glb`).
    NoMesh,
    /// The server's disk (or its file-system quota) is full: the change was not made and
    /// nothing of it is stored (HTTP 507). Free room (`delete_clip`, `delete_asset`) or ask
    /// the operator.
    StorageFull,
    /// The command may or may not have been applied (HTTP 504): in a cluster, the server
    /// ticking the scene did not answer in time, or its write to the cluster's store was not
    /// answered and may have landed. Retry with the same idempotency key: it applies at most
    /// once. (`unavailable`, by contrast, means not applied.)
    OutcomeUnknown,
    /// The avatar has no morph target or expression of that name (or no morph targets at
    /// all): `set_morph_weights`, `set_expression` (HTTP 404).
    UnknownExpression,
    /// No take of that name (`get_take`, `replay`, `delete_take`, the take exports; HTTP 404),
    /// or a take file that cannot be read (the message says why).
    UnknownTake,
}

/// What a connection (or a REST request) may do, as decided from its token.
///
/// `scenes` / `avatars` are `None` when the token is not limited that way. A token limited
/// to avatars commands only those avatars; one limited to scenes commands those scenes and
/// every avatar in them; a token with both limits may do either.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Access {
    /// May subscribe and read (list, get) — within `scenes` when that is set.
    pub view: bool,
    /// May run commands that change state, within the limits.
    pub control: bool,
    /// The token's name (never the token itself), when one was accepted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// Only these scenes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scenes: Option<Vec<SceneId>>,
    /// Only these avatars.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub avatars: Option<Vec<AvatarId>>,
    /// Everything the token may do, in detail (empty without a token). `control` above is
    /// `rights` holding `control`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rights: Vec<crate::tokens::Right>,
    /// Unix time (seconds) from which the token is refused: minted tokens only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expires_at: Option<u64>,
}

/// A pose frame in the JSON encoding: the same content as a binary keyframe, with float
/// quaternions `[x, y, z, w]` (unquantised).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct FrameJson {
    /// The scene.
    pub scene: SceneId,
    /// Tick number of the scene, +1 per tick (ticks skipped under load leave gaps).
    pub seq: u64,
    /// The server clock at the tick, microseconds since the Unix epoch.
    pub server_time_us: u64,
    /// One entry per avatar the subscription covers.
    pub avatars: Vec<AvatarPoseJson>,
}

/// One avatar's pose in a [`FrameJson`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct AvatarPoseJson {
    /// The avatar.
    pub avatar: AvatarId,
    /// The description hash the pose belongs to (16 hex digits).
    pub hash: String,
    /// Local rotation of every joint, `[x, y, z, w]`, in description order (with a joint
    /// subset: of the joints in `joints`, in that order).
    pub rotations: Vec<[f32; 4]>,
    /// Local translation of every joint in the description's `translated_joints`, in order.
    pub translations: Vec<[f32; 3]>,
    /// Local scale of every joint in the description's `scaled_joints`, in order.
    pub scales: Vec<[f32; 3]>,
    /// The avatar's world placement at this tick (every JSON frame carries it; absent from a
    /// server that predates placement: the identity).
    #[serde(default)]
    pub placement: crate::placement::Placement,
    /// With a joint subset ([`crate::subset`]): the joints `rotations` are of, ascending; the
    /// translations and scales are then those of these joints only. Absent: every joint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joints: Option<Vec<u16>>,
    /// Morph weights by channel name (every channel of the description's `morph_targets`,
    /// zeros included), each within 1/2046 of the weight set; absent for a rig without
    /// morph targets.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub weights: std::collections::BTreeMap<String, f32>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hello_round_trips_and_unknown_fields_are_refused() {
        let hello = ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding: Encoding::Json,
            token: None,
            client: Some("test".into()),
        };
        let text = serde_json::to_string(&hello).unwrap();
        assert_eq!(
            text,
            r#"{"type":"hello","version":1,"encoding":"json","client":"test"}"#
        );
        assert_eq!(serde_json::from_str::<ClientMsg>(&text).unwrap(), hello);
        assert!(serde_json::from_str::<ClientMsg>(r#"{"type":"hello","version":1}"#).is_err());
        assert!(serde_json::from_str::<ClientMsg>(r#"{"type":"launch"}"#).is_err());
    }

    #[test]
    fn change_messages_serialise_as_documented() {
        assert_eq!(
            serde_json::to_string(&ClientMsg::WatchScenes).unwrap(),
            r#"{"type":"watch_scenes"}"#
        );
        assert_eq!(
            serde_json::from_str::<ClientMsg>(r#"{"type":"unwatch_scenes"}"#).unwrap(),
            ClientMsg::UnwatchScenes
        );
        assert_eq!(
            serde_json::to_string(&ServerMsg::SceneCreated {
                scene: SceneId("lobby".into())
            })
            .unwrap(),
            r#"{"type":"scene_created","scene":"lobby"}"#
        );
        assert_eq!(
            serde_json::to_string(&ServerMsg::Scenes { scenes: Vec::new() }).unwrap(),
            r#"{"type":"scenes","scenes":[]}"#
        );
        let changed: ServerMsg = serde_json::from_str(
            r#"{"type":"avatar_changed","scene":"lobby","seq":42,"avatar":{"avatar":"guest",
                "scene":"lobby","asset":"avatar","clip":"walk","clip_asset":null,"time":0.5,
                "speed":1.0,"looping":true,"paused":false,"overrides":[]}}"#,
        )
        .unwrap();
        assert!(
            matches!(&changed, ServerMsg::AvatarChanged { seq: 42, avatar, .. } if avatar.fade.is_none()),
            "{changed:?}"
        );
    }

    #[test]
    fn errors_serialise_with_snake_case_codes() {
        let e = ServerMsg::Error(ProtocolError::new(ErrorCode::UnknownScene, "no scene x"));
        assert_eq!(
            serde_json::to_string(&e).unwrap(),
            r#"{"type":"error","code":"unknown_scene","message":"no scene x"}"#
        );
    }
}
