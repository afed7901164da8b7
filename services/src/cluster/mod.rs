//! Scale-out: one scene served from many servers through NATS (`--nats`).
//!
//! - this module: [`connect`] (NATS and its two key-value buckets, before the server
//!   listens), [`Cluster`] (what the services ask of the cluster, [`crate::state::Cluster`]),
//!   and the lease loop that decides which server ticks which scene.
//! - `commit`: a command on a scene ticked here applied, stored with fencing, and
//!   acknowledged — or undone; idempotency keys.
//! - `owner`: a scene ticked here — its frames, descriptions and avatar changes published,
//!   commands and joiners' requests answered.
//! - `assets`: uploaded assets in object store `posecast_assets`, imported by every server.
//! - `drive`: live driving of an avatar through its scene's owner.
//! - `takes`: takes of scenes (`record_scene`) in object store `posecast_takes`, replayed by
//!   any server.
//! - `relay`: a scene ticked elsewhere — its frames fanned out here to this server's
//!   subscribers, as the same bytes.
//!
//! **Ownership.** Every scene of the cluster has a key in bucket `posecast_scenes` holding its
//! snapshot (the scene file of [`crate::store`], written at every acknowledged change) and, while
//! some server ticks it, a key in bucket `posecast_leases` (entries expire after the lease
//! time) holding that server's name. A server acquires a lease by creating the key (only one
//! create succeeds) and renews it every third of the lease time by updating it at the revision
//! it last wrote (compare-and-set: a renewal after somebody else took the lease fails). Every
//! third of the lease time each server also looks at every scene: one without a lease is taken
//! over (restored from its snapshot and ticked here); one leased to another server is relayed.
//!
//! Keys and subject tokens are the scene id in lowercase hex (ids may hold characters NATS
//! does not allow in either).

mod assets;
mod commit;
mod credentials;
mod drive;
pub mod identity;
mod owner;
mod relay;
mod takes;

use crate::config::Config;
use crate::control;
use crate::restore::{DEFAULT_AVATAR, DEFAULT_SCENE};
use crate::state::Services;
use crate::store::snapshot;
use async_nats::jetstream::{self, kv};
use bytes::Bytes;
use futures_util::StreamExt;
use futures_util::future::BoxFuture;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, SceneInfo};
use posecast_proto::msg::{AvatarId, ProtocolError, SceneId};
use posecast_rigs::builtin::BUILTIN_ASSET;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;
use tokio::task::JoinHandle;
use tracing::{info, warn};

/// The bucket of scene snapshots (one key per scene of the cluster).
const SCENES_BUCKET: &str = "posecast_scenes";
/// The bucket of leases (one key per ticked scene; entries expire).
const LEASES_BUCKET: &str = "posecast_leases";
/// The bucket of revoked minted tokens (one key per token id, holding when it would have
/// expired; entries expire after the longest lifetime a token can have).
const REVOKED_BUCKET: &str = "posecast_revoked";
/// How long a forwarded command or a request to a scene's owner may take.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// How long connecting to NATS at start may take before the start fails.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// Header naming what a message on a scene's relay subject is (`avatars`, `frame`, `change`,
/// `deleted`) or what a request asks (`command`, `sync`, `info`).
const KIND: &str = "Posecast-Kind";
/// Header with a forwarded command's idempotency key.
const IDEMPOTENCY_KEY: &str = "Posecast-Idempotency-Key";
/// Header with the owner's epoch: the revision of the lease it created. A newer owner's is
/// higher, so relays never interleave two owners' frames.
const EPOCH: &str = "Posecast-Epoch";

/// A scene id as a key and subject token: its bytes in lowercase hex.
fn key(id: &SceneId) -> String {
    id.0.bytes().map(|b| format!("{b:02x}")).collect()
}

/// The scene id of a key ([`key`]), if it is one.
fn unkey(key: &str) -> Option<SceneId> {
    if !key.len().is_multiple_of(2) {
        return None;
    }
    let bytes = (0..key.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(key.get(i..i + 2)?, 16).ok())
        .collect::<Option<Vec<u8>>>()?;
    String::from_utf8(bytes).ok().map(SceneId)
}

/// Where a scene's owner publishes what its subscribers get.
fn relay_subject(id: &SceneId) -> String {
    format!("posecast.scene.{}.relay", key(id))
}

/// Where a scene's owner answers commands and joiners.
fn request_subject(id: &SceneId) -> String {
    format!("posecast.scene.{}.req", key(id))
}

