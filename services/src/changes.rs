//! Scene and avatar changes pushed to clients, so a dashboard never polls `list_scenes`.
//!
//! After a command changed the world ([`crate::control::execute`], and `drive` for a
//! websocket connection; also when a live driver leaves), [`after`] tells, once each:
//! - the scene's subscribers covering the avatar (through its [`posecast_stream::feed::Feed`]):
//!   `avatar_changed` — `avatar_removed` they already get from the feed;
//! - the connections watching the scene list ([`crate::state::Watchers`], `watch_scenes`) that may watch the
//!   scene: `scene_created`, `scene_deleted`, `avatar_changed`, `avatar_removed`.
//!
//! Why here and not per tick: clip time moves every tick, but it follows from the state at one
//! tick (`avatar_changed.seq`), the speed and the clip, so a client computes it for each frame
//! itself; the server sends one message per change a command makes, never per tick. Joint
//! overrides (a slider dragged sends dozens of commands a second) are announced only when the
//! set of overridden joints changes. Each message is bounded like every control message (a
//! connection that does not read is closed, [`posecast_stream::outbox::MAX_CONTROL_BYTES`]).
//!
//! What a command announces is its handler's declaration ([`command::Handler::announce`],
//! [`command::Handler::scene_change`]).
//!
//! Pushes to one scene's watchers and subscribers happen under the scene's lock, so two
//! changes of one avatar reach every connection in the order they were made.

use crate::scene::Scene;
use crate::state::Services;
use crate::world::command::{self, Announce, SceneChange};
use posecast_proto::command::{AvatarState, Command, CommandResult};
use posecast_proto::msg::{AvatarId, ServerMsg};
use posecast_stream::feed::text;
use std::sync::Arc;

/// What a command may change, noted before it runs.
#[derive(Debug)]
pub struct Before {
    /// The avatar's scene and the parts of its state that commands change often, for a
    /// command about an existing avatar.
    avatar: Option<(Arc<Scene>, Often)>,
}

/// The parts of an avatar's state that commands sent many times a second change (a joint
/// dragged, a goal followed): such a command is announced only when one of them changes.
#[derive(Debug, PartialEq)]
struct Often {
    /// The overridden joints.
    overrides: Vec<String>,
    /// The effectors with IK goals, and whether a gaze is set.
    goals: (Vec<String>, bool),
    /// The morph channels above 0 (a face's weights change every frame; which channels are
    /// in use, rarely).
    morphs: Vec<String>,
}

impl Often {
    fn of(state: AvatarState) -> Self {
        Self {
            overrides: state.overrides,
            goals: (state.ik_goals, state.looking),
            morphs: state.morph_weights.into_keys().collect(),
        }
    }
}

/// Notes what [`after`] compares with. Read-only commands note nothing.
#[must_use]
pub fn before(state: &Services, command: &Command) -> Before {
    let notes = matches!(
        command::handler(command).announce(),
        Announce::Removed
            | Announce::State
            | Announce::Overrides
            | Announce::Goals
            | Announce::Faces
    );
    let avatar = match command.avatar() {
        Some(id) if notes && !command.is_read_only() => {
            state.world.find_avatar(id).ok().and_then(|scene| {
                let often = scene
                    .lock()
                    .avatars
                    .iter()
                    .find(|a| &a.id == id)
                    .map(|a| Often::of(a.state(&scene.id)))?;
                Some((scene, often))
            })
        }
        _ => None,
    };
    Before { avatar }
}

/// Tells subscribers and watchers what `command` (which succeeded with `result`) changed.
pub fn after(state: &Services, command: &Command, before: Before, result: &CommandResult) {
    let access = &state.config.access;
    let handler = command::handler(command);
    match (handler.scene_change(), command.scene()) {
        (SceneChange::Creates, Some(scene)) => {
            let msg = text(&ServerMsg::SceneCreated {
                scene: scene.clone(),
            });
            state.watchers.push(access, scene, &msg, &[]);
            // A replay starts with the avatars of the take's first frame on stage.
            if let Ok(scene) = state.world.scene(scene) {
                let ids: Vec<AvatarId> =
                    scene.lock().avatars.iter().map(|a| a.id.clone()).collect();
                for id in ids {
                    announce(state, &scene, &id, |_| true);
                }
            }
            return;
        }
        (SceneChange::Deletes, Some(scene)) => {
            let msg = text(&ServerMsg::SceneDeleted {
                scene: scene.clone(),
            });
            state.watchers.push(access, scene, &msg, &[]);
            return;
        }
        _ => {}
    }
    match (handler.announce(), result) {
        (Announce::Nothing, _) => {}
        (Announce::Added, CommandResult::AvatarAdded { avatar }) => {
            if let Some(scene) = command.scene().and_then(|s| state.world.scene(s).ok()) {
                announce(state, &scene, avatar, |_| true);
            }
        }
        (Announce::Added, _) => {}
        (Announce::Removed, _) => {
            let (Some(avatar), Some((scene, _))) = (command.avatar(), before.avatar) else {
                return;
            };
            // The feed told the subscribers covering it; the watchers among them are told.
            let told = scene.feed().covering(avatar);
            let msg = text(&ServerMsg::AvatarRemoved {
                scene: scene.id.clone(),
                avatar: avatar.clone(),
            });
            state.watchers.push(access, &scene.id, &msg, &told);
        }
        (which, _) => {
            let (Some(id), Some((scene, often))) = (command.avatar(), before.avatar) else {
                return;
            };
            match which {
                Announce::Overrides => {
                    announce(state, &scene, id, |now| now.overrides != often.overrides);
                }
                Announce::Goals => announce(state, &scene, id, |now| {
                    (&now.ik_goals, now.looking) != (&often.goals.0, often.goals.1)
                }),
                Announce::Faces => announce(state, &scene, id, |now| {
                    !now.morph_weights.keys().eq(often.morphs.iter())
                }),
                _ => announce(state, &scene, id, |_| true),
            }
        }
    }
}

