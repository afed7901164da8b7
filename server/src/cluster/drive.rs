//! Live driving through the cluster: a connection on a server that relays a scene drives an
//! avatar of it through the scene's owner, as it would on the owner.
//!
//! The relaying server sends `drive` to the owner (request kind `drive` on the scene's
//! request subject, header `Posecast-Driver: <node>/<connection>`); the owner runs it for a
//! driver of its own standing for that connection ([`Drives`]) and answers as for a command.
//! The relaying server then checks each pose of the connection itself (driver, rate, joints,
//! values: errors go back to the client at once) and passes it on as a binary pose on
//! `posecast.scene.<hex>.pose`, in order through one bounded queue; the owner applies it as a
//! pose of that driver. `leave` on the same subject (the connection closed) releases the
//! avatars as the `drive` asked (back to the clip, or holding the last pose); a relaying
//! server that dies without saying so leaves them to the drive timeout.

use super::{Cluster, KIND, Reply, key, lock, request_subject, unavailable};
use crate::error::Error;
use crate::live::Drives;
use crate::metrics::Metrics;
use crate::state::AppState;
use bytes::Bytes;
use futures_util::StreamExt;
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
    state: Weak<AppState>,
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
                // seen differently) is dropped.
                if let Err(e) = drives.binary_pose(&state, &msg.payload) {
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
    state: &AppState,
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
    let drives = drivers
        .entry(driver)
        .or_insert_with(|| Drives::new(state.new_driver_id()));
    match drives.command(state, &command) {
        Some(Ok(result)) => Reply::Ok(result.to_value()),
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
        let payload = serde_json::to_vec(command)
            .map_err(|e| Error::internal("cannot serialise the command", &e))?;
        let mut headers = async_nats::HeaderMap::new();
        headers.insert(KIND, "drive");
        headers.insert(DRIVER, self.driver(conn).as_str());
        let state = self.state();
        if let Some(s) = &state {
            s.metrics.cluster.published(payload.len());
        }
        let reply = self
            .conn
            .client
            .request_with_headers(request_subject(scene), headers, Bytes::from(payload))
            .await
            .map_err(|e| {
                unavailable(
                    &format!("the server ticking scene {scene} did not answer (try again)"),
                    &e,
                )
            })?;
        if let Some(s) = &state {
            s.metrics.cluster.received(reply.payload.len());
        }
        match serde_json::from_slice::<Reply>(&reply.payload) {
            Ok(Reply::Ok(value)) => serde_json::from_value(value)
                .map_err(|e| Error::internal("unreadable answer from the scene's server", &e)),
            Ok(Reply::Error(wire)) => Err(Error::Remote(wire)),
            Err(e) => Err(Error::internal(
                "unreadable answer from the scene's server",
                &e,
            )),
        }
    }

    pub(super) fn send_pose(&self, scene: &SceneId, conn: u64, kind: &'static str, pose: Bytes) {
        let item = (pose_subject(scene), kind, self.driver(conn), pose);
        if self.poses.try_send(item).is_err()
            && let Some(state) = self.state()
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