/// This server's connection to NATS, made before it listens.
#[derive(Debug)]
pub struct Connection {
    client: async_nats::Client,
    scenes: kv::Store,
    leases: kv::Store,
    revoked: kv::Store,
    /// The revocations in the bucket when this server connected, and the bucket's revision
    /// then: applied before the server serves anything, then watched from there on.
    revocations: (Vec<(String, u64)>, u64),
    assets: assets::Bucket,
    takes: assets::Bucket,
    node: String,
    lease: Duration,
    lost: Arc<AtomicBool>,
    /// Names and signs this server's relay messages, checks others' ([`identity`]).
    signer: identity::Signer,
}

impl Connection {
    /// This server's name in the cluster.
    #[must_use]
    pub fn node(&self) -> &str {
        &self.node
    }

    /// Applies the token revocations the cluster had when this server connected, before it
    /// serves anything (later ones arrive through the watch [`start`] begins).
    pub fn apply_revocations(&mut self, minter: &crate::auth::Minter) {
        for (id, until) in std::mem::take(&mut self.revocations.0) {
            if let Err(e) = minter.revoke_until(&id, until) {
                warn!(token = %id, error = %e, "cannot store a cluster revocation");
            }
        }
    }
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_owned())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "posecast".into())
}

/// Connects to the NATS servers of `config.nats` (any one of them will do; the client fails
/// over between them) and opens the cluster's buckets, creating them on the first start.
/// `port` is the port this server listens on (part of its default node name).
///
/// # Errors
/// No NATS server can be reached, or JetStream is not enabled there: the error names the
/// URLs.
pub async fn connect(config: &Config, port: u16) -> std::io::Result<Connection> {
    // Printed without their credentials, which go to the client as options.
    let urls = config
        .nats
        .iter()
        .map(|u| credentials::redact(u))
        .collect::<Vec<_>>()
        .join(",");
    let fail = |what: String| {
        std::io::Error::new(
            std::io::ErrorKind::ConnectionRefused,
            format!("cannot join the cluster through NATS at {urls}: {what}"),
        )
    };
    let lease = config.lease_ttl.max(Duration::from_millis(300));
    let node = config
        .node
        .clone()
        .unwrap_or_else(|| format!("{}:{port}", host_name()));
    let (plain, auth) = credentials::take(&config.nats).map_err(fail)?;
    let lost = Arc::new(AtomicBool::new(false));
    let flag = lost.clone();
    let options = credentials::options(auth, &config.nats_security)
        .await
        .map_err(fail)?;
    let options = options
        .name(format!("posecast {node}"))
        .connection_timeout(CONNECT_TIMEOUT)
        .request_timeout(Some(REQUEST_TIMEOUT))
        .event_callback(move |event| {
            let flag = flag.clone();
            async move {
                match event {
                    async_nats::Event::Disconnected => {
                        warn!("NATS connection lost: serving local scenes only until it is back");
                        flag.store(true, Ordering::SeqCst);
                    }
                    async_nats::Event::Connected if flag.swap(false, Ordering::SeqCst) => {
                        info!("NATS connection back");
                    }
                    _ => {}
                }
            }
        });
    let client = tokio::time::timeout(CONNECT_TIMEOUT * 2, options.connect(plain.as_slice()))
        .await
        .map_err(|_| fail("timed out".into()))?
        .map_err(|e| fail(e.to_string()))?;
    let js = jetstream::new(client.clone());
    // The bucket's stream made here rather than by `create_key_value`, which first reads the
    // account's information in a shape servers before 2.10 (Debian's 2.9) do not answer in.
    // The layout is the key-value one: one subject per key, the last value kept.
    let open = |name: &'static str, max_age: Duration| {
        let js = js.clone();
        async move {
            let config = jetstream::stream::Config {
                name: format!("KV_{name}"),
                subjects: vec![format!("$KV.{name}.>")],
                max_messages_per_subject: 1,
                max_age,
                allow_rollup: true,
                deny_delete: true,
                allow_direct: true,
                discard: jetstream::stream::DiscardPolicy::New,
                num_replicas: 1,
                ..Default::default()
            };
            if let Err(created) = js.get_or_create_stream(config).await {
                return Err(fail(format!(
                    "cannot create key-value bucket {name} ({created}): is JetStream enabled (nats-server -js)?"
                )));
            }
            js.get_key_value(name)
                .await
                .map_err(|e| fail(format!("cannot open key-value bucket {name}: {e}")))
        }
    };
    let scenes = open(SCENES_BUCKET, Duration::ZERO).await?;
    let leases = open(LEASES_BUCKET, lease).await?;
    let revoked = open(
        REVOKED_BUCKET,
        Duration::from_secs(posecast_proto::tokens::MAX_TTL_S + 3600),
    )
    .await?;
    let revocations = read_revocations(&revoked).await.map_err(fail)?;
    let assets = assets::open(&js, assets::ASSETS_BUCKET)
        .await
        .map_err(fail)?;
    let takes = assets::open(&js, takes::TAKES_BUCKET).await.map_err(fail)?;
    info!(nats = %urls, node = %node, lease_ms = lease.as_millis() as u64, "joined the cluster");
    Ok(Connection {
        client,
        scenes,
        leases,
        revoked,
        revocations,
        assets,
        takes,
        node,
        lease,
        lost,
        signer: identity::Signer::new(config.cluster_secret.as_ref()),
    })
}

