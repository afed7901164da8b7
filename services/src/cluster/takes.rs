//! Takes of scenes shared by the cluster (issue 32): JetStream object store `posecast_takes`,
//! one object per take, named as the take, holding the take file's bytes; its description
//! holds the take as `list_takes` describes it (JSON), so the list needs no download.
//!
//! - **Recording** happens where the scene is ticked (`record_scene` is forwarded to its
//!   owner), into that server's takes as on a server alone. A take that ends — stopped, at a
//!   limit, its scene given up or deleted — is put into the bucket: by `stop_recording_scene`
//!   before it answers, else by the lease loop's next look ([`Cluster::sync_takes`], which
//!   also retries a put NATS refused). A take being recorded is listed by the server
//!   recording it.
//! - **Using** a take (`get_take`, `replay`, the exports) on any server reads the bucket's
//!   object into that server's takes first, once per version: a take kept there is marked as
//!   the copy of an object (`Takes::mark_shared`); a copy whose object changed is read again,
//!   one whose object is gone is deleted.
//! - **Deleting** removes the object, then the copy here; other servers' copies go at their
//!   next look.

use super::{Cluster, unavailable};
use crate::scene::Scene;
use crate::state::Services;
use crate::store::snapshot::{ReplayRecord, SceneFile};
use crate::world::replays::ReplayStart;
use async_nats::jetstream::object_store::{self, ObjectMetadata};
use futures_util::StreamExt;
use posecast_core::error::Error;
use posecast_proto::command::TakeInfo;
use posecast_stream::take::TakeIndex;
use std::collections::HashMap;
use std::sync::Arc;
use tokio::io::AsyncReadExt;
use tracing::{info, warn};

/// The bucket of takes.
pub(super) const TAKES_BUCKET: &str = "posecast_takes";

impl Cluster {
    /// The takes in the bucket, described as they were put, by name → (description, the
    /// object's id).
    pub(super) async fn bucket_takes(&self) -> Result<HashMap<String, (TakeInfo, String)>, Error> {
        let mut list = self
            .conn
            .takes
            .0
            .list()
            .await
            .map_err(|e| unavailable("cannot list the cluster's takes", &e))?;
        let mut found = HashMap::new();
        while let Some(info) = list.next().await {
            let info = info.map_err(|e| unavailable("cannot list the cluster's takes", &e))?;
            if info.deleted {
                continue;
            }
            match info
                .description
                .as_deref()
                .map(serde_json::from_str::<TakeInfo>)
            {
                Some(Ok(take)) if take.take == info.name => {
                    found.insert(info.name, (take, info.nuid));
                }
                _ => {
                    warn!(object = %info.name, "a take in the cluster's store has no usable description: left out")
                }
            }
        }
        Ok(found)
    }

    /// The id of the bucket's object of take `take` (`None`: not there).
    pub(super) async fn take_object(&self, take: &str) -> Result<Option<String>, Error> {
        match self.conn.takes.0.info(take).await {
            Ok(info) if !info.deleted => Ok(Some(info.nuid)),
            Ok(_) => Ok(None),
            Err(e) if e.kind() == object_store::InfoErrorKind::NotFound => Ok(None),
            Err(e) => Err(unavailable("cannot read the cluster's takes", &e)),
        }
    }

    /// Puts take `take`, kept here, into the bucket and marks it as that object's copy.
    pub(super) async fn put_take(&self, state: &Services, take: &str) -> Result<(), Error> {
        let name = take.to_owned();
        let takes = state.takes.clone();
        let described = tokio::task::spawn_blocking(move || takes.describe(&name))
            .await
            .map_err(|e| Error::internal("take task failed", &e))??;
        let description = serde_json::to_string(&described)
            .map_err(|e| Error::internal("cannot describe the take", &e))?;
        let meta = ObjectMetadata {
            name: take.to_owned(),
            description: Some(description),
            ..Default::default()
        };
        // Read from its file as it is put (a take may be hundreds of megabytes), or from
        // memory; the file is complete (its take ended), so the description matches it.
        let bucket = &self.conn.takes.0;
        let put = match state.takes.file(take) {
            Some(path) => {
                let mut file =
                    tokio::fs::File::open(&path)
                        .await
                        .map_err(|_| Error::UnknownTake {
                            take: take.to_string(),
                            unreadable: None,
                        })?;
                bucket.put(meta, &mut file).await
            }
            None => {
                let bytes = state.takes.bytes(take)?;
                bucket.put(meta, &mut bytes.as_slice()).await
            }
        }
        .map_err(|e| unavailable("cannot store the take in NATS", &e))?;
        state.metrics.cluster.published(put.size);
        state.metrics.takes.shared();
        let (takes, name) = (state.takes.clone(), take.to_owned());
        tokio::task::spawn_blocking(move || takes.mark_shared(&name, &put.nuid))
            .await
            .map_err(|e| Error::internal("take task failed", &e))??;
        info!(%take, bytes = put.size, "take shared with the cluster");
        Ok(())
    }

