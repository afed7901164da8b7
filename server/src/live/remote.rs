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

use super::{JsonPose, pose_rate, rate_limited, root, rotation};
use crate::scene::Scene;
use crate::state::AppState;
use glam::Vec3;
use posecast_core::error::Error;
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
            expression_binds,
            rate: pose_rate(),
        }
    }

    /// A binary pose: checked (joints, values, weights' channels) and passed on.
    pub(super) fn binary_pose(
        &mut self,
        state: &AppState,
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
                owner: format!("avatar {} (of {channels} morph channels)", self.avatar),
                name: format!("channel {c}"),
                has_targets: channels > 0,
            });
        }
        self.send(state, conn, &pose)
    }

    /// A JSON pose: joints and weights resolved by name ([`RemoteDrive::slot`]), checked and
    /// passed on.
    pub(super) fn json_pose(
        &mut self,
        state: &AppState,
        conn: u64,
        pose: &JsonPose<'_>,
    ) -> Result<(), Error> {
        let mut out = BinaryPose {
            avatar_num: self.num,
            time_us: pose.time_us,
            root_position: pose.root_position.map(Vec3::from_array),
            rotations: Vec::with_capacity(pose.rotations.len()),
            weights: Vec::with_capacity(pose.weights.len()),
        };
        for (name, q) in pose.rotations {
            let j = self
                .joints
                .iter()
                .position(|n| n == name)
                .and_then(|j| u16::try_from(j).ok())
                .ok_or_else(|| Error::UnknownJoint {
                    owner: format!("the rig driving {}", self.avatar),
                    joint: name.clone(),
                })?;
            out.rotations.push((j, rotation(name, *q)?));
        }
        // As `world::morph::resolve_weights` on the owner: per name, known first, then valued.
        for (name, &w) in pose.weights {
            let slot = self.slot(name).ok_or_else(|| Error::UnknownExpression {
                owner: format!("avatar {}", self.avatar),
                name: name.clone(),
                has_targets: !self.morph_targets.is_empty(),
            })?;
            let w = morph::check_weight(name, w).map_err(|e| Error::invalid(e.to_string()))?;
            out.weights.push((slot, morph::weight_level(w)));
        }
        self.rate.take_at(Instant::now()).map_err(rate_limited)?;
        self.check_joints(&out)?;
        self.send(state, conn, &out)
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

    /// Every joint index in the source rig's, every value finite and in range.
    fn check_joints(&self, pose: &BinaryPose) -> Result<(), Error> {
        root(pose.root_position)?;
        for &(j, q) in &pose.rotations {
            if usize::from(j) >= self.joints.len() {
                return Err(Error::UnknownJoint {
                    owner: format!("the driven rig (of {} joints)", self.joints.len()),
                    joint: format!("index {j}"),
                });
            }
            rotation(&format!("index {j}"), q.to_array())?;
        }
        Ok(())
    }

    fn send(&self, state: &AppState, conn: u64, pose: &BinaryPose) -> Result<(), Error> {
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
            expression_binds: vec![happy],
            rate: pose_rate(),
        }
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
