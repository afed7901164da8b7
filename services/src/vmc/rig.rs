//! The VMC performer as a source rig: the Unity humanoid's T-pose ([`super::unity::BONES`])
//! normalised like every imported rig, so the stream drives avatars through the same
//! world-space retargeting ([`posecast_rigs::rig::retarget::PoseRetargeter`]) as any other source.
//!
//! The T-pose is the rig's rest pose with identity rotations, as VMC's local rotations are
//! relative to it. Normalisation (seed 000) makes the H-Anim pose (arms down) its neutral pose
//! with per-bone rotations `V_i`; a T-pose-relative local rotation `R` of bone `i` is then
//! `R' = V_parent(i) · R · V_i⁻¹` on the normalised rig (the pipeline's rotation maps), and
//! back `R = V_parent(i)⁻¹ · R' · V_i`.

use std::collections::BTreeMap;
use std::sync::Arc;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

use super::unity::{BONES, NECK, TORSO};
use posecast_rigs::asset::{Asset, SourceFormat, SourceInfo};
use posecast_rigs::rig::names::HANIM_SPINE;
use posecast_rigs::rig::neutral::NeutralPose;
use posecast_rigs::rig::{PipelineOptions, Rig, RigError, normalise};

/// The source rig's name (not a valid asset id, so no uploaded rig can share it).
pub const RIG_NAME: &str = "VMC humanoid (T-pose)";

/// The normalised VMC source rig and the rotation maps between VMC's T-pose frames and it.
#[derive(Debug)]
pub struct VmcRig {
    rig: Rig,
    /// Per bone `(pre, post)` with `R' = pre · R · post` (`V_parent`, `V⁻¹`).
    maps: Vec<(Quat, Quat)>,
}

impl VmcRig {
    /// Builds and normalises the T-pose rig.
    ///
    /// # Errors
    /// Only if the bone table were broken (a test builds it).
    pub fn new() -> Result<Self, RigError> {
        let n = BONES.len();
        let names: Vec<String> = BONES.iter().map(|b| b.name.to_owned()).collect();
        let parents: Vec<Option<usize>> = BONES.iter().map(|b| b.parent).collect();
        let rest: Vec<Transform> = BONES
            .iter()
            .map(|b| Transform::from_translation_rotation(Vec3::from(b.offset), Quat::IDENTITY))
            .collect();
        let mut world = vec![Vec3::ZERO; n];
        for (i, b) in BONES.iter().enumerate() {
            world[i] = b.parent.map_or(Vec3::ZERO, |p| world[p]) + Vec3::from(b.offset);
        }
        let inverse_bind = world.iter().map(|&c| Mat4::from_translation(-c)).collect();
        let skeleton = Skeleton::new(names, parents, rest, inverse_bind)?;
        let asset = Asset {
            name: RIG_NAME.to_owned(),
            skeleton,
            meshes: Vec::new(),
            clips: Vec::new(),
            source: SourceInfo::new(SourceFormat::Gltf),
            boxes: None,
            expressions: Vec::new(),
        };
        let name_map: BTreeMap<String, String> = BONES
            .iter()
            .map(|b| (b.name.to_owned(), b.hanim.to_owned()))
            .collect();
        let options = PipelineOptions {
            metres_per_unit: Some(1.0),
            neutral: NeutralPose::HAnim,
            name_map: Some(name_map),
            ..PipelineOptions::default()
        };
        let normalised = normalise(asset, &options)?;
        let maps = normalised.rotation_maps.clone();
        let rig = Rig::new(
            normalised.asset,
            normalised.steps,
            Vec::new(),
            normalised.hanim,
        );
        Ok(Self { rig, maps })
    }

    /// The source rig for driving (or reading) an avatar of `target`: the normalised T-pose
    /// rig with its torso and neck bones' H-Anim names fitted to the target's spine, so that
    /// each of the target's spine joints takes one Unity bone's rotation where it can.
    ///
    /// The target's torso joints (`vl*`, `vt*` in [`HANIM_SPINE`] order, pelvis up) take, with
    /// three or more, `Spine` the lowest, `Chest` the middle one and `UpperChest` the highest;
    /// with two, `Spine` and `UpperChest`; with one, `UpperChest` (what the arms and the neck
    /// hang from keeps the right world rotation). `Neck` takes the lowest `vc*` joint. Unity
    /// bones left without a partner drop out of the matching (world-space retargeting carries
    /// their rotation into the next matched joint).
    #[must_use]
    pub fn for_target(&self, target: &Rig) -> Arc<Rig> {
        let mut hanim = self.rig.hanim.clone();
        let has = |name: &str| target.hanim.iter().any(|h| h.as_deref() == Some(name));
        let torso: Vec<&str> = HANIM_SPINE
            .iter()
            .copied()
            .filter(|n| (n.starts_with("vl") || n.starts_with("vt")) && has(n))
            .collect();
        let neck = HANIM_SPINE
            .iter()
            .copied()
            .find(|n| n.starts_with("vc") && has(n));
        let [spine, chest, upper] = TORSO;
        for j in TORSO {
            hanim[j] = None;
        }
        match torso.as_slice() {
            [] => {}
            [only] => hanim[upper] = Some((*only).to_owned()),
            [low, high] => {
                hanim[spine] = Some((*low).to_owned());
                hanim[upper] = Some((*high).to_owned());
            }
            all => {
                hanim[spine] = all.first().map(|s| (*s).to_owned());
                hanim[chest] = all.get((all.len() - 1) / 2).map(|s| (*s).to_owned());
                hanim[upper] = all.last().map(|s| (*s).to_owned());
            }
        }
        hanim[NECK] = neck.map(str::to_owned);
        Arc::new(Rig::new(
            (*self.rig.asset).clone(),
            self.rig.pipeline.clone(),
            Vec::new(),
            hanim,
        ))
    }