/// What a scene's owner answers a forwarded command with: the result tagged with its kind (a
/// server of before tagged results sent the bare value, read by its shape).
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Reply {
    Ok(#[serde(deserialize_with = "tagged_or_bare")] CommandResult),
    Error(ProtocolError),
}

fn tagged_or_bare<'de, D: serde::Deserializer<'de>>(d: D) -> Result<CommandResult, D::Error> {
    let value = serde_json::Value::deserialize(d)?;
    CommandResult::from_tagged_or_bare(value).map_err(serde::de::Error::custom)
}

/// The cluster as this server sees it.
#[derive(Debug)]
pub struct Cluster {
    conn: Connection,
    state: Weak<Services>,
    /// Scenes ticked here: their lease revisions and tasks.
    owned: Mutex<HashMap<SceneId, owner::Owned>>,
    /// Scenes relayed here: their owners and relay tasks.
    relays: Mutex<HashMap<SceneId, relay::Relayed>>,
    /// Scenes about to be created here, claimed cluster-wide (the lease loop leaves them be).
    claims: Mutex<std::collections::HashSet<SceneId>>,
    /// Per scene ticked here: the lock its commands commit under, and its keyed answers.
    slots: Mutex<HashMap<SceneId, commit::Slot>>,
    /// Uploads of the assets bucket this server has (or refused): name → object nuid.
    applied: Mutex<HashMap<String, String>>,
    /// The assets bucket's last sequence number at the last complete look.
    assets_seen: Mutex<Option<u64>>,
    /// Scenes not taken over for want of an asset, each logged once.
    short_of_assets: Mutex<HashMap<SceneId, std::collections::BTreeSet<String>>>,
    /// Drivers on other servers of avatars ticked here.
    drivers: drive::Drivers,
    /// Drives of this server's connections run by other servers.
    remote_drives: drive::RemoteDrives,
    /// Poses of this server's drivers for avatars ticked elsewhere, to publish.
    poses: tokio::sync::mpsc::Sender<drive::Outgoing>,
    _pose_publisher: Task,
    /// Applies the cluster's token revocations here ([`watch_revocations`]).
    _revocations: Task,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A request to a scene's owner that got no answer. With no server listening on the scene's
/// subject, or a request NATS refused to send, nothing was applied (`unavailable`); a request
/// that was sent and not answered in time may have been applied by its owner, which may only
/// be slow (`outcome_unknown`: retry with the same idempotency key).
fn relay_failed(id: &SceneId, e: &async_nats::RequestError) -> Error {
    use async_nats::RequestErrorKind as Kind;
    match e.kind() {
        Kind::NoResponders | Kind::InvalidSubject | Kind::MaxPayloadExceeded => unavailable(
            &format!("no server ticks scene {id} now: the command was not applied (try again)"),
            e,
        ),
        Kind::TimedOut | Kind::Other => Error::OutcomeUnknown(format!(
            "the server ticking scene {id} did not answer in time ({e}): the command may have been applied; retry with the same idempotency key to apply it at most once"
        )),
    }
}

fn unavailable(what: &str, e: &dyn std::fmt::Display) -> Error {
    Error::Unavailable(format!("{what}: {e}"))
}

/// The revocations in the cluster's bucket, and its latest revision.
async fn read_revocations(bucket: &kv::Store) -> Result<(Vec<(String, u64)>, u64), String> {
    use futures_util::StreamExt;
    let fail = |e: &dyn std::fmt::Display| format!("cannot read bucket {REVOKED_BUCKET}: {e}");
    let mut found = Vec::new();
    let mut seen = 0;
    let mut keys = bucket.keys().await.map_err(|e| fail(&e))?;
    while let Some(key) = keys.next().await {
        let key = key.map_err(|e| fail(&e))?;
        if let Some(entry) = bucket.entry(key).await.map_err(|e| fail(&e))? {
            seen = seen.max(entry.revision);
            if let Some(until) = revoked_until(&entry) {
                found.push((entry.key, until));
            }
        }
    }
    Ok((found, seen))
}

/// Until when an entry of the revoked bucket revokes its token (`None`: not a revocation).
fn revoked_until(entry: &kv::Entry) -> Option<u64> {
    if entry.operation != kv::Operation::Put {
        return None;
    }
    std::str::from_utf8(&entry.value).ok()?.parse().ok()
}

fn revoke_here(state: &Services, id: &str, until: u64) {
    if let Some(minter) = &state.config.access.mint
        && let Err(e) = minter.revoke_until(id, until)
    {
        warn!(token = %id, error = %e, "cannot store a cluster revocation");
    }
}

/// Applies the revocations made after revision `seen` of the cluster's bucket until the
/// server stops (a broken watch is opened again from where it stopped).
async fn watch_revocations(bucket: kv::Store, mut seen: u64, state: Weak<Services>) {
    use futures_util::StreamExt;
    loop {
        match bucket.watch_all_from_revision(seen + 1).await {
            Ok(mut entries) => {
                while let Some(Ok(entry)) = entries.next().await {
                    let Some(state) = state.upgrade() else { return };
                    seen = seen.max(entry.revision);
                    if let Some(until) = revoked_until(&entry) {
                        revoke_here(&state, &entry.key, until);
                    }
                }
            }
            Err(e) => warn!(error = %e, "cannot watch the cluster's revoked tokens"),
        }
        if state.strong_count() == 0 {
            return;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// Joins the cluster once the server is ready (everything loaded): from then on, scenes are
/// created cluster-wide, commands reach their scene's owner, and scenes are owned and relayed
/// (the lease loop runs until the server stops).
pub fn start(state: &Arc<Services>, mut conn: Connection) -> Arc<Cluster> {
    let (poses, queued) = tokio::sync::mpsc::channel(drive::POSE_QUEUE);
    let publisher = tokio::spawn(drive::publish(
        conn.client.clone(),
        queued,
        state.metrics.clone(),
    ));
    // Those of the bucket before this server connected are applied already (`startup`).
    let (known, seen) = std::mem::take(&mut conn.revocations);
    for (id, until) in known {
        revoke_here(state, &id, until);
    }
    let revocations = tokio::spawn(watch_revocations(
        conn.revoked.clone(),
        seen,
        Arc::downgrade(state),
    ));
    let cluster = Arc::new(Cluster {
        conn,
        _revocations: Task(revocations),
        state: Arc::downgrade(state),
        owned: Mutex::new(HashMap::new()),
        relays: Mutex::new(HashMap::new()),
        claims: Mutex::new(std::collections::HashSet::new()),
        slots: Mutex::new(HashMap::new()),
        applied: Mutex::new(HashMap::new()),
        assets_seen: Mutex::new(None),
        short_of_assets: Mutex::new(HashMap::new()),
        drivers: Arc::new(Mutex::new(HashMap::new())),
        remote_drives: Arc::new(Mutex::new(HashMap::new())),
        poses,
        _pose_publisher: Task(publisher),
    });
    state.join_cluster(cluster.clone());
    let running = cluster.clone();
    let state_for_takes = state.clone();
    let state = state.clone();
    tokio::spawn(async move {
        if state.readiness.wait().await.is_err() {
            return;
        }
        running.run().await;
    });
    // Takes are shared by a loop of their own: putting a long take must never hold up the
    // lease renewals.
    let sharing = cluster.clone();
    tokio::spawn(async move {
        if state_for_takes.readiness.wait().await.is_err() {
            return;
        }
        sharing.share_takes().await;
    });
    cluster
}

impl Cluster {
    fn state(&self) -> Option<Arc<Services>> {
        self.state.upgrade()
    }

    /// The first server to start on a new NATS makes scene `default` with the built-in avatar
    /// playing `idle`, as a server on its own does on a new data folder (a key `initialised`
    /// in the scenes bucket — not a scene id's hex — records that it was done, so a deleted
    /// `default` stays deleted).
    async fn first_start(&self, state: &Arc<Services>) {
        if !state.config.builtin || state.world.library.get(BUILTIN_ASSET).is_none() {
            return;
        }
        if self
            .conn
            .scenes
            .create("initialised", Bytes::from_static(b"1"))
            .await
            .is_err()
        {
            return;
        }
        let commands = [
            Command::CreateScene {
                scene: SceneId(DEFAULT_SCENE.into()),
            },
            Command::AddAvatar {
                scene: SceneId(DEFAULT_SCENE.into()),
                asset: BUILTIN_ASSET.into(),
                avatar: Some(AvatarId(DEFAULT_AVATAR.into())),
                clip: Some("idle".into()),
                position: None,
                rotation: None,
            },
        ];
        for command in &commands {
            if let Err(e) = control::execute_here(state, command, None).await {
                warn!(error = %e, "could not create the default scene");
                return;
            }
        }
    }

    /// The lease loop: renew what is owned, take over what lost its owner, relay the rest.
    async fn run(self: Arc<Self>) {
        if let Some(state) = self.state() {
            // The cluster's uploads before any scene is owned here: a scene taken over finds
            // its avatars' rigs.
            if let Err(e) = self.sync_assets(&state).await {
                warn!(error = %e, "cannot read the cluster's uploads from NATS");
            }
            self.first_start(&state).await;
        }
        let period = self.conn.lease / 3;
        loop {
            let Some(state) = self.state() else { return };
            if state.readiness.stopped() {
                return;
            }
            self.renew(&state).await;
            self.repair(&state).await;
            if let Err(e) = self.sync_assets(&state).await {
                warn!(error = %e, "cannot read the cluster's uploads from NATS");
            }
            if let Err(e) = self.scan(&state).await {
                warn!(error = %e, "cannot read the cluster's scenes from NATS");
            }
            state.metrics.cluster.scenes(
                lock(&self.owned).len() as u64,
                lock(&self.relays).len() as u64,
            );
            drop(state);
            tokio::time::sleep(period).await;
        }
    }

    /// Renews every lease held; a scene whose lease another server took is given up.
    async fn renew(&self, state: &Arc<Services>) {
        let held: Vec<(SceneId, u64)> = lock(&self.owned)
            .iter()
            .map(|(id, o)| (id.clone(), o.lease_revision))
            .collect();
        for (id, revision) in held {
            let value = Bytes::from(self.conn.node.clone());
            let asked = std::time::Instant::now();
            match self.conn.leases.update(key(&id), value, revision).await {
                Ok(next) => {
                    if let Some(o) = lock(&self.owned).get_mut(&id) {
                        o.lease_revision = next;
                        o.renewed(asked + self.conn.lease);
                    }
                }
                Err(e) if e.kind() == kv::UpdateErrorKind::WrongLastRevision => {
                    // Lapsed (NATS was unreachable for longer than the lease): taken again if
                    // nobody took it meanwhile, given up if somebody did.
                    let value = Bytes::from(self.conn.node.clone());
                    match self.conn.leases.create(key(&id), value).await {
                        Ok(next) => self.retake(state, &id, next).await,
                        Err(_) => {
                            warn!(scene = %id, "lease taken by another server: giving the scene up");
                            self.give_up(&state.world, &id);
                        }
                    }
                }
                // NATS unreachable: keep ticking (local subscribers are served) and retry.
                Err(e) => warn!(scene = %id, error = %e, "cannot renew the lease"),
            }
        }
    }

    /// The lease of a scene ticked here lapsed and was taken again at `revision`. If nobody
    /// changed the scene meanwhile (its snapshot is the one written here), it goes on here
    /// under a new epoch (relays that saw a newer owner's epoch would ignore the old one);
    /// otherwise another server owned it in between, and the scene restarts from the bucket.
    async fn retake(&self, state: &Arc<Services>, id: &SceneId, revision: u64) {
        let ours = lock(&self.owned).get(id).map(|o| o.snapshot_revision);
        let stored = self.conn.scenes.entry(key(id)).await.ok().flatten();
        match (ours, stored, state.world.scene(id)) {
            (Some(ours), Some(entry), Ok(scene)) if entry.revision == ours => {
                info!(scene = %id, "lease had lapsed: taken again");
                if let Some(o) = lock(&self.owned).remove(id) {
                    o.stop();
                }
                self.adopt(state, &scene, revision, ours);
            }
            _ => {
                warn!(scene = %id, "the scene changed elsewhere while its lease had lapsed: restarting it from the cluster's copy");
                self.give_up(&state.world, id);
                self.conn.leases.delete(key(id)).await.ok();
            }
        }
    }

    /// Stops ticking a scene another server now owns: it becomes a relayed scene here (the
    /// next look relays it), and its subscribers here stay subscribed and get the new owner's
    /// frames, from a keyframe.
    fn give_up(&self, world: &crate::world::World, id: &SceneId) {
        if let Some(o) = lock(&self.owned).remove(id) {
            o.stop();
        }
        lock(&self.slots).remove(id);
        if let Ok(scene) = world.scene(id) {
            scene.set_tap(None);
        }
        if world.demote(id).is_err() {
            world.delete_scene(id).ok();
        }
    }

    /// Every scene of the cluster: take over those without a lease, relay the others.
    async fn scan(self: &Arc<Self>, state: &Arc<Services>) -> Result<(), Error> {
        let mut keys = self
            .conn
            .scenes
            .keys()
            .await
            .map_err(|e| unavailable("cannot list scenes", &e))?;
        let mut ids = Vec::new();
        while let Some(k) = keys.next().await {
            let k = k.map_err(|e| unavailable("cannot list scenes", &e))?;
            if let Some(id) = unkey(&k) {
                ids.push(id);
            }
        }
        for id in &ids {
            if lock(&self.owned).contains_key(id) || lock(&self.claims).contains(id) {
                continue;
            }
            // One lease that cannot be read is skipped (the next scan tries again), not the
            // rest of the scan: the other scenes are relayed or taken over, and those gone are
            // dropped, all the same.
            let lease = match self.conn.leases.entry(key(id)).await {
                Ok(lease) => lease,
                Err(e) => {
                    warn!(scene = %id, error = %e, "cannot read a lease");
                    continue;
                }
            };
            match lease {
                Some(entry) if entry.operation == kv::Operation::Put => {
                    let owner = String::from_utf8_lossy(&entry.value).into_owned();
                    if owner == self.conn.node {
                        // Ours from before a restart of this process: it lapses by itself,
                        // then a scan takes it over from its snapshot.
                        continue;
                    }
                    self.relay(state, id, owner, entry.revision);
                }
                _ => match self
                    .conn
                    .leases
                    .create(key(id), Bytes::from(self.conn.node.clone()))
                    .await
                {
                    Ok(revision) => self.take_over(state, id, revision).await,
                    Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {}
                    Err(e) => warn!(scene = %id, error = %e, "cannot take a lease"),
                },
            }
        }
        // Scenes gone from the cluster (deleted on a server whose message was missed).
        let gone: Vec<SceneId> = lock(&self.relays)
            .keys()
            .filter(|id| !ids.contains(id))
            .cloned()
            .collect();
        for id in gone {
            self.drop_relay(state, &id);
        }
        Ok(())
    }

    /// A scene without a lease, now ours: restored from its snapshot and ticked here.
    async fn take_over(self: &Arc<Self>, state: &Arc<Services>, id: &SceneId, revision: u64) {
        let mut snapshot_revision = 0;
        let file = match self.conn.scenes.entry(key(id)).await {
            Ok(Some(entry)) if entry.operation == kv::Operation::Put => {
                snapshot_revision = entry.revision;
                serde_json::from_slice::<serde_json::Value>(&entry.value)
                    .map_err(|e| e.to_string())
                    .and_then(|v| snapshot::parse_lenient(&v))
            }
            Ok(_) => Err("no snapshot".into()),
            Err(e) => Err(e.to_string()),
        };
        let mut file = match file {
            Ok((file, dropped)) => {
                for d in dropped {
                    warn!(scene = %id, "{d}");
                }
                file
            }
            Err(e) => {
                warn!(scene = %id, error = %e, "cannot take the scene over: its snapshot is unusable");
                self.conn.leases.delete(key(id)).await.ok();
                return;
            }
        };
        // Restoring without an avatar's rig would drop the avatar, and the next snapshot
        // written here would lose it for good: the scene waits for a server that has them.
        let missing = Self::missing_assets(&state.world, &file);
        if !missing.is_empty() {
            let again = lock(&self.short_of_assets).insert(id.clone(), missing.clone());
            if again.as_ref() != Some(&missing) {
                warn!(scene = %id, ?missing, "not taking the scene over: this server lacks assets its avatars use");
            }
            self.conn.leases.delete(key(id)).await.ok();
            return;
        }
        // A replay's take is read here first (its rigs must be here too).
        let resumable = match self.prepare_resume(state, &mut file).await {
            Ok(r) => r,
            Err(e) => {
                warn!(scene = %id, error = %e, "not taking the replay scene over yet");
                self.conn.leases.delete(key(id)).await.ok();
                return;
            }
        };
        lock(&self.short_of_assets).remove(id);
        let now = crate::scene::unix_micros();
        let scene = if state.world.scene(id).is_ok_and(|s| s.is_relay()) {
            match state.world.promote(id) {
                Ok(scene) => {
                    snapshot::restore_into(&state.world, &file, now);
                    Ok(scene)
                }
                Err(e) => Err(e),
            }
        } else {
            snapshot::restore(&state.world, &file, now).and_then(|()| state.world.scene(id))
        };
        // The relay is forgotten only now that the avatars are restored: until then the scene
        // is listed (and commands routed) as the previous owner's, never as ours and empty.
        // Its task is harmless meanwhile: the feed no longer takes relayed frames, and the
        // lease (ours) is the only one its messages are believed from.
        if let Some(r) = lock(&self.relays).remove(id) {
            r.stop();
        }
        if let (Ok(scene), Some(r)) = (&scene, resumable) {
            self.resume(state, scene, r, file.saved_us).await;
        }
        match scene {
            Ok(scene) => {
                // Written back before it is ticked here: from now on the previous owner's
                // writes fail (fencing), so whatever it still applies is never acknowledged.
                let recent: crate::scene::answers::Recent = file.recent.iter().cloned().collect();
                let slot = self.slot(id);
                let mut table = slot.lock().await;
                match self
                    .fence(&state.world, id, snapshot_revision, &recent)
                    .await
                {
                    Ok(fenced) => {
                        *table = recent;
                        state.metrics.cluster.takeover();
                        info!(scene = %id, avatars = file.avatars.len(), "took the scene over");
                        self.adopt(state, &scene, revision, fenced);
                    }
                    Err(e) => {
                        drop(table);
                        // The previous owner wrote meanwhile: the next look starts again
                        // from its newer snapshot.
                        info!(scene = %id, error = %e, "the scene changed while being taken over: trying again at the next look");
                        self.give_up(&state.world, id);
                        self.conn.leases.delete(key(id)).await.ok();
                    }
                }
            }
            Err(e) => {
                warn!(scene = %id, error = %e, "cannot take the scene over");
                self.conn.leases.delete(key(id)).await.ok();
            }
        }
    }

    /// Sends a request to scene `id`'s owner and waits for the answer.
    async fn request(
        &self,
        id: &SceneId,
        kind: &str,
        idempotency_key: Option<&str>,
        payload: Bytes,
    ) -> Result<Bytes, Error> {
        let mut headers = async_nats::HeaderMap::new();
        headers.insert(KIND, kind);
        if let Some(k) = idempotency_key {
            headers.insert(IDEMPOTENCY_KEY, k);
        }
        let state = self.state();
        if let Some(s) = &state {
            s.metrics.cluster.published(payload.len());
        }
        let reply = self
            .conn
            .client
            .request_with_headers(request_subject(id), headers, payload)
            .await
            .map_err(|e| relay_failed(id, &e))?;
        if let Some(s) = &state {
            s.metrics.cluster.received(reply.payload.len());
        }
        Ok(reply.payload)
    }

    /// The scene a command acts on, when it is relayed here.
    fn relayed_target(&self, command: &Command) -> Option<SceneId> {
        let state = self.state()?;
        let scene = match command.scene() {
            Some(id) => state.world.scene(id).ok()?,
            None => state.world.find_avatar(command.avatar()?).ok()?,
        };
        scene.is_relay().then(|| scene.id.clone())
    }
}

impl crate::state::Cluster for Cluster {
    fn forward<'a>(
        &'a self,
        command: &'a Command,
        idempotency_key: Option<&'a str>,
    ) -> Option<BoxFuture<'a, Result<CommandResult, Error>>> {
        if matches!(command, Command::ListScenes) {
            return None;
        }
        let id = self.relayed_target(command)?;
        Some(Box::pin(async move {
            let payload = serde_json::to_vec(command)
                .map_err(|e| Error::internal("cannot serialise the command", &e))?;
            let reply = self
                .request(&id, "command", idempotency_key, Bytes::from(payload))
                .await?;
            match serde_json::from_slice::<Reply>(&reply) {
                Ok(Reply::Ok(result)) => Ok(result),
                Ok(Reply::Error(wire)) => Err(Error::Remote(wire)),
                Err(e) => Err(Error::internal(
                    "unreadable answer from the scene's server",
                    &e,
                )),
            }
        }))
    }

    fn commit<'a>(
        &'a self,
        command: &'a Command,
        scene: &'a SceneId,
        idempotency_key: Option<&'a str>,
        run: BoxFuture<'a, Result<CommandResult, crate::state::RunError>>,
    ) -> BoxFuture<'a, Result<CommandResult, Error>> {
        Box::pin(async move {
            let Some(state) = self.state() else {
                return Err(Error::Unavailable("the server is stopping".into()));
            };
            self.commit_command(&state, command, scene, idempotency_key, run)
                .await
        })
    }

    fn listing(&self, local: Vec<SceneInfo>) -> BoxFuture<'_, Vec<SceneInfo>> {
        Box::pin(async move {
            // The owners are asked all at once: one round trip, not one per scene.
            let each = local.into_iter().map(|mut info| async move {
                let owner = lock(&self.relays).get(&info.scene).map(|r| r.owner.clone());
                match owner {
                    None => info.owner = Some(self.conn.node.clone()),
                    Some(owner) => {
                        // The owner knows the avatars and what they play.
                        let asked = self.request(&info.scene, "info", None, Bytes::new()).await;
                        match asked.and_then(|b| {
                            serde_json::from_slice::<SceneInfo>(&b)
                                .map_err(|e| Error::internal("info", &e))
                        }) {
                            Ok(remote) => info.avatars = remote.avatars,
                            Err(e) => {
                                warn!(scene = %info.scene, error = %e, "listed without its avatars");
                            }
                        }
                        info.owner = Some(owner);
                    }
                }
                info
            });
            futures_util::future::join_all(each).await
        })
    }

    fn degraded(&self) -> bool {
        self.conn.lost.load(Ordering::SeqCst)
    }

    fn revoke_token<'a>(&'a self, id: &'a str, until: u64) -> BoxFuture<'a, Result<(), Error>> {
        Box::pin(async move {
            self.conn
                .revoked
                .put(id, until.to_string().into())
                .await
                .map(|_| ())
                .map_err(|e| unavailable("storing the revocation in the cluster", &e))
        })
    }

    fn share_asset<'a>(
        &'a self,
        name: &'a str,
        files: &'a posecast_rigs::import::files::FileSet,
        options: &'a posecast_rigs::rig::PipelineOptions,
    ) -> BoxFuture<'a, Result<(), Error>> {
        Box::pin(self.share(name, files, options))
    }

    fn unshare_asset<'a>(&'a self, name: &'a str) -> BoxFuture<'a, ()> {
        Box::pin(self.unshare(name))
    }

    fn unshare_recording<'a>(&'a self, rig: &'a str, clip: &'a str) -> BoxFuture<'a, ()> {
        Box::pin(self.unshare_recording(rig, clip))
    }

    fn shared_asset<'a>(
        &'a self,
        name: &'a str,
    ) -> BoxFuture<'a, Result<Option<posecast_rigs::import::files::FileSet>, Error>> {
        Box::pin(self.shared_files(name))
    }

    fn share_recording<'a>(
        &'a self,
        rig: &'a str,
        clip: &'a str,
        glb: Vec<u8>,
    ) -> BoxFuture<'a, Result<(), Error>> {
        Box::pin(self.put_recording(rig, clip, glb))
    }

    fn shared_takes(&self) -> BoxFuture<'_, Result<Vec<posecast_proto::command::TakeInfo>, Error>> {
        Box::pin(async move {
            let mut takes: Vec<_> = self
                .bucket_takes()
                .await?
                .into_values()
                .map(|(t, _)| t)
                .collect();
            takes.sort_by_key(|t| (t.started_us, t.take.clone()));
            Ok(takes)
        })
    }

    fn has_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>> {
        Box::pin(async move { Ok(self.take_object(take).await?.is_some()) })
    }

    fn share_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<(), Error>> {
        Box::pin(async move {
            let Some(state) = self.state() else {
                return Err(Error::Unavailable("the server is stopping".into()));
            };
            self.put_take(&state, take).await
        })
    }

    fn fetch_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>> {
        Box::pin(async move {
            let Some(state) = self.state() else {
                return Err(Error::Unavailable("the server is stopping".into()));
            };
            self.fetch_take(&state, take).await
        })
    }

    fn delete_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>> {
        Box::pin(self.delete_take(take))
    }

    fn drive<'a>(
        &'a self,
        scene: &'a SceneId,
        conn: u64,
        command: &'a Command,
    ) -> BoxFuture<'a, Result<CommandResult, Error>> {
        Box::pin(self.drive_remote(scene, conn, command))
    }

    fn pose(&self, scene: &SceneId, conn: u64, pose: Vec<u8>) {
        self.send_pose(scene, conn, Bytes::from(pose));
    }

    fn release(&self, scene: &SceneId, conn: u64) {
        self.end_drives(scene, conn);
    }
}

/// Stops a task when its owner is dropped.
#[derive(Debug)]
struct Task(JoinHandle<()>);

impl Drop for Task {
    fn drop(&mut self) {
        self.0.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keys are valid NATS key and subject tokens, and give the id back.
    #[test]
    fn keys_round_trip_and_use_only_hex() {
        for id in ["default", "a.b c/*>", "ünï", ""] {
            let id = SceneId(id.into());
            let k = key(&id);
            assert!(k.bytes().all(|b| b.is_ascii_hexdigit()), "{k}");
            assert_eq!(unkey(&k), Some(id));
        }
        assert_eq!(key(&SceneId("a.".into())), "612e");
        assert_eq!(unkey("6"), None);
        assert_eq!(unkey("zz"), None);
    }
}
