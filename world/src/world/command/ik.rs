//! The IK commands (`set_ik_goal`, `clear_ik_goal`, `look_at`, seed 002):
//! checked in full before anything changes, then set on the avatar under its scene's lock and
//! the pose re-evaluated at once. The goals themselves and their solve are the avatar's
//! ([`posecast_sim::avatar::goals`]); the scene keeps frames relative to other avatars' joints
//! current every tick ([`crate::scene`]).

use super::{Announce, Handler, Needs, fields, joint_index, quat, with_avatar};
use crate::world::World;
use glam::Mat4;
use posecast_core::error::{Error, Owner};
use posecast_proto::command::{Command, CommandResult, JointRef};
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::goals::{self, GazeGoal, GoalError, IkGoal};
use posecast_sim::avatar::playback::DEFAULT_FADE;

/// `set_ik_goal`: an effector reaching for a point (and a rotation), in the world or
/// relative to a joint.
#[derive(Debug)]
pub struct SetIkGoal;

impl Handler for SetIkGoal {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn announce(&self) -> Announce {
        Announce::Goals
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SetIkGoal {
                avatar,
                effector,
                position,
                rotation,
                weight,
                pole,
                relative_to,
                chain,
            }
        );
        set_goal(
            world,
            avatar,
            |a| {
                let (end, solver) = goals::solver(&a.rig, effector, chain.map(usize::from))
                    .map_err(|e| error(a, e))?;
                Ok(Pending::Goal(IkGoal {
                    effector: end,
                    solver,
                    position: goals::point("position", *position).map_err(|e| error(a, e))?,
                    rotation: rotation.map(quat).transpose()?,
                    pole: pole
                        .map(|p| goals::point("pole", p))
                        .transpose()
                        .map_err(|e| error(a, e))?,
                    weight: goals::weight(*weight).map_err(|e| error(a, e))?,
                    relative_to: relative_to.clone().map(joint_ref),
                    chain: chain.map(usize::from),
                    frame: Mat4::IDENTITY,
                }))
            },
            relative_to.as_ref(),
        )
    }
}

/// `look_at`: the head and eyes turned to a target; weight 0 ends the gaze.
#[derive(Debug)]
pub struct LookAt;

impl Handler for LookAt {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn announce(&self) -> Announce {
        Announce::Goals
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            LookAt {
                avatar,
                target,
                weight,
                relative_to,
            }
        );
        set_goal(
            world,
            avatar,
            |a| {
                let weight = goals::weight(*weight).map_err(|e| error(a, e))?;
                let target = goals::point("target", *target).map_err(|e| error(a, e))?;
                if weight == 0.0 {
                    return Ok(Pending::EndGaze);
                }
                Ok(Pending::Gaze(GazeGoal {
                    joints: goals::gaze(&a.rig).map_err(|e| error(a, e))?,
                    target,
                    weight,
                    relative_to: relative_to.clone().map(joint_ref),
                    frame: Mat4::IDENTITY,
                }))
            },
            relative_to.as_ref(),
        )
    }
}

/// `clear_ik_goal`: one effector's goal, or every goal, faded out.
#[derive(Debug)]
pub struct ClearIkGoal;

impl Handler for ClearIkGoal {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn announce(&self) -> Announce {
        Announce::Goals
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            ClearIkGoal {
                avatar,
                effector,
                fade,
            }
        );
        let fade = fade.unwrap_or(DEFAULT_FADE);
        if !(fade.is_finite() && fade >= 0.0) {
            return Err(Error::invalid_field("fade", "fade must be finite and ≥ 0"));
        }
        with_avatar(world, avatar, |a| {
            let joint = effector.as_deref().map(|e| joint_index(a, e)).transpose()?;
            let clock = a.player.clock();
            a.goals.release(joint, clock, fade);
            a.evaluate();
            Ok(CommandResult::Done)
        })
    }
}

/// What a checked command sets.
enum Pending {
    Goal(IkGoal),
    Gaze(GazeGoal),
    EndGaze,
}

/// Checks the command on the avatar (`make`) and the joint its values are relative to, then
/// sets the goal with that joint's frame as it is now, and re-evaluates the pose.
fn set_goal(
    world: &World,
    avatar: &AvatarId,
    make: impl FnOnce(&Avatar) -> Result<Pending, Error>,
    relative_to: Option<&JointRef>,
) -> Result<CommandResult, Error> {
    let scene = world.find_avatar(avatar)?;
    let mut s = scene.lock();
    let pending = {
        let a = s
            .avatar_mut(avatar)
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
        make(a)?
    };
    let frame = match relative_to {
        None => Mat4::IDENTITY,
        Some(r) => {
            let other = s.avatar_mut(&r.avatar).ok_or_else(|| {
                Error::invalid(format!(
                    "relative_to: avatar {} is not in avatar {avatar}'s scene",
                    r.avatar
                ))
            })?;
            let j = joint_index(other, &r.joint)?;
            other.scene_matrix(j)
        }
    };
    let a = s
        .avatar_mut(avatar)
        .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
    match pending {
        Pending::Goal(goal) => a.goals.set(IkGoal { frame, ..goal }),
        Pending::Gaze(gaze) => a.goals.set_gaze(Some(GazeGoal { frame, ..gaze })),
        Pending::EndGaze => {
            let clock = a.player.clock();
            a.goals.release_gaze(clock, DEFAULT_FADE);
        }
    }
    a.evaluate();
    Ok(CommandResult::Done)
}

fn joint_ref(r: JointRef) -> goals::JointRef {
    goals::JointRef {
        avatar: r.avatar,
        joint: r.joint,
    }
}

fn error(avatar: &Avatar, e: GoalError) -> Error {
    match e {
        GoalError::UnknownJoint(joint) => Error::UnknownJoint {
            owner: Owner::Avatar(avatar.id.clone()),
            joint,
        },
        other => Error::invalid(other.to_string()),
    }
}
