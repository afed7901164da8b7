//! How a command on a scene ticked here becomes an acknowledgement: applied, stored in bucket
//! `posecast_scenes` *conditioned on this server still owning the scene*, then answered — or
//! undone and answered with an error.
//!
//! **Fencing.** The owner writes a scene's snapshot with a compare-and-set on the revision of
//! the key it last wrote or restored (`update` at that revision), and a server taking a scene
//! over writes the snapshot it restored before it ticks it (the same compare-and-set), which
//! moves the revision on. So once a scene is taken over, every later write of the previous
//! owner fails, however long that owner was paused or cut off and whatever it still believes
//! of its lease: it answers `unavailable` (not applied, try again), undoes the change, and
//! gives the scene up. A write of the previous owner that landed before the takeover's is
//! in the snapshot the new owner restored: nothing acknowledged is lost either way.
//!
//! **Undo.** Commands on one scene commit one at a time (one async lock per scene, held from
//! before the command is applied until its write is answered), so the scene before a command
//! is the last stored state. A command whose write fails is undone by restoring, from that
//! snapshot, what it touched: avatars it added are removed, and the avatar it changed or
//! removed is put back as it was (its clip's clock moved on by the time since, as after a
//! takeover). A write whose outcome is unknown (NATS did not answer in time: it may have
//! landed) is remembered; the next write — or the lease loop's next look — recognises it in
//! the bucket by its bytes and overwrites it with the scene as it is (undone), so an undone
//! command cannot come back through a takeover.
//!
//! **Idempotency.** A command may carry a key chosen by the client. The answers of the
//! scene's latest keyed commands ([`crate::scene::answers::RECENT`]) live in the scene's lock and in its snapshot
//! ([`snapshot::SceneFile::recent`]), so a retry of an acknowledged command — on this server,
//! or on the one that took the scene over — is answered with the first answer and applied
//! once.

use super::{Cluster, key, lock, relay_subject, unavailable};
use crate::scene::answers::{Recent, answered, op_of, remember};
use crate::state::{RunError, Services};
use crate::store::snapshot::{self, SceneFile};
use crate::world::command::SceneChange;
use async_nats::jetstream::kv;
use bytes::Bytes;
use futures_util::future::BoxFuture;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{AvatarId, SceneId};
use std::collections::BTreeSet;
use std::sync::Arc;
use tracing::{info, warn};

/// One lock per scene ticked here, guarding its [`Recent`] table.
pub(super) type Slot = Arc<tokio::sync::Mutex<Recent>>;

/// How a write of a scene's snapshot went.
#[derive(Debug)]
pub(super) enum Written {
    /// Stored at the revision expected: the change is durable.
    Stored,
    /// Another server took the scene over: the write did not happen.
    Fenced,
    /// NATS refused it or did not answer; `unknown` when it may have landed.
    Failed { error: String, unknown: bool },
}

fn fenced(id: &SceneId) -> Error {
    Error::Unavailable(format!(
        "scene {id} was taken over by another server while this one was paused or cut off: the command was not applied (try again)"
    ))
}

/// A write that failed: `unavailable` when NATS refused it (not applied); when NATS did not
/// answer, the write may have landed and this server may be stopped before it overwrites it,
/// so the answer is `outcome_unknown` (the stored snapshot then holds the command's
/// idempotency key too, and a retry with it is answered from there, applied once).
fn not_stored(error: &str, unknown: bool) -> Error {
    if unknown {
        return Error::OutcomeUnknown(format!(
            "cannot store the scene in NATS ({error}): NATS did not answer in time, so the command may have been applied; this server undoes it, and a retry with the same idempotency key applies it at most once"
        ));
    }
    Error::Unavailable(format!(
        "cannot store the scene in NATS ({error}): the command was not applied (try again)"
    ))
}

fn not_here(id: &SceneId) -> Error {
    Error::Unavailable(format!(
        "scene {id} is not ticked by this server (any longer): the command was not applied (try again)"
    ))
}

