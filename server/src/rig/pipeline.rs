//! The normalisation pipeline every imported rig goes through: simplify → re-orient → units →
//! neutral pose (H-Anim when the rig is humanoid), configurable per asset, recording what it
//! did.

use std::collections::BTreeMap;

use glam::Quat;
use posecast_proto::fk::forward_kinematics;
use serde::{Deserialize, Serialize};

use super::names::{NameMapping, map_names};
use super::neutral::{NeutralPose, REQUIRED, apply_neutral_pose, hanim_pose};
use super::reorient::{SignedAxis, reorient, reorient_bind_frame, scale_units};
use super::simplify::simplify;
use super::{JointMaps, RigError, compose_maps};
use crate::asset::{Asset, SourceFormat, UpAxis};
use crate::clip::ChannelMap;

/// Per-asset pipeline configuration; `Default` is the default pipeline. Deserialises from JSON
/// with every field optional, e.g.
/// `{"up_axis": {"up": "+z", "forward": "-y"}, "metres_per_unit": 0.01, "neutral": "keep",
///   "name_map": {"Bip01_L_Thigh": "l_hip"}}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
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
}

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            simplify: true,
            up_axis: None,
            metres_per_unit: None,
            neutral: NeutralPose::Auto,
            name_map: None,
        }
    }
}

/// The source's orientation, as axes or as a rotation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct UpAxisOverride {
    /// The source's up axis (default `+y`).
    pub up: SignedAxis,
    /// The source's forward axis (the way the avatar faces); `None` picks the first of `+z`,
    /// `-y`, `+x` perpendicular to `up`.
    pub forward: Option<SignedAxis>,
    /// A rotation `R` (x, y, z, w) to apply instead of the axes.
    pub rotation: Option<[f32; 4]>,
    /// What to rotate; `None`: [`ReorientFrame::Bind`] for glTF (whose scene is Y-up by
    /// specification), [`ReorientFrame::World`] otherwise.
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
#[serde(rename_all = "snake_case")]
pub enum ReorientFrame {
    /// Everything, posed world included ([`reorient`]): for sources whose world is not Y-up.
    World,
    /// Bind-space data only ([`reorient_bind_frame`]): for sources whose posed world is
    /// already Y-up but whose mesh and binds are not (glTF `Z_UP` exports).
    Bind,
}

/// A normalised asset and what the pipeline did to it.
#[derive(Clone, Debug)]
pub struct Normalised {
    pub asset: Asset,
    /// One line per step, in order.
    pub steps: Vec<String>,
    /// Per joint `(pre, post)`, composed over all steps, with `R' = pre · R · post` mapping an
    /// authored local rotation to the normalised one (`V_parent(i)`, `V_i⁻¹` overall).
    pub rotation_maps: Vec<(Quat, Quat)>,
    /// Per joint, the full channel map applied to clips (rotation, translation, units).
    pub channel_maps: Vec<ChannelMap>,
    /// Per joint, its H-Anim name if mapped.
    pub hanim: Vec<Option<String>>,
    /// Joints without an H-Anim name.
    pub unmapped: Vec<String>,
    /// The neutral pose `H` applied (local rotations in the frame before that step), if any.
    pub neutral_pose: Option<Vec<Quat>>,
    /// How posed world points changed: `p' = scale · (rotation · p)` for every frame of every
    /// clip (rotation: a [`ReorientFrame::World`] re-orientation; scale: units).
    pub world_change: (Quat, f32),
}

