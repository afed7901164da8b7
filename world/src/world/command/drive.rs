//! Live driving (issue 16) and trackers (issue 33): `drive` (run by the websocket session
//! that sends it, [`Runs::Connection`]), `calibrate_trackers`, `release_drive`.

use super::{Handler, Needs, Runs, fields, with_avatar};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::trackers::CalibrationInfo;
use posecast_sim::avatar::trackers::TrackerError;

/// `drive`: the connection that sends it becomes the avatar's live driver.
#[derive(Debug)]
pub struct Drive;

impl Handler for Drive {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn runs(&self) -> Runs {
        Runs::Connection
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        Err(Error::NotAllowedNow(
            "drive needs a websocket connection (poses stream over it)".into(),
        ))
    }
}

/// `calibrate_trackers`: the user's size and the trackers' offsets measured from their
/// latest poses in a known pose.
#[derive(Debug)]
pub struct CalibrateTrackers;

impl Handler for CalibrateTrackers {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, CalibrateTrackers { avatar, pose });
        with_avatar(world, avatar, |a| {
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
        })
    }
}

/// `release_drive`: the live driver let go (the avatar does what its `on_release` says).
#[derive(Debug)]
pub struct ReleaseDrive;

impl Handler for ReleaseDrive {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, ReleaseDrive { avatar });
        with_avatar(world, avatar, |a| {
            a.release_drive();
            Ok(CommandResult::Done)
        })
    }
}
