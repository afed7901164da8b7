//! [`Driver`]: drives avatars live over its own websocket (no subscription).
//!
//! ```no_run
//! # async fn demo() -> Result<(), posecast_client::net::ClientError> {
//! use posecast_client::net::Driver;
//! use posecast_proto::msg::AvatarId;
//! let driver = Driver::connect("ws://127.0.0.1:8080/ws", Some("token".into())).await?;
//! let avatar = AvatarId("avatar".into());
//! let info = driver.drive(&avatar, None, None).await?;
//! driver.send_pose(&avatar, [("l_elbow".to_string(), [0.0, 0.0, 0.38, 0.92])], None, None).await?;
//! # let _ = info; Ok(()) }
//! ```
//!
//! Poses are not acknowledged; the server's errors (bad pose, rate limited, …) arrive on
//! [`Driver::next_error`].
//!
//! **Pacing.** The server takes at most [`DriveInfo::max_rate_hz`] poses a second per driven
//! avatar (a token bucket with a small burst) and refuses the rest with `rate_limited`. The
//! driver spaces each avatar's poses at that rate: a pose sent early waits for its turn (the
//! send returns later) instead of being refused — so a capture loop that bursts to catch up
//! after a stall, or one simply faster than the server's budget, loses nothing to the limit.
//! [`Driver::set_pacing`] turns it off.

use super::client::ClientError;
use futures_util::stream::SplitSink;
use futures_util::{SinkExt, StreamExt};
use posecast_proto::command::{Command, CommandResult, DriveInfo, OnRelease};
use posecast_proto::live::{BinaryPose, MAX_RATE_HZ};
use posecast_proto::msg::{
    AvatarId, ClientMsg, Encoding, PROTOCOL_VERSION, ProtocolError, ServerMsg,
};
use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};
use tokio_tungstenite::tungstenite::Message;

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;
type Pending = Arc<Mutex<HashMap<u64, oneshot::Sender<Result<CommandResult, ProtocolError>>>>>;

/// How many server errors wait unread before the oldest are dropped.
const ERROR_BACKLOG: usize = 1024;

/// A live driver's connection.
#[derive(Debug)]
pub struct Driver {
    sink: tokio::sync::Mutex<SplitSink<Ws, Message>>,
    pending: Pending,
    errors: tokio::sync::Mutex<mpsc::Receiver<ProtocolError>>,
    next_id: AtomicU64,
    reader: tokio::task::JoinHandle<()>,
    pacing: Mutex<Pacing>,
}

/// When each avatar's next pose may go ([`Driver`]'s pacing).
#[derive(Debug)]
struct Pacing {
    on: bool,
    /// Avatar numbers of the avatars driven through [`Driver::drive`] (binary poses name
    /// avatars by number).
    nums: HashMap<AvatarId, u32>,
    /// Per avatar (by number when known, else by id): the interval and the next free slot.
    slots: HashMap<PaceKey, (Duration, tokio::time::Instant)>,
    /// The interval of avatars whose budget no drive answer gave.
    default_interval: Duration,
}

#[derive(Debug, Clone, PartialEq, Eq, Hash)]
enum PaceKey {
    Num(u32),
    Id(AvatarId),
}

impl Pacing {
    fn new() -> Self {
        Self {
            on: true,
            nums: HashMap::new(),
            slots: HashMap::new(),
            default_interval: interval_of(MAX_RATE_HZ),
        }
    }

    /// Reserves the avatar's next slot: the time its pose may be sent (now or later).
    fn reserve(&mut self, key: PaceKey, now: tokio::time::Instant) -> Option<tokio::time::Instant> {
        if !self.on {
            return None;
        }
        let key = match key {
            PaceKey::Id(id) => self
                .nums
                .get(&id)
                .map_or(PaceKey::Id(id), |&n| PaceKey::Num(n)),
            key => key,
        };
        let default = self.default_interval;
        let (interval, next) = self.slots.entry(key).or_insert((default, now));
        let slot = (*next).max(now);
        *next = slot + *interval;
        Some(slot)
    }
}

/// Longest spacing pacing keeps, whatever budget a server announces (a rate of 1e-30 a second
/// must not overflow the clock).
const MAX_INTERVAL: Duration = Duration::from_secs(60);