    /// Makes the copy of take `take` kept here the bucket's current one: read when missing
    /// or older, deleted when the bucket no longer has it. A take recorded here and not
    /// shared yet is left as it is. Returns whether the bucket has the take.
    pub(super) async fn fetch_take(&self, state: &Services, take: &str) -> Result<bool, Error> {
        let object = self.take_object(take).await?;
        let copy = state.takes.shared_as(take);
        let nuid = match object {
            None => {
                if copy.is_some() {
                    // Deleted on another server: the copy goes too.
                    let (takes, name) = (state.takes.clone(), take.to_owned());
                    tokio::task::spawn_blocking(move || takes.delete(&name))
                        .await
                        .map_err(|e| Error::internal("take task failed", &e))?
                        .ok();
                }
                return Ok(false);
            }
            Some(nuid) if copy.as_ref() == Some(&nuid) => return Ok(true),
            Some(nuid) => nuid,
        };
        if copy.is_none() && state.takes.names().iter().any(|n| n == take) {
            // Recorded here and not shared yet (the lease loop shares it).
            return Ok(true);
        }
        let mut object = match self.conn.takes.0.get(take).await {
            Ok(object) => object,
            Err(e) if e.kind() == object_store::GetErrorKind::NotFound => return Ok(false),
            Err(e) => return Err(unavailable("cannot read the take from NATS", &e)),
        };
        // A copy counts toward this server's data quota like a take recorded here (an older
        // copy it replaces, too: it goes only once the new one is in).
        let size = object.info.size as u64;
        crate::ingest::check_room(
            state,
            &crate::auth::Caller::Anonymous,
            &format!("a copy of take {take}"),
            size,
        )?;
        let mut bytes = Vec::with_capacity(object.info.size);
        // Bounded whatever the size claimed.
        (&mut object)
            .take(size + 1)
            .read_to_end(&mut bytes)
            .await
            .map_err(|e| unavailable("cannot read the take from NATS", &e))?;
        state.metrics.cluster.received(bytes.len());
        if bytes.len() as u64 != size {
            return Err(Error::Unavailable(format!(
                "the cluster's copy of take {take} changed while it was read: try again"
            )));
        }
        let (takes, name) = (state.takes.clone(), take.to_owned());
        tokio::task::spawn_blocking(move || takes.install(&name, &nuid, &bytes))
            .await
            .map_err(|e| Error::internal("take task failed", &e))??;
        state.metrics.takes.fetched();
        Ok(true)
    }

    /// Removes take `take` from the bucket. Returns whether it was there.
    pub(super) async fn delete_take(&self, take: &str) -> Result<bool, Error> {
        if self.take_object(take).await?.is_none() {
            return Ok(false);
        }
        match self.conn.takes.0.delete(take).await {
            Ok(()) => Ok(true),
            Err(e) if e.kind() == object_store::DeleteErrorKind::NotFound => Ok(false),
            Err(e) => Err(unavailable("cannot delete the take from NATS", &e)),
        }
    }

    /// Every third of the lease time, [`Self::sync_takes`], until the server stops.
    pub(super) async fn share_takes(&self) {
        let period = self.conn.lease / 3;
        loop {
            let Some(state) = self.state() else { return };
            if state.readiness.stopped() {
                return;
            }
            if let Err(e) = self.sync_takes(&state).await {
                warn!(error = %e, "cannot share takes with the cluster");
            }
            drop(state);
            tokio::time::sleep(period).await;
        }
    }

