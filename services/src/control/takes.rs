//! The take commands (issue 32): `record_scene`, `stop_recording_scene`, `list_takes`,
//! `get_take`, `delete_take`, `replay` ([`crate::takes`] keeps the takes; `control_replay`
//! is the world's, [`crate::world::replays`]). Whatever touches files runs on the blocking
//! pool; the scene's feed only gains or loses its sink under its lock.

use crate::auth::Caller;
use crate::state::{RunError, Services};
use crate::takes::{TakeLimits, Takes};
use crate::world::replays::ReplayStart;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, TakeInfo};
use posecast_proto::msg::SceneId;

/// The room `record_scene` needs left in the data quota (about 8 s of 10 avatars at 60 Hz):
/// less would make a take that ends before it starts.
pub const MIN_ROOM: u64 = 64 << 10;

/// The longest take, seconds of scene time (`record_scene`'s `max_seconds` at most).
pub const MAX_TAKE_SECONDS: f32 = 4.0 * 3600.0;

/// Runs a take command (`internal` for any other command). `key`: the command's idempotency
/// key (a replay in a cluster is answered again from it, as `create_scene` is).
pub(super) async fn run(
    state: &Services,
    caller: &Caller,
    command: &Command,
    key: Option<&str>,
) -> Result<CommandResult, Error> {
    match command {
        Command::RecordScene {
            scene,
            take,
            max_seconds,
        } => record_scene(state, caller, scene, take, *max_seconds).await,
        Command::StopRecordingScene { scene } => stop_recording_scene(state, scene).await,
        Command::ListTakes => list_takes(state).await.map(|takes| {
            // A token limited to some scenes sees the takes of those.
            let access = &state.config.access;
            CommandResult::Takes(
                takes
                    .into_iter()
                    .filter(|t| access.authorize_view(caller, &t.scene).is_ok())
                    .collect(),
            )
        }),
        Command::GetTake { take } => describe(state, caller, take)
            .await
            .map(|t| CommandResult::Take(Box::new(t))),
        Command::DeleteTake { take } => delete_take(state, take).await,
        Command::Replay {
            take,
            scene,
            speed,
            looping,
            from,
        } => {
            let start = ReplayStart {
                from: f64::from(from.unwrap_or(0.0)),
                speed: speed.unwrap_or(1.0),
                looping: looping.unwrap_or(false),
            };
            match describe(state, caller, take).await {
                Ok(_) => match state.cluster() {
                    // Claimed cluster-wide like a new scene, and stored with its replay: every
                    // server serves it, and one taking it over resumes it.
                    Some(cluster) => {
                        let run = Box::pin(async move {
                            replay(state, take, scene, start)
                                .await
                                .map_err(RunError::Refused)
                        });
                        cluster.commit(command, scene, key, run).await
                    }
                    None => replay(state, take, scene, start).await,
                },
                Err(e) => Err(e),
            }
        }
        other => Err(Error::Internal(format!("{other:?} is not a take command"))),
    }
}

/// The takes: on a server of a cluster the cluster's, with those being recorded (or not yet
/// shared) here.
async fn list_takes(state: &Services) -> Result<Vec<TakeInfo>, Error> {
    let Some(cluster) = state.cluster() else {
        return blocking(state, |s| Ok(s.list())).await;
    };
    let mut takes = cluster.shared_takes().await?;
    let here = blocking(state, |s| {
        Ok(s.names()
            .into_iter()
            .filter(|n| s.shared_as(n).is_none())
            .filter_map(|n| s.describe(&n).ok())
            .collect::<Vec<_>>())
    })
    .await?;
    for t in here {
        if !takes.iter().any(|c| c.take == t.take) {
            takes.push(t);
        }
    }
    takes.sort_by_key(|t| (t.started_us, t.take.clone()));
    Ok(takes)
}

/// Runs `f` with the takes on the blocking pool (it reads or writes files).
async fn blocking<T: Send + 'static>(
    state: &Services,
    f: impl FnOnce(&Takes) -> Result<T, Error> + Send + 'static,
) -> Result<T, Error> {
    let takes = state.takes.clone();
    tokio::task::spawn_blocking(move || f(&takes))
        .await
        .map_err(|e| Error::internal("take task failed", &e))?
}

/// Take `take` described, if `caller` may watch the scene it recorded (a take shows that
/// scene).
///
/// # Errors
/// `unknown_take`; `forbidden`/`unauthorized` as for watching its scene.
pub async fn describe(
    state: &Services,
    caller: &Caller,
    take: &str,
) -> Result<posecast_proto::command::TakeInfo, Error> {
    if let Some(cluster) = state.cluster() {
        // The cluster's take, read here first (once per version).
        cluster.fetch_take(take).await?;
    }
    let name = take.to_owned();
    let info = blocking(state, move |s| s.describe(&name)).await?;
    state.config.access.authorize_view(caller, &info.scene)?;
    Ok(info)
}

