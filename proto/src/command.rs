//! Control commands: the same types over REST (JSON bodies) and over the websocket
//! ([`crate::msg::ClientMsg::Command`]). Every command is acknowledged with a JSON result or a
//! typed error.

use crate::ids::{AvatarId, SceneId};
use crate::rig_options::PipelineOptions;
use serde::{Deserialize, Serialize};

/// Something a dashboard or application asks the server to do.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Command {
    /// Scenes with their avatars. Result: `[SceneInfo]`.
    ListScenes,
    /// Loaded rigs (assets) and their clips. Result: `[AssetInfo]`.
    ListAssets,
    /// One rig in full: its joints and their H-Anim names (the effective mapping), whether it
    /// is a humanoid, and the pipeline options it was normalised with. Result: `AssetDetail`.
    GetAsset {
        /// The rig's asset name.
        asset: String,
    },
    /// Normalise an uploaded asset again with new pipeline options (name map, units, up axis,
    /// humanoid or not, …), replacing the ones it had; stored with the upload, so a restart
    /// keeps them. Avatars added from then on use the new rig; avatars already in scenes keep
    /// theirs. Needs an unlimited control token (like uploads). Result: `[AssetInfo]` (several
    /// for a multi-skin glTF).
    ConfigureAsset {
        /// The upload's name (a multi-skin glTF's `name`, not `name#skin`).
        asset: String,
        /// The options, replacing the asset's (absent fields take their defaults).
        options: PipelineOptions,
    },
    /// One avatar's state. Result: `AvatarState`.
    GetAvatar {
        /// The avatar.
        avatar: AvatarId,
    },
    /// One joint of an avatar: its DOFs with their limits and current values, and its local
    /// rotation. Result: `JointInfo`.
    GetJoint {
        /// The avatar.
        avatar: AvatarId,
        /// The joint's name.
        joint: String,
    },
    /// The pose a private copy of the avatar has playing `clip` (default: the clip it plays
    /// now) paused at `time`: its rig, joint overrides and placement, with the clip instead of
    /// whatever drives it. Read-only: the avatar and what every viewer sees do not change, so
    /// a view token suffices (e.g. to render one moment of a clip). Result: the pose as a JSON
    /// frame carries it ([`crate::msg::AvatarPoseJson`]).
    SamplePose {
        /// The avatar.
        avatar: AvatarId,
        /// The clip (of the avatar's rig, or of `from_asset`'s, retargeted); absent: the
        /// avatar's current clip.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        clip: Option<String>,
        /// The rig `clip` belongs to, when another (as in `play`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        from_asset: Option<String>,
        /// Seconds from the clip's start (wrapped for a looping clip, clamped otherwise).
        time: f32,
    },
    /// Create an empty scene.
    CreateScene {
        /// Its id (letters, digits, `-`, `_`; at most 64).
        scene: SceneId,
    },
    /// Delete a scene and its avatars; subscribers receive `unsubscribed`.
    DeleteScene {
        /// The scene.
        scene: SceneId,
    },
    /// Add an avatar of a loaded rig to a scene. Result: `{ "avatar": id }`.
    AddAvatar {
        /// The scene.
        scene: SceneId,
        /// The rig's asset name.
        asset: String,
        /// The avatar's id; chosen by the server when absent.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        avatar: Option<AvatarId>,
        /// The clip to start playing, if any.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        clip: Option<String>,
        // --- placement (issue 16) ---
        /// World position `[x, y, z]` in metres; default the origin.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        position: Option<[f32; 3]>,
        /// World rotation `[x, y, z, w]`; default none.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rotation: Option<[f32; 4]>,
    },
    /// Remove an avatar from its scene.
    RemoveAvatar {
        /// The avatar.
        avatar: AvatarId,
    },
    /// Play a clip on an avatar, cross-fading from what it plays now.
    Play {
        /// The avatar.
        avatar: AvatarId,
        /// The clip's name.
        clip: String,
        /// Take the clip from another loaded rig and retarget it; absent: the avatar's own rig.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        from_asset: Option<String>,
        /// Playback speed (1 = authored; negative plays backwards). Default 1.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        speed: Option<f32>,
        /// Loop (default) or hold the last pose.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        looping: Option<bool>,
        /// Start offset into the clip, seconds from its start. Default 0.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        start: Option<f32>,
        /// Cross-fade duration in seconds. Default 0.25.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fade: Option<f32>,
        /// What the clip's root translation does; default in place for looping clips,
        /// accumulate (as authored) otherwise.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        root_motion: Option<RootMotion>,
    },
    /// Freeze the clock of the avatar's clip.
    Pause {
        /// The avatar.
        avatar: AvatarId,
    },
    /// Restart a paused clip's clock.
    Resume {
        /// The avatar.
        avatar: AvatarId,
    },
    /// Jump to a clip time (seconds from the clip's start).
    Seek {
        /// The avatar.
        avatar: AvatarId,
        /// Clip time.
        time: f32,
    },
    /// Change the playback speed.
    SetSpeed {
        /// The avatar.
        avatar: AvatarId,
        /// New speed.
        speed: f32,
    },
    /// Stop the clip; the avatar holds its neutral (rest) pose.
    Stop {
        /// The avatar.
        avatar: AvatarId,
    },
    // --- clip layers (issue 29 goal 4) ---
    /// Play a clip on a named layer over the avatar's clip: on the joints of `mask` only
    /// (absent: every joint), replacing their rotations (blended by `weight`) or, `additive`,
    /// adding on top the rotation the clip turns each joint through from the rig's rest pose.
    /// Playing on an existing layer cross-fades to the new clip there (its mask, mode and
    /// weight change at once); a new layer fades in over `fade` seconds. Layers apply after the
    /// clip and its root motion and before a live driver, IK goals, overrides and DOF limits,
    /// in the order they were first played; at most [`MAX_LAYERS`] per avatar.
    PlayLayer {
        /// The avatar.
        avatar: AvatarId,
        /// The layer's name (e.g. `upper`, `breathing`).
        layer: String,
        /// The clip's name.
        clip: String,
        /// Take the clip from another loaded rig and retarget it; absent: the avatar's own rig.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        from_asset: Option<String>,
        /// The joints the layer owns; absent: all.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mask: Option<JointMask>,
        /// Add the clip's rotations (away from the reference pose) on top instead of replacing.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        additive: bool,
        /// What an additive layer's rotations are taken away from: the rig's rest pose
        /// (default) or the clip's first frame (a clip authored as whole poses, such as an
        /// idle, then adds only its motion).
        #[serde(default, skip_serializing_if = "AdditiveReference::is_rest")]
        reference: AdditiveReference,
        /// How much of the layer shows, 0 to 1 (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        weight: Option<f32>,
        /// Playback speed (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        speed: Option<f32>,
        /// Loop (default) or hold the last pose.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        looping: Option<bool>,
        /// Start offset into the clip, seconds. Default 0.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        start: Option<f32>,
        /// Fade-in (or cross-fade) seconds. Default 0.25.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fade: Option<f32>,
    },
    /// Fade a layer out over `fade` seconds (default 0.25) and remove it.
    StopLayer {
        /// The avatar.
        avatar: AvatarId,
        /// The layer's name.
        layer: String,
        /// Fade-out seconds. Default 0.25.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fade: Option<f32>,
    },
    /// Override a joint's local rotation (layered over the clip until released).
    SetJointRotation {
        /// The avatar.
        avatar: AvatarId,
        /// Joint name.
        joint: String,
        /// Local rotation `[x, y, z, w]`.
        rotation: [f32; 4],
    },
    /// Override a joint with its DOF values (radians for rotations), clamped to its limits.
    SetJointDofs {
        /// The avatar.
        avatar: AvatarId,
        /// Joint name.
        joint: String,
        /// One value per DOF of the joint's type.
        values: Vec<f32>,
    },
    /// Apply a local increment `Ul' = incr · Ul` to the joint's current rotation.
    RotateJointLocal {
        /// The avatar.
        avatar: AvatarId,
        /// Joint name.
        joint: String,
        /// The increment `[x, y, z, w]`.
        rotation: [f32; 4],
    },
    /// Apply a world-space increment `U` so that `W' = U · W` (seed 001:
    /// `Ul' = L⁻¹ W_parent⁻¹ U W`). The result is clamped to the joint's limits.
    RotateJointWorld {
        /// The avatar.
        avatar: AvatarId,
        /// Joint name.
        joint: String,
        /// The world-space rotation `[x, y, z, w]`.
        rotation: [f32; 4],
    },
    /// Release a joint's override (or every override when `joint` is absent).
    Release {
        /// The avatar.
        avatar: AvatarId,
        /// Joint name, or all.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        joint: Option<String>,
    },
    // --- inverse kinematics (seed 002) ---
    /// Set (or replace) the IK goal of a chain named by its end joint: the effector reaches
    /// `position` (and takes `rotation`) in the scene's space, or in the frame of
    /// `relative_to`'s joint (then it follows that joint). Solved every tick after the clip and
    /// the live pose, before overrides and DOF limits. A limb end (`l_wrist`, `r_wrist`,
    /// `l_ankle`, `r_ankle`) moves its limb, bending toward `pole`; any other joint moves
    /// `chain` joints up from it (3 by default, itself included).
    SetIkGoal {
        /// The avatar.
        avatar: AvatarId,
        /// The chain's end joint.
        effector: String,
        /// Where it goes `[x, y, z]`, metres (each within ±10⁶).
        position: [f32; 3],
        /// Its rotation `[x, y, z, w]` in the same frame (finite, non-zero; normalised).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rotation: Option<[f32; 4]>,
        /// How much of the solve applies, 0 to 1 (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        weight: Option<f32>,
        /// A point the limb's middle joint (elbow, knee) bends toward, in the same frame.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pole: Option<[f32; 3]>,
        /// The joint (of this avatar or another of its scene) whose frame the values are in.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        relative_to: Option<JointRef>,
        /// Joints in the chain, the effector included (2 to 32): solved by FABRIK; absent for a
        /// limb end, its limb in closed form.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        chain: Option<u8>,
    },
    /// Clear one effector's IK goal, or every goal and the gaze when `effector` is absent:
    /// the goals' weights fall to 0 over `fade` seconds, so the joints return to their clip
    /// smoothly.
    ClearIkGoal {
        /// The avatar.
        avatar: AvatarId,
        /// The effector whose goal ends.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        effector: Option<String>,
        /// Seconds to let go over (finite, ≥ 0; default 0.25, `play`'s default fade; 0: at once).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fade: Option<f32>,
    },
    /// Turn the neck, head and eyes toward `target` (scene space, or `relative_to`'s joint's
    /// frame: look at another avatar's head); weight 0 lets the gaze go over 0.25 s.
    LookAt {
        /// The avatar.
        avatar: AvatarId,
        /// The point looked at `[x, y, z]`, metres.
        target: [f32; 3],
        /// How much of the turn applies, 0 to 1 (default 1; 0 lets the gaze go).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        weight: Option<f32>,
        /// The joint whose frame `target` is in.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        relative_to: Option<JointRef>,
    },
    // --- faces (issue 30) ---
    /// Set morph weights by name: a morph channel of the avatar's (its description's
    /// `morph_targets`) or a standard expression its `expressions` map (ARKit, VRM 1.0 or 0.x
    /// preset, `viseme_*`). Each weight in `[0, 1]`; `reset` sets every other channel to 0
    /// first. All names and values are checked before anything changes.
    SetMorphWeights {
        /// The avatar.
        avatar: AvatarId,
        /// Name → weight.
        weights: std::collections::BTreeMap<String, f32>,
        /// Every channel not named goes to 0 first (default: they keep their weights).
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        reset: bool,
    },
    /// Show one expression: `set_morph_weights` of one name, weight 1 unless given.
    SetExpression {
        /// The avatar.
        avatar: AvatarId,
        /// A standard expression (`happy`, `blink`, `aa`, `jawOpen`, `viseme_PP`, …) or one of
        /// the avatar's morph channels.
        expression: String,
        /// How much, 0 to 1 (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        weight: Option<f32>,
    },
    // --- placement (issue 16) ---
    /// Move an avatar in its scene: to `position` / `rotation`, over `duration` seconds
    /// (position lerped, rotation slerped on the scene's clock; absent or 0: at once).
    PlaceAvatar {
        /// The avatar.
        avatar: AvatarId,
        /// World position `[x, y, z]`, metres (each within ±[`crate::placement::MAX_PLACEMENT_METRES`]).
        position: [f32; 3],
        /// World rotation `[x, y, z, w]` (normalised; must be finite and non-zero).
        rotation: [f32; 4],
        /// Seconds to get there (finite, ≥ 0).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        duration: Option<f32>,
    },

    // --- Live driving (issue 16): a websocket connection streams poses to an avatar. ---
    /// Become the avatar's live driver (websocket only): `pose` messages from this connection
    /// then set its pose, retargeted from `source` when given. Result: [`DriveInfo`].
    Drive {
        /// The avatar.
        avatar: AvatarId,
        /// The rig (asset) whose joints the poses name; absent: the avatar's own rig.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        source: Option<String>,
        /// What the avatar does when the driver leaves, goes silent or releases: return to
        /// its clip (default) or hold the last pose.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        on_release: Option<OnRelease>,
        /// The joints the driver owns (`{"joints": ["r_sternoclavicular"]}`: the right arm):
        /// its poses set only these, and the avatar's clip and layers keep the rest; absent:
        /// every joint. The root's translation follows the driver only when it owns the root.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        joints: Option<JointMask>,
        /// Tracker driving: the trackers this driver's poses give, in the order binary poses
        /// index them — `head`, `l_hand` and `r_hand` always; `hips`, `l_foot`, `r_foot` and
        /// joints of the avatar's rig (by its own or H-Anim name) optionally; at most
        /// [`crate::trackers::MAX_TRACKERS`], no name twice. Poses then carry tracker
        /// transforms in the scene's space (`trackers`), not rotations, and the server solves
        /// the avatar's whole body from them every tick. Only on the avatar's own rig (no
        /// `source`). Absent: poses carry local rotations.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        trackers: Option<Vec<String>>,
        /// With `trackers`: what moves the legs (default `planted`: feet stand where they are
        /// planted and step when the hips move away, or follow foot trackers).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        legs: Option<crate::trackers::Legs>,
        /// With `legs: "locomotion"`: the avatar's clips the legs play, each with the speed
        /// (m/s) its walk covers; the server picks the one nearest the hips' speed and plays it
        /// at the matching rate on a `@locomotion` layer over the legs.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        locomotion: Option<Vec<crate::trackers::LocomotionClip>>,
    },
    /// Measure a tracker-driven avatar's user (`drive … trackers`) from their trackers'
    /// latest transforms while they stand in `pose`: their height (and with a T-pose their arm
    /// span) scales their trackers to the avatar, and each tracker's offset from the joint it
    /// stands for is kept. Result: [`crate::trackers::CalibrationInfo`].
    CalibrateTrackers {
        /// The avatar.
        avatar: AvatarId,
        /// The pose the user holds (default `neutral`: standing, arms at the sides).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pose: Option<crate::trackers::CalibrationPose>,
    },
    /// End live driving of the avatar (also clears a held pose); it returns to its clip.
    #[serde(alias = "undrive")]
    ReleaseDrive {
        /// The avatar.
        avatar: AvatarId,
    },

    // --- Recording (issue 16) ---
    /// Start recording what the avatar streams — whatever drives it: clips, overrides, a live
    /// driver — into a new clip `clip` on its rig, taken at every tick until `stop_recording`
    /// (or `max_seconds`, at most the server's limit, after which ticks are dropped).
    Record {
        /// The avatar.
        avatar: AvatarId,
        /// The new clip's name (an id: 1–64 letters, digits, `-`, `_`, `.`), not yet a clip of
        /// the avatar's rig.
        clip: String,
        /// Longest recording, seconds of scene time (default and most: the server's limit).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_seconds: Option<f32>,
    },
    /// Stop the avatar's recording: with a data folder the clip is stored, then it joins its
    /// rig (playable by every avatar of that rig), then the answer. Result: [`RecordingInfo`].
    /// A refusal (`quota_exceeded`, `storage_full`, `internal`) discards the take and leaves
    /// nothing: the clip's name is free again.
    StopRecording {
        /// The avatar.
        avatar: AvatarId,
    },
    /// Delete a clip recorded on a rig (`stop_recording`): taken off the rig and, with a data
    /// folder, removed from it before the answer, freeing its bytes from the quotas. Refused
    /// with `conflict` while an avatar plays it (stop the avatar first); `unknown_clip` for a
    /// clip that is not a stored recording (a file's clips go with `delete_asset`). A token
    /// limited to scenes or avatars deletes only recordings it made.
    DeleteClip {
        /// The rig.
        asset: String,
        /// The recorded clip.
        clip: String,
    },
    /// Delete an uploaded asset: its rigs leave the library and its folder the data folder
    /// (and the cluster's store), with the recordings made on its rigs, freeing their bytes.
    /// Refused with `conflict` while an avatar is made of one of its rigs or plays a clip
    /// retargeted from one. Needs an unlimited control token, or the token that uploaded it.
    DeleteAsset {
        /// The upload's name.
        asset: String,
    },

    // --- Takes of a whole scene (issue 32) ---
    /// Start recording everything the scene streams — every avatar's poses and morph weights,
    /// placements, avatars added and removed — as the frames already encoded for its binary
    /// subscribers, into take `take`: a file of the data folder written as the scene ticks (a
    /// crash loses at most its last second), or memory on a server without one. Until
    /// `stop_recording_scene`, `max_seconds` of scene time (default and most: the server's
    /// limit) or the data quota, whichever comes first. Result: [`TakeInfo`].
    RecordScene {
        /// The scene.
        scene: SceneId,
        /// The take's name (an id: 1–64 letters, digits, `-`, `_`, `.`), not yet a take.
        take: String,
        /// Longest take, seconds of scene time.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_seconds: Option<f32>,
    },
    /// Stop recording the scene: the take is complete and synced before the answer. Result:
    /// [`TakeInfo`].
    StopRecordingScene {
        /// The scene.
        scene: SceneId,
    },
    /// The takes, oldest first. Result: `[TakeInfo]`.
    ListTakes,
    /// One take. Result: [`TakeInfo`].
    GetTake {
        /// The take.
        take: String,
    },
    /// Delete a take (not while it is recorded or replayed), freeing its bytes.
    DeleteTake {
        /// The take.
        take: String,
    },
    /// Replay a take as a new scene `scene`, which viewers subscribe to like any other: its
    /// avatars (made of the rigs the take names, which must still be loaded) move as
    /// recorded, each frame what the recorded scene's subscribers received. A replayed avatar
    /// taken over by `play` or `drive` leaves the replay; the others go on. Deleting the scene
    /// ends the replay. Replays are not stored: a restart ends them. Result: [`ReplayState`].
    Replay {
        /// The take.
        take: String,
        /// The new scene's id.
        scene: SceneId,
        /// Take seconds per scene second (default 1; 0.01–100).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        speed: Option<f32>,
        /// Start again at the beginning after the end (default: hold the last frame).
        #[serde(rename = "loop", default, skip_serializing_if = "Option::is_none")]
        looping: Option<bool>,
        /// Where to start, seconds into the take (default 0).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        from: Option<f32>,
    },
    /// Seek, pause or resume, change the speed or looping of a replay; absent fields stay.
    /// Result: [`ReplayState`].
    ControlReplay {
        /// The replay's scene.
        scene: SceneId,
        /// Seek to this time, seconds into the take (clamped to it).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        time: Option<f32>,
        /// Pause (`true`) or resume (`false`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        paused: Option<bool>,
        /// Take seconds per scene second (0.01–100).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        speed: Option<f32>,
        /// Loop at the end.
        #[serde(rename = "loop", default, skip_serializing_if = "Option::is_none")]
        looping: Option<bool>,
    },
}

