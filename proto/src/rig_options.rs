//! How the server normalises a rig it imports: the per-asset pipeline options a client gives
//! with an upload or a `configure_asset` command, and reads back with `get_asset`. The server
//! runs the pipeline (`posecast_server::rig::normalise`); these are the options' types and the
//! maths of naming an orientation.

use std::collections::BTreeMap;

use glam::{Mat3, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// An orientation that names a forward axis not perpendicular to its up axis.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("forward {forward} is not perpendicular to up {up}")]
pub struct AxisError {
    /// The up axis.
    pub up: Vec3,
    /// The forward axis.
    pub forward: Vec3,
}

/// A coordinate axis with a sign, as written in a pipeline config: `"+x"` (or `"x"`), `"-z"`, …
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub enum SignedAxis {
    /// `+x` (also written `x`).
    #[serde(rename = "+x", alias = "x")]
    PosX,
    /// `-x`.
    #[serde(rename = "-x")]
    NegX,
    /// `+y` (also written `y`).
    #[serde(rename = "+y", alias = "y")]
    PosY,
    /// `-y`.
    #[serde(rename = "-y")]
    NegY,
    /// `+z` (also written `z`).
    #[serde(rename = "+z", alias = "z")]
    PosZ,
    /// `-z`.
    #[serde(rename = "-z")]
    NegZ,
}

impl SignedAxis {
    /// The unit vector.
    #[must_use]
    pub fn vector(self) -> Vec3 {
        match self {
            Self::PosX => Vec3::X,
            Self::NegX => Vec3::NEG_X,
            Self::PosY => Vec3::Y,
            Self::NegY => Vec3::NEG_Y,
            Self::PosZ => Vec3::Z,
            Self::NegZ => Vec3::NEG_Z,
        }
    }

    /// The rotation `R` with `R·up = +Y` and `R·forward = +Z` (posecast's convention). Without
    /// `forward`, the first of `+Z`, `−Y`, `+X` perpendicular to `up` is taken (Z-up tools face
    /// `−Y`, so Z-up gives `R` = −90° about X).
    pub fn rotation_to_y_up(
        up: SignedAxis,
        forward: Option<SignedAxis>,
    ) -> Result<Quat, AxisError> {
        let u = up.vector();
        let f = match forward {
            Some(f) => f.vector(),
            None => [Vec3::Z, Vec3::NEG_Y, Vec3::X]
                .into_iter()
                .find(|f| f.dot(u) == 0.0)
                .unwrap_or(Vec3::Z),
        };
        if f.dot(u) != 0.0 {
            return Err(AxisError { up: u, forward: f });
        }
        // The source basis (right, up, forward) must land on (X, Y, Z): R = [u×f, u, f]ᵀ.
        let m = Mat3::from_cols(u.cross(f), u, f).transpose();
        Ok(Quat::from_mat3(&m).normalize())
    }
}

/// Which neutral pose the pipeline gives a rig.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum NeutralPose {
    /// H-Anim when the rig is humanoid (its hips, knees, shoulders and elbows are mapped),
    /// otherwise keep.
    #[default]
    Auto,
    /// H-Anim; an error when the rig is not humanoid.
    HAnim,
    /// Keep the current one (the bind pose, after simplification).
    Keep,
}

/// Per-asset pipeline configuration; `Default` is the default pipeline. Deserialises from JSON
/// with every field optional, e.g.
/// `{"up_axis": {"up": "+z", "forward": "-y"}, "metres_per_unit": 0.01, "neutral": "keep",
///   "name_map": {"Bip01_L_Thigh": "l_hip"}}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(default, deny_unknown_fields)]
pub struct PipelineOptions {
    /// Simplify bind matrices to translations (default true).
    pub simplify: bool,
    /// The source's orientation; `None` detects it (glTF `Z_UP` exports; BVH and CSE169 are
    /// Y-up by convention).
    pub up_axis: Option<UpAxisOverride>,
    /// Metres per file unit; `None` takes the file's (glTF: 1) or, where the format does not
    /// say (BVH, CSE169), guesses from the rig's height: 1 when it is 0.3–3 units tall,
    /// centimetres when 30–300, millimetres when 300–3000, else 1.
    pub metres_per_unit: Option<f32>,
    /// Which neutral pose (default: H-Anim when humanoid).
    pub neutral: NeutralPose,
    /// Joint name → H-Anim name, replacing the guesses for the joints it names (`""` unmaps).
    pub name_map: Option<BTreeMap<String, String>>,
    /// Whether the rig is a humanoid; `None` classifies it (humanoid when its mapping covers
    /// the H-Anim core chain and its legs hang away from its spine). A non-humanoid keeps its
    /// neutral pose and cannot take humanoid clips.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub humanoid: Option<bool>,
    /// Standard expression name (ARKit, VRM preset, `viseme_*`: `crate::expressions`) → the
    /// rig's morph target that plays it, replacing the guess for the names it lists (`""`
    /// unmaps). Each name must be a standard one and each target one of the rig's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub expression_map: Option<BTreeMap<String, String>>,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            simplify: true,
            up_axis: None,
            metres_per_unit: None,
            neutral: NeutralPose::Auto,
            name_map: None,
            humanoid: None,
            expression_map: None,
        }
    }
}

/// The source's orientation, as axes or as a rotation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(default, deny_unknown_fields)]
pub struct UpAxisOverride {
    /// The source's up axis (default `+y`).
    pub up: SignedAxis,
    /// The source's forward axis (the way the avatar faces); `None` picks the first of `+z`,
    /// `-y`, `+x` perpendicular to `up`.
    pub forward: Option<SignedAxis>,
    /// A rotation `R` (x, y, z, w) to apply instead of the axes.
    pub rotation: Option<[f32; 4]>,
    /// What to rotate; `None`: `bind` for glTF (whose scene is Y-up by
    /// specification), `world` otherwise.
    pub frame: Option<ReorientFrame>,
}

impl Default for UpAxisOverride {
    fn default() -> Self {
        Self {
            up: SignedAxis::PosY,
            forward: None,
            rotation: None,
            frame: None,
        }
    }
}

/// What a re-orientation rotates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum ReorientFrame {
    /// Everything, posed world included (`posecast_server::rig::reorient`): for sources whose world is not Y-up.
    World,
    /// Bind-space data only (`posecast_server::rig::reorient_bind_frame`): for sources whose posed world is
    /// already Y-up but whose mesh and binds are not (glTF `Z_UP` exports).
    Bind,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_round_trip_and_refuse_unknown_fields() {
        let json = r#"{"simplify": false, "up_axis": {"up": "+z", "forward": "-y", "frame": "world"},
            "metres_per_unit": 0.01, "neutral": "keep", "name_map": {"a": "l_hip"}, "humanoid": false}"#;
        let o: PipelineOptions = serde_json::from_str(json).unwrap();
        assert_eq!(o.humanoid, Some(false));
        assert_eq!(o.neutral, NeutralPose::Keep);
        let back: PipelineOptions =
            serde_json::from_value(serde_json::to_value(&o).unwrap()).unwrap();
        assert_eq!(back, o);
        assert!(serde_json::from_str::<PipelineOptions>(r#"{"humanoids": true}"#).is_err());
        assert!(SignedAxis::rotation_to_y_up(SignedAxis::PosY, Some(SignedAxis::NegY)).is_err());
    }
}
