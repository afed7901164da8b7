//! Control commands, one handler each. A [`Handler`] owns everything about its command that is
//! not the transport's: the right a token needs for it ([`Handler::needs`]), the slow part
//! done off the scene lock first ([`Handler::bake`]), an extra rule for tokens limited to some
//! scenes or avatars ([`Handler::limited`]), where its work runs ([`Handler::runs`]), the scene
//! it makes or ends ([`Handler::scene_change`]), what the connections that follow the world
//! hear of it ([`Handler::announce`]) and — for the commands the world runs — the change itself
//! ([`Handler::apply`], under the scene's lock, re-evaluated at once so the next tick's frame
//! shows it). [`handler`] is the registration: one line per command.
//!
//! The services read a handler's declarations instead of matching commands themselves:
//! access control (`posecast_services::auth`, handed the facts by `posecast_services::control::authorize`), the
//! control layer (`posecast_services::control`: bake, run, count, persist), announcements
//! (`posecast_services::changes`) and a cluster's scene claims (`posecast_services::cluster`). Adding a command is
//! its variant in `posecast_proto::command`, a handler in the file of its family here, and its
//! line in [`handler`].
//!
//! | file | commands |
//! |---|---|
//! | `scenes.rs` | `list_scenes`, `create_scene`, `delete_scene` |
//! | `assets.rs` | `list_assets`, `get_asset`, `configure_asset`, `delete_clip`, `delete_asset` |
//! | `avatars.rs` | `get_avatar`, `add_avatar`, `remove_avatar`, `place_avatar` |
//! | `playback.rs` | `play`, `pause`, `resume`, `seek`, `set_speed`, `stop`, `sample_pose` |
//! | `layers.rs` | `play_layer`, `stop_layer` |
//! | `joints.rs` | `get_joint`, `set_joint_rotation`, `set_joint_dofs`, `rotate_joint_local`, `rotate_joint_world`, `release` |
//! | `ik.rs` | `set_ik_goal`, `clear_ik_goal`, `look_at` |
//! | `face.rs` | `set_morph_weights`, `set_expression` |
//! | `drive.rs` | `drive`, `calibrate_trackers`, `release_drive` |
//! | `recording.rs` | `record`, `stop_recording` |
//! | `takes.rs` | `record_scene`, `stop_recording_scene`, `list_takes`, `get_take`, `delete_take`, `replay`, `control_replay` |

mod assets;
mod avatars;
mod drive;
pub mod face;
mod ik;
mod joints;
mod layers;
mod playback;
mod recording;
mod scenes;
mod takes;

pub use recording::{finish_recording, take_recording};

use super::World;
use glam::Quat;
use posecast_core::error::{Error, Owner};
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::AvatarId;
use posecast_proto::placement::Placement;
use posecast_sim::avatar::Avatar;

/// Which of a token's rights a command that changes something needs (a command that only
/// reads, [`Command::is_read_only`], needs any token that may view its scene).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Needs {
    /// The control right: scenes, avatars, playback, joints, placement, takes.
    Control,
    /// The drive right: live driving, trackers, IK goals, faces.
    Drive,
    /// The record right: recordings of avatars and takes of scenes.
    Record,
    /// Deleting an object a token made (an upload, a recording): any right that makes objects
    /// (control, upload, record) — and then who made it decides, where it runs
    /// (`AccessConfig::authorize_delete`).
    DeleteOwned,
    /// Deleting what has no maker on record (a take): the rights of
    /// [`Needs::DeleteOwned`], and a token not limited to scenes or avatars.
    Delete,
}

/// Where a command's work runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Runs {
    /// In the world ([`Handler::apply`]), and then — with a data folder or a cluster — stored
    /// with its scene before the answer.
    World,
    /// In the services, because it reads or writes files (uploads, recordings, takes):
    /// `crate::control` runs it, and it stores what it makes itself. Its `apply` refuses.
    Files,
    /// In the services, because it writes a file, and then — with a data folder or a
    /// cluster — stored with its scene before the answer, like [`Runs::World`]
    /// (`stop_recording`: its clip is written off the scene's lock, and the avatar no longer
    /// records). Its `apply` does the whole change in memory, for callers without a data
    /// folder.
    FilesThenScene,
    /// In the websocket session that sends it (`drive`: poses stream over that connection).
    /// Its `apply` refuses.
    Connection,
}

