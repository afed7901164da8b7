//! Playback of an avatar's base clip: `play`, `pause`, `resume`, `seek`, `set_speed`, `stop`,
//! and `sample_pose` (a clip's pose at a time, read without playing it).

use super::{Announce, Bake, Handler, clip_for, fields, finite, with_avatar};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::playback::{DEFAULT_FADE, Layer};

/// `play`: cross-faded from what plays.
#[derive(Debug)]
pub struct Play;

impl Handler for Play {
    fn bake<'c>(&self, command: &'c Command) -> Option<Bake<'c>> {
        match command {
            Command::Play {
                avatar,
                clip,
                from_asset: Some(source),
                ..
            } => Some(Bake {
                avatar,
                clip,
                source,
            }),
            _ => None,
        }
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            Play {
                avatar,
                clip,
                from_asset,
                speed,
                looping,
                start,
                fade,
                root_motion,
            }
        );
        let speed = finite("speed", speed.unwrap_or(1.0))?;
        let start = finite("start", start.unwrap_or(0.0))?;
        let fade = finite("fade", fade.unwrap_or(DEFAULT_FADE))?.max(0.0);
        let source = match from_asset {
            Some(name) => Some(world.library.require(name)?),
            None => None,
        };
        with_avatar(world, avatar, |a| {
            let (clip, source_asset) = clip_for(world, a, clip, source.as_ref())?;
            let mut layer = Layer::new(clip, source_asset, start, speed, looping.unwrap_or(true));
            if let Some(mode) = root_motion {
                layer.root_motion = *mode;
            }
            a.play(layer, fade);
            Ok(CommandResult::Done)
        })
    }
}

/// Runs `f` on the clip avatar `avatar` plays, or refuses when it plays none.
fn with_current(
    world: &World,
    avatar: &AvatarId,
    f: impl FnOnce(&mut Layer),
) -> Result<CommandResult, Error> {
    with_avatar(world, avatar, |a| {
        let layer = a
            .player
            .current_mut()
            .ok_or_else(|| Error::invalid("no clip is playing"))?;
        f(layer);
        Ok(CommandResult::Done)
    })
}

/// `pause`.
#[derive(Debug)]
pub struct Pause;

impl Handler for Pause {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, Pause { avatar });
        with_current(world, avatar, |layer| layer.set_paused(true))
    }
}

/// `resume`.
#[derive(Debug)]
pub struct Resume;

impl Handler for Resume {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, Resume { avatar });
        with_current(world, avatar, |layer| layer.set_paused(false))
    }
}

/// `seek`: the pose at the new time at once.
#[derive(Debug)]
pub struct Seek;

impl Handler for Seek {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, Seek { avatar, time });
        let time = finite("time", *time)?;
        with_avatar(world, avatar, |a| {
            let layer = a
                .player
                .current_mut()
                .ok_or_else(|| Error::invalid("no clip is playing"))?;
            layer.seek(time);
            a.evaluate();
            Ok(CommandResult::Done)
        })
    }
}

/// `set_speed`.
#[derive(Debug)]
pub struct SetSpeed;

impl Handler for SetSpeed {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, SetSpeed { avatar, speed });
        let speed = finite("speed", *speed)?;
        with_current(world, avatar, |layer| layer.set_speed(speed))
    }
}

/// `stop`: back to the neutral pose.
#[derive(Debug)]
pub struct Stop;

impl Handler for Stop {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, Stop { avatar });
        with_avatar(world, avatar, |a| {
            a.player.stop();
            a.evaluate();
            Ok(CommandResult::Done)
        })
    }
}

/// `sample_pose`: a private copy of the avatar (rig, overrides, placement) plays the clip,
/// paused at `time`, and is evaluated as a tick would; the avatar itself is only read. A clip
/// from another rig is baked beforehand ([`Handler::bake`]), so this is a cache lookup.
#[derive(Debug)]
pub struct SamplePose;

impl Handler for SamplePose {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn bake<'c>(&self, command: &'c Command) -> Option<Bake<'c>> {
        match command {
            Command::SamplePose {
                avatar,
                clip: Some(clip),
                from_asset: Some(source),
                ..
            } => Some(Bake {
                avatar,
                clip,
                source,
            }),
            _ => None,
        }
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SamplePose {
                avatar,
                clip,
                from_asset,
                time,
            }
        );
        sample_pose(world, avatar, clip.as_deref(), from_asset.as_deref(), *time)
    }
}

fn sample_pose(
    world: &World,
    id: &AvatarId,
    clip: Option<&str>,
    from_asset: Option<&str>,
    time: f32,
) -> Result<CommandResult, Error> {
    let time = finite("time", time)?;
    let source = from_asset
        .map(|name| world.library.require(name))
        .transpose()?;
    let scene = world.find_avatar(id)?;
    let (rig, overrides, placement, current, num) = {
        let s = scene.lock();
        let a = s
            .avatars
            .iter()
            .find(|a| &a.id == id)
            .ok_or_else(|| Error::UnknownAvatar(id.clone()))?;
        let current = a.player.current().map(|l| {
            (
                l.clip.clone(),
                l.source_asset.clone(),
                l.looping,
                l.root_motion,
            )
        });
        (
            a.rig.clone(),
            a.overrides.clone(),
            a.pose().placement,
            current,
            a.num(),
        )
    };
    let layer = match (clip, current) {
        (Some(clip), _) => {
            let baked = match &source {
                Some(src) if src.name != rig.name => {
                    world.retargets.bake_blocking(src, clip, &rig)?
                }
                _ => rig.clip(clip).cloned().ok_or_else(|| Error::UnknownClip {
                    rig: rig.name.clone(),
                    clip: clip.to_owned(),
                })?,
            };
            let source_asset = source.as_ref().map(|s| s.name.clone());
            Layer::new(baked, source_asset, time, 1.0, true)
        }
        (None, Some((clip, source_asset, looping, root_motion))) => {
            let mut layer = Layer::new(clip, source_asset, time, 1.0, looping);
            layer.root_motion = root_motion;
            layer
        }
        (None, None) => {
            return Err(Error::invalid(format!(
                "avatar {id} plays no clip: name the clip to sample"
            )));
        }
    };
    let mut copy = Avatar::new(id.clone(), num, rig);
    copy.overrides = overrides;
    copy.play(layer, 0.0);
    if let Some(layer) = copy.player.current_mut() {
        layer.set_paused(true);
    }
    copy.evaluate();
    let pose = copy.pose();
    Ok(CommandResult::Pose(Box::new(
        posecast_proto::msg::AvatarPoseJson {
            avatar: id.clone(),
            hash: copy.description.hash.clone(),
            rotations: pose.rotations.iter().map(|q| q.to_array()).collect(),
            translations: pose.translations.iter().map(|t| t.to_array()).collect(),
            scales: pose.scales.iter().map(|s| s.to_array()).collect(),
            placement,
            joints: None,
            weights: copy
                .description
                .morph_targets
                .iter()
                .cloned()
                .zip(copy.pose().weights.iter().copied())
                .collect(),
        },
    )))
}