async fn record_scene(
    state: &Services,
    caller: &Caller,
    scene: &SceneId,
    take: &str,
    max_seconds: Option<f32>,
) -> Result<CommandResult, Error> {
    let s = state.world.scene(scene)?;
    if s.is_relay() {
        return Err(Error::Unavailable(format!(
            "scene {scene} is ticked by another server now: try again"
        )));
    }
    let seconds = match max_seconds {
        None => MAX_TAKE_SECONDS,
        Some(m) if m.is_finite() && m > 0.0 => m.min(MAX_TAKE_SECONDS),
        Some(m) => {
            return Err(Error::invalid(format!(
                "max_seconds {m} is not a positive number of seconds"
            )));
        }
    };
    if let Some(cluster) = state.cluster()
        && cluster.has_take(take).await?
    {
        return Err(Error::Conflict(format!("take {take} exists")));
    }
    let rate = state.config.tick_rate;
    // Room for a useful take at least; what it may grow to is the quota's rest.
    crate::ingest::check_room(state, caller, &format!("take {take}"), MIN_ROOM)?;
    let max = state.config.quotas.max_upload_total_bytes;
    let used = state.store.upload_bytes() + state.takes.held_bytes();
    let limits = TakeLimits {
        max_frames: (f64::from(seconds) * f64::from(rate)).ceil() as u64,
        max_bytes: max.saturating_sub(used),
    };
    let (scene_id, take_name) = (scene.clone(), take.to_owned());
    let sink = blocking(state, move |s| s.begin(&scene_id, &take_name, rate, limits)).await?;
    s.feed().record(Some(Box::new(sink)));
    let take = take.to_owned();
    blocking(state, move |s| s.describe(&take))
        .await
        .map(|t| CommandResult::Take(Box::new(t)))
}

async fn stop_recording_scene(state: &Services, scene: &SceneId) -> Result<CommandResult, Error> {
    let s = state.world.scene(scene)?;
    if state.takes.recording_of(scene).is_none() {
        return Err(Error::NotAllowedNow(format!(
            "scene {scene} is not being recorded"
        )));
    }
    // The sink leaves the feed: the writer gets what was queued, syncs and ends.
    drop(s.feed().record(None));
    let scene = scene.clone();
    let info = blocking(state, move |s| {
        let (take, why) = s.finish(&scene)?;
        if let Some(why) = why {
            tracing::info!(%take, why, "the take had ended by itself");
        }
        s.describe(&take)
    })
    .await?;
    if let Some(cluster) = state.cluster()
        && let Err(e) = cluster.share_take(&info.take).await
    {
        // Kept here meanwhile (listed by this server) and shared at the lease loop's next
        // look that NATS answers.
        tracing::warn!(take = %info.take, error = %e, "the take is not shared with the cluster yet");
    }
    Ok(CommandResult::Take(Box::new(info)))
}

async fn delete_take(state: &Services, take: &str) -> Result<CommandResult, Error> {
    if state.world.replayed_takes().iter().any(|t| t == take) {
        return Err(Error::Conflict(format!(
            "take {take} is being replayed: delete its replay scenes first"
        )));
    }
    // In a cluster the cluster's copy goes first; the one here (if any) after it, and other
    // servers' copies at their next look.
    let shared = match state.cluster() {
        Some(cluster) => cluster.delete_take(take).await?,
        None => false,
    };
    let take = take.to_owned();
    match blocking(state, move |s| s.delete(&take)).await {
        Ok(_) => Ok(CommandResult::Done),
        Err(Error::UnknownTake { .. }) if shared => Ok(CommandResult::Done),
        Err(e) => Err(e),
    }
}

async fn replay(
    state: &Services,
    take: &str,
    scene: &SceneId,
    start: ReplayStart,
) -> Result<CommandResult, Error> {
    let take_name = take.to_owned();
    let (index, source) = blocking(state, move |s| {
        let index = s.index(&take_name)?;
        let source = s.source(&take_name)?;
        Ok((index, source))
    })
    .await?;
    if index.frames.is_empty() {
        return Err(Error::NotAllowedNow(format!(
            "take {take} has no frames to replay"
        )));
    }
    let (_, replay) = state
        .world
        .start_replay(scene, take, index, source, start)?;
    Ok(CommandResult::Replay(Box::new(replay)))
}