/// A scene a command makes or ends: a cluster claims or releases the scene's id for it, and
/// the world's watchers hear of it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneChange {
    /// Neither.
    None,
    /// It makes the scene it names (`create_scene`, `replay`).
    Creates,
    /// It ends the scene it names (`delete_scene`).
    Deletes,
}

/// What the connections that follow an avatar hear when a command on it succeeds
/// (`avatar_changed`, `avatar_removed`; `posecast_services::changes`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Announce {
    /// Nothing (reads, and commands on no avatar).
    Nothing,
    /// The avatar of its result is new in its scene.
    Added,
    /// The avatar it names left its scene.
    Removed,
    /// The avatar's state, always.
    State,
    /// The avatar's state when the set of overridden joints changed (not for every new angle).
    Overrides,
    /// The avatar's state when its set of IK goals, or whether a gaze is set, changed.
    Goals,
    /// The avatar's state when the set of morph channels above 0 changed (the stream carries
    /// the weights).
    Faces,
}

/// The clip a command plays from another rig, retargeted ahead of it off the scene lock
/// ([`Handler::bake`]).
#[derive(Debug, Clone, Copy)]
pub struct Bake<'c> {
    /// The avatar that plays it (its rig is the target).
    pub avatar: &'c AvatarId,
    /// The clip.
    pub clip: &'c str,
    /// The rig the clip belongs to.
    pub source: &'c str,
}

/// One command's steps (see the module documentation). Only [`Handler::apply`] has no
/// default.
pub trait Handler: Sync + std::fmt::Debug {
    /// The right it needs when it changes something.
    fn needs(&self) -> Needs {
        Needs::Control
    }

    /// A check for tokens limited to some scenes or avatars, on top of the scene or avatar
    /// they may command (`add_avatar`: the rig's size).
    ///
    /// # Errors
    /// The refusal.
    fn limited(&self, _world: &World, _command: &Command) -> Result<(), Error> {
        Ok(())
    }

    /// The clip to retarget before applying (the slow part, done off the scene lock).
    fn bake<'c>(&self, _command: &'c Command) -> Option<Bake<'c>> {
        None
    }

    /// Where it runs.
    fn runs(&self) -> Runs {
        Runs::World
    }

    /// The scene it makes or ends.
    fn scene_change(&self) -> SceneChange {
        SceneChange::None
    }

    /// What its success tells the connections that follow its avatar.
    fn announce(&self) -> Announce {
        Announce::State
    }

    /// The command applied to `world`; nothing changes when it fails.
    ///
    /// # Errors
    /// A typed error naming what is wrong.
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error>;
}

/// The handler of a command whose work is all files ([`Runs::Files`]: uploads, takes), which
/// the services run: its declarations are its whole handler, and the world refuses it.
#[derive(Debug)]
pub struct InServices {
    /// The command's `op`.
    pub op: &'static str,
    /// The right it needs when it changes something.
    pub needs: Needs,
    /// The scene it makes (`replay`) or none.
    pub scene_change: SceneChange,
    /// Why the world refuses it: what it works on.
    pub files: &'static str,
}

impl Handler for InServices {
    fn needs(&self) -> Needs {
        self.needs
    }

    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn scene_change(&self) -> SceneChange {
        self.scene_change
    }

    /// What it changes is files; the connections following an avatar hear nothing of it.
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        Err(Error::NotAllowedNow(format!(
            "{} runs in the server's services, not in the world: it works on {}",
            self.op, self.files
        )))
    }
}

