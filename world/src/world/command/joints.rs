//! A joint's rotation read or overridden: `get_joint`, `set_joint_rotation`,
//! `set_joint_dofs`, `rotate_joint_local`, `rotate_joint_world`, `release`.

use super::{Announce, Handler, fields, finite, joint_index, quat, with_avatar};
use crate::world::World;
use glam::Quat;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, DofInfo, JointInfo};
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;
use serde_json::Value;

/// `get_joint`.
#[derive(Debug)]
pub struct GetJoint;

impl Handler for GetJoint {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, GetJoint { avatar, joint });
        with_avatar(world, avatar, |a| {
            let j = joint_index(a, joint)?;
            Ok(CommandResult::Joint(Box::new(joint_info(a, j))))
        })
    }
}

/// `set_joint_rotation`: the joint's local rotation overridden (within its limits).
#[derive(Debug)]
pub struct SetJointRotation;

impl Handler for SetJointRotation {
    fn announce(&self) -> Announce {
        Announce::Overrides
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SetJointRotation {
                avatar,
                joint,
                rotation,
            }
        );
        with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.set_rotation(j, q)
                .map_err(|e| Error::invalid(e.to_string()))
        })
    }
}

/// `set_joint_dofs`: the joint's DOF values, as its rig's joint type defines them.
#[derive(Debug)]
pub struct SetJointDofs;

impl Handler for SetJointDofs {
    fn announce(&self) -> Announce {
        Announce::Overrides
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SetJointDofs {
                avatar,
                joint,
                values,
            }
        );
        with_avatar(world, avatar, |a| {
            let j = joint_index(a, joint)?;
            let limits = a.rig.limits.get(j).cloned().flatten().ok_or_else(|| {
                Error::invalid(format!("joint {joint} has no DOFs (its rig has no joint types); set its rotation instead"))
            })?;
            let mut dofs = limits.dofs.clone();
            if values.len() != dofs.dofs().len() {
                return Err(Error::invalid(format!(
                    "joint {joint} has {} DOFs, got {} values",
                    dofs.dofs().len(),
                    values.len()
                )));
            }
            for (i, &v) in values.iter().enumerate() {
                dofs.set(i, finite("dofs", v)?)
                    .map_err(|e| Error::invalid(e.to_string()))?;
            }
            let q =
                posecast_proto::unit_quat((limits.pre * dofs.rotation() * limits.post).to_array())
                    .ok_or_else(|| {
                        Error::invalid(format!("joint {joint}: the DOF values give no rotation"))
                    })?;
            a.overrides[j] = Some(q);
            a.evaluate();
            Ok(CommandResult::Dofs {
                rotation: q.to_array(),
                values: dofs.dofs().iter().map(|d| d.value).collect(),
            })
        })
    }
}

/// `rotate_joint_local`: the joint's rotation turned in its parent's frame.
#[derive(Debug)]
pub struct RotateJointLocal;

impl Handler for RotateJointLocal {
    fn announce(&self) -> Announce {
        Announce::Overrides
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            RotateJointLocal {
                avatar,
                joint,
                rotation,
            }
        );
        with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.rotate_local(j, q)
                .map_err(|e| Error::invalid(format!("joint {joint}: {e}")))
        })
    }
}

/// `rotate_joint_world`: the joint's rotation turned in the world's frame.
#[derive(Debug)]
pub struct RotateJointWorld;

impl Handler for RotateJointWorld {
    fn announce(&self) -> Announce {
        Announce::Overrides
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            RotateJointWorld {
                avatar,
                joint,
                rotation,
            }
        );
        with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.rotate_world(j, q)
                .map_err(|e| Error::invalid(format!("joint {joint}: {e}")))
        })
    }
}

/// `release`: one joint's override, or all of them, given back to the clip.
#[derive(Debug)]
pub struct Release;

impl Handler for Release {
    fn announce(&self) -> Announce {
        Announce::Overrides
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, Release { avatar, joint });
        with_avatar(world, avatar, |a| {
            let j = joint
                .as_deref()
                .map(|name| joint_index(a, name))
                .transpose()?;
            a.release(j);
            Ok(CommandResult::Done)
        })
    }
}

/// The three rotation commands share this: validate the quaternion, find the joint, apply
/// `f` under the scene lock, answer with the rotation actually set (after limits).
fn with_joint_rotation(
    world: &World,
    avatar: &AvatarId,
    joint: &str,
    rotation: [f32; 4],
    f: impl FnOnce(&mut Avatar, usize, Quat) -> Result<Quat, Error>,
) -> Result<CommandResult, Error> {
    let q = quat(rotation)?;
    with_avatar(world, avatar, |a| {
        let j = joint_index(a, joint)?;
        let set = f(a, j, q)?;
        Ok(CommandResult::Rotation {
            rotation: set.to_array(),
        })
    })
}

/// `get_joint`'s answer: the joint's DOFs hold the current local rotation, mapped back to the
/// authored frame (`pre⁻¹ · R · post⁻¹`) and projected onto them.
fn joint_info(a: &Avatar, j: usize) -> JointInfo {
    let skeleton = a.rig.skeleton();
    let rotation = a.locals[j].rotation;
    let (joint_type, dofs) = match a.rig.limits.get(j).cloned().flatten() {
        Some(limits) => {
            let mut dofs = limits.dofs.clone();
            let authored = (limits.pre.inverse() * rotation * limits.post.inverse()).normalize();
            // A rotation that the joint cannot take is projected and clamped; a failure (not
            // finite) leaves the DOFs at their last values, which is still a valid answer.
            dofs.set_rotation(authored).ok();
            let name = serde_json::to_value(dofs.joint_type)
                .ok()
                .and_then(|v| v.get("type").and_then(Value::as_str).map(str::to_owned));
            let limit = |v: f32| v.is_finite().then_some(v);
            let infos = dofs
                .dofs()
                .iter()
                .map(|d| DofInfo {
                    value: d.value,
                    min: limit(d.min),
                    max: limit(d.max),
                })
                .collect();
            (name, infos)
        }
        None => (None, Vec::new()),
    };
    JointInfo {
        joint: skeleton.names()[j].clone(),
        parent: skeleton.parents()[j].map(|p| skeleton.names()[p].clone()),
        joint_type,
        dofs,
        rotation: rotation.to_array(),
        overridden: a.overrides[j].is_some(),
    }
}
