//! Re-orienting an avatar (seed 000, "Reorienting your avatar", with DESIGN.md's erratum
//! `U' = R U R⁻¹`) and changing its units.

use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
pub use posecast_proto::rig_options::SignedAxis;

use super::adjust::{conjugate_scale, rebuild, rotate_box};
use super::{JointMaps, RigError};
use crate::asset::Asset;
use crate::asset::AssetMesh;
use crate::clip::ChannelMap;

/// Re-orients the whole asset by the rotation `R` (a change of coordinates):
/// `t' = R t`, `L' = R L R⁻¹` (rest and every clip), `B'⁻¹ = R B⁻¹ R⁻¹` (so `C' = R C`,
/// `U' = R U R⁻¹`), mesh `v' = R v`, normals `n' = R n`. Every skinned vertex and world joint
/// position becomes `R` times the original.
pub fn reorient(mut asset: Asset, r: Quat) -> Result<(Asset, JointMaps), RigError> {
    let r = unit(r)?;
    let sk = &asset.skeleton;
    let n = sk.len();
    let mut rest = Vec::with_capacity(n);
    for (j, t) in sk.rest().iter().enumerate() {
        let scale = conjugate_scale(r, t.scale).ok_or_else(|| RigError::NonUniformScale {
            joint: j,
            name: sk.names()[j].clone(),
            scale: t.scale,
            step: "re-orientation",
        })?;
        rest.push(Transform {
            translation: r * t.translation,
            rotation: (r * t.rotation * r.inverse()).normalize(),
            scale,
        });
    }
    let rm = Mat4::from_quat(r);
    let rm_inv = Mat4::from_quat(r.inverse());
    let inverse_bind = sk
        .inverse_bind()
        .iter()
        .map(|ib| rm * *ib * rm_inv)
        .collect();
    let map = ChannelMap {
        rot_pre: r,
        rot_post: r.inverse(),
        trans_rot: r,
        ..ChannelMap::IDENTITY
    };
    for clip in &mut asset.clips {
        for j in 0..n {
            clip.map_joint(j, map);
        }
    }
    asset.skeleton = rebuild(sk, rest, inverse_bind)?;
    map_meshes(&mut asset.meshes, |p| r * p, |v| r * v);
    for (_, offset) in &mut asset.source.end_sites {
        *offset = r * *offset;
    }
    if let Some(boxes) = &mut asset.boxes {
        for b in boxes.iter_mut() {
            *b = rotate_box(*b, |p| r * p);
        }
    }
    Ok((asset, vec![map; n]))
}

/// Re-orients only the bind-space data (mesh, inverse binds, joint frames) by `R`, leaving
/// the posed world as it is: [`reorient`], then every root's local transform pre-multiplied
/// by `R⁻¹` (rest and clips), which undoes the world rotation. Equivalently the bind
/// adjustment with every `V_i = R` followed by the mesh change `v' = R v`, `B'⁻¹ ← B'⁻¹ R⁻¹`.
///
/// This is the case of glTF files from Z-up tools: their `Z_UP` node is folded into the root
/// joints, so posed world space is already Y-up while mesh and inverse binds are Z-up. The
/// skinned mesh of every pose is unchanged; the bind-pose mesh becomes `R·v`.
pub fn reorient_bind_frame(asset: Asset, r: Quat) -> Result<(Asset, JointMaps), RigError> {
    let r = unit(r)?;
    let (mut asset, mut maps) = reorient(asset, r)?;
    let sk = &asset.skeleton;
    let undo = ChannelMap {
        rot_pre: r.inverse(),
        trans_rot: r.inverse(),
        ..ChannelMap::IDENTITY
    };
    let mut rest = sk.rest().to_vec();
    let roots: Vec<usize> = sk.roots().collect();
    for &j in &roots {
        let t = rest[j];
        rest[j] = Transform {
            translation: r.inverse() * t.translation,
            rotation: (r.inverse() * t.rotation).normalize(),
            scale: t.scale,
        };
        maps[j] = maps[j].then(&undo);
        for clip in &mut asset.clips {
            clip.map_joint(j, undo);
        }
    }
    asset.skeleton = rebuild(sk, rest, sk.inverse_bind().to_vec())?;
    Ok((asset, maps))
}

/// Changes units by the uniform factor `s` (e.g. 0.01 for centimetres to metres): rest and
/// animated translations, inverse binds' translations, mesh positions, end sites and boxes are
/// multiplied by `s`; rotations and joint scales are unchanged. Every skinned vertex and world
/// joint position becomes `s` times the original.
pub fn scale_units(mut asset: Asset, s: f32) -> Result<(Asset, JointMaps), RigError> {
    if !(s.is_finite() && s > 0.0) {
        return Err(RigError::BadInput {
            what: "units",
            message: format!("metres per unit {s} is not a positive number"),
        });
    }
    let sk = &asset.skeleton;
    let n = sk.len();
    let rest = sk
        .rest()
        .iter()
        .map(|t| Transform {
            translation: t.translation * s,
            ..*t
        })
        .collect();
    let inverse_bind = sk
        .inverse_bind()
        .iter()
        .map(|ib| {
            let mut m = *ib;
            m.w_axis = (m.w_axis.truncate() * s).extend(m.w_axis.w);
            m
        })
        .collect();
    let map = ChannelMap {
        trans_scale: s,
        ..ChannelMap::IDENTITY
    };
    for clip in &mut asset.clips {
        for j in 0..n {
            clip.map_joint(j, map);
        }
    }
    asset.skeleton = rebuild(sk, rest, inverse_bind)?;
    map_meshes(&mut asset.meshes, |p| p * s, |v| v);
    for (_, offset) in &mut asset.source.end_sites {
        *offset *= s;
    }
    if let Some(boxes) = &mut asset.boxes {
        for b in boxes.iter_mut() {
            *b = (b.0 * s, b.1 * s);
        }
    }
    Ok((asset, vec![map; n]))
}

fn map_meshes(meshes: &mut [AssetMesh], f: impl Fn(Vec3) -> Vec3, g: impl Fn(Vec3) -> Vec3) {
    for m in meshes {
        m.mesh = m.mesh.map_vertices(&f, &g);
    }
}

fn unit(r: Quat) -> Result<Quat, RigError> {
    if r.is_finite() && r.length_squared() > 0.5 {
        Ok(r.normalize())
    } else {
        Err(RigError::BadInput {
            what: "re-orientation",
            message: format!("{r} is not a unit quaternion"),
        })
    }
}