/// The handler of `command`: the registration, one line per command.
#[must_use]
pub fn handler(command: &Command) -> &'static dyn Handler {
    use Command as C;
    match command {
        C::ListScenes => &scenes::ListScenes,
        C::CreateScene { .. } => &scenes::CreateScene,
        C::DeleteScene { .. } => &scenes::DeleteScene,
        C::ListAssets => &assets::ListAssets,
        C::GetAsset { .. } => &assets::GetAsset,
        C::ConfigureAsset { .. } => &assets::CONFIGURE_ASSET,
        C::DeleteClip { .. } => &assets::DeleteClip,
        C::DeleteAsset { .. } => &assets::DELETE_ASSET,
        C::GetAvatar { .. } => &avatars::GetAvatar,
        C::AddAvatar { .. } => &avatars::AddAvatar,
        C::RemoveAvatar { .. } => &avatars::RemoveAvatar,
        C::PlaceAvatar { .. } => &avatars::PlaceAvatar,
        C::Play { .. } => &playback::Play,
        C::Pause { .. } => &playback::Pause,
        C::Resume { .. } => &playback::Resume,
        C::Seek { .. } => &playback::Seek,
        C::SetSpeed { .. } => &playback::SetSpeed,
        C::Stop { .. } => &playback::Stop,
        C::SamplePose { .. } => &playback::SamplePose,
        C::PlayLayer { .. } => &layers::PlayLayer,
        C::StopLayer { .. } => &layers::StopLayer,
        C::GetJoint { .. } => &joints::GetJoint,
        C::SetJointRotation { .. } => &joints::SetJointRotation,
        C::SetJointDofs { .. } => &joints::SetJointDofs,
        C::RotateJointLocal { .. } => &joints::RotateJointLocal,
        C::RotateJointWorld { .. } => &joints::RotateJointWorld,
        C::Release { .. } => &joints::Release,
        C::SetIkGoal { .. } => &ik::SetIkGoal,
        C::ClearIkGoal { .. } => &ik::ClearIkGoal,
        C::LookAt { .. } => &ik::LookAt,
        C::SetMorphWeights { .. } => &face::SetMorphWeights,
        C::SetExpression { .. } => &face::SetExpression,
        C::Drive { .. } => &drive::Drive,
        C::CalibrateTrackers { .. } => &drive::CalibrateTrackers,
        C::ReleaseDrive { .. } => &drive::ReleaseDrive,
        C::Record { .. } => &recording::Record,
        C::StopRecording { .. } => &recording::StopRecording,
        C::RecordScene { .. } => &takes::RECORD_SCENE,
        C::StopRecordingScene { .. } => &takes::STOP_RECORDING_SCENE,
        C::ListTakes => &takes::LIST_TAKES,
        C::GetTake { .. } => &takes::GET_TAKE,
        C::DeleteTake { .. } => &takes::DELETE_TAKE,
        C::Replay { .. } => &takes::REPLAY,
        C::ControlReplay { .. } => &takes::ControlReplay,
    }
}

/// Applies `command` to `world` through its handler; nothing changes when it fails.
///
/// # Errors
/// A typed error naming what is wrong; `not_allowed_now` for a command that runs elsewhere
/// ([`Runs::Files`], [`Runs::Connection`]).
pub fn apply(world: &World, command: &Command) -> Result<CommandResult, Error> {
    handler(command).apply(world, command)
}

/// The error of a handler given another command than its own: [`handler`] registered it
/// wrongly (a bug, answered as `internal`, never a panic).
fn misrouted(command: &Command) -> Error {
    Error::Internal(format!(
        "command {command:?} reached another command's handler"
    ))
}

/// Binds the fields of `command`'s variant `$variant`, or returns [`misrouted`] from the
/// enclosing function.
macro_rules! fields {
    ($command:expr, $variant:ident { $($field:tt)* }) => {
        let posecast_proto::command::Command::$variant { $($field)* } = $command else {
            return Err($crate::world::command::misrouted($command));
        };
    };
}
use fields;

/// A finite, non-zero quaternion, normalised (in f64, so huge finite components cannot
/// overflow into a zero or NaN rotation that would then be acknowledged and stored): the
/// command's `rotation`.
fn quat(q: [f32; 4]) -> Result<Quat, Error> {
    posecast_proto::unit_quat(q).ok_or_else(|| {
        Error::invalid_field(
            "rotation",
            format!("rotation {q:?} is not a finite non-zero quaternion"),
        )
    })
}

/// `v`, the command's field `field`, when finite.
fn finite(field: &'static str, v: f32) -> Result<f32, Error> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(Error::invalid_field(
            field,
            format!("{field} must be finite"),
        ))
    }
}

