//! Live driving through the cluster: a connection on a server that relays a scene drives an
//! avatar of it through the scene's owner, as it would on the owner.
//!
//! The relaying server sends `drive` to the owner (request kind `drive` on the scene's
//! request subject, header `Posecast-Driver: <node>/<connection>`); the owner runs it for a
//! driver of its own standing for that connection ([`Drives`]) and answers as for a command.
//! The relaying server then checks each pose of the connection itself (driver, rate, joints,
//! values, morph weights: errors go back to the client at once) and passes it on as a binary
//! pose on `posecast.scene.<hex>.pose`, in order through one bounded queue; the owner applies
//! it as a pose of that driver ([`Drives::relayed_pose`]: checked again, a refusal dropped and
//! logged, as the client has its answer already). Its weights are slots as
//! `Avatar::morph_channel` numbers them: morph channels, then the expressions the avatar's
//! file defines, to which the relaying server resolved a JSON pose's names (`live::remote`).
//! `leave` on the same subject (the connection closed) releases the avatars as the `drive`
//! asked (back to the clip, or holding the last pose); a relaying server that dies without
//! saying so leaves them to the drive timeout.
//!
//! When the scene changes owner, the relaying server sends the `drive` again to the new
//! owner before its next pose (poses in between are dropped); when it takes the scene over
//! itself, it runs the `drive` for the connection here and applies the poses directly.

use super::{Cluster, KIND, Reply, key, lock, request_subject, unavailable};
use crate::live::Drives;
use crate::metrics::Metrics;
use crate::state::Services;
use bytes::Bytes;
use futures_util::StreamExt;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{ErrorCode, ProtocolError, SceneId};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use tokio::sync::mpsc;
use tracing::{debug, warn};

/// Header naming the driver (`<node>/<connection>`) of a remote `drive`, pose or leave.
const DRIVER: &str = "Posecast-Driver";
/// Poses and leaves waiting to be published (about 8 s of one driver at 120 Hz).
pub(super) const POSE_QUEUE: usize = 1024;

/// Where the relaying servers send a scene's poses.
fn pose_subject(id: &SceneId) -> String {
    format!("posecast.scene.{}.pose", key(id))
}

/// The remote drivers of the scenes ticked here, by name.
pub(super) type Drivers = Arc<Mutex<HashMap<String, Drives>>>;