/// A take of a whole scene (`record_scene`), as listed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct TakeInfo {
    /// Its name.
    pub take: String,
    /// The scene it recorded.
    pub scene: SceneId,
    /// Seconds from its first frame to its last.
    pub duration: f64,
    /// Frames (ticks) it holds.
    pub frames: usize,
    /// Every avatar that appears in it, in order of appearance.
    pub avatars: Vec<AvatarId>,
    /// Its size in bytes.
    pub bytes: u64,
    /// When recording started, µs since the Unix epoch.
    pub started_us: u64,
    /// Whether it is being recorded now.
    pub recording: bool,
    /// Bytes after its last complete frame that a crash cut short (ignored when read).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub torn_bytes: u64,
    /// Who drove which avatar live during the take, each pair once, in order of first drive
    /// (listed once the take is stopped).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub drivers: Vec<TakeDriver>,
}

/// A live driver of an avatar during a take ([`TakeInfo::drivers`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct TakeDriver {
    /// The avatar (its id in the take).
    pub avatar: AvatarId,
    /// The driver's name, as the scene list shows it ([`Driver::name`]).
    pub name: String,
    /// How its poses arrived.
    pub via: DriveVia,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

/// Where a replay (`replay`, `control_replay`) is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct ReplayState {
    /// The replay's scene.
    pub scene: SceneId,
    /// The take it replays.
    pub take: String,
    /// Seconds into the take.
    pub time: f64,
    /// The take's duration, seconds.
    pub duration: f64,
    /// Whether it is paused.
    pub paused: bool,
    /// Take seconds per scene second.
    pub speed: f32,
    /// Whether it loops.
    #[serde(rename = "loop")]
    pub looping: bool,
}

