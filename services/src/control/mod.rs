//! Executes control commands for clients (REST and websocket): the `World`'s
//! [`command::apply`] with the slow part done first off the lock, counted in the metrics,
//! announced to the connections that follow the world ([`changes`]), and — with a data
//! folder — acknowledged only once stored.

mod objects;
pub mod takes;

use crate::auth::{Caller, CommandFacts, Grant};
use crate::changes;
use crate::scene::{Scene, answers};
use crate::state::{RunError, Services};
use crate::world::command::{self, Runs};
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, RecordingInfo};

/// Executes a command in memory and tells the connections that follow what it changed
/// ([`changes`]). Authorisation is checked by the caller. Servers with a data folder answer
/// clients through [`execute_durable`] instead.
///
/// # Errors
/// A typed error; nothing is changed (and nothing announced) when a command fails.
pub fn execute(state: &Services, command: &Command) -> Result<CommandResult, Error> {
    let before = changes::before(state, command);
    let result = command::apply(&state.world, command);
    state.metrics.command(result.is_ok());
    if let Ok(r) = &result {
        changes::after(state, command, before, r);
    }
    result
}

/// May `caller` run `command`? The access rules ([`crate::auth`]) are handed the facts —
/// the right its handler needs, the scene it names or its avatar is in, the avatar — and a
/// command a limited token may run passes its handler's rule for limited tokens
/// ([`command::Handler::limited`]).
///
/// # Errors
/// `unauthorized`, `forbidden`, or the handler's refusal (`quota_exceeded`).
pub fn authorize(state: &Services, caller: &Caller, command: &Command) -> Result<(), Error> {
    let handler = command::handler(command);
    let avatar_scene = match command.scene() {
        Some(_) => None,
        None => command
            .avatar()
            .and_then(|a| state.world.find_avatar(a).ok()),
    };
    let facts = CommandFacts {
        read_only: command.is_read_only(),
        needs: handler.needs(),
        scene: command.scene().or(avatar_scene.as_ref().map(|s| &s.id)),
        avatar: command.avatar(),
    };
    match state.config.access.authorize(caller, &facts)? {
        Grant::Full => Ok(()),
        Grant::Limited => handler.limited(&state.world, command),
    }
}

/// Runs a command whose work is files ([`Runs::Files`], [`Runs::FilesThenScene`]): uploads,
/// recordings and takes, each file stored before its answer.
async fn run_files(
    state: &Services,
    caller: &Caller,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    match command {
        Command::DeleteClip { asset, clip } => objects::delete_clip(state, caller, asset, clip)
            .await
            .map(|()| CommandResult::Done),
        Command::DeleteAsset { asset } => objects::delete_asset(state, caller, asset)
            .await
            .map(|()| CommandResult::Done),
        Command::StopRecording { avatar } => objects::stop_recording(state, caller, avatar).await,
        // Stored (meta.json) before the answer, like an upload.
        Command::ConfigureAsset { asset, options } => {
            crate::ingest::configure(state, asset, options.clone())
                .await
                .map(CommandResult::Assets)
        }
        _ => takes::run(state, caller, command, key).await,
    }
}

/// [`execute`], then — for a command that changed something — waits until the scene it
/// changed is stored (see [`crate::store`]), so the answer is an acknowledgement that survives
/// a crash. Read-only and failed commands write nothing.
///
/// # Errors
/// As [`execute`]; or `internal` when storing failed, in which case the change
/// *is* in effect in memory but not on disk (on a server of a cluster it is undone:
/// [`crate::state::Cluster::commit`]).
pub async fn execute_durable(state: &Services, command: &Command) -> Result<CommandResult, Error> {
    execute_as(state, &Caller::Anonymous, command, None).await
}

/// [`execute_durable`] for `caller` (authorised already): what it makes (a recording) is
/// owned by its token and counted against its quota ([`crate::auth::TokenQuota`]), and what
/// it may delete depends on who made it. `key` is the client's idempotency key (REST
/// `Idempotency-Key`, a websocket command's `idempotency_key`): on a server of a cluster a
/// command whose key the scene's latest commands carried is answered with that command's
/// result and not applied again, on whichever server the retry arrives.
///
/// # Errors
/// As [`execute_durable`].
pub async fn execute_as(
    state: &Services,
    caller: &Caller,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    // In a cluster, a command on a scene another server ticks runs there; its answer comes
    // back through here.
    if let Some(forwarded) = state.cluster().and_then(|c| c.forward(command, key)) {
        return forwarded.await;
    }
    execute_here_as(state, caller, command, key).await
}