/// One pose or leave to publish: subject, kind, driver, payload.
pub(super) type Outgoing = (String, &'static str, String, Bytes);

/// A drive of a connection here, run by a scene's owner: the command, and the owner that
/// runs it (`None` while it is being sent again to a new owner).
#[derive(Debug)]
pub(super) struct RemoteDrive {
    command: Command,
    owner: Option<String>,
}

/// This server's connections' drives run elsewhere, by scene and connection.
pub(super) type RemoteDrives = Arc<Mutex<HashMap<(SceneId, u64), RemoteDrive>>>;

/// Sends `drive` to scene `scene`'s owner for `driver`; the owner's answer.
async fn request_drive(
    client: &async_nats::Client,
    scene: &SceneId,
    driver: &str,
    command: &Command,
    metrics: Option<&Metrics>,
) -> Result<CommandResult, Error> {
    let payload = serde_json::to_vec(command)
        .map_err(|e| Error::internal("cannot serialise the command", &e))?;
    let mut headers = async_nats::HeaderMap::new();
    headers.insert(KIND, "drive");
    headers.insert(DRIVER, driver);
    if let Some(m) = metrics {
        m.cluster.published(payload.len());
    }
    let reply = client
        .request_with_headers(request_subject(scene), headers, Bytes::from(payload))
        .await
        .map_err(|e| {
            unavailable(
                &format!("the server ticking scene {scene} did not answer (try again)"),
                &e,
            )
        })?;
    if let Some(m) = metrics {
        m.cluster.received(reply.payload.len());
    }
    match serde_json::from_slice::<Reply>(&reply.payload) {
        Ok(Reply::Ok(result)) => Ok(result),
        Ok(Reply::Error(wire)) => Err(Error::Remote(wire)),
        Err(e) => Err(Error::internal(
            "unreadable answer from the scene's server",
            &e,
        )),
    }
}

/// Publishes the queued poses and leaves in order until the queue closes.
pub(super) async fn publish(
    client: async_nats::Client,
    mut rx: mpsc::Receiver<Outgoing>,
    metrics: Arc<Metrics>,
) {
    while let Some((subject, kind, driver, payload)) = rx.recv().await {
        let mut headers = async_nats::HeaderMap::new();
        headers.insert(KIND, kind);
        headers.insert(DRIVER, driver.as_str());
        let n = payload.len();
        match client.publish_with_headers(subject, headers, payload).await {
            Ok(()) => metrics.cluster.published(n),
            Err(e) => debug!(error = %e, "pose not published"),
        }
    }
}

/// Applies the poses and leaves of scene `id`'s remote drivers until stopped.
pub(super) async fn serve_poses(
    client: async_nats::Client,
    id: SceneId,
    drivers: Drivers,
    state: Weak<Services>,
) {
    let mut poses = match client.subscribe(pose_subject(&id)).await {
        Ok(s) => s,
        Err(e) => {
            warn!(scene = %id, error = %e, "cannot take live poses for the scene");
            return;
        }
    };
    while let Some(msg) = poses.next().await {
        let Some(state) = state.upgrade() else { return };
        state.metrics.cluster.received(msg.payload.len());
        let header = |name: &str| {
            msg.headers
                .as_ref()
                .and_then(|h| h.get(name))
                .map(|v| v.as_str().to_owned())
                .unwrap_or_default()
        };
        let driver = header(DRIVER);
        match header(KIND).as_str() {
            "pose" => {
                let mut drivers = lock(&drivers);
                let Some(drives) = drivers.get_mut(&driver) else {
                    debug!(scene = %id, driver, "pose of an unknown driver");
                    continue;
                };
                // Checked where the client is; a pose refused here (the drive ended, a rate
                // seen differently, a weight's slot the avatar no longer has) is dropped: the
                // driver's connection is elsewhere and goes on.
                if let Err(e) = drives.relayed_pose(&msg.payload) {
                    debug!(scene = %id, driver, error = %e, "remote pose not applied");
                }
            }
            "leave" => {
                let removed = lock(&drivers).remove(&driver);
                if let Some(mut drives) = removed {
                    drives.leave(&state);
                }
            }
            _ => {}
        }
    }
}

/// Answers a `drive` request: runs it for the driver standing for the requesting connection.
pub(super) fn answer_drive(
    state: &Services,
    drivers: &Drivers,
    driver: String,
    payload: &[u8],
) -> Reply {
    let command = match serde_json::from_slice::<Command>(payload) {
        Ok(command @ Command::Drive { .. }) => command,
        Ok(_) => {
            return Reply::Error(ProtocolError::new(
                ErrorCode::BadMessage,
                "only drive is sent as a drive request",
            ));
        }
        Err(e) => {
            return Reply::Error(ProtocolError::new(
                ErrorCode::BadMessage,
                format!("not a valid command: {e}"),
            ));
        }
    };
    let mut drivers = lock(drivers);
    // Drivers whose drives all ended (released, timed out, their relay gone) are forgotten.
    drivers.retain(|_, d| d.is_driving());
    let drives = drivers.entry(driver.clone()).or_insert_with(|| {
        let mut drives = Drives::new(state.new_driver_id());
        // Presence: the driver as the cluster names it (its server and connection).
        drives.identify(posecast_proto::command::Driver {
            name: driver,
            via: posecast_proto::command::DriveVia::Cluster,
        });
        drives
    });
    match drives.command(state, &command) {
        Some(Ok(result)) => Reply::Ok(result),
        Some(Err(e)) => Reply::Error(e.into()),
        None => Reply::Error(ProtocolError::new(ErrorCode::BadMessage, "not a drive")),
    }
}

impl Cluster {
    fn driver(&self, conn: u64) -> String {
        format!("{}/{conn}", self.conn.node)
    }

    pub(super) async fn drive_remote(
        &self,
        scene: &SceneId,
        conn: u64,
        command: &Command,
    ) -> Result<CommandResult, Error> {
        // An owner not known yet counts as another one: the next pose sends `drive` again.
        let owner = Some(
            lock(&self.relays)
                .get(scene)
                .map(|r| r.owner.clone())
                .unwrap_or_default(),
        );
        let state = self.state();
        let result = request_drive(
            &self.conn.client,
            scene,
            &self.driver(conn),
            command,
            state.as_ref().map(|s| &*s.metrics),
        )
        .await;
        if result.is_ok() {
            lock(&self.remote_drives).insert(
                (scene.clone(), conn),
                RemoteDrive {
                    command: command.clone(),
                    owner,
                },
            );
        }
        result
    }

    /// Passes a pose of connection `conn` on to whoever ticks `scene` now: published for its
    /// owner, sent after the `drive` again when the owner changed, applied here when this
    /// server took the scene over.
    pub(super) fn send_pose(&self, scene: &SceneId, conn: u64, pose: Bytes) {
        let Some(state) = self.state() else { return };
        let driver = self.driver(conn);
        let key = (scene.clone(), conn);
        if lock(&self.owned).contains_key(scene) {
            let command = lock(&self.remote_drives)
                .get(&key)
                .map(|r| r.command.clone());
            let mut drivers = lock(&self.drivers);
            if !drivers.contains_key(&driver)
                && let Some(command) = command
            {
                let payload = serde_json::to_vec(&command).unwrap_or_default();
                drop(drivers);
                if let Reply::Error(e) =
                    answer_drive(&state, &self.drivers, driver.clone(), &payload)
                {
                    warn!(scene = %scene, driver, error = ?e, "cannot go on driving after the takeover");
                }
                drivers = lock(&self.drivers);
            }
            if let Some(drives) = drivers.get_mut(&driver)
                && let Err(e) = drives.relayed_pose(&pose)
            {
                debug!(scene = %scene, driver, error = %e, "pose not applied");
            }
            return;
        }
        let current = lock(&self.relays).get(scene).map(|r| r.owner.clone());
        let mut remote = lock(&self.remote_drives);
        let Some(drive) = remote.get_mut(&key) else {
            return;
        };
        if current.is_some() && drive.owner == current {
            drop(remote);
            self.publish_pose(scene, "pose", driver, pose, &state);
            return;
        }
        let (Some(new_owner), Some(_)) = (current, drive.owner.take()) else {
            // Being sent to the new owner already, or no owner known right now: dropped.
            return;
        };
        let command = drive.command.clone();
        drop(remote);
        let client = self.conn.client.clone();
        let remote = self.remote_drives.clone();
        let scene = scene.clone();
        tokio::spawn(async move {
            match request_drive(&client, &scene, &driver, &command, None).await {
                Ok(_) => {
                    if let Some(d) = lock(&remote).get_mut(&(scene.clone(), conn)) {
                        d.owner = Some(new_owner);
                    }
                }
                Err(e) => {
                    warn!(scene = %scene, driver, error = %e, "cannot go on driving with the scene's new owner");
                    lock(&remote).remove(&(scene, conn));
                }
            }
        });
    }

    /// Connection `conn` left: its drives of `scene` end where the scene is ticked.
    pub(super) fn end_drives(&self, scene: &SceneId, conn: u64) {
        let Some(state) = self.state() else { return };
        lock(&self.remote_drives).remove(&(scene.clone(), conn));
        let driver = self.driver(conn);
        if lock(&self.owned).contains_key(scene) {
            let removed = lock(&self.drivers).remove(&driver);
            if let Some(mut drives) = removed {
                drives.leave(&state);
            }
            return;
        }
        self.publish_pose(scene, "leave", driver, Bytes::new(), &state);
    }

    fn publish_pose(
        &self,
        scene: &SceneId,
        kind: &'static str,
        driver: String,
        payload: Bytes,
        state: &Services,
    ) {
        if self
            .poses
            .try_send((pose_subject(scene), kind, driver, payload))
            .is_err()
        {
            state.metrics.cluster.publish_dropped();
        }
    }
}

/// The driver a remote driver's request names.
pub(super) fn driver_of(msg: &async_nats::Message) -> String {
    msg.headers
        .as_ref()
        .and_then(|h| h.get(DRIVER))
        .map(|v| v.as_str().to_owned())
        .unwrap_or_default()
}
