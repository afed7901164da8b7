//! Executes control commands for clients (REST and websocket): the `World`'s
//! [`command::apply`] with the slow part done first off the lock, counted in the metrics, and —
//! with a data folder — acknowledged only once stored.

use crate::error::Error;
use crate::state::AppState;
use crate::world::command;
use posecast_proto::command::{Command, CommandResult};

/// Executes a command in memory. Authorisation is checked by the caller. Servers with a data
/// folder answer clients through [`execute_durable`] instead.
///
/// # Errors
/// A typed error; nothing is changed when a command fails.
pub fn execute(state: &AppState, command: &Command) -> Result<CommandResult, Error> {
    let result = command::apply(&state.world, command);
    state.metrics.command(result.is_ok());
    result
}

/// [`execute`], then — for a command that changed something — waits until the scene it
/// changed is stored (see [`crate::store`]), so the answer is an acknowledgement that survives
/// a crash. Read-only and failed commands write nothing.
///
/// # Errors
/// As [`execute`]; or `internal` when storing failed, in which case the change
/// *is* in effect in memory but not on disk.
pub async fn execute_durable(state: &AppState, command: &Command) -> Result<CommandResult, Error> {
    if let Err(e) = prepare(state, command).await {
        state.metrics.command(false);
        return Err(e);
    }
    if command.is_read_only() || state.store.root().is_none() {
        return execute(state, command);
    }
    // The scene is looked up before executing: after `remove_avatar` the avatar is gone.
    let scene = match command.scene() {
        Some(s) => Some(s.clone()),
        None => command
            .avatar()
            .and_then(|a| state.world.find_avatar(a).ok())
            .map(|s| s.id.clone()),
    };
    let result = execute(state, command)?;
    if let Some(scene) = scene {
        state.store.persist_scene(&state.world, &scene).await?;
    }
    Ok(result)
}

/// The slow part of a command, done before it takes any scene lock and off the async
/// workers: `play … from_asset` bakes the retargeted clip ([`crate::bake`]), so applying the
/// command is a cache lookup and no other scene's tick waits for the bake.
async fn prepare(state: &AppState, command: &Command) -> Result<(), Error> {
    let Command::Play {
        avatar,
        clip,
        from_asset: Some(source),
        ..
    } = command
    else {
        return Ok(());
    };
    let source = state.world.library.require(source)?;
    let target = {
        let scene = state.world.find_avatar(avatar)?;
        let s = scene.lock();
        s.avatars
            .iter()
            .find(|a| &a.id == avatar)
            .map(|a| a.rig.clone())
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?
    };
    if source.name != target.name {
        state.world.retargets.bake(source, clip, target).await?;
    }
    Ok(())
}