/// [`execute_durable`] on this server, never forwarded: what a scene's owner runs for a
/// command another server of the cluster forwarded to it. In a cluster a change is also
/// stored where every server reads it ([`crate::state::Cluster::commit`]) before the answer,
/// and `create_scene` claims the id cluster-wide first; `list_scenes` lists the cluster's.
///
/// # Errors
/// As [`execute_durable`]; `unavailable` for a scene that another server ticks.
pub async fn execute_here(
    state: &Services,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    // Forwarded by another server: the caller is not known here, so what it makes has no
    // owner (it counts against the server's quota only).
    execute_here_as(state, &Caller::Anonymous, command, key).await
}

async fn execute_here_as(
    state: &Services,
    caller: &Caller,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    // A server on its own answers a keyed command's retry from the scene's answers
    // (`scene::answers`); a cluster's owner does so in `cluster::commit`. The scene's keyed
    // lock is held until the answer is remembered and stored.
    let keyed = match key {
        Some(k) if state.cluster().is_none() && !command.is_read_only() => {
            target_scene(&state.world, command).map(|scene| (k, scene))
        }
        _ => None,
    };
    let Some((key, scene)) = keyed else {
        return execute_unkeyed(state, caller, command, key).await;
    };
    let _order = scene.keyed.lock().await;
    let op = answers::op_of(command);
    if let Some(again) = answers::answered(&scene.answers(), key, &op) {
        return again;
    }
    let result = execute_unkeyed(state, caller, command, Some(key)).await;
    let known = scene.answers().iter().any(|a| a.key == key);
    if let Ok(r) = &result
        && !known
    {
        // Not stored with the scene (no data folder, or a command that does not store it):
        // remembered for retries while the server runs.
        answers::remember(&mut scene.answers(), key, op, r);
    }
    result
}

/// The scene a command acts on, when it exists (looked up before executing: after
/// `remove_avatar` the avatar is gone).
fn target_scene(world: &crate::world::World, command: &Command) -> Option<std::sync::Arc<Scene>> {
    match command.scene() {
        Some(id) => world.scene(id).ok(),
        None => world.find_avatar(command.avatar()?).ok(),
    }
}

async fn execute_unkeyed(
    state: &Services,
    caller: &Caller,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    let handler = command::handler(command);
    if handler.runs() == Runs::Files {
        let result = run_files(state, caller, command, key).await;
        state.metrics.command(result.is_ok());
        if let Ok(r) = &result {
            // These name no avatar: noting what comes before costs nothing.
            changes::after(state, command, changes::before(state, command), r);
        }
        return result;
    }
    if let Err(e) = prepare(&state.world, handler, command).await {
        state.metrics.command(false);
        return Err(e);
    }
    let cluster = state.cluster();
    if let Some(cluster) = cluster
        && matches!(command, Command::ListScenes)
    {
        return match execute(state, command)? {
            CommandResult::Scenes(local) => Ok(CommandResult::Scenes(cluster.listing(local).await)),
            other => Ok(other),
        };
    }
    // Applies the command here: a world command under the scene's lock; `stop_recording`'s
    // file off the tick path, stored before its clip joins the rig ([`Runs::FilesThenScene`]).
    let apply = || async move {
        if handler.runs() == Runs::FilesThenScene {
            let result = run_files(state, caller, command, key).await;
            state.metrics.command(result.is_ok());
            result
        } else {
            execute(state, command)
        }
    };
    if command.is_read_only() || (state.store.root().is_none() && cluster.is_none()) {
        return apply().await;
    }
    // The scene is looked up before executing: after `remove_avatar` the avatar is gone.
    let scene = match command.scene() {
        Some(s) => Some(s.clone()),
        None => command
            .avatar()
            .and_then(|a| state.world.find_avatar(a).ok())
            .map(|s| s.id.clone()),
    };
    if cluster.is_some()
        && let Some(id) = &scene
        && state.world.scene(id).is_ok_and(|s| s.is_relay())
    {
        // Forwarded here while the scene's ownership moved away: the sender may retry.
        return Err(Error::Unavailable(format!(
            "scene {id} is ticked by another server now: try again"
        )));
    }
    let result = match (cluster, &scene) {
        (Some(cluster), Some(id)) => {
            let run = Box::pin(async move {
                let result = apply().await.map_err(RunError::Refused)?;
                state
                    .store
                    .persist_scene(&state.world, id)
                    .await
                    .map_err(RunError::NotStored)?;
                Ok(result)
            });
            cluster.commit(command, id, key, run).await?
        }
        (_, scene) => {
            let result = apply().await?;
            if let Some(scene) = scene {
                // A keyed command's answer goes into the stored snapshot with its change, so
                // a retry after a restart is answered too.
                let remembered = key.zip(state.world.scene(scene).ok()).inspect(|(k, s)| {
                    answers::remember(&mut s.answers(), k, answers::op_of(command), &result);
                });
                if let Err(e) = state.store.persist_scene(&state.world, scene).await {
                    if let Some((k, s)) = remembered {
                        answers::forget(&mut s.answers(), k);
                    }
                    return Err(e);
                }
            }
            result
        }
    };
    if let CommandResult::Recorded(info) = &result
        && let Some(cluster) = cluster
    {
        share_recording(&state.world, cluster.as_ref(), info).await?;
    }
    Ok(result)
}