/// Puts back what a command changed: avatars of `touched` that exist now are removed, and
/// those of `before` (the scene before the command) restored as they were.
pub(super) fn roll_back(
    world: &crate::world::World,
    before: &SceneFile,
    touched: &BTreeSet<AvatarId>,
    now_us: u64,
) {
    let Ok(scene) = world.scene(&before.scene) else {
        return;
    };
    if scene.is_relay() {
        return;
    }
    for id in touched {
        scene.remove_avatar(id);
    }
    let back = SceneFile {
        avatars: before
            .avatars
            .iter()
            .filter(|a| touched.contains(&a.id))
            .cloned()
            .collect(),
        ..before.clone()
    };
    snapshot::restore_into(world, &back, now_us);
}

/// The avatars a command may have changed: the one it names, and any that came or went.
fn touched(command: &Command, before: &SceneFile, after: &SceneFile) -> BTreeSet<AvatarId> {
    let ids = |f: &SceneFile| {
        f.avatars
            .iter()
            .map(|a| a.id.clone())
            .collect::<BTreeSet<_>>()
    };
    let (was, is) = (ids(before), ids(after));
    let mut touched: BTreeSet<AvatarId> = was.symmetric_difference(&is).cloned().collect();
    if let Some(a) = command.avatar() {
        touched.insert(a.clone());
    }
    touched
}

impl Cluster {
    /// The lock (and keyed answers) of scene `id`.
    pub(super) fn slot(&self, id: &SceneId) -> Slot {
        lock(&self.slots).entry(id.clone()).or_default().clone()
    }

    /// [`crate::state::Cluster::commit`].
    pub(super) async fn commit_command(
        &self,
        state: &Arc<Services>,
        command: &Command,
        id: &SceneId,
        key: Option<&str>,
        run: BoxFuture<'_, Result<CommandResult, RunError>>,
    ) -> Result<CommandResult, Error> {
        let slot = self.slot(id);
        let mut recent = slot.lock().await;
        let op = op_of(command);
        let change = crate::world::command::handler(command).scene_change();
        if change == SceneChange::Creates {
            if let Some(again) = key.and_then(|k| answered(&recent, k, &op)) {
                return again;
            }
            let result = self.create(state, id, key, op, run, &mut recent).await?;
            let filled = state.world.scene(id).is_ok_and(|s| {
                let s = s.lock();
                s.replay.is_some() || !s.avatars.is_empty()
            });
            if filled {
                // The claim stored the empty scene: now what it was made with (a replay and
                // its avatars), so a server taking the scene over resumes it.
                if let Written::Failed { error, .. } =
                    self.write_snapshot(&state.world, id, &recent).await
                {
                    warn!(scene = %id, %error, "the new replay's snapshot is not stored yet: the next change stores it");
                }
            }
            return Ok(result);
        }
        let Some(expected) = lock(&self.owned).get(id).map(|o| o.snapshot_revision) else {
            return Err(not_here(id));
        };
        if let Some(again) = key.and_then(|k| answered(&recent, k, &op)) {
            return again;
        }
        if change == SceneChange::Deletes {
            return self.delete(state, id, expected, run).await;
        }
        let scene = state.world.scene(id)?;
        let now = crate::scene::unix_micros();
        let before = snapshot::snapshot(&scene, now);
        let result = match run.await {
            Ok(result) => result,
            Err(RunError::Refused(e)) => return Err(e),
            Err(RunError::NotStored(e)) => {
                let after = snapshot::snapshot(&scene, now);
                roll_back(
                    &state.world,
                    &before,
                    &touched(command, &before, &after),
                    now,
                );
                return Err(e);
            }
        };
        let after = snapshot::snapshot(&scene, now);
        if let Some(k) = key {
            remember(&mut recent, k, op, &result);
        }
        match self.write_snapshot(&state.world, id, &recent).await {
            Written::Stored => Ok(result),
            outcome => {
                if key.is_some() {
                    recent.pop_back();
                }
                roll_back(
                    &state.world,
                    &before,
                    &touched(command, &before, &after),
                    crate::scene::unix_micros(),
                );
                match outcome {
                    Written::Fenced => {
                        warn!(scene = %id, "another server took the scene over: giving it up, the command undone");
                        self.give_up(&state.world, id);
                        Err(fenced(id))
                    }
                    Written::Failed { error, unknown } => Err(not_stored(&error, unknown)),
                    Written::Stored => Ok(result),
                }
            }
        }
    }