    /// A look at takes: those recorded here that ended are put into the
    /// bucket; copies of takes the bucket no longer has are deleted (not while replayed here).
    pub(super) async fn sync_takes(&self, state: &Arc<Services>) -> Result<(), Error> {
        let takes = state.takes.clone();
        let (unshared, copies) = tokio::task::spawn_blocking(move || {
            let copies: Vec<String> = takes
                .names()
                .into_iter()
                .filter(|n| takes.shared_as(n).is_some())
                .collect();
            (takes.unshared(), copies)
        })
        .await
        .map_err(|e| Error::internal("take task failed", &e))?;
        for take in unshared {
            self.put_take(state, &take).await?;
        }
        if copies.is_empty() {
            return Ok(());
        }
        let bucket = self.bucket_takes().await?;
        let replayed = state.world.replayed_takes();
        for take in copies {
            if bucket.contains_key(&take) || replayed.contains(&take) {
                continue;
            }
            let (takes, name) = (state.takes.clone(), take.clone());
            let deleted = tokio::task::spawn_blocking(move || takes.delete(&name))
                .await
                .map_err(|e| Error::internal("take task failed", &e))?;
            if deleted.is_ok() {
                info!(%take, "take deleted from the cluster: its copy here too");
            }
        }
        Ok(())
    }
}

/// A replay scene's take, read here before the scene is taken over.
pub(super) struct Resumable {
    record: ReplayRecord,
    index: Arc<TakeIndex>,
}

impl Cluster {
    /// Before a replay scene (`file`) is taken over: its take read here, and the replayed
    /// avatars left out of the snapshot's (the replay makes them again). `Ok(None)`: not a
    /// replay, or one whose take is gone (the scene goes on without it, logged). `Err`: try
    /// later (NATS, a rig the take needs is missing here).
    pub(super) async fn prepare_resume(
        &self,
        state: &Services,
        file: &mut SceneFile,
    ) -> Result<Option<Resumable>, String> {
        let Some(record) = file.replay.clone() else {
            return Ok(None);
        };
        if !self
            .fetch_take(state, &record.take)
            .await
            .map_err(|e| e.to_string())?
        {
            warn!(scene = %file.scene, take = %record.take, "the scene replayed a take the cluster no longer has: it goes on without the replay");
            return Ok(None);
        }
        let (takes, name) = (state.takes.clone(), record.take.clone());
        let index = tokio::task::spawn_blocking(move || takes.index(&name))
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())?;
        let missing: Vec<&str> = index
            .avatar_lists
            .iter()
            .flatten()
            .map(|d| d.name.as_str())
            .filter(|rig| state.world.library.get(rig).is_none())
            .collect();
        if !missing.is_empty() {
            return Err(format!("this server lacks rigs the take uses: {missing:?}"));
        }
        file.avatars.retain(|a| !record.replayed.contains(&a.id));
        Ok(Some(Resumable { record, index }))
    }

    /// The replay resumed in `scene`, restored from a snapshot taken at `saved_us`, where it
    /// would be now had it run on.
    pub(super) async fn resume(
        &self,
        state: &Services,
        scene: &Arc<Scene>,
        resumable: Resumable,
        saved_us: u64,
    ) {
        let Resumable { record, index } = resumable;
        let (takes, name) = (state.takes.clone(), record.take.clone());
        let source = match tokio::task::spawn_blocking(move || takes.source(&name)).await {
            Ok(Ok(source)) => source,
            Ok(Err(e)) => {
                warn!(scene = %scene.id, error = %e, "replay not resumed");
                return;
            }
            Err(e) => {
                warn!(scene = %scene.id, error = %e, "replay not resumed");
                return;
            }
        };
        let elapsed = crate::scene::unix_micros().saturating_sub(saved_us) as f64 / 1e6;
        let from = if record.paused {
            record.time
        } else {
            record.time + elapsed * f64::from(record.speed)
        };
        let start = ReplayStart {
            from,
            speed: record.speed,
            looping: record.looping,
        };
        match state
            .world
            .resume_replay(scene, &record.take, index, source, start, record.paused)
        {
            Ok(replay) => {
                info!(scene = %scene.id, take = %record.take, time = replay.time, "replay resumed")
            }
            Err(e) => warn!(scene = %scene.id, error = %e, "replay not resumed"),
        }
    }
}
