//! Avatars driven through their scene's owner (a cluster): what this server knows of each from
//! the owner's `drive` answer, and each pose for one checked here — where the driver is, so
//! errors return at once — and passed on to the owner as a binary pose
//! ([`crate::state::Cluster::pose`]).
//!
//! Morph weights travel as the binary pose's `(slot, level)` pairs. A slot is what
//! `Avatar::morph_channel` gives on the owner: a morph channel (below the channel count) or,
//! past the channels, an expression the avatar's file defines. A binary driver's weights name
//! channels only (checked here against the `drive` answer's `morph_targets`); a JSON pose's
//! names are resolved here to slots, so the owner applies them as its own driver's
//! ([`super::Drives::relayed_pose`]). Weights cross as levels of 1/1023, the precision every
//! frame carries them at.
//!
//! A tracker drive's trackers travel as the binary pose's `(index, position, rotation)`
//! entries, indexes into the `drive` answer's `trackers`: a JSON pose's names are resolved
//! here, and every index and value checked, before the pose goes on. Positions cross exactly,
//! rotations smallest-three quantised (at most 0.0075° off), as in a binary pose.

use super::{
    JsonPose, pose_rate, rate_limited, root, rotation, rotations_to_trackers, tracker_sample,
    trackers_to_rotations, unknown_tracker,
};
use crate::scene::Scene;
use crate::state::Services;
use glam::Vec3;
use posecast_core::error::{Error, Owner};
use posecast_core::quota::TokenBucket;
use posecast_proto::command::DriveInfo;
use posecast_proto::expressions::{Expression, find_expression, resolve};
use posecast_proto::live::BinaryPose;
use posecast_proto::morph;
use posecast_proto::msg::{AvatarId, SceneId};
use std::collections::BTreeMap;
use std::time::Instant;

/// An avatar driven through its owner ([`super::Drives::command_remote`]).
#[derive(Debug)]
pub(super) struct RemoteDrive {
    pub(super) avatar: AvatarId,
    pub(super) num: u32,
    pub(super) scene: SceneId,
    /// The source rig's joints, as the owner's `drive` answer listed them.
    joints: Vec<String>,
    /// The avatar's morph channels, as the `drive` answer listed them.
    morph_targets: Vec<String>,
    /// Standard expression names → channel, as the `drive` answer listed them.
    expressions: BTreeMap<String, String>,
    /// A tracker drive's trackers, as the `drive` answer listed them (empty: by rotations).
    trackers: Vec<String>,
    /// The expressions the avatar's file defines (slots past the channels), from the
    /// description the owner relays to this server's subscribers.
    expression_binds: Vec<Expression>,
    rate: TokenBucket,
}

impl RemoteDrive {
    /// The drive the owner answered `info` for, of an avatar of `scene` (relayed here).
    pub(super) fn new(info: &DriveInfo, scene: &Scene) -> Self {
        let expression_binds = scene
            .feed()
            .relayed_avatars()
            .iter()
            .find(|d| d.id == info.avatar)
            .map(|d| d.expression_binds.clone())
            .unwrap_or_default();
        Self {
            avatar: info.avatar.clone(),
            num: info.avatar_num,
            scene: scene.id.clone(),
            joints: info.joints.clone(),
            morph_targets: info.morph_targets.clone(),
            expressions: info.expressions.clone(),
            trackers: info.trackers.clone(),
            expression_binds,
            rate: pose_rate(),
        }
    }

    /// A binary pose: checked (joints, values, weights' channels) and passed on.
    pub(super) fn binary_pose(
        &mut self,
        state: &Services,
        conn: u64,
        pose: BinaryPose,
    ) -> Result<(), Error> {
        self.rate.take_at(Instant::now()).map_err(rate_limited)?;
        self.check_joints(&pose)?;
        let channels = self.morph_targets.len();
        if let Some(&(c, _)) = pose
            .weights
            .iter()
            .find(|(c, _)| usize::from(*c) >= channels)
        {
            return Err(Error::UnknownExpression {
                owner: Owner::Channels {
                    avatar: self.avatar.clone(),
                    channels,
                    expressions: 0,
                },
                name: format!("channel {c}"),
                has_targets: channels > 0,
            });
        }
        self.send(state, conn, &pose)
    }

    /// A JSON pose: joints, trackers and weights resolved by name ([`RemoteDrive::resolve`]),
    /// checked and passed on.
    pub(super) fn json_pose(
        &mut self,
        state: &Services,
        conn: u64,
        pose: &JsonPose<'_>,
    ) -> Result<(), Error> {
        let out = self.resolve(pose)?;
        self.rate.take_at(Instant::now()).map_err(rate_limited)?;
        self.check_joints(&out)?;
        self.send(state, conn, &out)
    }