    /// `create_scene`: the id claimed cluster-wide (its key created holding the empty scene,
    /// and the key's answer when the command carries one: the create is durable with the
    /// claim), then the scene made here.
    async fn create(
        &self,
        state: &Arc<Services>,
        id: &SceneId,
        key: Option<&str>,
        op: String,
        run: BoxFuture<'_, Result<CommandResult, RunError>>,
        recent: &mut Recent,
    ) -> Result<CommandResult, Error> {
        // What this server would refuse (a quota, a scene of that name here) is refused before
        // the id is claimed: a claim is seen by the other servers, which relay it.
        state.world.room_for_scene(id)?;
        let mut table = Recent::new();
        if let Some(k) = key {
            remember(
                &mut table,
                k,
                op,
                &CommandResult::SceneCreated { scene: id.clone() },
            );
        }
        let (lease, stored) = self.claim(id, &table).await?;
        match run.await {
            Ok(result) => {
                lock(&self.claims).remove(id);
                *recent = table;
                if let Ok(scene) = state.world.scene(id) {
                    self.adopt(state, &scene, lease, stored);
                }
                Ok(result)
            }
            Err(e) => {
                if let RunError::NotStored(_) = e {
                    state.world.delete_scene(id).ok();
                }
                self.unclaim(id).await;
                Err(e.into_error())
            }
        }
    }

    /// `delete_scene`: the key removed first, at the revision this server last wrote (a
    /// stale owner's delete fails and changes nothing), then the scene here.
    async fn delete(
        &self,
        state: &Arc<Services>,
        id: &SceneId,
        expected: u64,
        run: BoxFuture<'_, Result<CommandResult, RunError>>,
    ) -> Result<CommandResult, Error> {
        match self
            .conn
            .scenes
            .delete_expect_revision(key(id), Some(expected))
            .await
        {
            Ok(()) => {}
            Err(e) if e.kind() == kv::DeleteErrorKind::WrongLastRevision => {
                warn!(scene = %id, "another server took the scene over: giving it up, not deleted");
                self.give_up(&state.world, id);
                return Err(fenced(id));
            }
            Err(e) => return Err(not_stored(&e.to_string(), false)),
        }
        let result = run.await.map_err(RunError::into_error);
        let mut epoch = 0;
        if let Some(o) = lock(&self.owned).remove(id) {
            epoch = o.epoch;
            o.stop();
        }
        lock(&self.slots).remove(id);
        self.conn.leases.delete(key(id)).await.ok();
        self.announce_deleted(id, epoch).await?;
        result
    }

    /// Tells the relays of scene `id` that it is gone. Named and signed like the scene's other
    /// relay messages: relays believe it only from the lease holder, once the scene is gone
    /// from the bucket (`relay.rs`).
    async fn announce_deleted(&self, id: &SceneId, epoch: u64) -> Result<(), Error> {
        let claim = super::identity::Claim {
            kind: "deleted".into(),
            epoch,
            node: self.conn.node.clone(),
        };
        let subject = relay_subject(id);
        let headers = self.conn.signer.headers(&subject, &claim, &Bytes::new());
        self.conn
            .client
            .publish_with_headers(subject, headers, Bytes::new())
            .await
            .map_err(|e| unavailable("cannot tell the cluster", &e))
    }

    /// Claims scene id `id` cluster-wide: creates its key (holding the empty scene and
    /// `recent`) and its lease. Returns the lease's and the key's revisions.
    async fn claim(&self, id: &SceneId, recent: &Recent) -> Result<(u64, u64), Error> {
        if crate::world::number_of(&id.0) == 0 {
            return Err(Error::invalid("scene id"));
        }
        let empty = SceneFile {
            format: snapshot::SCENE_FORMAT,
            scene: id.clone(),
            saved_us: crate::scene::unix_micros(),
            avatars: Vec::new(),
            recent: recent.iter().cloned().collect(),
            replay: None,
        };
        let bytes = serde_json::to_vec(&empty)
            .map_err(|e| Error::internal("cannot serialise the scene", &e))?;
        // The lease first, then the scene's key: the other servers' lease loops look at scene
        // keys, and one without a lease is taken over — created in the other order, a new
        // scene could be taken over between the two creates, and its creator refused.
        let lease = Bytes::from(self.conn.node.clone());
        let lease_revision = match self.conn.leases.create(key(id), lease).await {
            Ok(revision) => revision,
            Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {
                return Err(Error::Conflict(format!("scene {id} exists")));
            }
            Err(e) => return Err(unavailable("cannot take the new scene's lease", &e)),
        };
        match self.conn.scenes.create(key(id), Bytes::from(bytes)).await {
            Ok(stored) => {
                lock(&self.claims).insert(id.clone());
                Ok((lease_revision, stored))
            }
            Err(e) => {
                self.conn
                    .leases
                    .delete_expect_revision(key(id), Some(lease_revision))
                    .await
                    .ok();
                if e.kind() == kv::CreateErrorKind::AlreadyExists {
                    Err(Error::Conflict(format!("scene {id} exists")))
                } else {
                    Err(unavailable("cannot create the scene in NATS", &e))
                }
            }
        }
    }