/// The answer to `stop_recording`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct RecordingInfo {
    /// The rig the clip was added to.
    pub asset: String,
    /// The clip's name.
    pub clip: String,
    /// Its length, seconds.
    pub duration: f32,
    /// Ticks recorded.
    pub frames: usize,
    /// Ticks past the recording's limit, not kept.
    pub dropped: u64,
}

/// What a clip's root translation does to the avatar (`play`'s `root_motion`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum RootMotion {
    /// The root's horizontal (X, Z) motion is removed, its height kept: the avatar walks on
    /// the spot where its placement puts it.
    InPlace,
    /// The root moves as authored, and every loop continues from where the last one ended:
    /// each wrap adds the clip's net horizontal root displacement, turned by the placement's
    /// rotation, to the placement's position.
    Accumulate,
}

/// What a live-driven avatar does when its driver goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum OnRelease {
    /// Play its clip again (overrides stay).
    #[default]
    Clip,
    /// Keep the last pose until `release_drive` or another `drive`.
    Hold,
}

/// The answer to `drive`: how to address poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct DriveInfo {
    /// The avatar.
    pub avatar: AvatarId,
    /// Its number (what binary pose messages carry).
    pub avatar_num: u32,
    /// The source rig's name.
    pub source: String,
    /// The source rig's joints, in order: binary pose messages index this list.
    pub joints: Vec<String>,
    /// The source rig's root joint (what `root_position` moves).
    pub root: String,
    /// Seconds of silence after which the driver is released.
    pub timeout: f32,
    /// Most poses per second accepted from the driver.
    pub max_rate_hz: f32,
    /// The avatar's morph channels (its description's `morph_targets`): binary pose messages
    /// give weights by index into this list. Absent for a rig without morph targets.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub morph_targets: Vec<String>,
    /// Standard expression names → channel (its description's `expressions`), which JSON
    /// poses may name weights by.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub expressions: std::collections::BTreeMap<String, String>,
    /// A tracker drive's trackers (`drive … trackers`), in order: binary poses index this
    /// list. Absent for a drive by rotations.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub trackers: Vec<String>,
}