/// Runs the pipeline on `asset`.
pub fn normalise(asset: Asset, options: &PipelineOptions) -> Result<Normalised, RigError> {
    let n = asset.skeleton.len();
    let mut steps = Vec::new();
    let mut maps: JointMaps = vec![ChannelMap::IDENTITY; n];
    let NameMapping { hanim, unmapped } =
        map_names(&asset.skeleton, options.name_map.as_ref(), &asset.name)?;
    steps.push(format!(
        "names: {} of {n} joints mapped to H-Anim{}",
        n - unmapped.len(),
        if options.name_map.is_some() {
            " (with a mapping)"
        } else {
            ""
        }
    ));
    let mut asset = asset;
    let mut world_change = (Quat::IDENTITY, 1.0f32);
    if options.simplify {
        let (a, m, notes) = simplify(asset)?;
        asset = a;
        compose_maps(&mut maps, &m);
        steps.push("simplify: inverse binds reduced to translations T(-C_i)".into());
        steps.extend(notes.into_iter().map(|s| format!("simplify: {s}")));
    }
    if let Some((r, frame, why)) = orientation(&asset, options.up_axis.as_ref())? {
        let (a, m) = match frame {
            ReorientFrame::World => reorient(asset, r)?,
            ReorientFrame::Bind => reorient_bind_frame(asset, r)?,
        };
        asset = a;
        compose_maps(&mut maps, &m);
        if frame == ReorientFrame::World {
            world_change.0 = r.normalize();
        }
        let (axis, angle) = r.to_axis_angle();
        steps.push(format!(
            "re-orient ({why}, {frame:?} frame): {:.1} deg about {axis:.3}",
            angle.to_degrees()
        ));
    }
    let (s, why) = units(&asset, options.metres_per_unit);
    if (s - 1.0).abs() > f32::EPSILON {
        let (a, m) = scale_units(asset, s)?;
        asset = a;
        compose_maps(&mut maps, &m);
        world_change.1 = s;
    }
    steps.push(format!("units ({why}): x{s}"));
    let humanoid = REQUIRED
        .iter()
        .all(|r| super::names::find(&hanim, r).is_some());
    let mut neutral_pose = None;
    match options.neutral {
        NeutralPose::Keep => steps.push("neutral pose: kept".into()),
        NeutralPose::Auto if !humanoid => {
            steps.push(
                "neutral pose: kept (not humanoid: hips, knees, shoulders, elbows not all mapped)"
                    .into(),
            );
        }
        NeutralPose::Auto | NeutralPose::HAnim => {
            let h = hanim_pose(&asset, &hanim)?;
            let (a, m, notes) = apply_neutral_pose(asset, &h)?;
            asset = a;
            compose_maps(&mut maps, &m);
            steps.push("neutral pose: H-Anim (upright, facing +Z, arms and legs down)".into());
            steps.extend(notes.into_iter().map(|s| format!("neutral pose: {s}")));
            neutral_pose = Some(h);
        }
    }
    Ok(Normalised {
        asset,
        steps,
        rotation_maps: maps.iter().map(|m| (m.rot_pre, m.rot_post)).collect(),
        channel_maps: maps,
        hanim,
        unmapped,
        neutral_pose,
        world_change,
    })
}

fn orientation(
    asset: &Asset,
    over: Option<&UpAxisOverride>,
) -> Result<Option<(Quat, ReorientFrame, &'static str)>, RigError> {
    let default_frame = if asset.source.format == SourceFormat::Gltf {
        ReorientFrame::Bind
    } else {
        ReorientFrame::World
    };
    match over {
        Some(o) => {
            let r = match o.rotation {
                Some(q) => Quat::from_array(q),
                None => SignedAxis::rotation_to_y_up(o.up, o.forward)?,
            };
            if r.is_finite() && (r.normalize().w.abs() >= 1.0 - 1e-7) {
                return Ok(None);
            }
            Ok(Some((r, o.frame.unwrap_or(default_frame), "configured")))
        }
        None => match asset.source.up_axis {
            UpAxis::Y => Ok(None),
            UpAxis::Z => Ok(Some((
                SignedAxis::rotation_to_y_up(SignedAxis::PosZ, None)?,
                default_frame,
                "Z-up source",
            ))),
        },
    }
}

fn units(asset: &Asset, configured: Option<f32>) -> (f32, &'static str) {
    if let Some(s) = configured {
        return (s, "configured");
    }
    if let Some(s) = asset.source.metres_per_unit {
        return (s, "from the file");
    }
    let h = rig_height(asset);
    let s = match h {
        h if (0.3..=3.0).contains(&h) => 1.0,
        h if (30.0..=300.0).contains(&h) => 0.01,
        h if (300.0..=3000.0).contains(&h) => 0.001,
        _ => return (1.0, "unknown, kept: set metres_per_unit"),
    };
    (s, "guessed from the rig's height")
}

/// The rig's extent along Y at rest (joints and meshes), in its units.
#[must_use]
pub fn rig_height(asset: &Asset) -> f32 {
    let sk = &asset.skeleton;
    let mut world = vec![glam::Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, sk.rest(), &mut world);
    let mut lo = f32::MAX;
    let mut hi = f32::MIN;
    for w in &world {
        let y = w.w_axis.y;
        lo = lo.min(y);
        hi = hi.max(y);
    }
    for m in &asset.meshes {
        let (a, b) = m.mesh.bounds();
        lo = lo.min(a.y);
        hi = hi.max(b.y);
    }
    let extent = hi - lo;
    if extent.is_finite() { extent } else { 0.0 }
}
