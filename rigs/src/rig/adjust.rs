//! The generic bind adjustment of seed 000 ("Adjusting bind matrices"): multiply each inverse
//! bind by a rotation `V_i` and change rest transforms and clips so that every skinning matrix,
//! hence the skinned mesh, stays the same.

use glam::{Mat3, Mat4, Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

use super::{JointMaps, RigError};
use crate::asset::Asset;
use crate::clip::{ChannelMap, VectorChannel};

/// Adjusts the bind by per-joint rotations `V_i` (one per joint):
/// `B'_i⁻¹ = V_i B_i⁻¹`, `t'_i = V_parent(i) t_i`, `R'_i = V_parent(i) R_i V_i⁻¹`, with
/// `V_parent(root) = I` so a root's translation (rest and animated) is untouched.
///
/// World matrices become `W'_i = W_i V_i⁻¹` for every pose, so `W'_i B'_i⁻¹ = W_i B_i⁻¹`.
/// A joint scale `S_i` becomes `V_i S_i V_i⁻¹`, which must stay axis-aligned (uniform scale
/// always does); otherwise [`RigError::NonUniformScale`]. Clip scale channels are not
/// changed by [`ChannelMap`]: a non-uniform animated scale on a joint with `V_i ≠ I` is only
/// approximately converted, and a note saying so is returned. BVH end sites and CSE169 boxes
/// (joint space) are rotated by `V_i`; a rotated box is replaced by its axis-aligned bounds.
///
/// Returns the adjusted asset, the maps applied to clips, and notes.
pub fn adjust_bind(
    mut asset: Asset,
    v: &[Quat],
) -> Result<(Asset, JointMaps, Vec<String>), RigError> {
    let sk = &asset.skeleton;
    let n = sk.len();
    if v.len() != n {
        return Err(RigError::Length {
            what: "bind adjustment rotations",
            expected: n,
            actual: v.len(),
        });
    }
    if let Some(bad) = v
        .iter()
        .find(|q| !q.is_finite() || q.length_squared() < 0.5)
    {
        return Err(RigError::BadInput {
            what: "bind adjustment rotation",
            message: format!("{bad} is not a unit quaternion"),
        });
    }
    let v: Vec<Quat> = v.iter().map(|q| q.normalize()).collect();
    let parent_v = |j: usize| sk.parents()[j].map_or(Quat::IDENTITY, |p| v[p]);
    let mut rest = Vec::with_capacity(n);
    let mut inverse_bind = Vec::with_capacity(n);
    let mut maps = Vec::with_capacity(n);
    for (j, &vj) in v.iter().enumerate() {
        let vp = parent_v(j);
        let r = sk.rest()[j];
        let scale = conjugate_scale(vj, r.scale).ok_or_else(|| RigError::NonUniformScale {
            joint: j,
            name: sk.names()[j].clone(),
            scale: r.scale,
            step: "bind adjustment",
        })?;
        rest.push(Transform {
            translation: vp * r.translation,
            rotation: (vp * r.rotation * vj.inverse()).normalize(),
            scale,
        });
        inverse_bind.push(Mat4::from_quat(vj) * sk.inverse_bind()[j]);
        maps.push(ChannelMap {
            rot_pre: vp,
            rot_post: vj.inverse(),
            trans_rot: vp,
            ..ChannelMap::IDENTITY
        });
    }
    let mut notes = Vec::new();
    for clip in &mut asset.clips {
        let mut approximate = Vec::new();
        for (j, map) in maps.iter().enumerate() {
            if has_non_uniform_scale(clip.channels().get(j).and_then(|c| c.scale.as_ref()))
                && !is_identity(v[j])
            {
                approximate.push(sk.names()[j].clone());
            }
            clip.map_joint(j, *map);
        }
        if !approximate.is_empty() {
            notes.push(format!(
                "clip {:?}: joints {approximate:?} animate non-uniform scale in a rotated \
                 frame; converted approximately",
                clip.name()
            ));
        }
    }
    let skeleton = rebuild(sk, rest, inverse_bind)?;
    for (joint, offset) in &mut asset.source.end_sites {
        if let Some(q) = v.get(*joint) {
            *offset = *q * *offset;
        }
    }
    if let Some(boxes) = &mut asset.boxes {
        for (b, q) in boxes.iter_mut().zip(&v) {
            *b = rotate_box(*b, |p| *q * p);
        }
    }
    asset.skeleton = skeleton;
    Ok((asset, maps, notes))
}

/// The same skeleton with new rest transforms and inverse binds (names, parents, DOFs kept).
pub(crate) fn rebuild(
    sk: &Skeleton,
    rest: Vec<Transform>,
    inverse_bind: Vec<Mat4>,
) -> Result<Skeleton, RigError> {
    Ok(Skeleton::new(
        sk.names().to_vec(),
        sk.parents().to_vec(),
        rest,
        inverse_bind,
    )?
    .with_dofs(sk.dofs().to_vec())?)
}

/// `q S q⁻¹` as a per-axis scale, when it still is one (relative tolerance 1e-5; a scale
/// uniform within 1e-6 always is).
pub(crate) fn conjugate_scale(q: Quat, s: Vec3) -> Option<Vec3> {
    if (s.max_element() - s.min_element()).abs() <= 1e-6 * s.abs().max_element() {
        return Some(s);
    }
    let m = Mat3::from_quat(q) * Mat3::from_diagonal(s) * Mat3::from_quat(q.inverse());
    let off = [
        m.x_axis.y, m.x_axis.z, m.y_axis.x, m.y_axis.z, m.z_axis.x, m.z_axis.y,
    ]
    .iter()
    .fold(0.0f32, |a, x| a.max(x.abs()));
    (off <= 1e-5 * s.abs().max_element()).then_some(Vec3::new(m.x_axis.x, m.y_axis.y, m.z_axis.z))
}

pub(crate) fn is_identity(q: Quat) -> bool {
    q.w.abs() >= 1.0 - 1e-7
}

fn has_non_uniform_scale(channel: Option<&VectorChannel>) -> bool {
    match channel {
        None => false,
        Some(VectorChannel::Keys(t)) => t
            .values()
            .iter()
            .any(|s| (s.max_element() - s.min_element()).abs() > 1e-4 * s.abs().max_element()),
        Some(VectorChannel::Curves(_)) => true,
    }
}

/// The axis-aligned bounds of a box's eight corners mapped by `f`.
pub(crate) fn rotate_box((lo, hi): (Vec3, Vec3), f: impl Fn(Vec3) -> Vec3) -> (Vec3, Vec3) {
    let mut out = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        let p = f(c);
        out = (out.0.min(p), out.1.max(p));
    }
    out
}