    /// Gives a claim back (the scene could not be created here after all). The scene's key
    /// goes before its lease (a key without a lease would be taken over), and the servers that
    /// began relaying the claimed scene are told it is gone, as after `delete_scene`, so the
    /// name is free everywhere at once.
    async fn unclaim(&self, id: &SceneId) {
        lock(&self.claims).remove(id);
        self.conn.scenes.delete(key(id)).await.ok();
        if let Err(e) = self.announce_deleted(id, 0).await {
            warn!(scene = %id, error = %e, "cannot tell the cluster a claim was given back: its relays drop it at their next scan");
        }
        self.conn.leases.delete(key(id)).await.ok();
    }

    /// Writes scene `id`'s snapshot (with `recent`) to the cluster's bucket at the revision
    /// this server last wrote: the caller holds the scene's slot.
    pub(super) async fn write_snapshot(
        &self,
        world: &crate::world::World,
        id: &SceneId,
        recent: &Recent,
    ) -> Written {
        let Some((expected, unsure)) = lock(&self.owned)
            .get(id)
            .map(|o| (o.snapshot_revision, o.unsure.clone()))
        else {
            return Written::Fenced;
        };
        let Ok(scene) = world.scene(id) else {
            return Written::Fenced;
        };
        let mut file = snapshot::snapshot(&scene, crate::scene::unix_micros());
        file.recent = recent.iter().cloned().collect();
        let bytes = match serde_json::to_vec(&file) {
            Ok(b) => Bytes::from(b),
            Err(e) => {
                return Written::Failed {
                    error: e.to_string(),
                    unknown: false,
                };
            }
        };
        // A put made while the client is disconnected would wait in its buffer and could land
        // after the command was answered as not applied: not attempted at all.
        if self.conn.client.connection_state() != async_nats::connection::State::Connected {
            return Written::Failed {
                error: "not connected to NATS".into(),
                unknown: false,
            };
        }
        let mut expected = expected;
        for attempt in 0..2 {
            match self
                .conn
                .scenes
                .update(key(id), bytes.clone(), expected)
                .await
            {
                Ok(revision) => {
                    if let Some(o) = lock(&self.owned).get_mut(id) {
                        o.snapshot_revision = revision;
                        o.unsure = None;
                    }
                    return Written::Stored;
                }
                Err(e) if e.kind() == kv::UpdateErrorKind::WrongLastRevision => {
                    // Our own earlier write whose answer was lost, or another owner's.
                    let Some(unsure) = unsure.as_ref().filter(|_| attempt == 0) else {
                        return Written::Fenced;
                    };
                    match self.conn.scenes.entry(key(id)).await {
                        Ok(Some(entry)) if entry.value == *unsure => {
                            info!(scene = %id, "a write thought lost had landed: overwriting it with the scene as it is");
                            expected = entry.revision;
                        }
                        Ok(_) => return Written::Fenced,
                        Err(e) => {
                            return Written::Failed {
                                error: e.to_string(),
                                unknown: false,
                            };
                        }
                    }
                }
                Err(e) => {
                    // A put NATS did not acknowledge may still have been stored.
                    let unknown = e.kind() == kv::UpdateErrorKind::TimedOut
                        || e.kind() == kv::UpdateErrorKind::Other;
                    if unknown && let Some(o) = lock(&self.owned).get_mut(id) {
                        o.unsure = Some(bytes.clone());
                    }
                    return Written::Failed {
                        error: e.to_string(),
                        unknown,
                    };
                }
            }
        }
        Written::Fenced
    }

