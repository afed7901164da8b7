//! Takes of whole scenes (issue 32). Takes are files, so the services run `record_scene`,
//! `stop_recording_scene`, `list_takes`, `get_take`, `delete_take` and `replay`
//! ([`Runs::Files`]: `crate::control`'s takes; their handlers are [`InServices`]
//! declarations); `control_replay` steers a replay scene in the world
//! ([`crate::world::replays`]).

use super::{Announce, Handler, InServices, Needs, SceneChange, fields};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};

const TAKES: &str = "takes, which are files";

/// `record_scene`: the scene's frames written to a take as it streams.
pub static RECORD_SCENE: InServices = InServices {
    op: "record_scene",
    needs: Needs::Record,
    scene_change: SceneChange::None,
    files: TAKES,
};

/// `stop_recording_scene`: the take closed and kept.
pub static STOP_RECORDING_SCENE: InServices = InServices {
    op: "stop_recording_scene",
    needs: Needs::Record,
    scene_change: SceneChange::None,
    files: TAKES,
};

/// `list_takes` (a read: its right is never asked).
pub static LIST_TAKES: InServices = InServices {
    op: "list_takes",
    needs: Needs::Control,
    scene_change: SceneChange::None,
    files: TAKES,
};

/// `get_take` (a read).
pub static GET_TAKE: InServices = InServices {
    op: "get_take",
    needs: Needs::Control,
    scene_change: SceneChange::None,
    files: TAKES,
};

/// `delete_take`.
pub static DELETE_TAKE: InServices = InServices {
    op: "delete_take",
    needs: Needs::Delete,
    scene_change: SceneChange::None,
    files: TAKES,
};

/// `replay`: a take played back as a new scene.
pub static REPLAY: InServices = InServices {
    op: "replay",
    needs: Needs::Control,
    scene_change: SceneChange::Creates,
    files: TAKES,
};

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