impl Command {
    /// The scene a command is about, when it names one directly.
    #[must_use]
    pub fn scene(&self) -> Option<&SceneId> {
        match self {
            Self::CreateScene { scene }
            | Self::DeleteScene { scene }
            | Self::AddAvatar { scene, .. }
            | Self::RecordScene { scene, .. }
            | Self::StopRecordingScene { scene }
            | Self::Replay { scene, .. }
            | Self::ControlReplay { scene, .. } => Some(scene),
            _ => None,
        }
    }

    /// The avatar a command is about, when it names one.
    #[must_use]
    pub fn avatar(&self) -> Option<&AvatarId> {
        match self {
            Self::GetAvatar { avatar }
            | Self::GetJoint { avatar, .. }
            | Self::SamplePose { avatar, .. }
            | Self::RemoveAvatar { avatar }
            | Self::Play { avatar, .. }
            | Self::PlayLayer { avatar, .. }
            | Self::StopLayer { avatar, .. }
            | Self::Pause { avatar }
            | Self::Resume { avatar }
            | Self::Seek { avatar, .. }
            | Self::SetSpeed { avatar, .. }
            | Self::Stop { avatar }
            | Self::SetJointRotation { avatar, .. }
            | Self::SetJointDofs { avatar, .. }
            | Self::RotateJointLocal { avatar, .. }
            | Self::RotateJointWorld { avatar, .. }
            | Self::Release { avatar, .. }
            | Self::SetIkGoal { avatar, .. }
            | Self::ClearIkGoal { avatar, .. }
            | Self::LookAt { avatar, .. }
            | Self::SetMorphWeights { avatar, .. }
            | Self::SetExpression { avatar, .. }
            | Self::PlaceAvatar { avatar, .. } => Some(avatar),
            Self::Drive { avatar, .. }
            | Self::CalibrateTrackers { avatar, .. }
            | Self::ReleaseDrive { avatar } => Some(avatar),
            Self::Record { avatar, .. } | Self::StopRecording { avatar } => Some(avatar),
            Self::AddAvatar { avatar, .. } => avatar.as_ref(),
            _ => None,
        }
    }