    /// A JSON pose as the binary pose the owner is sent: joints and trackers by index into the
    /// `drive` answer's lists, weights by slot ([`RemoteDrive::slot`]); tracker values checked.
    fn resolve(&self, pose: &JsonPose<'_>) -> Result<BinaryPose, Error> {
        let mut out = BinaryPose {
            avatar_num: self.num,
            time_us: pose.time_us,
            root_position: pose.root_position.map(Vec3::from_array),
            rotations: Vec::with_capacity(pose.rotations.len()),
            weights: Vec::with_capacity(pose.weights.len()),
            trackers: Vec::with_capacity(pose.trackers.len()),
        };
        if !self.trackers.is_empty() && (!pose.rotations.is_empty() || pose.root_position.is_some())
        {
            return Err(rotations_to_trackers(&self.avatar));
        }
        if !self.trackers.is_empty() {
            // Names resolved and values checked here (the check below sees indexes only).
            for (name, t) in pose.trackers {
                let i = self
                    .trackers
                    .iter()
                    .position(|n| n == name)
                    .and_then(|i| u8::try_from(i).ok())
                    .ok_or_else(|| unknown_tracker(&self.avatar, &self.trackers, name))?;
                let s = tracker_sample(name, t.position, t.rotation)?;
                out.trackers.push((i, s.position, s.rotation));
            }
        } else if !pose.trackers.is_empty() {
            return Err(trackers_to_rotations(&self.avatar));
        }
        for (name, q) in pose.rotations {
            let j = self
                .joints
                .iter()
                .position(|n| n == name)
                .and_then(|j| u16::try_from(j).ok())
                .ok_or_else(|| Error::UnknownJoint {
                    owner: Owner::DriverOf(self.avatar.clone()),
                    joint: name.clone(),
                })?;
            out.rotations.push((j, rotation(name, *q)?));
        }
        // As `world::command::face::resolve_weights` on the owner: per name, known first, then valued.
        for (name, &w) in pose.weights {
            let slot = self.slot(name).ok_or_else(|| Error::UnknownExpression {
                owner: Owner::Avatar(self.avatar.clone()),
                name: name.clone(),
                has_targets: !self.morph_targets.is_empty(),
            })?;
            let w = morph::check_weight(name, w).map_err(|e| Error::invalid(e.to_string()))?;
            out.weights.push((slot, morph::weight_level(w)));
        }
        Ok(out)
    }

    /// The slot weight `name` sets, resolved as `Avatar::morph_channel` does on the owner: an
    /// expression the file defines (slot `channels + k`), else a morph channel, else a
    /// standard expression name the avatar maps onto one.
    fn slot(&self, name: &str) -> Option<u16> {
        find_expression(&self.expression_binds, name)
            .map(|k| self.morph_targets.len() + k)
            .or_else(|| resolve(name, &self.morph_targets, &self.expressions))
            .and_then(|slot| u16::try_from(slot).ok())
    }

    /// Every joint (or tracker) index in the source rig's (or the drive's trackers), every
    /// value finite and in range, and the pose's kind the drive's (rotations or trackers).
    fn check_joints(&self, pose: &BinaryPose) -> Result<(), Error> {
        if self.trackers.is_empty() {
            if !pose.trackers.is_empty() {
                return Err(trackers_to_rotations(&self.avatar));
            }
        } else {
            if !pose.rotations.is_empty() || pose.root_position.is_some() {
                return Err(rotations_to_trackers(&self.avatar));
            }
            for &(i, p, q) in &pose.trackers {
                let name = self.trackers.get(usize::from(i)).ok_or_else(|| {
                    unknown_tracker(&self.avatar, &self.trackers, &format!("index {i}"))
                })?;
                tracker_sample(name, p.to_array(), q.to_array())?;
            }
        }
        root(pose.root_position)?;
        for &(j, q) in &pose.rotations {
            if usize::from(j) >= self.joints.len() {
                return Err(Error::UnknownJoint {
                    owner: Owner::DriverOfJoints {
                        avatar: self.avatar.clone(),
                        joints: self.joints.len(),
                    },
                    joint: format!("index {j}"),
                });
            }
            rotation(&format!("index {j}"), q.to_array())?;
        }
        Ok(())
    }

