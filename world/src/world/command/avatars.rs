//! `get_avatar`, `add_avatar`, `remove_avatar`, `place_avatar`.

use super::{Announce, Handler, fields, placement};
use crate::world::World;
use posecast_core::error::Error;
use posecast_core::quota::Quota;
use posecast_proto::command::{Command, CommandResult};
use posecast_sim::avatar::playback::Layer;

/// `get_avatar`.
#[derive(Debug)]
pub struct GetAvatar;

impl Handler for GetAvatar {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, GetAvatar { avatar });
        let scene = world.find_avatar(avatar)?;
        let s = scene.lock();
        let a = s
            .avatars
            .iter()
            .find(|a| &a.id == avatar)
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
        Ok(CommandResult::Avatar(Box::new(a.state(&scene.id))))
    }
}

/// `add_avatar`: placed, and playing its clip from the start when it names one.
#[derive(Debug)]
pub struct AddAvatar;

impl Handler for AddAvatar {
    fn announce(&self) -> Announce {
        Announce::Added
    }

    /// A limited token places only rigs of at most
    /// [`posecast_core::quota::Quotas::limited_max_joints`] joints: one user's avatar cannot
    /// make every viewer of the scene download a huge rig.
    fn limited(&self, world: &World, command: &Command) -> Result<(), Error> {
        fields!(command, AddAvatar { asset, .. });
        let max = world.quotas().limited_max_joints;
        match world.library.get(asset) {
            Some(rig) if rig.skeleton().len() > max => Err(world.metrics.refuse_quota(
                Quota::LimitedJoints,
                format!(
                    "rig {asset} has {} joints; a limited token may place rigs of up to",
                    rig.skeleton().len()
                ),
                max,
            )),
            // An unknown asset is reported by the command itself.
            _ => Ok(()),
        }
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            AddAvatar {
                scene,
                asset,
                avatar,
                clip,
                position,
                rotation,
            }
        );
        let placement = placement(
            position.unwrap_or([0.0; 3]),
            rotation.unwrap_or([0.0, 0.0, 0.0, 1.0]),
        )?;
        if let Some(clip) = clip {
            let rig = world.library.require(asset)?;
            if rig.clip(clip).is_none() {
                return Err(Error::UnknownClip {
                    rig: asset.clone(),
                    clip: clip.clone(),
                });
            }
        }
        let (scene, id) = world.add_avatar_at(scene, asset, avatar.clone(), placement, true)?;
        if let Some(clip) = clip {
            let mut s = scene.lock();
            if let Some(a) = s.avatar_mut(&id)
                && let Some(c) = a.rig.clip(clip).cloned()
            {
                a.play(Layer::new(c, None, 0.0, 1.0, true), 0.0);
            }
        }
        Ok(CommandResult::AvatarAdded { avatar: id })
    }
}

/// `remove_avatar`.
#[derive(Debug)]
pub struct RemoveAvatar;

impl Handler for RemoveAvatar {
    fn announce(&self) -> Announce {
        Announce::Removed
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, RemoveAvatar { avatar });
        let scene = world.find_avatar(avatar)?;
        scene.remove_avatar(avatar);
        Ok(CommandResult::Done)
    }
}

/// `place_avatar`: at once, or moved there over `duration` seconds.
#[derive(Debug)]
pub struct PlaceAvatar;

impl Handler for PlaceAvatar {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            PlaceAvatar {
                avatar,
                position,
                rotation,
                duration,
            }
        );
        let to = placement(*position, *rotation)?;
        let duration = duration.unwrap_or(0.0);
        if !(duration.is_finite() && duration >= 0.0) {
            return Err(Error::invalid_field(
                "duration",
                "duration must be finite and ≥ 0",
            ));
        }
        let scene = world.find_avatar(avatar)?;
        let mut s = scene.lock();
        let a = s
            .avatar_mut(avatar)
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
        a.place(to, f64::from(duration));
        // The scene's cached frames show the old placement: a joiner gets a fresh keyframe.
        scene.feed().placed();
        Ok(CommandResult::Done)
    }
}