    /// Whether the command only reads (allowed with a view token).
    #[must_use]
    pub fn is_read_only(&self) -> bool {
        matches!(
            self,
            Self::ListScenes
                | Self::ListAssets
                | Self::GetAsset { .. }
                | Self::GetAvatar { .. }
                | Self::GetJoint { .. }
                | Self::SamplePose { .. }
                | Self::ListTakes
                | Self::GetTake { .. }
        )
    }
}

/// A scene as listed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct SceneInfo {
    /// The scene.
    pub scene: SceneId,
    /// Its avatars.
    pub avatars: Vec<AvatarState>,
    /// Current subscriber count.
    pub subscribers: usize,
    /// The server ticking it, when servers form a cluster (`--nats`); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub owner: Option<String>,
    /// Who watches it (presence): its subscribers by token name, the most connections first
    /// (at most [`MAX_VIEWER_NAMES`] names; the rest count under `name: null` with the
    /// anonymous ones). Changes follow as `viewers` messages to the scene list's watchers.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub viewers: Vec<Viewer>,
}

/// Most token names a scene's [`SceneInfo::viewers`] lists.
pub const MAX_VIEWER_NAMES: usize = 64;

/// Connections watching a scene under one token name.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Viewer {
    /// The token's name; `null`: anonymous (and the names beyond the list's limit).
    pub name: Option<String>,
    /// Its subscribed connections.
    pub connections: u32,
}

/// Who drives an avatar live, and how.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Driver {
    /// The driving connection's token name (`anonymous` without one); for a VMC input
    /// `vmc ADDRESS` (the UDP address it listens on).
    pub name: String,
    /// How the poses arrive.
    pub via: DriveVia,
}

/// How a live driver's poses arrive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum DriveVia {
    /// A websocket connection of this server (`drive`, then `pose` messages).
    Websocket,
    /// A VMC input (`--vmc-in`, or a `posecast-client vmc-relay`).
    Vmc,
    /// A websocket connection of another server of the cluster.
    Cluster,
}

/// A loaded rig as listed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct AssetInfo {
    /// The asset's name (what `add_avatar` and `from_asset` take).
    pub name: String,
    /// Joint count.
    pub joints: usize,
    /// Its clips.
    pub clips: Vec<ClipInfo>,
    /// What the import pipeline did to the rig, in order.
    pub pipeline: Vec<String>,
    /// Whether the rig is a humanoid: it has the H-Anim neutral pose and takes (and gives)
    /// humanoid clips; rigs that are not keep their own neutral pose.
    #[serde(default)]
    pub humanoid: bool,
    /// Joints with an H-Anim name (of `joints`).
    #[serde(default)]
    pub mapped: usize,
    /// What the importer skipped, defaulted or approximated (a material not imported, a
    /// repeated name suffixed, a channel skipped, a clip with fewer channels than the rig).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

/// One rig in full, as `get_asset` reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct AssetDetail {
    /// What `list_assets` says about it.
    #[serde(flatten)]
    pub info: AssetInfo,
    /// Every joint, in order, with its parent and H-Anim name: the effective mapping.
    pub mapping: Vec<JointMapping>,
    /// The pipeline options it was normalised with (change them with `configure_asset`).
    pub options: PipelineOptions,
    /// Metres per file unit the normalisation used, and how it was decided.
    pub units: Units,
    /// Whether `configure_asset` can normalise it again (uploaded assets can).
    pub configurable: bool,
}

/// A joint and its H-Anim name.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct JointMapping {
    /// The joint's name in the rig.
    pub joint: String,
    /// Its parent's name (none for a root).
    pub parent: Option<String>,
    /// Its H-Anim name, if mapped.
    pub hanim: Option<String>,
}

/// The unit conversion a rig went through.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Units {
    /// Metres per file unit (applied to translations and the mesh).
    pub metres_per_unit: f32,
    /// `configured`, `file` (the format or file says) or `guessed` (from the rig's height).
    pub source: String,
    /// The rig's height at rest in file units (joints and mesh, along its up axis).
    pub height: f32,
}

/// A clip as listed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct ClipInfo {
    /// Its name.
    pub name: String,
    /// Duration in seconds.
    pub duration: f32,
}

