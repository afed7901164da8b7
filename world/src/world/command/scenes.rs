//! `list_scenes`, `create_scene`, `delete_scene`.

use super::{Announce, Handler, SceneChange, fields};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};

/// `list_scenes` (a cluster lists every server's: `crate::control`).
#[derive(Debug)]
pub struct ListScenes;

impl Handler for ListScenes {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, _command: &Command) -> Result<CommandResult, Error> {
        Ok(CommandResult::Scenes(
            world.scenes().iter().map(|s| s.info()).collect(),
        ))
    }
}

/// `create_scene`.
#[derive(Debug)]
pub struct CreateScene;

impl Handler for CreateScene {
    /// The scene's news ([`Handler::scene_change`]), no avatar's.
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn scene_change(&self) -> SceneChange {
        SceneChange::Creates
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, CreateScene { scene });
        world.create_scene(scene.clone())?;
        Ok(CommandResult::SceneCreated {
            scene: scene.clone(),
        })
    }
}

/// `delete_scene`.
#[derive(Debug)]
pub struct DeleteScene;

impl Handler for DeleteScene {
    /// The scene's news ([`Handler::scene_change`]), no avatar's.
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn scene_change(&self) -> SceneChange {
        SceneChange::Deletes
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, DeleteScene { scene });
        world.delete_scene(scene)?;
        Ok(CommandResult::Done)
    }
}
