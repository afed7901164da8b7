//! Recording an avatar (issue 16): `record`, `stop_recording`. A server stops a recording off
//! the scene's tick path and stores the clip before it joins the rig ([`Runs::FilesThenScene`]:
//! `crate::control`'s objects, with [`take_recording`]); [`StopRecording`]'s `apply` does both
//! halves in place, for in-memory callers.

use super::{Handler, Needs, Runs, fields, with_avatar};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, RecordingInfo};
use posecast_proto::msg::{AvatarId, check_id};
use posecast_sim::avatar::recording::{RecordLimits, Recorder};

/// `record`: the avatar's poses sampled every tick until `stop_recording` (or the limit).
#[derive(Debug)]
pub struct Record;

impl Handler for Record {
    fn needs(&self) -> Needs {
        Needs::Record
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            Record {
                avatar,
                clip,
                max_seconds,
            }
        );
        check_id("clip", clip).map_err(|e| Error::invalid_field("clip", e.message))?;
        let mut limits = RecordLimits::DEFAULT;
        if let Some(s) = max_seconds {
            if !(s.is_finite() && *s > 0.0) {
                return Err(Error::invalid_field(
                    "max_seconds",
                    "max_seconds must be finite and > 0",
                ));
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
}

/// `stop_recording`: the samples become a clip of the avatar's rig.
#[derive(Debug)]
pub struct StopRecording;

impl Handler for StopRecording {
    fn needs(&self) -> Needs {
        Needs::Record
    }

    fn runs(&self) -> Runs {
        Runs::FilesThenScene
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, StopRecording { avatar });
        let (rig, recorder) = take_recording(world, avatar)?;
        let info = finish_recording(world, &rig, recorder)?;
        Ok(CommandResult::Recorded(Box::new(info)))
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
/// workers (`posecast_services::control`), so no scene's tick waits for it.
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