/// One joint as `get_joint` reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct JointInfo {
    /// The joint's name.
    pub joint: String,
    /// Its parent's name (none for a root).
    pub parent: Option<String>,
    /// Its joint type (`hinge`, `universal`, `ball_euler`, `ball_quaternion`, `prismatic`,
    /// `translational`) when the rig defines joint types (e.g. `.skel`), else none: set it by
    /// rotation.
    pub joint_type: Option<String>,
    /// Its DOFs, in `set_joint_dofs` order: the current value (radians; the current local
    /// rotation projected onto the DOFs) and the limits (none: unlimited).
    pub dofs: Vec<DofInfo>,
    /// Its current local rotation `[x, y, z, w]` (clip plus override).
    pub rotation: [f32; 4],
    /// Whether an override holds it.
    pub overridden: bool,
}

/// One DOF of a joint.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct DofInfo {
    /// Current value (radians, or metres for translational DOFs).
    pub value: f32,
    /// Lower limit, if any.
    pub min: Option<f32>,
    /// Upper limit, if any.
    pub max: Option<f32>,
}

/// What an additive clip layer's rotations are measured from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum AdditiveReference {
    /// The rig's rest (neutral) pose.
    #[default]
    Rest,
    /// The clip's first frame.
    FirstFrame,
}

impl AdditiveReference {
    /// Whether this is the default, [`AdditiveReference::Rest`] (for `skip_serializing_if`).
    #[must_use]
    pub fn is_rest(&self) -> bool {
        *self == Self::Rest
    }
}

/// Most clip layers an avatar plays at once (`play_layer`).
pub const MAX_LAYERS: usize = 8;

/// The joints a clip layer owns: each joint of `joints` and everything below it, less each
/// joint of `except` and everything below it. Names are the rig's own or H-Anim names
/// (`{"joints": ["vl5"], "except": ["l_sternoclavicular"]}`: the upper body but the left arm).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(deny_unknown_fields)]
pub struct JointMask {
    /// Subtrees the layer owns.
    pub joints: Vec<String>,
    /// Subtrees taken out of them.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub except: Vec<String>,
}

fn one() -> f32 {
    1.0
}

/// A clip layer as `get_avatar` reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct LayerState {
    /// The layer's name.
    pub layer: String,
    /// The clip it plays.
    pub clip: String,
    /// Clip time, seconds.
    pub time: f32,
    /// Clip seconds per second (what `play_layer … speed` set, or a tracker drive's
    /// locomotion rate).
    #[serde(default = "one")]
    pub speed: f32,
    /// Whether it adds to the pose below rather than replacing it.
    pub additive: bool,
    /// The weight it shows now (fades included).
    pub weight: f32,
    /// How many joints it owns.
    pub joints: usize,
}

/// An avatar's playback state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct AvatarState {
    /// The avatar.
    pub avatar: AvatarId,
    /// Its scene.
    pub scene: SceneId,
    /// The rig it uses.
    pub asset: String,
    /// The clip playing, if any.
    pub clip: Option<String>,
    /// The asset the clip came from when retargeted.
    pub clip_asset: Option<String>,
    /// Clip time in seconds from the clip's start.
    pub time: f32,
    /// Playback speed.
    pub speed: f32,
    /// Whether it loops.
    pub looping: bool,
    /// Whether paused.
    pub paused: bool,
    /// Joints with an override.
    pub overrides: Vec<String>,
    // --- placement (issue 16) ---
    /// Where it stands now (mid-move: the interpolated placement).
    #[serde(default)]
    pub placement: crate::placement::Placement,
    /// The current clip's root motion, if a clip plays.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_motion: Option<RootMotion>,
    // --- live driving and recording (issue 16) ---
    /// Whether a live driver sets its pose (a held pose counts: `drive … on_release hold`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub driven: bool,
    /// Who drives it live and how, while a driver is connected (presence).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub driver: Option<Driver>,
    /// The clip being recorded, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recording: Option<String>,
    // --- VMC (issue 17) ---
    /// Blend shape (expression) values its live driver applied, by name (VMC
    /// `/VMC/Ext/Blend/Val` + `Apply`), as sent; those naming a morph channel or a standard
    /// expression of the avatar also set `morph_weights`.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub blend_shapes: std::collections::BTreeMap<String, f32>,
    /// Morph weights by channel name as shown (streamed), those above 0 (issue 30): per
    /// channel the larger of the weight set (`set_morph_weights`, a live driver, VMC) and the
    /// playing clip's; absent when all are 0.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub morph_weights: std::collections::BTreeMap<String, f32>,
    /// The cross-fade in progress (after `play … fade`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fade: Option<FadeState>,
    /// The effectors with an IK goal (`set_ik_goal`), in the order they are solved.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ik_goals: Vec<String>,
    /// Whether a gaze (`look_at`) is set.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub looking: bool,
    /// Clip layers over the clip (`play_layer`), in the order they apply.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub layers: Vec<LayerState>,
}

/// A joint of an avatar, whose frame an IK goal is given in.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct JointRef {
    /// The avatar (this one, or another of the same scene).
    pub avatar: AvatarId,
    /// The joint's name on its rig.
    pub joint: String,
}

