//! A control command applied to the [`World`] — the same code behind REST, the websocket and
//! restoring stored scenes. Every change happens under the scene's lock and is re-evaluated at
//! once, so the next tick's frame shows it. Authorisation, metrics and durability are the
//! callers' ([`crate::control`]).

use super::World;
use glam::Quat;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, DofInfo, JointInfo, RecordingInfo};
use posecast_proto::msg::{AvatarId, check_id};
use posecast_proto::placement::Placement;
use posecast_proto::trackers::CalibrationInfo;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::playback::{DEFAULT_FADE, Layer};
use posecast_sim::avatar::recording::{RecordLimits, Recorder};
use posecast_sim::avatar::trackers::TrackerError;
use serde_json::Value;

/// A finite, non-zero quaternion, normalised (in f64, so huge finite components cannot
/// overflow into a zero or NaN rotation that would then be acknowledged and stored).
pub(super) fn quat(q: [f32; 4]) -> Result<Quat, Error> {
    posecast_proto::unit_quat(q).ok_or_else(|| {
        Error::invalid(format!(
            "rotation {q:?} is not a finite non-zero quaternion"
        ))
    })
}

pub(super) fn finite(name: &str, v: f32) -> Result<f32, Error> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(Error::invalid(format!("{name} must be finite")))
    }
}

pub(super) fn joint_index(avatar: &Avatar, joint: &str) -> Result<usize, Error> {
    avatar.rig.joint(joint).ok_or_else(|| Error::UnknownJoint {
        owner: format!("avatar {}", avatar.id),
        joint: joint.to_owned(),
    })
}