/// Tells subscribers and watchers the state of avatar `id` of `scene` now: for changes not made
/// by a command (a live driver that left).
pub fn avatar_changed(state: &Services, scene: &Scene, id: &AvatarId) {
    announce(state, scene, id, |_| true);
}

/// Sends `avatar_changed` with the avatar's state now, if `changed` says so, to the scene's
/// subscribers covering it and to its watchers — under the scene's lock (see the module docs).
fn announce(
    state: &Services,
    scene: &Scene,
    id: &AvatarId,
    changed: impl FnOnce(&AvatarState) -> bool,
) {
    let s = scene.lock();
    let Some(avatar) = s.avatars.iter().find(|a| &a.id == id) else {
        return;
    };
    let now = avatar.state(&scene.id);
    if !changed(&now) {
        return;
    }
    let msg = text(&ServerMsg::AvatarChanged {
        scene: scene.id.clone(),
        seq: s.last_seq(),
        avatar: Box::new(now),
    });
    let told = scene.feed().push_change(id, &msg);
    state
        .watchers
        .push(&state.config.access, &scene.id, &msg, &told);
}

/// Announces what ticks changed by themselves ([`crate::scene::TickChanges`]): a drive a tick
/// ends because its driver went silent past `--drive-timeout` (`avatar_changed`, `driven`
/// false or the pose held with no driver), as a driver that disconnects is announced; a
/// replay's avatar that came on stage (`avatar_changed`) or went off (`avatar_removed` to the
/// watchers; the feed told the subscribers). Runs until the server's world is gone.
pub async fn announce_tick_changes(state: std::sync::Weak<Services>) {
    let Some(mut changes) = state.upgrade().and_then(|s| s.world.take_tick_changes()) else {
        return;
    };
    while let Some((scene, avatar)) = changes.recv().await {
        let Some(state) = state.upgrade() else {
            return;
        };
        let Ok(scene) = state.world.scene(&scene) else {
            continue;
        };
        let on_stage = scene.lock().avatars.iter().any(|a| a.id == avatar);
        if on_stage {
            avatar_changed(&state, &scene, &avatar);
        } else {
            let told = scene.feed().covering(&avatar);
            let msg = text(&ServerMsg::AvatarRemoved {
                scene: scene.id.clone(),
                avatar,
            });
            state
                .watchers
                .push(&state.config.access, &scene.id, &msg, &told);
        }
    }
}

/// How long viewer changes of one scene are gathered before watchers hear of them.
pub const VIEWERS_COALESCE: std::time::Duration = std::time::Duration::from_secs(1);

/// A connection subscribed to or left `scene`: its subscribers and watchers hear who watches
/// it now, in one `viewers` message per scene and [`VIEWERS_COALESCE`] however many joined or
/// left (a crowd joining does not make each dashboard a message per viewer).
pub fn viewers_changed(state: &Arc<Services>, scene: &Arc<Scene>) {
    if scene
        .viewers_pending
        .swap(true, std::sync::atomic::Ordering::SeqCst)
    {
        return;
    }
    let (state, scene) = (Arc::downgrade(state), Arc::downgrade(scene));
    tokio::spawn(async move {
        tokio::time::sleep(VIEWERS_COALESCE).await;
        let (Some(state), Some(scene)) = (state.upgrade(), scene.upgrade()) else {
            return;
        };
        scene
            .viewers_pending
            .store(false, std::sync::atomic::Ordering::SeqCst);
        let told = {
            let feed = scene.feed();
            let msg = text(&ServerMsg::Viewers {
                scene: scene.id.clone(),
                viewers: feed.viewers(),
            });
            (feed.push_to_all(&msg), msg)
        };
        state
            .watchers
            .push(&state.config.access, &scene.id, &told.1, &told.0);
    });
}