/// Puts a clip `stop_recording` just added where every server of the cluster reads it.
///
/// # Errors
/// `internal` or `unavailable`: the clip is then playable here only.
async fn share_recording(
    world: &crate::world::World,
    cluster: &dyn crate::state::Cluster,
    info: &RecordingInfo,
) -> Result<(), Error> {
    let rig = world.library.require(&info.asset)?;
    let clip = rig
        .clip(&info.clip)
        .cloned()
        .ok_or_else(|| Error::UnknownClip {
            rig: info.asset.clone(),
            clip: info.clip.clone(),
        })?;
    let glb = tokio::task::spawn_blocking(move || posecast_rigs::export::clip_glb(&rig, &clip))
        .await
        .map_err(|e| Error::internal("export task failed", &e))?
        .map_err(|e| Error::internal("cannot write the recording as glTF", &e))?;
    cluster.share_recording(&info.asset, &info.clip, glb).await
}

/// Writes the audit line of a client's command: at `info` for one that changes something
/// (refusals included), at `debug` for a read — op, target, the caller's token name (never the
/// token), and the outcome.
pub fn audit(caller: &str, command: &Command, result: &Result<CommandResult, Error>) {
    let op = serde_json::to_value(command)
        .ok()
        .and_then(|v| v.get("op").and_then(|o| o.as_str()).map(str::to_owned))
        .unwrap_or_default();
    let target = match (command.scene(), command.avatar()) {
        (_, Some(a)) => format!("avatar {a}"),
        (Some(s), None) => format!("scene {s}"),
        (None, None) => String::new(),
    };
    let outcome = match result {
        Ok(_) => "ok".to_owned(),
        Err(e) => format!("{:?}: {e}", e.code()),
    };
    if command.is_read_only() {
        tracing::debug!(target: "posecast::audit", op, target, caller, outcome, "command");
    } else {
        tracing::info!(target: "posecast::audit", op, target, caller, outcome, "command");
    }
}

/// The slow part of a command, done before it takes any scene lock and off the async
/// workers: `play … from_asset` bakes the retargeted clip ([`posecast_sim::bake`],
/// [`command::Handler::bake`]), so applying the command is a cache lookup and no other
/// scene's tick waits for the bake.
async fn prepare(
    world: &crate::world::World,
    handler: &dyn command::Handler,
    command: &Command,
) -> Result<(), Error> {
    let Some(command::Bake {
        avatar,
        clip,
        source,
    }) = handler.bake(command)
    else {
        return Ok(());
    };
    let source = world.library.require(source)?;
    let target = {
        let scene = world.find_avatar(avatar)?;
        let s = scene.lock();
        s.avatars
            .iter()
            .find(|a| &a.id == avatar)
            .map(|a| a.rig.clone())
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?
    };
    if source.name != target.name {
        world.retargets.bake(source, clip, target).await?;
    }
    Ok(())
}