/// The spacing of `rate` poses a second, at most [`MAX_INTERVAL`] (a non-positive or
/// non-finite rate: none).
fn interval_of(rate_hz: f32) -> Duration {
    if rate_hz.is_finite() && rate_hz > 0.0 {
        Duration::try_from_secs_f64(1.0 / f64::from(rate_hz))
            .map_or(MAX_INTERVAL, |d| d.min(MAX_INTERVAL))
    } else {
        Duration::ZERO
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

fn send_failed(e: impl std::fmt::Display) -> ClientError {
    ClientError::Connect {
        url: String::new(),
        message: e.to_string(),
    }
}

impl Driver {
    /// Connects and says hello with `token` (a control token that may command the avatars to
    /// drive); waits up to 10 s for the welcome.
    ///
    /// # Errors
    /// The connection fails or the server refuses the hello.
    pub async fn connect(url: &str, token: Option<String>) -> Result<Self, ClientError> {
        let connect_err = |e: &dyn std::fmt::Display| ClientError::Connect {
            url: url.to_owned(),
            message: e.to_string(),
        };
        // TCP_NODELAY: a pose is a small write every 8–17 ms, and Nagle's algorithm would hold
        // one back until the server acknowledges the previous (up to a delayed-ACK time).
        let (ws, _) = tokio_tungstenite::connect_async_with_config(url, None, true)
            .await
            .map_err(|e| connect_err(&e))?;
        let (mut sink, mut stream) = ws.split();
        let hello = ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding: Encoding::Json,
            token,
            client: Some("posecast-driver".into()),
        };
        let text = serde_json::to_string(&hello).map_err(|e| connect_err(&e))?;
        sink.send(Message::Text(text.into()))
            .await
            .map_err(|e| connect_err(&e))?;
        let welcome = tokio::time::timeout(Duration::from_secs(10), async {
            while let Some(Ok(m)) = stream.next().await {
                if let Message::Text(t) = m {
                    return serde_json::from_str::<ServerMsg>(t.as_str()).ok();
                }
            }
            None
        })
        .await
        .map_err(|_| ClientError::Timeout("welcome"))?;
        match welcome {
            Some(ServerMsg::Welcome { .. }) => {}
            Some(ServerMsg::Error(e)) => return Err(ClientError::Server(e)),
            _ => return Err(ClientError::Closed),
        }
        let pending: Pending = Arc::default();
        let (errors_tx, errors) = mpsc::channel(ERROR_BACKLOG);
        let reader = tokio::spawn(read(stream, pending.clone(), errors_tx));
        Ok(Self {
            sink: tokio::sync::Mutex::new(sink),
            pending,
            errors: tokio::sync::Mutex::new(errors),
            next_id: AtomicU64::new(1),
            reader,
            pacing: Mutex::new(Pacing::new()),
        })
    }

    /// Turns pacing (see the module doc) on (the default) or off: off, every pose goes at
    /// once and those past the server's budget are refused with `rate_limited`.
    pub fn set_pacing(&self, on: bool) {
        lock(&self.pacing).on = on;
    }

    /// Waits for the avatar's next pose slot.
    async fn pace(&self, key: PaceKey) {
        let slot = lock(&self.pacing).reserve(key, tokio::time::Instant::now());
        if let Some(slot) = slot {
            tokio::time::sleep_until(slot).await;
        }
    }

    async fn send_text(&self, msg: &ClientMsg) -> Result<(), ClientError> {
        let text = serde_json::to_string(msg).map_err(send_failed)?;
        self.sink
            .lock()
            .await
            .send(Message::Text(text.into()))
            .await
            .map_err(send_failed)
    }

    /// Sends a command and waits (up to 10 s) for its answer.
    ///
    /// # Errors
    /// The server's typed error, a timeout, or a closed connection.
    pub async fn command(&self, command: Command) -> Result<CommandResult, ClientError> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let (tx, rx) = oneshot::channel();
        lock(&self.pending).insert(id, tx);
        self.send_text(&ClientMsg::Command {
            id,
            command,
            idempotency_key: None,
        })
        .await?;
        match tokio::time::timeout(Duration::from_secs(10), rx).await {
            Ok(Ok(result)) => result.map_err(ClientError::Server),
            Ok(Err(_)) => Err(ClientError::Closed),
            Err(_) => {
                lock(&self.pending).remove(&id);
                Err(ClientError::Timeout("command acknowledgement"))
            }
        }
    }

    /// Becomes `avatar`'s driver; poses name `source`'s joints (absent: the avatar's rig).
    ///
    /// # Errors
    /// `conflict` (another driver), `forbidden`, unknown avatar or asset, …
    pub async fn drive(
        &self,
        avatar: &AvatarId,
        source: Option<&str>,
        on_release: Option<OnRelease>,
    ) -> Result<DriveInfo, ClientError> {
        let result = self
            .command(Command::Drive {
                avatar: avatar.clone(),
                source: source.map(str::to_owned),
                on_release,
                joints: None,
                trackers: None,
                legs: None,
                locomotion: None,
            })
            .await?;
        let info: DriveInfo = match result {
            CommandResult::Drive(info) => *info,
            // Read by its shape (this connection's protocol version sends bare results): the
            // value is the drive's answer whatever variant it read as.
            other => serde_json::from_value(other.to_value()).map_err(send_failed)?,
        };
        // Its poses are paced at the budget the server gave.
        let mut pacing = lock(&self.pacing);
        pacing.nums.insert(info.avatar.clone(), info.avatar_num);
        let now = tokio::time::Instant::now();
        pacing.slots.insert(
            PaceKey::Num(info.avatar_num),
            (interval_of(info.max_rate_hz), now),
        );
        drop(pacing);
        Ok(info)
    }

    /// Ends driving `avatar`; it returns to its clip.
    ///
    /// # Errors
    /// As [`Driver::command`].
    pub async fn release(&self, avatar: &AvatarId) -> Result<(), ClientError> {
        self.command(Command::ReleaseDrive {
            avatar: avatar.clone(),
        })
        .await
        .map(drop)
    }

    /// Sends one pose as JSON: local rotations by source joint name (not acknowledged), once
    /// the avatar's pace allows (see the module doc).
    ///
    /// # Errors
    /// The connection failed.
    pub async fn send_pose(
        &self,
        avatar: &AvatarId,
        rotations: impl IntoIterator<Item = (String, [f32; 4])>,
        root_position: Option<[f32; 3]>,
        time_us: Option<u64>,
    ) -> Result<(), ClientError> {
        self.pace(PaceKey::Id(avatar.clone())).await;
        self.send_text(&ClientMsg::Pose {
            avatar: avatar.clone(),
            rotations: rotations.into_iter().collect::<BTreeMap<_, _>>(),
            root_position,
            time_us,
            weights: BTreeMap::new(),
            trackers: BTreeMap::new(),
        })
        .await
    }

    /// Sends one pose in the binary form (joints by index into [`DriveInfo::joints`]), once
    /// the avatar's pace allows (see the module doc).
    ///
    /// # Errors
    /// The connection failed.
    pub async fn send_binary_pose(&self, pose: &BinaryPose) -> Result<(), ClientError> {
        self.pace(PaceKey::Num(pose.avatar_num)).await;
        self.sink
            .lock()
            .await
            .send(Message::Binary(pose.encode().into()))
            .await
            .map_err(send_failed)
    }

    /// The next server error (a refused pose or command), waiting at most `wait`.
    pub async fn next_error(&self, wait: Duration) -> Option<ProtocolError> {
        let mut errors = self.errors.lock().await;
        tokio::time::timeout(wait, errors.recv())
            .await
            .ok()
            .flatten()
    }

    /// Closes the connection (the server releases what it drives).
    pub async fn close(self) {
        // A failed close leaves the socket to be dropped, which the server sees the same way.
        self.sink.lock().await.close().await.ok();
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

async fn read(
    mut stream: futures_util::stream::SplitStream<Ws>,
    pending: Pending,
    errors: mpsc::Sender<ProtocolError>,
) {
    while let Some(Ok(m)) = stream.next().await {
        let Message::Text(t) = m else { continue };
        match serde_json::from_str::<ServerMsg>(t.as_str()) {
            Ok(ServerMsg::Ack { id, result }) => {
                if let Some(tx) = lock(&pending).remove(&id) {
                    // The caller gave up waiting; nothing to deliver to.
                    tx.send(Ok(result)).ok();
                }
            }
            Ok(ServerMsg::Error(e)) => match e.id.and_then(|id| lock(&pending).remove(&id)) {
                Some(tx) => {
                    tx.send(Err(e)).ok();
                }
                None => {
                    if errors.try_send(e).is_err() {
                        tracing::debug!("driver error backlog full; an error was dropped");
                    }
                }
            },
            Ok(_) => {}
            Err(e) => tracing::debug!("unparsable server message: {e}"),
        }
    }
    lock(&pending).clear();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn any_announced_budget_gives_a_bounded_spacing() {
        assert_eq!(interval_of(120.0), Duration::from_secs_f64(1.0 / 120.0));
        assert_eq!(interval_of(1e-30), MAX_INTERVAL);
        assert_eq!(interval_of(f32::MIN_POSITIVE), MAX_INTERVAL);
        assert_eq!(interval_of(3e38), Duration::from_secs_f64(1.0 / 3e38));
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert_eq!(interval_of(bad), Duration::ZERO);
        }
        // Slots far apart still add up without overflowing the clock.
        let mut pacing = Pacing::new();
        let now = tokio::time::Instant::now();
        pacing
            .slots
            .insert(PaceKey::Num(1), (interval_of(1e-30), now));
        for _ in 0..1000 {
            pacing.reserve(PaceKey::Num(1), now);
        }
    }
}
