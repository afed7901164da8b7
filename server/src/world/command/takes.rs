//! Takes of whole scenes (issue 32). Takes are files, so the services run `record_scene`,
//! `stop_recording_scene`, `list_takes`, `get_take`, `delete_take` and `replay`
//! ([`Runs::Files`]: `crate::control`'s takes); `control_replay` steers a replay scene in the
//! world ([`crate::world::replays`]).

use super::{Announce, Handler, Needs, Runs, SceneChange, fields};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};

/// What a take command's `apply` answers: the services run it.
fn files() -> Result<CommandResult, Error> {
    Err(Error::NotAllowedNow(
        "takes run through the server's takes service (they are files)".into(),
    ))
}

/// `record_scene`: the scene's frames written to a take as it streams.
#[derive(Debug)]
pub struct RecordScene;

impl Handler for RecordScene {
    fn needs(&self) -> Needs {
        Needs::Record
    }

    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `stop_recording_scene`: the take closed and kept.
#[derive(Debug)]
pub struct StopRecordingScene;

impl Handler for StopRecordingScene {
    fn needs(&self) -> Needs {
        Needs::Record
    }

    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `list_takes`.
#[derive(Debug)]
pub struct ListTakes;

impl Handler for ListTakes {
    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `get_take`.
#[derive(Debug)]
pub struct GetTake;

impl Handler for GetTake {
    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `delete_take`.
#[derive(Debug)]
pub struct DeleteTake;

impl Handler for DeleteTake {
    fn needs(&self) -> Needs {
        Needs::Delete
    }

    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `replay`: a take played back as a new scene.
#[derive(Debug)]
pub struct Replay;

impl Handler for Replay {
    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn scene_change(&self) -> SceneChange {
        SceneChange::Creates
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, _world: &World, _command: &Command) -> Result<CommandResult, Error> {
        files()
    }
}

/// `control_replay`: a replay scene's time, pause, speed and looping.
#[derive(Debug)]
pub struct ControlReplay;

impl Handler for ControlReplay {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            ControlReplay {
                scene,
                time,
                paused,
                speed,
                looping,
            }
        );
        world
            .control_replay(scene, time.map(f64::from), *paused, *speed, *looping)
            .map(|r| CommandResult::Replay(Box::new(r)))
    }
}