/// Runs `f` on an avatar under its scene's lock.
pub(super) fn with_avatar<T>(
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

/// `sample_pose`: a private copy of the avatar (rig, overrides, placement) plays the clip,
/// paused at `time`, and is evaluated as a tick would; the avatar itself is only read. A clip
/// from another rig is baked by the caller beforehand ([`crate::world::World::retargets`]),
/// so this is a cache lookup.
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

/// Applies `command` to `world`; nothing changes when it fails.
///
/// # Errors
/// A typed error naming what is wrong.
pub fn apply(world: &World, command: &Command) -> Result<CommandResult, Error> {
    match command {
        Command::ListScenes => Ok(CommandResult::Scenes(
            world.scenes().iter().map(|s| s.info()).collect(),
        )),
        Command::ListAssets => Ok(CommandResult::Assets(
            world.library.all().iter().map(|r| r.info()).collect(),
        )),
        Command::GetAsset { asset } => Ok(CommandResult::Asset(Box::new(
            world.library.require(asset)?.detail(),
        ))),
        // It re-imports the upload's files, which the world does not hold.
        Command::ConfigureAsset { .. } => Err(Error::NotAllowedNow(
            "configure_asset is run by the service layer (REST or websocket)".into(),
        )),
        Command::GetAvatar { avatar } => {
            let scene = world.find_avatar(avatar)?;
            let s = scene.lock();
            let a = s
                .avatars
                .iter()
                .find(|a| &a.id == avatar)
                .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
            Ok(CommandResult::Avatar(Box::new(a.state(&scene.id))))
        }
        Command::GetJoint { avatar, joint } => with_avatar(world, avatar, |a| {
            let j = joint_index(a, joint)?;
            Ok(CommandResult::Joint(Box::new(joint_info(a, j))))
        }),
        Command::SamplePose {
            avatar,
            clip,
            from_asset,
            time,
        } => sample_pose(world, avatar, clip.as_deref(), from_asset.as_deref(), *time),
        Command::CreateScene { scene } => {
            world.create_scene(scene.clone())?;
            Ok(CommandResult::SceneCreated {
                scene: scene.clone(),
            })
        }
        Command::DeleteScene { scene } => {
            world.delete_scene(scene)?;
            Ok(CommandResult::Done)
        }
        Command::AddAvatar {
            scene,
            asset,
            avatar,
            clip,
            position,
            rotation,
        } => {
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
        Command::RemoveAvatar { avatar } => {
            let scene = world.find_avatar(avatar)?;
            scene.remove_avatar(avatar);
            Ok(CommandResult::Done)
        }
        Command::Play {
            avatar,
            clip,
            from_asset,
            speed,
            looping,
            start,
            fade,
            root_motion,
        } => {
            let speed = finite("speed", speed.unwrap_or(1.0))?;
            let start = finite("start", start.unwrap_or(0.0))?;
            let fade = finite("fade", fade.unwrap_or(DEFAULT_FADE))?.max(0.0);
            let source = match from_asset {
                Some(name) => Some(world.library.require(name)?),
                None => None,
            };
            with_avatar(world, avatar, |a| {
                let (clip, source_asset) = clip_for(world, a, clip, source.as_ref())?;
                let mut layer =
                    Layer::new(clip, source_asset, start, speed, looping.unwrap_or(true));
                if let Some(mode) = root_motion {
                    layer.root_motion = *mode;
                }
                a.play(layer, fade);
                Ok(CommandResult::Done)
            })
        }
        layer @ (Command::PlayLayer { .. } | Command::StopLayer { .. }) => {
            super::layers::apply(world, layer)
                .unwrap_or_else(|| Err(Error::invalid("not a layer command")))
        }
        Command::Pause { avatar } | Command::Resume { avatar } => {
            let paused = matches!(command, Command::Pause { .. });
            with_avatar(world, avatar, |a| {
                let layer = a
                    .player
                    .current_mut()
                    .ok_or_else(|| Error::invalid("no clip is playing"))?;
                layer.set_paused(paused);
                Ok(CommandResult::Done)
            })
        }
        Command::Seek { avatar, time } => {
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
        Command::SetSpeed { avatar, speed } => {
            let speed = finite("speed", *speed)?;
            with_avatar(world, avatar, |a| {
                let layer = a
                    .player
                    .current_mut()
                    .ok_or_else(|| Error::invalid("no clip is playing"))?;
                layer.set_speed(speed);
                Ok(CommandResult::Done)
            })
        }
        Command::Stop { avatar } => with_avatar(world, avatar, |a| {
            a.player.stop();
            a.evaluate();
            Ok(CommandResult::Done)
        }),
        Command::SetJointRotation {
            avatar,
            joint,
            rotation,
        } => with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.set_rotation(j, q)
                .map_err(|e| Error::invalid(e.to_string()))
        }),
        Command::SetJointDofs {
            avatar,
            joint,
            values,
        } => with_avatar(world, avatar, |a| {
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
                dofs.set(i, finite("DOF value", v)?)
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
        }),
        Command::RotateJointLocal {
            avatar,
            joint,
            rotation,
        } => with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.rotate_local(j, q)
                .map_err(|e| Error::invalid(format!("joint {joint}: {e}")))
        }),
        Command::RotateJointWorld {
            avatar,
            joint,
            rotation,
        } => with_joint_rotation(world, avatar, joint, *rotation, |a, j, q| {
            a.rotate_world(j, q)
                .map_err(|e| Error::invalid(format!("joint {joint}: {e}")))
        }),
        ik @ (Command::SetIkGoal { .. } | Command::ClearIkGoal { .. } | Command::LookAt { .. }) => {
            super::ik::apply(world, ik).unwrap_or_else(|| Err(Error::invalid("not an IK command")))
        }
        face @ (Command::SetMorphWeights { .. } | Command::SetExpression { .. }) => {
            super::morph::apply(world, face)
                .unwrap_or_else(|| Err(Error::invalid("not a face command")))
        }
        Command::Release { avatar, joint } => with_avatar(world, avatar, |a| {
            let j = joint
                .as_deref()
                .map(|name| joint_index(a, name))
                .transpose()?;
            a.release(j);
            Ok(CommandResult::Done)
        }),
        // --- placement (issue 16) ---
        Command::PlaceAvatar {
            avatar,
            position,
            rotation,
            duration,
        } => {
            let to = placement(*position, *rotation)?;
            let duration = duration.unwrap_or(0.0);
            if !(duration.is_finite() && duration >= 0.0) {
                return Err(Error::invalid("duration must be finite and ≥ 0"));
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

        // --- Live driving (issue 16); `drive` itself runs in the websocket session. ---
        Command::Drive { .. } => Err(Error::NotAllowedNow(
            "drive needs a websocket connection (poses stream over it)".into(),
        )),
        // --- Recording (issue 16) ---
        Command::Record {
            avatar,
            clip,
            max_seconds,
        } => {
            check_id("clip", clip).map_err(|e| Error::Invalid(e.message))?;
            let mut limits = RecordLimits::DEFAULT;
            if let Some(s) = max_seconds {
                if !(s.is_finite() && *s > 0.0) {
                    return Err(Error::invalid("max_seconds must be finite and > 0"));
                }
                limits.max_seconds = limits.max_seconds.min(f64::from(*s));
            }
            with_avatar(world, avatar, |a| {
                if let Some(r) = &a.recording {
                    return Err(Error::Conflict(format!(
                        "avatar {} is already recording {}",
                        a.id,
                        r.name()
                    )));
                }
                if a.rig.clip(clip).is_some() {
                    return Err(Error::Conflict(format!(
                        "rig {} already has a clip {clip}",
                        a.rig.name
                    )));
                }
                a.recording = Some(Recorder::new(clip.clone(), &a.description, limits));
                Ok(CommandResult::Done)
            })
        }
        Command::StopRecording { avatar } => {
            let (rig, recorder) = take_recording(world, avatar)?;
            let info = finish_recording(world, &rig, recorder)?;
            Ok(CommandResult::Recorded(Box::new(info)))
        }
        Command::DeleteClip { asset, clip } => {
            world.remove_clip(asset, clip, true)?;
            Ok(CommandResult::Done)
        }
        Command::DeleteAsset { .. } => Err(Error::NotAllowedNow(
            "delete_asset runs through the store (uploads are files)".into(),
        )),
        Command::RecordScene { .. }
        | Command::StopRecordingScene { .. }
        | Command::ListTakes
        | Command::GetTake { .. }
        | Command::DeleteTake { .. }
        | Command::Replay { .. } => Err(Error::NotAllowedNow(
            "takes run through the server's takes service (they are files)".into(),
        )),
        Command::ControlReplay {
            scene,
            time,
            paused,
            speed,
            looping,
        } => world
            .control_replay(scene, time.map(f64::from), *paused, *speed, *looping)
            .map(|r| CommandResult::Replay(Box::new(r))),

        Command::CalibrateTrackers { avatar, pose } => with_avatar(world, avatar, |a| {
            let placement = a.placing.current().to_mat4();
            let trackers = a
                .live
                .as_mut()
                .and_then(|l| l.trackers.as_mut())
                .ok_or_else(|| {
                    Error::NotAllowedNow(format!(
                        "avatar {avatar} is not driven by trackers: drive it with trackers \
                         (drive … trackers) and send their poses first"
                    ))
                })?;
            let measured = trackers
                .calibrate(pose.unwrap_or_default(), placement)
                .map_err(|e| match e {
                    TrackerError::NoSample(_) => Error::NotAllowedNow(format!(
                        "cannot calibrate avatar {avatar}'s trackers: {e}"
                    )),
                    _ => {
                        Error::invalid(format!("cannot calibrate avatar {avatar}'s trackers: {e}"))
                    }
                })?;
            a.evaluate();
            Ok(CommandResult::Calibration(Box::new(CalibrationInfo {
                avatar: avatar.clone(),
                user_height: measured.user_height,
                scale: measured.scale,
                arm_scale: measured.arm_scale,
                trackers: measured.trackers,
            })))
        }),
        Command::ReleaseDrive { avatar } => with_avatar(world, avatar, |a| {
            a.release_drive();
            Ok(CommandResult::Done)
        }),
    }
}

/// `stop_recording`'s first, quick half, under the scene's lock: the avatar stops recording
/// and its recorder is handed over. Returns the rig's name and the recorder.
///
/// # Errors
/// `unknown_avatar`, or `not_allowed_now` when it is not recording.
pub fn take_recording(world: &World, avatar: &AvatarId) -> Result<(String, Recorder), Error> {
    with_avatar(world, avatar, |a| {
        let recorder = a
            .recording
            .take()
            .ok_or_else(|| Error::NotAllowedNow(format!("avatar {} is not recording", a.id)))?;
        Ok((a.rig.name.clone(), recorder))
    })
}

/// `stop_recording`'s slow half, with no scene lock held: the samples become a clip (tens
/// of milliseconds for a 64 MiB take) that joins rig `rig`. Callers run it off the async
/// workers ([`crate::control`]), so no scene's tick waits for it.
///
/// # Errors
/// `invalid_value` when nothing was recorded; `conflict` when the rig got a clip of that
/// name meanwhile.
pub fn finish_recording(
    world: &World,
    rig: &str,
    recorder: Recorder,
) -> Result<RecordingInfo, Error> {
    let (frames, dropped) = (recorder.frames(), recorder.dropped());
    let clip = recorder
        .finish()
        .map_err(|e| Error::invalid(format!("nothing to keep: {e}")))?;
    let info = RecordingInfo {
        asset: rig.to_owned(),
        clip: clip.name().to_owned(),
        duration: clip.duration(),
        frames,
        dropped,
    };
    world.add_clip(rig, clip)?;
    Ok(info)
}

/// A validated placement, or `invalid_value` naming what is wrong.
fn placement(position: [f32; 3], rotation: [f32; 4]) -> Result<Placement, Error> {
    Placement::try_new(position, rotation).map_err(|e| Error::invalid(e.to_string()))
}

/// The clip `clip` for avatar `a`: its rig's own, or `source`'s retargeted onto it (normally
/// baked already: `execute_durable` bakes off the lock first; only start-up restore and
/// in-memory callers bake here), with the source's name when it is another rig.
pub(super) fn clip_for(
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
