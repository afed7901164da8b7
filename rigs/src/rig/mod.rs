//! Rig normalisation (seed 000, DESIGN.md "Rig normalisation") and cross-rig retargeting.
//!
//! Every step takes an [`crate::asset::Asset`] and gives one back whose skinned mesh is
//! the same for every frame of every clip (re-orient and units: the same up to `R·v`, `s·v`),
//! plus the per-joint [`crate::clip::ChannelMap`] it applied to clip channels:
//!
//! - `adjust`: the generic bind adjustment by per-joint rotations `V_i`.
//! - `simplify`: `V_i = U_i`, so inverse binds become translations `T(−C_i)`.
//! - `reorient`: a coordinate change by a rotation `R`, and units (a uniform scale).
//! - [`neutral`](mod@neutral): a new neutral pose `H` (`V_i = V_parent(i) H_i`) and the H-Anim pose found by
//!   aligning named segments with target directions.
//! - [`names`](mod@names): joint names to H-Anim names, by names and limb chains.
//! - [`rest_shape`](mod@rest_shape): what the rest skeleton says (lengths, directions, up, hips).
//! - [`humanoid`](mod@humanoid): whether a rig is a humanoid, from its rest skeleton.
//! - [`retarget`](mod@retarget): a clip of one normalised rig replayed on another, matched in world space.
//! - [`pipeline`](mod@pipeline): the default sequence, configurable per asset, recording what it did.

mod adjust;
pub mod humanoid;
pub mod names;
pub mod neutral;
pub mod pipeline;
mod playable;
mod reorient;
pub mod rest_shape;
pub mod retarget;
mod simplify;

pub use adjust::adjust_bind;
pub use names::{NameMapping, map_names};
pub use neutral::{NeutralPose, apply_neutral_pose, hanim_pose};
pub use pipeline::{Normalised, PipelineOptions, UpAxisOverride, normalise};
pub use playable::{JointLimits, Rig};
pub use reorient::{SignedAxis, reorient, reorient_bind_frame, scale_units};
pub use retarget::{RigView, retarget, retarget_at_rate};
pub use simplify::simplify;

use posecast_proto::{MeshError, SkeletonError};

use crate::clip::ChannelMap;

/// Why a rig could not be normalised or a clip retargeted.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RigError {
    /// The configured `expression_map` names a non-standard expression or a morph target the
    /// rig lacks.
    #[error("expression_map of {asset:?}: {message}")]
    ExpressionMap {
        /// The asset.
        asset: String,
        /// What is wrong with which entry.
        message: String,
    },
    /// The bind matrix mirrors (negative determinant): no rotation can express it, and folding
    /// the mirror into the mesh would turn it inside out, so the asset is refused.
    #[error("joint {joint} ({name:?}) has a mirrored bind matrix (determinant {determinant})")]
    MirroredBind {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
        /// The determinant of the bind matrix's linear part (negative).
        determinant: f32,
    },
    /// The bind matrix is singular or not finite.
    #[error("joint {joint} ({name:?}) has a degenerate bind matrix (determinant {determinant})")]
    DegenerateBind {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
        /// The determinant of the bind matrix's linear part (near zero, or not finite).
        determinant: f32,
    },
    /// A non-uniform scale that the new joint frame would turn into a shear, which `T·R·S`
    /// cannot hold.
    #[error("joint {joint} ({name:?}) has non-uniform scale {scale} that {step} would shear")]
    NonUniformScale {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
        /// The joint's rest scale `S`, per axis of its own frame.
        scale: glam::Vec3,
        /// The step that turns the frame (`"bind adjustment"` or `"re-orientation"`).
        step: &'static str,
    },
    /// A per-joint list does not have one entry per joint.
    #[error("{what} has {actual} entries, expected one per joint ({expected})")]
    Length {
        /// Which list is wrong (`"bind adjustment rotations"`, `"neutral pose rotations"`, …).
        what: &'static str,
        /// The number of joints.
        expected: usize,
        /// The list's actual length.
        actual: usize,
    },
    /// A rotation, scale or direction given by the caller is not usable.
    #[error("bad {what}: {message}")]
    BadInput {
        /// Which input (`"metres_per_unit"`, `"orientation"`, `"pipeline options"`, …).
        what: &'static str,
        /// What is wrong with it.
        message: String,
    },
    /// The H-Anim neutral pose or retargeting needs joints the rig has not got.
    #[error("{rig}: no H-Anim joint mapped for {missing:?}")]
    NotHumanoid {
        /// The rig's name.
        rig: String,
        /// The H-Anim names no joint is mapped to.
        missing: Vec<String>,
    },
    /// Retargeting between a humanoid and a rig that is not one: their neutral poses do not
    /// correspond, so matching world rotations would, say, make a fox walk upright.
    #[error(
        "cannot retarget from {from} ({}) onto {onto} ({}): both must be humanoids, or neither",
        humanoid_word(*from_humanoid),
        humanoid_word(*onto_humanoid)
    )]
    HumanoidMismatch {
        /// The source rig's name.
        from: String,
        /// Whether the source rig is a humanoid.
        from_humanoid: bool,
        /// The target rig's name.
        onto: String,
        /// Whether the target rig is a humanoid.
        onto_humanoid: bool,
    },
    /// A mapping file names a joint the skeleton does not have.
    #[error("mapping names joint {joint:?}, which {rig} does not have")]
    UnknownJoint {
        /// The rig's name.
        rig: String,
        /// The joint name the mapping gives.
        joint: String,
    },
    /// Two joints map to the same H-Anim name.
    #[error("{rig}: joints {first:?} and {second:?} both map to H-Anim {hanim:?}")]
    DuplicateMapping {
        /// The rig's name.
        rig: String,
        /// The H-Anim name mapped twice.
        hanim: String,
        /// The joint mapped to it first.
        first: String,
        /// The later joint mapped to it.
        second: String,
    },
    /// A step's new skeleton was refused.
    #[error("rebuilding the skeleton failed: {0}")]
    Skeleton(#[from] SkeletonError),
    /// A step's re-posed mesh was refused.
    #[error("rebuilding a mesh failed: {0}")]
    Mesh(#[from] MeshError),
    /// A step's re-keyed or retargeted clip was refused.
    #[error("building a clip failed: {0}")]
    Clip(#[from] crate::clip::ClipError),
}

impl From<posecast_proto::rig_options::AxisError> for RigError {
    fn from(e: posecast_proto::rig_options::AxisError) -> Self {
        Self::BadInput {
            what: "orientation",
            message: e.to_string(),
        }
    }
}

fn humanoid_word(h: bool) -> &'static str {
    if h { "a humanoid" } else { "not a humanoid" }
}

/// Per joint, the [`ChannelMap`] a step applied to clip channels (the rotation part is the
/// `(V_parent(i), V_i⁻¹)` pair DOF limits need).
pub type JointMaps = Vec<ChannelMap>;

/// Composes `next` after `acc`, joint by joint.
pub(crate) fn compose_maps(acc: &mut [ChannelMap], next: &[ChannelMap]) {
    for (a, n) in acc.iter_mut().zip(next) {
        *a = a.then(n);
    }
}

impl RigError {
    /// A retargeting failure as the server's error, `context` first: `not_humanoid` when a
    /// humanoid meets a rig that is not one, else `invalid_value`.
    #[must_use]
    pub fn to_error(&self, context: &str) -> posecast_core::error::Error {
        let message = format!("{context}: {self}");
        match self {
            Self::HumanoidMismatch { .. } => posecast_core::error::Error::NotHumanoid(message),
            _ => posecast_core::error::Error::invalid(message),
        }
    }
}