fn joint_index(avatar: &Avatar, joint: &str) -> Result<usize, Error> {
    avatar.rig.joint(joint).ok_or_else(|| Error::UnknownJoint {
        owner: Owner::Avatar(avatar.id.clone()),
        joint: joint.to_owned(),
    })
}

/// A validated placement, or `invalid_value` naming what is wrong.
fn placement(position: [f32; 3], rotation: [f32; 4]) -> Result<Placement, Error> {
    Placement::try_new(position, rotation).map_err(|e| Error::invalid(e.to_string()))
}

/// Runs `f` on an avatar under its scene's lock.
fn with_avatar<T>(
    world: &World,
    id: &AvatarId,
    f: impl FnOnce(&mut Avatar) -> Result<T, Error>,
) -> Result<T, Error> {
    let scene = world.find_avatar(id)?;
    let mut s = scene.lock();
    let avatar = s
        .avatar_mut(id)
        .ok_or_else(|| Error::UnknownAvatar(id.clone()))?;
    f(avatar)
}

/// The commands that play a clip, on the current avatar: the clip `clip` for avatar `a`, its
/// rig's own, or `source`'s retargeted onto it (normally baked already: the control layer
/// bakes off the lock first, [`Handler::bake`]; only start-up restore and in-memory callers
/// bake here), with the source's name when it is another rig.
fn clip_for(
    world: &World,
    a: &Avatar,
    clip: &str,
    source: Option<&std::sync::Arc<posecast_rigs::rig::Rig>>,
) -> Result<(std::sync::Arc<posecast_rigs::clip::Clip>, Option<String>), Error> {
    let baked = match source {
        Some(src) if src.name != a.rig.name => world.retargets.bake_blocking(src, clip, &a.rig)?,
        _ => a
            .rig
            .clip(clip)
            .cloned()
            .ok_or_else(|| Error::UnknownClip {
                rig: a.rig.name.clone(),
                clip: clip.to_owned(),
            })?,
    };
    let source_asset = source.map(|s| s.name.clone()).filter(|n| n != &a.rig.name);
    Ok((baked, source_asset))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::Metrics;
    use posecast_core::quota::Quotas;
    use serde_json::{Value, json};
    use std::collections::BTreeSet;
    use std::sync::Arc;

    /// The ops of the command table in `proto/PROTOCOL.md` ("Commands"), as documented.
    fn documented_ops() -> Vec<String> {
        let doc = include_str!("../../../../proto/PROTOCOL.md");
        let table = &doc[doc.find("## Commands").unwrap()..];
        let table = &table[..table.find("```json").unwrap()];
        let mut ops = Vec::new();
        for row in table.lines().filter(|l| l.starts_with("| `")) {
            let first = row.split('|').nth(1).unwrap();
            // `pause` / `resume` / `stop`; `release_drive` (alias `undrive`): the names before
            // any parenthesis.
            let names = first.split('(').next().unwrap();
            ops.extend(names.split('`').skip(1).step_by(2).map(str::to_owned));
        }
        ops
    }

    /// A command of `op` with every field it takes, made by leaving out of a superset of every
    /// command's fields those that `op` refuses as unknown.
    fn example(op: &str) -> Command {
        let mut fields = json!({
            "op": op, "avatar": "a", "scene": "s", "asset": "x", "clip": "c", "joint": "j",
            "time": 0.5, "speed": 1.0, "rotation": [0.0, 0.0, 0.0, 1.0],
            "position": [0.0, 0.0, 0.0], "values": [0.1], "effector": "e",
            "target": [0.0, 1.0, 0.0], "weights": {"smile": 0.5}, "expression": "smile",
            "take": "t", "layer": "l", "options": {}
        });
        for _ in 0..64 {
            match serde_json::from_value::<Command>(fields.clone()) {
                Ok(command) => return command,
                Err(e) => {
                    let message = e.to_string();
                    let unknown = message
                        .strip_prefix("unknown field `")
                        .and_then(|rest| rest.split('`').next())
                        .unwrap_or_else(|| panic!("{op}: {message}"));
                    fields.as_object_mut().unwrap().remove(unknown);
                }
            }
        }
        panic!("{op}: no example");
    }

    /// The right each documented op needs, as `proto/PROTOCOL.md` ("Access control", **Rights**)
    /// and the command table say: `drive` for driving, goals and faces; `record` for
    /// recordings and takes; any right that makes objects for deletes (its own objects; a take
    /// with an unlimited token); `control` for every other change.
    fn documented_needs(op: &str) -> Option<Needs> {
        let read_only = [
            "list_scenes",
            "list_assets",
            "get_asset",
            "get_avatar",
            "get_joint",
            "sample_pose",
            "list_takes",
            "get_take",
        ];
        Some(match op {
            _ if read_only.contains(&op) => return None,
            "drive" | "release_drive" | "calibrate_trackers" | "set_ik_goal" | "clear_ik_goal"
            | "look_at" | "set_morph_weights" | "set_expression" => Needs::Drive,
            "record" | "stop_recording" | "record_scene" | "stop_recording_scene" => Needs::Record,
            "delete_clip" | "delete_asset" => Needs::DeleteOwned,
            "delete_take" => Needs::Delete,
            _ => Needs::Control,
        })
    }

    #[tokio::test]
    async fn every_documented_command_has_its_own_handler_with_the_documented_right() {
        let world = World::new(60.0, Quotas::default(), Arc::new(Metrics::new()));
        let ops = documented_ops();
        let distinct: BTreeSet<&String> = ops.iter().collect();
        assert_eq!(distinct.len(), ops.len(), "an op documented twice: {ops:?}");
        // Every variant (the registration's match is exhaustive: a new variant without a
        // handler does not compile; one the table lacks fails here).
        assert_eq!(ops.len(), 44, "{ops:?}");
        let mut handlers = BTreeSet::new();
        for op in &ops {
            let command = example(op);
            let h = handler(&command);
            handlers.insert(format!("{h:?}"));
            // The registration sends every command to the handler of its variant: the
            // handler takes its fields, so it never answers "reached another command's
            // handler" (the world is empty: most refuse the unknown avatar or scene).
            if let Err(Error::Internal(m)) = h.apply(&world, &command) {
                panic!("{op}: {m}");
            }
            assert_eq!(
                (!command.is_read_only()).then(|| h.needs()),
                documented_needs(op),
                "{op}"
            );
            if command.is_read_only() {
                assert_eq!(h.announce(), Announce::Nothing, "{op} only reads");
                assert_eq!(h.scene_change(), SceneChange::None, "{op} only reads");
            }
            // A handler that is only declarations names its command in its refusal.
            if let Err(Error::NotAllowedNow(m)) = h.apply(&world, &command)
                && let Some((named, _)) = m.split_once(" runs in the server's services")
            {
                assert_eq!(named, op, "{op} is registered to {named}'s declarations");
            }
            if matches!(h.runs(), Runs::Files | Runs::Connection) {
                assert!(
                    matches!(h.apply(&world, &command), Err(Error::NotAllowedNow(_)))
                        || op == "delete_clip",
                    "{op} runs elsewhere: the world refuses it"
                );
            }
            let creates = ["create_scene", "replay"].contains(&op.as_str());
            let deletes = op == "delete_scene";
            assert_eq!(
                h.scene_change(),
                match (creates, deletes) {
                    (true, _) => SceneChange::Creates,
                    (_, true) => SceneChange::Deletes,
                    _ => SceneChange::None,
                },
                "{op}"
            );
        }
        // One handler per command.
        assert_eq!(handlers.len(), ops.len());
        assert_eq!(
            format!("{:?}", handler(&example("undrive"))),
            format!("{:?}", handler(&example("release_drive")))
        );
    }

    #[test]
    fn a_handler_given_another_command_refuses_it_as_internal() {
        let world = World::new(60.0, Quotas::default(), Arc::new(Metrics::new()));
        let pause = example("pause");
        let seek = handler(&example("seek"));
        assert!(matches!(
            seek.apply(&world, &pause),
            Err(Error::Internal(_))
        ));
        let _: Value = serde_json::to_value(&pause).unwrap();
    }
}