    fn send(&self, state: &Services, conn: u64, pose: &BinaryPose) -> Result<(), Error> {
        let cluster = state
            .cluster()
            .ok_or_else(|| Error::Unavailable("not in a cluster".into()))?;
        cluster.pose(&self.scene, conn, pose.encode());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two channels (`mouthOpen`, `mouthSmile`), ARKit's `jawOpen` mapped to `mouthOpen`, and
    /// one expression the file defines (`happy`, VRM 0.x `Joy`): slot 2, past the channels.
    fn drive() -> RemoteDrive {
        let happy: Expression =
            serde_json::from_str(r#"{"name":"happy","binds":[]}"#).expect("an expression");
        RemoteDrive {
            avatar: AvatarId("face".into()),
            num: 1,
            scene: SceneId("stage".into()),
            joints: vec!["hips".into()],
            morph_targets: vec!["mouthOpen".into(), "mouthSmile".into()],
            expressions: BTreeMap::from([("jawOpen".into(), "mouthOpen".into())]),
            trackers: Vec::new(),
            expression_binds: vec![happy],
            rate: pose_rate(),
        }
    }

    /// A tracker drive's JSON trackers become indexes into the drive's list, in its order,
    /// their values kept; a name the drive lacks, a bad value, rotations to a tracker drive and
    /// trackers to a drive by rotations are refused here, as on the owner; binary trackers are
    /// checked by index.
    #[test]
    fn trackers_resolve_to_the_drives_indexes() {
        use posecast_proto::trackers::TrackerTransform;
        let mut r = drive();
        r.trackers = vec!["r_hand".into(), "head".into(), "l_hand".into()];
        let at = |x: f32| TrackerTransform {
            position: [x, 1.0, 0.0],
            rotation: [0.0, 0.0, 0.0, 2.0],
        };
        let rotations = BTreeMap::new();
        let weights = BTreeMap::new();
        let pose = |trackers| JsonPose {
            rotations: &rotations,
            root_position: None,
            time_us: Some(5),
            weights: &weights,
            trackers,
        };
        let named = BTreeMap::from([
            ("head".to_owned(), at(0.5)),
            ("l_hand".to_owned(), at(0.25)),
        ]);
        let out = r.resolve(&pose(&named)).unwrap();
        // By name (a map: `head` before `l_hand`), each at its index in the drive's list.
        assert_eq!(
            out.trackers,
            vec![
                (1, Vec3::new(0.5, 1.0, 0.0), glam::Quat::IDENTITY),
                (2, Vec3::new(0.25, 1.0, 0.0), glam::Quat::IDENTITY)
            ]
        );
        r.check_joints(&out).unwrap();
        let unknown = BTreeMap::from([("l_foot".to_owned(), at(0.0))]);
        let e = r.resolve(&pose(&unknown)).unwrap_err();
        assert!(
            matches!(&e, Error::UnknownJoint { joint, .. } if joint.contains("l_foot")),
            "{e}"
        );
        let far = BTreeMap::from([("head".to_owned(), at(1e30))]);
        assert!(matches!(r.resolve(&pose(&far)), Err(Error::Invalid { .. })));
        let mut past = out.clone();
        past.trackers.push((3, Vec3::ZERO, glam::Quat::IDENTITY));
        assert!(matches!(
            r.check_joints(&past),
            Err(Error::UnknownJoint { .. })
        ));
        let mut nan = out.clone();
        nan.trackers[0].1.x = f32::NAN;
        assert!(matches!(r.check_joints(&nan), Err(Error::Invalid { .. })));
        let mut rotated = out.clone();
        rotated.rotations.push((0, glam::Quat::IDENTITY));
        assert!(matches!(
            r.check_joints(&rotated),
            Err(Error::Invalid { .. })
        ));
        // A drive by rotations takes no trackers.
        let plain = drive();
        assert!(matches!(
            plain.resolve(&pose(&named)),
            Err(Error::Invalid { .. })
        ));
        assert!(matches!(
            plain.check_joints(&out),
            Err(Error::Invalid { .. })
        ));
    }

    /// Names resolve in the owner's order: file-defined expressions, channels, standard names.
    #[test]
    fn names_resolve_to_the_owners_slots() {
        let r = drive();
        for (name, slot) in [
            ("mouthSmile", Some(1)),
            ("jawOpen", Some(0)),
            ("happy", Some(2)),
            ("Joy", Some(2)),
            ("noSuchShape", None),
        ] {
            assert_eq!(r.slot(name), slot, "{name}");
        }
    }
}