/// A cross-fade in progress: the clip fading out and how far the fade is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct FadeState {
    /// The clip fading out.
    pub from: String,
    /// The rig that clip came from when it was retargeted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_asset: Option<String>,
    /// Seconds of the fade done at the state's tick (scene time; the new clip's weight is
    /// `elapsed / duration`).
    pub elapsed: f32,
    /// The fade's length, seconds.
    pub duration: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_are_tagged_by_op_and_reject_unknown_fields() {
        let c = Command::Seek {
            avatar: AvatarId("a".into()),
            time: 1.5,
        };
        let text = serde_json::to_string(&c).unwrap();
        assert_eq!(text, r#"{"op":"seek","avatar":"a","time":1.5}"#);
        assert_eq!(serde_json::from_str::<Command>(&text).unwrap(), c);
        assert!(
            serde_json::from_str::<Command>(r#"{"op":"seek","avatar":"a","time":1,"x":2}"#)
                .is_err()
        );
        assert!(serde_json::from_str::<Command>(r#"{"op":"fly"}"#).is_err());
        assert!(c.avatar().is_some() && !c.is_read_only());
    }

    /// A tracker drive names its trackers and legs; a drive without them writes neither, and
    /// `calibrate_trackers` is tagged in snake case with an optional pose.
    #[test]
    fn tracker_drives_and_calibration_read_and_write() {
        let drive: Command = serde_json::from_str(
            r#"{"op":"drive","avatar":"a","trackers":["head","l_hand","r_hand"],"legs":"animated"}"#,
        )
        .unwrap();
        let Command::Drive { trackers, legs, .. } = &drive else {
            panic!("{drive:?}");
        };
        assert_eq!(trackers.as_deref().map(<[String]>::len), Some(3));
        assert_eq!(*legs, Some(crate::trackers::Legs::Animated));
        let plain = Command::Drive {
            avatar: AvatarId("a".into()),
            source: None,
            on_release: None,
            joints: None,
            trackers: None,
            legs: None,
            locomotion: None,
        };
        assert_eq!(
            serde_json::to_string(&plain).unwrap(),
            r#"{"op":"drive","avatar":"a"}"#
        );
        let calibrate: Command =
            serde_json::from_str(r#"{"op":"calibrate_trackers","avatar":"a","pose":"t_pose"}"#)
                .unwrap();
        assert_eq!(
            calibrate,
            Command::CalibrateTrackers {
                avatar: AvatarId("a".into()),
                pose: Some(crate::trackers::CalibrationPose::TPose),
            }
        );
        assert!(calibrate.avatar().is_some() && !calibrate.is_read_only());
        assert!(
            serde_json::from_str::<Command>(
                r#"{"op":"calibrate_trackers","avatar":"a","pose":"x"}"#
            )
            .is_err()
        );
    }
}

/// What a successful command returns, one variant per shape. Tagged: `kind` names the shape
/// (snake_case, e.g. `avatar_added`) and `result` holds the value — an array or an object;
/// `null` in an `ack` or a REST answer for [`CommandResult::Done`] (these write
/// [`CommandResult::to_tagged_value`]), absent in serde's own form (cluster messages, stored
/// answers). An `ack` of protocol version 1 or 2 carries the bare value alone
/// ([`CommandResult::to_value`]), which [`CommandResult::from_bare`] reads back by its shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(tag = "kind", content = "result", rename_all = "snake_case")]
pub enum CommandResult {
    /// `list_scenes`.
    Scenes(Vec<SceneInfo>),
    /// `list_assets`, `configure_asset`, an upload.
    Assets(Vec<AssetInfo>),
    /// `get_avatar`.
    Avatar(Box<AvatarState>),
    /// `get_joint`.
    Joint(Box<JointInfo>),
    /// `drive`.
    Drive(Box<DriveInfo>),
    /// `stop_recording`.
    Recorded(Box<RecordingInfo>),
    /// `get_asset`.
    Asset(Box<AssetDetail>),
    /// `sample_pose`.
    Pose(Box<crate::msg::AvatarPoseJson>),
    /// `calibrate_trackers`.
    Calibration(Box<crate::trackers::CalibrationInfo>),
    /// `list_takes`.
    Takes(Vec<TakeInfo>),
    /// `record_scene`, `stop_recording_scene`, `get_take`.
    Take(Box<TakeInfo>),
    /// `replay`, `control_replay`.
    Replay(Box<ReplayState>),
    /// `create_scene`.
    SceneCreated {
        /// The new scene.
        scene: SceneId,
    },
    /// `add_avatar`.
    AvatarAdded {
        /// The new avatar's id (chosen by the server when the command named none).
        avatar: AvatarId,
    },
    /// `set_joint_dofs`: the rotation set and the DOF values after clamping.
    Dofs {
        /// The joint's new local rotation.
        rotation: [f32; 4],
        /// Its DOF values, in the joint's order, after limits.
        values: Vec<f32>,
    },
    /// `set_joint_rotation`, `rotate_joint_local`, `rotate_joint_world`: the local rotation
    /// actually set (after limits).
    Rotation {
        /// The joint's new local rotation.
        rotation: [f32; 4],
    },
    /// Every other command: nothing to say beyond the ack.
    Done,
}

impl CommandResult {
    /// The shape's name on the wire (`kind`): `scenes`, `avatar_added`, `done`, …
    #[must_use]
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Scenes(_) => "scenes",
            Self::Assets(_) => "assets",
            Self::Avatar(_) => "avatar",
            Self::Joint(_) => "joint",
            Self::Drive(_) => "drive",
            Self::Recorded(_) => "recorded",
            Self::Asset(_) => "asset",
            Self::Pose(_) => "pose",
            Self::Calibration(_) => "calibration",
            Self::Takes(_) => "takes",
            Self::Take(_) => "take",
            Self::Replay(_) => "replay",
            Self::SceneCreated { .. } => "scene_created",
            Self::AvatarAdded { .. } => "avatar_added",
            Self::Dofs { .. } => "dofs",
            Self::Rotation { .. } => "rotation",
            Self::Done => "done",
        }
    }

    /// The bare value, as versions 1 and 2 of the protocol carry it in `ack.result` (`null` for
    /// [`CommandResult::Done`]).
    #[must_use]
    pub fn to_value(&self) -> serde_json::Value {
        // Serialising these types cannot fail (no maps with non-string keys).
        match serde_json::to_value(self) {
            Ok(serde_json::Value::Object(mut tagged)) => {
                tagged.remove("result").unwrap_or(serde_json::Value::Null)
            }
            _ => serde_json::Value::Null,
        }
    }

    /// `{"kind": …, "result": …}` with the bare value (`null` for [`CommandResult::Done`]): an
    /// `ack` of protocol version 3 and a REST answer.
    #[must_use]
    pub fn to_tagged_value(&self) -> serde_json::Value {
        serde_json::json!({ "kind": self.kind(), "result": self.to_value() })
    }

    /// Reads a bare value (an `ack` of protocol version 1 or 2, an answer stored before results
    /// were tagged) by its shape: the first variant whose type reads it, in declaration order.
    /// An empty list reads as [`CommandResult::Scenes`]; a client that knows which command it
    /// sent can read the value as that command's type instead.
    ///
    /// # Errors
    /// No variant's type reads the value.
    pub fn from_bare(value: serde_json::Value) -> Result<Self, serde_json::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Bare {
            Scenes(Vec<SceneInfo>),
            Assets(Vec<AssetInfo>),
            Takes(Vec<TakeInfo>),
            Avatar(Box<AvatarState>),
            Joint(Box<JointInfo>),
            Drive(Box<DriveInfo>),
            Recorded(Box<RecordingInfo>),
            Asset(Box<AssetDetail>),
            Pose(Box<crate::msg::AvatarPoseJson>),
            // Before `avatar_added`, which would read its `avatar` alone.
            Calibration(Box<crate::trackers::CalibrationInfo>),
            Take(Box<TakeInfo>),
            Replay(Box<ReplayState>),
            SceneCreated {
                scene: SceneId,
            },
            AvatarAdded {
                avatar: AvatarId,
            },
            Dofs {
                rotation: [f32; 4],
                values: Vec<f32>,
            },
            Rotation {
                rotation: [f32; 4],
            },
            Done(()),
        }
        Ok(match serde_json::from_value(value)? {
            Bare::Scenes(v) => Self::Scenes(v),
            Bare::Assets(v) => Self::Assets(v),
            Bare::Takes(v) => Self::Takes(v),
            Bare::Avatar(v) => Self::Avatar(v),
            Bare::Joint(v) => Self::Joint(v),
            Bare::Drive(v) => Self::Drive(v),
            Bare::Recorded(v) => Self::Recorded(v),
            Bare::Asset(v) => Self::Asset(v),
            Bare::Pose(v) => Self::Pose(v),
            Bare::Calibration(v) => Self::Calibration(v),
            Bare::Take(v) => Self::Take(v),
            Bare::Replay(v) => Self::Replay(v),
            Bare::SceneCreated { scene } => Self::SceneCreated { scene },
            Bare::AvatarAdded { avatar } => Self::AvatarAdded { avatar },
            Bare::Dofs { rotation, values } => Self::Dofs { rotation, values },
            Bare::Rotation { rotation } => Self::Rotation { rotation },
            Bare::Done(()) => Self::Done,
        })
    }

    /// Reads a result either way it is written: tagged (`{"kind", "result"}`) or bare
    /// ([`CommandResult::from_bare`]) — for what was stored or sent before results were tagged.
    ///
    /// # Errors
    /// Neither way reads the value.
    pub fn from_tagged_or_bare(value: serde_json::Value) -> Result<Self, serde_json::Error> {
        if value.get("kind").is_some_and(serde_json::Value::is_string) {
            serde_json::from_value(value)
        } else {
            Self::from_bare(value)
        }
    }
}

#[cfg(test)]
mod result_tests {
    use super::*;
    use serde_json::json;

    /// Version 3 (and REST) write the kind beside the value; `done` has no value.
    #[test]
    fn results_are_tagged_with_their_kind() {
        let added = CommandResult::AvatarAdded {
            avatar: AvatarId("a".into()),
        };
        assert_eq!(
            serde_json::to_value(&added).unwrap(),
            json!({ "kind": "avatar_added", "result": { "avatar": "a" } })
        );
        assert_eq!(
            serde_json::to_value(CommandResult::Done).unwrap(),
            json!({ "kind": "done" })
        );
        assert_eq!(
            serde_json::to_value(CommandResult::Scenes(Vec::new())).unwrap(),
            json!({ "kind": "scenes", "result": [] })
        );
        // An empty list keeps its kind (bare, it would read as `scenes`).
        let assets = CommandResult::Assets(Vec::new());
        let back: CommandResult =
            serde_json::from_value(serde_json::to_value(&assets).unwrap()).unwrap();
        assert_eq!(back, assets);
        // `done` is read with or without a null value.
        let done: CommandResult =
            serde_json::from_value(json!({ "kind": "done", "result": null })).unwrap();
        assert_eq!(done, CommandResult::Done);
        for r in [
            added,
            CommandResult::Done,
            CommandResult::Rotation {
                rotation: [0.0, 0.0, 0.0, 1.0],
            },
            CommandResult::Dofs {
                rotation: [0.0, 0.0, 0.0, 1.0],
                values: vec![0.5],
            },
            CommandResult::Calibration(Box::new(crate::trackers::CalibrationInfo {
                avatar: AvatarId("a".into()),
                user_height: 1.8,
                scale: 0.9,
                arm_scale: 0.9,
                trackers: vec!["head".into()],
            })),
        ] {
            let tagged = serde_json::to_value(&r).unwrap();
            assert_eq!(tagged["kind"], r.kind(), "{tagged}");
            assert_eq!(CommandResult::from_tagged_or_bare(tagged).unwrap(), r);
            assert_eq!(CommandResult::from_tagged_or_bare(r.to_value()).unwrap(), r);
        }
    }

    /// The bare shapes versions 1 and 2 carry, as clients parsed them before the kind.
    #[test]
    fn results_serialise_as_bare_values() {
        assert_eq!(CommandResult::Done.to_value(), serde_json::Value::Null);
        assert_eq!(
            CommandResult::AvatarAdded {
                avatar: AvatarId("a".into())
            }
            .to_value(),
            json!({ "avatar": "a" })
        );
        assert_eq!(
            CommandResult::Rotation {
                rotation: [0.0, 0.0, 0.0, 1.0]
            }
            .to_value(),
            json!({ "rotation": [0.0, 0.0, 0.0, 1.0] })
        );
        assert_eq!(CommandResult::Scenes(Vec::new()).to_value(), json!([]));
        let dofs =
            CommandResult::from_bare(json!({ "rotation": [0.0, 0.0, 0.0, 1.0], "values": [0.5] }))
                .unwrap();
        assert!(matches!(dofs, CommandResult::Dofs { .. }), "{dofs:?}");
        assert!(CommandResult::from_bare(json!({ "nothing": 1 })).is_err());
    }
}