    /// Scenes ticked here with a write of unknown outcome: written again as they are (the lease
    /// loop, once NATS answers), so an undone command's write that did land is overwritten.
    pub(super) async fn repair(&self, state: &Arc<Services>) {
        let unsure: Vec<SceneId> = lock(&self.owned)
            .iter()
            .filter(|(_, o)| o.unsure.is_some())
            .map(|(id, _)| id.clone())
            .collect();
        for id in unsure {
            let slot = self.slot(&id);
            let recent = slot.lock().await;
            match self.write_snapshot(&state.world, &id, &recent).await {
                Written::Stored => {
                    info!(scene = %id, "stored again after a write of unknown outcome")
                }
                Written::Fenced => {
                    warn!(scene = %id, "another server took the scene over: giving it up");
                    self.give_up(&state.world, &id);
                }
                Written::Failed { .. } => {}
            }
        }
    }

    /// The first write of a scene just restored here for a takeover, at the revision it was
    /// restored from: after it, the previous owner's writes fail (fencing). An error when the
    /// previous owner wrote in between (the takeover must start again from the new snapshot).
    pub(super) async fn fence(
        &self,
        world: &crate::world::World,
        id: &SceneId,
        restored: u64,
        recent: &Recent,
    ) -> Result<u64, String> {
        let scene = world.scene(id).map_err(|e| e.to_string())?;
        let mut file = snapshot::snapshot(&scene, crate::scene::unix_micros());
        file.recent = recent.iter().cloned().collect();
        let bytes = serde_json::to_vec(&file).map_err(|e| e.to_string())?;
        self.conn
            .scenes
            .update(key(id), Bytes::from(bytes), restored)
            .await
            .map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every kind of change a command makes to a scene is undone: the scene's snapshot after
    /// the undo is the one before the command (at the same instant, nothing playing), and an
    /// avatar the command did not touch is left alone (the same `Arc` description, never
    /// removed and added again).
    #[tokio::test]
    async fn a_rolled_back_command_leaves_the_scene_as_it_was_stored() {
        use posecast_rigs::builtin::BUILTIN_ASSET;
        let state = Services::new(crate::config::Config::default());
        state
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        let run = |json: &str| {
            let command: Command = serde_json::from_str(json).unwrap();
            crate::control::execute(&state, &command).unwrap();
            command
        };
        run(r#"{"op":"create_scene","scene":"s"}"#);
        for a in ["kept", "changed"] {
            run(&format!(
                r#"{{"op":"add_avatar","scene":"s","asset":"{BUILTIN_ASSET}","avatar":"{a}"}}"#
            ));
        }
        run(
            r#"{"op":"set_joint_rotation","avatar":"changed","joint":"l_knee","rotation":[0.3826834,0,0,0.9238795]}"#,
        );
        let id = SceneId("s".into());
        let scene = state.world.scene(&id).unwrap();
        let kept = |s: &crate::scene::Scene| {
            s.lock()
                .avatars
                .iter()
                .find(|a| a.id.0 == "kept")
                .unwrap()
                .description
                .clone()
        };
        let kept_before = kept(&scene);
        for json in [
            format!(r#"{{"op":"add_avatar","scene":"s","asset":"{BUILTIN_ASSET}"}}"#),
            r#"{"op":"remove_avatar","avatar":"changed"}"#.into(),
            r#"{"op":"release","avatar":"changed"}"#.into(),
            r#"{"op":"place_avatar","avatar":"changed","position":[1,0,2],"rotation":[0,0,0,1]}"#.into(),
            r#"{"op":"rotate_joint_local","avatar":"changed","joint":"l_elbow","rotation":[0,0.7071068,0,0.7071068]}"#.into(),
        ] {
            let before = snapshot::snapshot(&scene, 1);
            let command = run(&json);
            let after = snapshot::snapshot(&scene, 1);
            assert_ne!(after.avatars, before.avatars, "{json} changed nothing");
            roll_back(&state.world, &before, &touched(&command, &before, &after), 1);
            let back = snapshot::snapshot(&scene, 1);
            let mut want = before.avatars.clone();
            let mut got = back.avatars.clone();
            want.sort_by(|a, b| a.id.0.cmp(&b.id.0));
            got.sort_by(|a, b| a.id.0.cmp(&b.id.0));
            assert_eq!(got, want, "{json} not undone");
            assert!(
                Arc::ptr_eq(&kept(&scene), &kept_before),
                "{json}: an untouched avatar was replaced"
            );
        }
    }
}
