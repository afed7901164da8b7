//! The normalisation pipeline every imported rig goes through: simplify → re-orient → units →
//! neutral pose (H-Anim when the rig is humanoid), configurable per asset, recording what it
//! did.

use glam::Quat;
use posecast_proto::fk::forward_kinematics;
pub use posecast_proto::rig_options::{PipelineOptions, ReorientFrame, UpAxisOverride};

use super::humanoid::classify;
use super::names::{NameMapping, map_names};
use super::neutral::{NeutralPose, apply_neutral_pose, hanim_pose};
use super::reorient::{SignedAxis, reorient, reorient_bind_frame, scale_units};
use super::rest_shape::RestShape;
use super::simplify::simplify;
use super::{JointMaps, RigError, compose_maps};
use crate::asset::{Asset, SourceFormat, UpAxis};
use crate::clip::ChannelMap;
use posecast_proto::command::Units;

/// A normalised asset and what the pipeline did to it.
#[derive(Clone, Debug)]
pub struct Normalised {
    /// The asset after the steps the options chose (simplified binds, re-oriented to +Y up,
    /// scaled to metres, neutral pose), its clips mapped to match.
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
    /// Whether the rig is a humanoid (classified, or as configured).
    pub humanoid: bool,
    /// The unit conversion applied, and why.
    pub units: Units,
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
    if let Some(corrections) = &options.expression_map {
        let channels = posecast_proto::morph::channels(asset.meshes.iter().map(|m| &m.mesh));
        posecast_proto::expressions::corrected(Default::default(), corrections, &channels)
            .map_err(|message| RigError::ExpressionMap {
                asset: asset.name.clone(),
                message,
            })?;
        steps.push(format!(
            "expressions: {} standard name(s) mapped by the configuration",
            corrections.len()
        ));
    }
    let mut maps: JointMaps = vec![ChannelMap::IDENTITY; n];
    // A mapping the file gives (a VRM humanoid) is authoritative; the user's wins over it.
    let mut overrides = asset.source.bone_map.clone();
    if let Some(user) = &options.name_map {
        overrides
            .get_or_insert_with(Default::default)
            .extend(user.iter().map(|(k, v)| (k.clone(), v.clone())));
    }
    let NameMapping {
        mut hanim,
        mut unmapped,
        mut corrections,
    } = map_names(&asset.skeleton, overrides.as_ref(), &asset.name)?;
    if let Some(file) = &asset.source.bone_map {
        // The file's map is authoritative: joints it leaves out (hair, skirt, accessories
        // bones) are not guessed from their names, unless the user maps them.
        let user = options.name_map.as_ref();
        for (j, name) in asset.skeleton.names().iter().enumerate() {
            let kept = file.contains_key(name) || user.is_some_and(|m| m.contains_key(name));
            if !kept && hanim[j].take().is_some() {
                unmapped.push(name.clone());
            }
        }
        corrections.clear();
        unmapped.sort_by_key(|n| asset.skeleton.find(n));
    }
    let by = match (asset.source.bone_map.is_some(), options.name_map.is_some()) {
        (true, true) => " (the file's humanoid bone map, then the configured mapping)",
        (true, false) => " (the file's humanoid bone map)",
        (false, true) => " (by names and limb chains, then the configured mapping)",
        (false, false) => " (by names and limb chains)",
    };
    steps.push(format!(
        "names: {} of {n} joints mapped to H-Anim{by}",
        n - unmapped.len()
    ));
    steps.extend(corrections.into_iter().map(|c| format!("names: {c}")));
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
    if options.up_axis.is_none() {
        let shape = RestShape::measure(&asset, &hanim);
        match shape.up_guess() {
            Some((up, off, forward)) if up != SignedAxis::PosY => {
                let r = SignedAxis::rotation_to_y_up(up, forward)?;
                let (a, m) = reorient(asset, r)?;
                asset = a;
                compose_maps(&mut maps, &m);
                world_change.0 = (r * world_change.0).normalize();
                let (axis, angle) = r.to_axis_angle();
                let note = format!(
                    "up axis guessed from the rest skeleton: {} (the legs point down it, \
                     {off:.0}° off; the head above the hips), facing {}; re-oriented to +Y \
                     ({:.1} deg about {axis:.3}); set up_axis to override",
                    axis_name(up),
                    forward.map_or("unknown", axis_name),
                    angle.to_degrees()
                );
                steps.push(format!("re-orient: {note}"));
                asset.source.notes.push(note);
            }
            Some((_, off, _)) => steps.push(format!(
                "up axis: +Y, as the rest skeleton shows (the legs point down it, {off:.0}° off)"
            )),
            None => steps.push(match shape.readable {
                Some(_) => "up axis: kept: the legs of the standing rest pose are not near an \
                            axis, or the head is below the hips"
                    .to_owned(),
                None if shape.legs.len() == 2 => "up axis: kept: the rest pose is not standing \
                                                  (legs bent or apart), so it shows no up axis"
                    .to_owned(),
                None => "up axis: kept: no legs mapped to read it from".to_owned(),
            }),
        }
    }
    let class = classify(&asset, &hanim);
    let humanoid = options.humanoid.unwrap_or(class.humanoid);
    let shape = RestShape::measure(&asset, &hanim);
    let hips = humanoid
        .then(|| shape.hip_height(asset.skeleton.parents()))
        .flatten();
    let (units, why) = units(&asset, options.metres_per_unit, hips);
    let s = units.metres_per_unit;
    if !(s.is_finite() && s > 0.0) {
        return Err(RigError::BadInput {
            what: "metres_per_unit",
            message: format!("{s} is not a positive number"),
        });
    }
    if (s - 1.0).abs() > f32::EPSILON {
        let (a, m) = scale_units(asset, s)?;
        asset = a;
        compose_maps(&mut maps, &m);
        world_change.1 = s;
    }
    steps.push(format!("units ({why}): x{s}"));
    if humanoid {
        let shape = RestShape::measure(&asset, &hanim);
        // Stature from the hips (the hip joint stands at 0.530 of it, Drillis & Contini):
        // neither raised arms, a crumpled rest pose nor props on the mesh change it.
        let (stature, how) = match shape.hip_height(asset.skeleton.parents()) {
            Some((h, _)) => (h / 0.530, "from its hips"),
            None => (rig_height(&asset), "at rest"),
        };
        if !(MIN_HUMAN_METRES..=MAX_HUMAN_METRES).contains(&stature) {
            let note = format!(
                "warning: this humanoid is {stature:.2} m tall ({how}), outside \
                 {MIN_HUMAN_METRES}–{MAX_HUMAN_METRES} m: check its units (set metres_per_unit)"
            );
            steps.push(format!("units: {note}"));
            asset.source.notes.push(note);
        }
    }
    let confidence = format!("confidence {:.2}", class.confidence);
    steps.push(match options.humanoid {
        Some(h) => format!(
            "classification: {} (configured; classified {}, {confidence}, from the rest \
             skeleton: {})",
            if h { "humanoid" } else { "not humanoid" },
            if class.humanoid {
                "humanoid"
            } else {
                "not humanoid"
            },
            class.reason
        ),
        None => format!(
            "classification: {} ({confidence}, from the rest skeleton: {})",
            if humanoid { "humanoid" } else { "not humanoid" },
            class.reason
        ),
    });
    let mut neutral_pose = None;
    match options.neutral {
        NeutralPose::Keep => steps.push("neutral pose: kept".into()),
        NeutralPose::Auto if !humanoid => {
            steps.push("neutral pose: kept (not humanoid)".into());
        }
        NeutralPose::HAnim if !humanoid && options.humanoid == Some(false) => {
            return Err(RigError::BadInput {
                what: "pipeline options",
                message: "neutral h_anim with humanoid false".into(),
            });
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
        humanoid,
        units,
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

/// Shortest humanoid (metres) that passes without a warning.
pub const MIN_HUMAN_METRES: f32 = 0.5;
/// Tallest humanoid (metres) that passes without a warning.
pub const MAX_HUMAN_METRES: f32 = 3.0;

/// Where a person's hip joints stand above the feet, metres: the units guess puts a humanoid's
/// hips in this range.
pub const HIP_METRES: (f32, f32) = (0.8, 1.1);

/// Units a skeleton-only file may be in, metres per unit. Their hip ranges do not overlap
/// (neighbours differ by more than 1.1 / 0.8), so at most one fits.
const NAMED_UNITS: &[(f32, &str)] = &[
    (1.0, "metres"),
    (0.304_8, "feet"),
    (0.1, "decimetres"),
    (
        0.025_4 / 0.45,
        "CMU motion-capture units (inches / 0.45, the CMU ASF length scale)",
    ),
    (0.025_4, "inches"),
    (0.01, "centimetres"),
    (0.001, "millimetres"),
];

/// The unit that puts hips `h` (file units) at [`HIP_METRES`]: the named unit they fit, else
/// the nearest one when within a factor 1.5 of the range, else the scale that puts them at
/// 0.95 m. Returns metres per unit and its description.
fn units_from_hips(h: f32) -> (f32, String) {
    let (lo, hi) = HIP_METRES;
    let off = |s: f32| (lo / (h * s)).ln().max((h * s / hi).ln()).max(0.0);
    let best = NAMED_UNITS
        .iter()
        .min_by(|a, b| off(a.0).total_cmp(&off(b.0)));
    match best {
        Some(&(s, name)) if off(s) == 0.0 => (s, name.to_owned()),
        Some(&(s, name)) if off(s) <= 1.5f32.ln() => (
            s,
            format!(
                "{name}, the nearest (the hips then stand {:.2} m high)",
                h * s
            ),
        ),
        _ => (
            0.95 / h,
            "no common unit fits: scaled so the hips stand 0.95 m high".to_owned(),
        ),
    }
}

/// Metres per file unit: as configured; else what the file says, unless the rig is then
/// implausibly tall or small (outside 0.3–3 m) and its height in file units names a unit
/// (0.3–3: metres, 30–300: centimetres, 300–3000: millimetres) — glTF says metres by
/// specification, yet centimetre exports are common; else, where the format does not say
/// (BVH, CSE169): for a humanoid, the unit that puts its hips 0.8–1.1 m above its feet
/// (`hips`: their height in file units and how it was found, [`units_from_hips`]); for other
/// rigs the height guess; else 1. Returns the scale and what decided it, with the height.
fn units(asset: &Asset, configured: Option<f32>, hips: Option<(f32, &str)>) -> (Units, String) {
    let height = rig_height(asset);
    let units = |metres_per_unit: f32, source: &str| Units {
        metres_per_unit,
        source: source.to_owned(),
        height,
    };
    if let Some(s) = configured {
        return (units(s, "configured"), "configured".to_owned());
    }
    let guess = match height {
        h if (0.3..=3.0).contains(&h) => Some((1.0, "metres")),
        h if (30.0..=300.0).contains(&h) => Some((0.01, "centimetres")),
        h if (300.0..=3000.0).contains(&h) => Some((0.001, "millimetres")),
        _ => None,
    };
    let plausible = |s: f32| (0.3..=3.0).contains(&(height * s));
    match (asset.source.metres_per_unit, guess, hips) {
        (Some(s), _, _) if plausible(s) => (units(s, "file"), "from the file".to_owned()),
        (Some(s), Some((g, name)), _) if (g - s).abs() > f32::EPSILON => (
            units(g, "guessed"),
            format!(
                "guessed from the rig's height, {height:.3} units: {name}, not the file's \
                 {s} m per unit; set metres_per_unit to override"
            ),
        ),
        (Some(s), _, _) => (units(s, "file"), "from the file".to_owned()),
        (None, _, Some((h, how))) => {
            let (s, name) = units_from_hips(h);
            (
                units(s, "guessed"),
                format!(
                    "guessed from the humanoid's hips, {h:.3} units above its feet ({how}): \
                     {name}; set metres_per_unit to override"
                ),
            )
        }
        (None, Some((g, name)), None) => (
            units(g, "guessed"),
            format!(
                "guessed from the rig's height, {height:.3} units: {name}; set \
                 metres_per_unit to override"
            ),
        ),
        (None, None, None) => (
            units(1.0, "guessed"),
            format!("unknown from the rig's height, {height:.3} units, kept: set metres_per_unit"),
        ),
    }
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

fn axis_name(a: SignedAxis) -> &'static str {
    match a {
        SignedAxis::PosX => "+X",
        SignedAxis::NegX => "-X",
        SignedAxis::PosY => "+Y",
        SignedAxis::NegY => "-Y",
        SignedAxis::PosZ => "+Z",
        SignedAxis::NegZ => "-Z",
    }
}