    /// Bone `bone`'s T-pose-relative local rotation (glTF frame) on the normalised rig:
    /// `R' = V_parent · R · V⁻¹`.
    #[must_use]
    pub fn to_normalised(&self, bone: usize, r: Quat) -> Quat {
        match self.maps.get(bone) {
            Some(&(pre, post)) => (pre * r * post).normalize(),
            None => r,
        }
    }

    /// The inverse of [`VmcRig::to_normalised`]: `R = V_parent⁻¹ · R' · V`.
    #[must_use]
    pub fn from_normalised(&self, bone: usize, r: Quat) -> Quat {
        match self.maps.get(bone) {
            Some(&(pre, post)) => (pre.inverse() * r * post.inverse()).normalize(),
            None => r,
        }
    }

    /// The normalised rig (default H-Anim names).
    #[must_use]
    pub fn rig(&self) -> &Rig {
        &self.rig
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vmc::unity::bone_index;
    use posecast_proto::fk::forward_kinematics;

    fn world_positions(rig: &Rig, rot: &[Quat]) -> Vec<Vec3> {
        let sk = rig.skeleton();
        let locals: Vec<Transform> = sk
            .rest()
            .iter()
            .zip(rot)
            .map(|(t, q)| Transform { rotation: *q, ..*t })
            .collect();
        let mut world = vec![Mat4::IDENTITY; sk.len()];
        forward_kinematics(sk, &locals, &mut world);
        world.iter().map(|w| w.w_axis.truncate()).collect()
    }

    /// Identity on the normalised rig is the H-Anim pose (arms down); the T-pose (identity in
    /// VMC's frames) mapped through `to_normalised` puts the arms back out along ±X.
    #[test]
    fn neutral_is_arms_down_and_the_t_pose_maps_back_to_arms_out() {
        let vmc = VmcRig::new().unwrap();
        let n = BONES.len();
        let at = |name: &str| bone_index(name).unwrap();
        let neutral = world_positions(vmc.rig(), &vec![Quat::IDENTITY; n]);
        let arm = (neutral[at("LeftLowerArm")] - neutral[at("LeftUpperArm")]).normalize();
        assert!(arm.abs_diff_eq(Vec3::NEG_Y, 1e-5), "{arm}");
        let t_pose: Vec<Quat> = (0..n)
            .map(|j| vmc.to_normalised(j, Quat::IDENTITY))
            .collect();
        let p = world_positions(vmc.rig(), &t_pose);
        // Every bone where the T-pose table puts it (arms out along ±X).
        let mut t = vec![Vec3::ZERO; n];
        for (j, b) in BONES.iter().enumerate() {
            t[j] = b.parent.map_or(Vec3::ZERO, |q| t[q]) + Vec3::from(b.offset);
            assert!(
                p[j].abs_diff_eq(t[j], 1e-5),
                "{}: {} vs {}",
                b.name,
                p[j],
                t[j]
            );
        }
        let arm = (p[at("LeftHand")] - p[at("LeftLowerArm")]).normalize();
        assert!(arm.abs_diff_eq(Vec3::X, 1e-5), "{arm}");
        for j in 0..n {
            let q = Quat::from_euler(glam::EulerRot::YXZ, 0.2 * j as f32, -0.4, 0.9);
            let back = vmc.from_normalised(j, vmc.to_normalised(j, q));
            assert!(back.dot(q).abs() > 1.0 - 1e-6, "{j}");
        }
    }

    #[test]
    fn the_torso_follows_the_targets_spine() {
        let vmc = VmcRig::new().unwrap();
        let builtin = posecast_rigs::builtin::rig().unwrap();
        let fitted = vmc.for_target(&builtin);
        let name = |bone: &str| fitted.hanim[bone_index(bone).unwrap()].clone();
        assert_eq!(name("Spine").as_deref(), Some("vl5"));
        assert_eq!(name("Chest").as_deref(), Some("vt10"));
        assert_eq!(name("UpperChest").as_deref(), Some("vt1"));
        assert_eq!(name("Neck").as_deref(), Some("vc4"));
        assert_eq!(name("Head").as_deref(), Some("skullbase"));
    }
}
