//! Tracker driving (`drive … trackers`): a headset, two controllers and optionally hip and
//! foot trackers (or named joints) give world transforms, and the server solves the whole body
//! from them (see `proto/PROTOCOL.md`, "Trackers").
//!
//! A tracker's transform is in the **scene's space** (metres, Y up). Without a calibration a
//! tracker *is* its joint: a hand tracker's position is its wrist joint's (H-Anim `l_wrist`,
//! `r_wrist`), the head's the `skullbase`'s, the hips' the `humanoid_root`'s, a foot's its
//! ankle's, and its rotation is the joint's world rotation relative to the rig's neutral pose
//! (so a hand hanging at the side in the H-Anim pose reads identity). `calibrate_trackers`
//! measures the offsets from where the user's trackers really sit to those joints.

use serde::{Deserialize, Serialize};

/// The head tracker (a headset): the `skullbase` joint.
pub const HEAD: &str = "head";
/// The left hand tracker (a controller): the `l_wrist` joint.
pub const LEFT_HAND: &str = "l_hand";
/// The right hand tracker: the `r_wrist` joint.
pub const RIGHT_HAND: &str = "r_hand";
/// A hip (waist) tracker: the `humanoid_root` joint.
pub const HIPS: &str = "hips";
/// The left foot tracker: the `l_ankle` joint.
pub const LEFT_FOOT: &str = "l_foot";
/// The right foot tracker: the `r_ankle` joint.
pub const RIGHT_FOOT: &str = "r_foot";

/// The standard trackers, in order, with the H-Anim joint each stands for.
pub const STANDARD: [(&str, &str); 6] = [
    (HEAD, "skullbase"),
    (LEFT_HAND, "l_wrist"),
    (RIGHT_HAND, "r_wrist"),
    (HIPS, "humanoid_root"),
    (LEFT_FOOT, "l_ankle"),
    (RIGHT_FOOT, "r_ankle"),
];

/// The trackers every tracker drive needs.
pub const REQUIRED: [&str; 3] = [HEAD, LEFT_HAND, RIGHT_HAND];

/// Most trackers one drive may name (the six standard ones and ten named joints).
pub const MAX_TRACKERS: usize = 16;

/// One tracker's transform in a JSON `pose` message.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(deny_unknown_fields)]
pub struct TrackerTransform {
    /// Position `[x, y, z]` in the scene's space, metres.
    pub position: [f32; 3],
    /// Rotation `[x, y, z, w]` in the scene's space (normalised; finite and non-zero).
    pub rotation: [f32; 4],
}

/// What moves a tracker-driven avatar's legs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum Legs {
    /// Feet stand where they were planted and step when the hips move away from them (the
    /// default without foot trackers); with foot trackers, the feet follow them.
    #[default]
    Planted,
    /// The legs keep what the avatar's clip and clip layers give them (a walk cycle on a
    /// `legs` layer, say); the trackers place the hips.
    Animated,
    /// The legs play a locomotion clip (the drive's `locomotion` list) picked by how fast the
    /// hips move, at the rate that matches it, cross-faded as the speed changes.
    Locomotion,
}

/// Most clips a `locomotion` list may name.
pub const MAX_LOCOMOTION_CLIPS: usize = 8;

/// A clip the legs of a tracker drive may play (`drive … legs: "locomotion"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(deny_unknown_fields)]
pub struct LocomotionClip {
    /// One of the avatar's clips (`idle`, `walk`, …).
    pub clip: String,
    /// How fast its walk covers ground played at rate 1, m/s (0 for standing still; finite,
    /// 0 to 20).
    pub speed: f32,
}

/// The pose the user holds while `calibrate_trackers` measures them.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum CalibrationPose {
    /// Standing straight, looking ahead, arms hanging at the sides (the H-Anim neutral pose).
    #[default]
    Neutral,
    /// Standing straight, looking ahead, arms straight out to the sides, palms down: also
    /// measures the arm span.
    TPose,
    /// As the T-pose with the arms 45° below horizontal: also measures the arm span.
    APose,
}

/// What `calibrate_trackers` measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct CalibrationInfo {
    /// The avatar.
    pub avatar: crate::ids::AvatarId,
    /// The user's head (tracker) height above the scene's floor, metres.
    pub user_height: f32,
    /// The avatar's over the user's size: tracker positions are scaled by it about the user's
    /// place on the floor.
    pub scale: f32,
    /// The same for the arms (from a T- or A-pose's hand span; `scale` otherwise).
    pub arm_scale: f32,
    /// The trackers whose offsets were measured.
    pub trackers: Vec<String>,
}
