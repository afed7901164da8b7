//! [`Client`]: a handle to a background task that owns the websocket.

use super::clock::ClockEstimator;
use super::jitter::JitterBuffer;
use super::transport::{self, Ack, Link, Transport, TransportChoice};
use futures_util::{SinkExt, StreamExt};
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{AvatarPose, Frame, FrameDecoder};
use posecast_proto::frame2::{self, Frame2Decoder};
use posecast_proto::msg::{
    AvatarId, AvatarPoseJson, ClientMsg, Encoding, ErrorCode, FrameJson, ProtocolError, SceneId,
    ServerMsg,
};
use posecast_proto::placement::Placement;
use posecast_proto::subset::{JointSet, Selection};
use posecast_proto::{Skeleton, Transform};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_tungstenite::tungstenite::Message;
use tracing::{debug, warn};

/// Microseconds since the Unix epoch on this machine.
#[must_use]
pub fn unix_micros() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// How to connect.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// The websocket URL, e.g. `ws://127.0.0.1:8080/ws`.
    pub url: String,
    /// Other servers of the same cluster (`--nats`), tried in turn after `url` when a
    /// connection cannot be made or drops: every one of them serves the same scenes.
    pub fallback_urls: Vec<String>,
    /// Pose frame encoding.
    pub encoding: Encoding,
    /// View or control token.
    pub token: Option<String>,
    /// Scenes to subscribe to (and optional avatar filters), again after every reconnect.
    pub subscriptions: Vec<(SceneId, Option<Vec<AvatarId>>)>,
    /// Reconnect with exponential back-off (100 ms doubling to 5 s) when the connection drops.
    pub reconnect: bool,
    /// How often to ping for clock offset and round-trip time.
    pub ping_interval: Duration,
    /// Name sent in hello.
    pub name: String,
    /// Frames per second wanted from every subscription (`None`: every tick); the server
    /// sends every `round(tick_rate / rate)`-th tick.
    pub rate: Option<f32>,
    /// Only these joints of every avatar, from every subscription (`None`: all). The joints
    /// left out stay at their rest transforms in the poses this client gives.
    pub joints: Option<JointSet>,
    /// Morph weights in every subscription's frames (default `true`; `false`: a view that
    /// draws no faces saves their bytes).
    pub morph_weights: bool,
    /// How finely every subscription's binary frames code each joint (protocol version 5;
    /// [`posecast_proto::precision`]): a worst angle, a world-space bound or a translation
    /// bound. `None`: the finest. JSON frames, and a connection that stepped down below
    /// version 5, do not ask for it (their frames are then the finest).
    pub precision: Option<posecast_proto::precision::Precision>,
    /// Protocol version asked for in hello (default 7): 2 to 7 get wire v2 binary frames
    /// ([`posecast_proto::frame2`], about half of v1's bytes), 1 the v1 frames
    /// ([`posecast_proto::frame`]); 3 and later also get command results tagged with their
    /// kind (1 and 2 bare values, read by their shape: [`CommandResult::from_bare`]); 4 and
    /// later also get morph weights in frames; 5 may ask for a `precision`; 6 gets a precision's
    /// frames with coarser steps near an axis (fewer bytes, the same bound); 7 gets packed
    /// deltas (every avatar's in one bit stream, less framing); 8 gets, over WebTransport, v2
    /// frames as datagrams (v1 frames before; on a websocket 8 is 7); 9 gets their deltas
    /// predicted over the ticks between the frames they name and their own (kind 5: fewer
    /// bytes than kind 4 while frames are in flight). A server that refuses
    /// the version (`unsupported_version`: one that predates it) gets a hello with the version
    /// before, down to 1.
    pub version: u32,
    /// The transport to use (default [`TransportChoice::Auto`]: WebTransport when the server
    /// offers it and it can be reached, the websocket otherwise; [`Client::transport`] says
    /// which).
    pub transport: TransportChoice,
    /// How long asking the server for its WebTransport endpoint, and then the QUIC handshake,
    /// may each take before the client falls back to the websocket (default 5 s): UDP blocked
    /// on the way looks like a handshake that never completes.
    pub quic_timeout: Duration,
    /// Where to reach the WebTransport endpoint instead of the host and port `/api/quic`
    /// gives (e.g. `https://edge.example.org:443/`, a UDP load balancer in front of the
    /// server, or a link emulator); `/api/quic` is still asked whether the server offers it,
    /// and for the hash of a self-signed certificate. `None`: where `/api/quic` says.
    pub webtransport_url: Option<String>,
}

impl ClientOptions {
    /// Binary frames, subscribed to `scene`, reconnecting, pinging every second.
    #[must_use]
    pub fn new(url: impl Into<String>, scene: &str) -> Self {
        Self {
            url: url.into(),
            fallback_urls: Vec::new(),
            encoding: Encoding::Binary,
            token: None,
            subscriptions: vec![(SceneId(scene.to_string()), None)],
            reconnect: true,
            ping_interval: Duration::from_secs(1),
            name: "posecast-client".into(),
            rate: None,
            joints: None,
            morph_weights: true,
            precision: None,
            version: 9,
            transport: TransportChoice::Auto,
            quic_timeout: Duration::from_secs(5),
            webtransport_url: None,
        }
    }
}

/// Client failures.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// Could not connect or the connection failed.
    #[error("connection to {url} failed: {message}")]
    Connect {
        /// The URL.
        url: String,
        /// Why.
        message: String,
    },
    /// The server answered with a typed error.
    #[error("server error: {0}")]
    Server(#[from] ProtocolError),
    /// No answer in time.
    #[error("timed out waiting for {0}")]
    Timeout(&'static str),
    /// The client was shut down.
    #[error("client closed")]
    Closed,
}

/// One decoded pose.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseSample {
    /// The scene's tick number.
    pub seq: u64,
    /// Server time of the tick, µs since the Unix epoch.
    pub server_time_us: u64,
    /// When it arrived, µs since the Unix epoch on this machine.
    pub received_us: u64,
    /// Local transform of every joint (rest translation / scale where not streamed), in the
    /// avatar's own frame (placement not applied).
    pub locals: Vec<Transform>,
    /// The avatar's world placement at this tick.
    pub placement: Placement,
    /// Morph weights, one per channel of the description's `morph_targets` (empty when the
    /// rig has none, or the connection's protocol version is below 4 and frames are binary).
    pub weights: Vec<f32>,
}

impl PoseSample {
    /// The locals with the placement composed into the roots (`placement · D_root`): forward
    /// kinematics of these gives the placed avatar's world matrices.
    #[must_use]
    pub fn placed_locals(&self, skeleton: &Skeleton) -> Vec<Transform> {
        let mut locals = self.locals.clone();
        self.placement.place_roots(skeleton.parents(), &mut locals);
        locals
    }
}

/// What the client knows about one avatar.
#[derive(Debug, Clone)]
pub struct AvatarView {
    /// Its scene.
    pub scene: SceneId,
    /// Its description.
    pub description: Arc<AvatarDescription>,
    /// The skeleton rebuilt from the description.
    pub skeleton: Arc<Skeleton>,
    /// The newest pose.
    pub latest: Option<PoseSample>,
    /// Recent poses for interpolation.
    pub jitter: JitterBuffer,
    /// The joints its binary frames carry, when its subscription asked for a joint set
    /// (`None`: every joint).
    pub selection: Option<Selection>,
}

impl AvatarView {
    /// The local transforms of a pose in the JSON form (a JSON frame's entry, or the answer
    /// of `sample_pose`): rest everywhere, then the streamed parts. `None` when the pose is of
    /// another rig (its hash differs from the description's) or its lengths do not fit.
    #[must_use]
    pub fn locals_of(&self, pose: &AvatarPoseJson) -> Option<Vec<Transform>> {
        if pose.hash != self.description.hash {
            return None;
        }
        let rotations: Vec<glam::Quat> = pose
            .rotations
            .iter()
            .map(|&q| glam::Quat::from_array(q))
            .collect();
        let translations: Vec<glam::Vec3> = pose
            .translations
            .iter()
            .map(|&t| glam::Vec3::from_array(t))
            .collect();
        let scales: Vec<glam::Vec3> = pose
            .scales
            .iter()
            .map(|&v| glam::Vec3::from_array(v))
            .collect();
        let listed = match &pose.joints {
            Some(joints) => Some(Selection::of_joints(&self.description, joints)?),
            None => None,
        };
        locals_from(self, listed.as_ref(), &rotations, &translations, &scales)
    }
}

/// Things that happened, for callers that wait on them (tests, the CLI).
#[derive(Debug, Clone)]
pub enum Event {
    /// Connected and welcomed (again, after a reconnect).
    Connected,
    /// A description arrived (new or changed avatar).
    Description(AvatarId),
    /// A frame was decoded.
    Frame {
        /// Its scene.
        scene_num: u32,
        /// Its tick.
        seq: u64,
        /// Whether it was a keyframe (binary) — JSON frames count as keyframes.
        key: bool,
        /// Payload bytes.
        bytes: usize,
    },
    /// An avatar left.
    AvatarRemoved(AvatarId),
    /// The server sent an error that answered no command.
    Error(ProtocolError),
    /// The connection dropped.
    Disconnected,
}

/// Running totals.
#[derive(Debug, Clone, Default)]
pub struct Stats {
    /// Frames decoded.
    pub frames: u64,
    /// Keyframes among them.
    pub keyframes: u64,
    /// Frame payload bytes received.
    pub frame_bytes: u64,
    /// Frames that could not be decoded (missing keyframe, stale rig, malformed).
    pub undecodable: u64,
    /// Frames for an avatar whose description hash differs (stale rig).
    pub stale: u64,
    /// Connections made.
    pub connects: u64,
    /// Sum and count of tick→receive latencies (µs), offset-corrected.
    pub latency_sum_us: f64,
    /// See `latency_sum_us`.
    pub latency_count: u64,
    /// Largest tick→receive latency seen, µs.
    pub latency_max_us: f64,
    /// The newest error the server sent that answered no command (e.g. a subscription to an
    /// unknown scene), also sent as [`Event::Error`]: kept here for callers that look after
    /// it arrived.
    pub last_error: Option<ProtocolError>,
    /// Age of the newest join pose (an avatar's first pose after its description: the
    /// scene's cached keyframe, up to a second old), µs — kept out of the latencies.
    pub join_age_us: Option<f64>,
    /// The transport of the newest connection.
    pub transport: Option<Transport>,
    /// Why the newest connection did not use WebTransport although the server offered it
    /// (the QUIC handshake failed or timed out: UDP blocked on the way?).
    pub webtransport_failure: Option<String>,
    /// Acknowledgements sent to the server (WebTransport): of v1 keyframes, or in protocol
    /// version 8 of every v2 frame.
    pub acks: u64,
}

#[derive(Default)]
struct Shared {
    tick_rate: f32,
    connected: bool,
    avatars: HashMap<AvatarId, AvatarView>,
    by_num: HashMap<u32, AvatarId>,
    scene_nums: HashMap<u32, SceneId>,
    /// Each subscribed scene's joint set, as `subscribed` said.
    joint_sets: HashMap<SceneId, JointSet>,
    pending: HashMap<u64, oneshot::Sender<Result<CommandResult, ProtocolError>>>,
    pings: HashMap<u32, u64>,
    clock: ClockEstimator,
    stats: Stats,
}

/// The pause before a command is sent again ([`Client::command_retrying`]): a cluster's
/// scene changes owner within its lease time, a few seconds.
const RETRY_PAUSE: Duration = Duration::from_millis(500);

/// A value no other client (of this process or another) picks: the clock in nanoseconds, the
/// process id and a counter, in hex.
fn nonce() -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!(
        "{now:x}-{:x}-{:x}",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )
}

/// A connection to a posecast server. Dropping it stops the background task.
pub struct Client {
    shared: Arc<Mutex<Shared>>,
    outgoing: mpsc::Sender<ClientMsg>,
    events: broadcast::Sender<Event>,
    next_id: AtomicU64,
    /// This client's part of its idempotency keys ([`Client::command_retrying`]).
    nonce: String,
    task: tokio::task::JoinHandle<()>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("connected", &self.is_connected())
            .finish_non_exhaustive()
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn lock(shared: &Mutex<Shared>) -> MutexGuard<'_, Shared> {
    shared
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Client {
    /// Connects, says hello, subscribes, and waits (up to 10 s) for the welcome.
    ///
    /// # Errors
    /// The first connection fails or the server refuses the hello.
    pub async fn connect(options: ClientOptions) -> Result<Self, ClientError> {
        let shared = Arc::new(Mutex::new(Shared::default()));
        let (outgoing, rx) = mpsc::channel(256);
        let (events, _) = broadcast::channel(1024);
        let mut first = events.subscribe();
        let (ready_tx, ready_rx) = oneshot::channel();
        // The welcome may come after asking for WebTransport and trying it.
        let patience = Duration::from_secs(10)
            + match options.transport {
                TransportChoice::WebSocket => Duration::ZERO,
                _ => options.quic_timeout * 2,
            };
        let task = tokio::spawn(run(
            options,
            shared.clone(),
            rx,
            events.clone(),
            Some(ready_tx),
        ));
        let client = Self {
            shared,
            outgoing,
            events,
            next_id: AtomicU64::new(1),
            nonce: nonce(),
            task,
        };
        match tokio::time::timeout(patience, ready_rx).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => return Err(e),
            Ok(Err(_)) => return Err(ClientError::Closed),
            Err(_) => return Err(ClientError::Timeout("welcome")),
        }
        // Drain the Connected event so callers' subscriptions start clean.
        while first.try_recv().is_ok() {}
        Ok(client)
    }

    /// A receiver of [`Event`]s from now on (lagging receivers lose the oldest events).
    #[must_use]
    pub fn events(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    /// Sends a message as is (subscribe, unsubscribe, ping…).
    ///
    /// # Errors
    /// The client was shut down.
    pub async fn send(&self, msg: ClientMsg) -> Result<(), ClientError> {
        self.outgoing
            .send(msg)
            .await
            .map_err(|_| ClientError::Closed)
    }

    /// Sends a command and waits (up to 10 s) for its acknowledgement.
    ///
    /// # Errors
    /// The server's typed error, a timeout, or a closed client.
    pub async fn command(&self, command: Command) -> Result<CommandResult, ClientError> {
        self.command_keyed(command, None).await
    }

    /// [`Client::command`] that is safe to retry: sent with an idempotency key of its own
    /// (this client's nonce and the command's number), and sent again with the same key after
    /// an unknown outcome — the connection dropped before the answer, no answer within 10 s,
    /// the server's `outcome_unknown` — or after `unavailable` (not applied), up to `attempts` times in all, after the client has
    /// reconnected (to its server or a fallback). A server of a cluster applies it at most
    /// once and answers a repeat with the first answer (PROTOCOL.md, "Idempotency").
    ///
    /// # Errors
    /// The last attempt's error; any other typed error at once.
    pub async fn command_retrying(
        &self,
        command: Command,
        attempts: u32,
    ) -> Result<CommandResult, ClientError> {
        let key = format!(
            "{}-{}",
            self.nonce,
            self.next_id.fetch_add(1, Ordering::Relaxed)
        );
        let mut left = attempts.max(1);
        loop {
            left -= 1;
            let outcome = self.command_keyed(command.clone(), Some(key.clone())).await;
            let unknown = match &outcome {
                Err(ClientError::Timeout(_)) => true,
                Err(ClientError::Closed) => !self.outgoing.is_closed(),
                Err(ClientError::Server(e)) => matches!(
                    e.code,
                    posecast_proto::msg::ErrorCode::Unavailable
                        | posecast_proto::msg::ErrorCode::OutcomeUnknown
                ),
                _ => false,
            };
            if !unknown || left == 0 {
                return outcome;
            }
            // Sent again once connected (a dropped connection reconnects by itself).
            let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
            while !self.is_connected() && tokio::time::Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            tokio::time::sleep(RETRY_PAUSE).await;
        }
    }

    async fn command_keyed(
        &self,
        command: Command,
        idempotency_key: Option<String>,
    ) -> Result<CommandResult, ClientError> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let (tx, rx) = oneshot::channel();
        lock(&self.shared).pending.insert(id, tx);
        self.send(ClientMsg::Command {
            id,
            command,
            idempotency_key,
        })
        .await?;
        match tokio::time::timeout(Duration::from_secs(10), rx).await {
            Ok(Ok(result)) => result.map_err(ClientError::Server),
            Ok(Err(_)) => Err(ClientError::Closed),
            Err(_) => {
                lock(&self.shared).pending.remove(&id);
                Err(ClientError::Timeout("command acknowledgement"))
            }
        }
    }

    /// Whether the connection is up.
    #[must_use]
    pub fn is_connected(&self) -> bool {
        lock(&self.shared).connected
    }

    /// Every avatar the client knows.
    #[must_use]
    pub fn avatars(&self) -> Vec<AvatarView> {
        lock(&self.shared).avatars.values().cloned().collect()
    }

    /// One avatar.
    #[must_use]
    pub fn avatar(&self, id: &AvatarId) -> Option<AvatarView> {
        lock(&self.shared).avatars.get(id).cloned()
    }

    /// The newest pose of an avatar.
    #[must_use]
    pub fn latest(&self, id: &AvatarId) -> Option<PoseSample> {
        lock(&self.shared)
            .avatars
            .get(id)
            .and_then(|a| a.latest.clone())
    }

    /// The pose to render now: interpolated through the jitter buffer a little in the past —
    /// far enough that the frames around it have arrived (see [`JitterBuffer::delay_us`]) —
    /// with the avatar's placement composed into its roots (see
    /// [`PoseSample::placed_locals`]), so it is drawn where it stands.
    #[must_use]
    pub fn pose_now(&self, id: &AvatarId) -> Option<Vec<Transform>> {
        let s = lock(&self.shared);
        s.avatars
            .get(id)
            .and_then(|a| a.jitter.playout(unix_micros()))
    }

    /// The avatar's morph weights to draw now, one per channel of its description's
    /// `morph_targets`: those of the newest frame (weights are not interpolated; a face
    /// changes at speech rate, far slower than the jitter buffer's delay).
    #[must_use]
    pub fn weights_now(&self, id: &AvatarId) -> Option<Vec<f32>> {
        lock(&self.shared)
            .avatars
            .get(id)
            .and_then(|a| a.latest.as_ref().map(|l| l.weights.clone()))
    }

    /// Totals so far.
    #[must_use]
    pub fn stats(&self) -> Stats {
        lock(&self.shared).stats.clone()
    }

    /// Estimated server − client clock offset and round-trip time, µs.
    #[must_use]
    pub fn clock(&self) -> (f64, Option<f64>) {
        let s = lock(&self.shared);
        (s.clock.offset_us(), s.clock.rtt_us())
    }

    /// The transport of the connection (the newest one while reconnecting): WebTransport
    /// or the websocket ([`TransportChoice`]).
    #[must_use]
    pub fn transport(&self) -> Option<Transport> {
        lock(&self.shared).stats.transport
    }

    /// Tick rate announced by the server.
    #[must_use]
    pub fn tick_rate(&self) -> f32 {
        lock(&self.shared).tick_rate
    }
}

type Ready = Option<oneshot::Sender<Result<(), ClientError>>>;

async fn run(
    options: ClientOptions,
    shared: Arc<Mutex<Shared>>,
    mut outgoing: mpsc::Receiver<ClientMsg>,
    events: broadcast::Sender<Event>,
    mut ready: Ready,
) {
    const FIRST_BACKOFF: Duration = Duration::from_millis(100);
    let urls: Vec<String> = std::iter::once(options.url.clone())
        .chain(options.fallback_urls.iter().cloned())
        .collect();
    // The URL tried next, and how many attempts in a row have failed to get a welcome.
    let mut at = 0usize;
    let mut failures = 0usize;
    let mut backoff = FIRST_BACKOFF;
    // The version said in hello: the one asked for, or one lower each time a server refused it
    // (a server that predates a version speaks the ones before).
    let mut version = options.version;
    loop {
        let url = &urls[at % urls.len()];
        let result = session(
            &options,
            version,
            url,
            &shared,
            &mut outgoing,
            &events,
            &mut ready,
        )
        .await;
        let welcomed = {
            let mut s = lock(&shared);
            let welcomed = s.connected;
            s.connected = false;
            // Commands in flight will not be answered on a new connection.
            s.pending.clear();
            welcomed
        };
        events.send(Event::Disconnected).ok();
        if welcomed {
            failures = 0;
            backoff = FIRST_BACKOFF;
        } else {
            failures += 1;
        }
        match result {
            Err(ClientError::Server(e))
                if e.code == ErrorCode::UnsupportedVersion && version > 1 =>
            {
                debug!(
                    url,
                    version, "version refused: saying hello with the version before"
                );
                version -= 1;
                failures = failures.saturating_sub(1);
                continue;
            }
            Err(e) => {
                // The next server of the list: its scenes are the same.
                at += 1;
                if ready.is_some() && failures < urls.len() {
                    debug!(url, error = %e, "cannot connect: trying the next server");
                    continue;
                }
                if let Some(r) = ready.take() {
                    r.send(Err(e)).ok();
                    return;
                }
                warn!(url, error = %e, "connection lost");
            }
            Ok(()) => debug!(url, "connection closed"),
        }
        if !options.reconnect || outgoing.is_closed() {
            return;
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(Duration::from_secs(5));
    }
}

async fn session(
    options: &ClientOptions,
    version: u32,
    url: &str,
    shared: &Arc<Mutex<Shared>>,
    outgoing: &mut mpsc::Receiver<ClientMsg>,
    events: &broadcast::Sender<Event>,
    ready: &mut Ready,
) -> Result<(), ClientError> {
    let connect_err = |e: &dyn std::fmt::Display| ClientError::Connect {
        url: url.to_owned(),
        message: e.to_string(),
    };
    let mut link = connect(options, url, shared).await?;
    let to_text =
        |m: &ClientMsg| Message::Text(serde_json::to_string(m).unwrap_or_default().into());
    let hello = ClientMsg::Hello {
        version,
        encoding: options.encoding,
        token: options.token.clone(),
        client: Some(options.name.clone()),
    };
    link.sink
        .send(to_text(&hello))
        .await
        .map_err(|e| connect_err(&e))?;
    for (scene, avatars) in &options.subscriptions {
        let sub = ClientMsg::Subscribe {
            scene: scene.clone(),
            avatars: avatars.clone(),
            rate: options.rate,
            joints: options.joints.clone(),
            morph_weights: (!options.morph_weights).then_some(false),
            precision: options
                .precision
                .filter(|_| version >= 5 && options.encoding == Encoding::Binary),
        };
        link.sink
            .send(to_text(&sub))
            .await
            .map_err(|e| connect_err(&e))?;
    }
    // Over WebTransport v2 frames come as datagrams (protocol version 8): lost, out of order,
    // their deltas naming the frames they refer to.
    let mut decoder = Decoders::default();
    if link.answers_pings() {
        decoder.v2 = Frame2Decoder::for_datagrams();
    }
    let mut ping = tokio::time::interval(options.ping_interval);
    let mut ping_id = 0u32;
    loop {
        tokio::select! {
            msg = link.stream.next() => {
                let Some(msg) = msg else { return Ok(()) };
                let msg = msg.map_err(|e| connect_err(&e))?;
                let received = unix_micros();
                match msg {
                    Message::Binary(bytes) => {
                        if let Some(ack) = on_binary(shared, events, &mut decoder, &bytes, received)
                            && link.acknowledge(&ack)
                        {
                            lock(shared).stats.acks += 1;
                        }
                    }
                    Message::Text(text) => {
                        match serde_json::from_str::<ServerMsg>(text.as_str()) {
                            Ok(m) => {
                                forget_frames(shared, &mut decoder, &m);
                                on_server_msg(shared, events, m, text.len(), received, ready, version > 1)?;
                            }
                            Err(e) => warn!(error = %e, "unparseable server message"),
                        }
                    }
                    Message::Close(_) => return Ok(()),
                    Message::Ping(payload) if link.answers_pings() => {
                        link.sink.send(Message::Pong(payload)).await.map_err(|e| connect_err(&e))?;
                    }
                    _ => {}
                }
            }
            out = outgoing.recv() => {
                let Some(out) = out else { return Ok(()) };
                link.sink.send(to_text(&out)).await.map_err(|e| connect_err(&e))?;
            }
            _ = ping.tick() => {
                ping_id = ping_id.wrapping_add(1);
                let now = unix_micros();
                {
                    let mut s = lock(shared);
                    if s.pings.len() > 64 { s.pings.clear(); }
                    s.pings.insert(ping_id, now);
                }
                link.sink.send(to_text(&ClientMsg::Ping { id: ping_id, client_time_us: now })).await.map_err(|e| connect_err(&e))?;
            }
        }
    }
}

/// The link of one connection to `url`: WebTransport first when `options` allow it and the
/// server offers it, the websocket otherwise (or when WebTransport cannot be reached); the
/// transport, and why WebTransport was not used, go into the stats.
async fn connect(
    options: &ClientOptions,
    url: &str,
    shared: &Mutex<Shared>,
) -> Result<Link, ClientError> {
    let connect_err = |message: String| ClientError::Connect {
        url: url.to_owned(),
        message,
    };
    // Why WebTransport was not used although the server offered it.
    let mut failure = None;
    if options.transport != TransportChoice::WebSocket {
        let offer = match transport::discover(url, options.quic_timeout).await {
            Ok(Some(mut offer)) => {
                if let Some(url) = &options.webtransport_url {
                    offer.url.clone_from(url);
                }
                Some(offer)
            }
            Ok(None) => None,
            // A server that cannot be asked: the websocket says why below.
            Err(e) => {
                debug!(url, error = %e, "cannot ask for WebTransport");
                None
            }
        };
        let tried = match &offer {
            Some(offer) => Some(
                tokio::time::timeout(options.quic_timeout, Link::webtransport(offer))
                    .await
                    .map_err(|_| {
                        format!(
                            "no QUIC handshake with {} within {:?} (UDP blocked?)",
                            offer.url, options.quic_timeout
                        )
                    })
                    .and_then(|link| link.map_err(|e| format!("{}: {e}", offer.url))),
            ),
            None => None,
        };
        match tried {
            Some(Ok(link)) => {
                let mut s = lock(shared);
                s.stats.transport = Some(Transport::WebTransport);
                s.stats.webtransport_failure = None;
                debug!(url, "connected over WebTransport");
                return Ok(link);
            }
            Some(Err(e)) => {
                if options.transport == TransportChoice::WebTransport {
                    return Err(connect_err(e));
                }
                warn!(url, error = %e, "WebTransport offered but not reached: the websocket instead");
                failure = Some(e);
            }
            None if options.transport == TransportChoice::WebTransport => {
                return Err(connect_err(
                    "the server does not offer WebTransport".to_owned(),
                ));
            }
            None => {}
        }
    }
    let link = Link::websocket(url).await.map_err(connect_err)?;
    let mut s = lock(shared);
    s.stats.transport = Some(Transport::WebSocket);
    s.stats.webtransport_failure = failure;
    Ok(link)
}

fn on_server_msg(
    shared: &Arc<Mutex<Shared>>,
    events: &broadcast::Sender<Event>,
    msg: ServerMsg,
    len: usize,
    received: u64,
    ready: &mut Ready,
    may_downgrade: bool,
) -> Result<(), ClientError> {
    let mut s = lock(shared);
    let event = match msg {
        ServerMsg::Welcome { tick_rate, .. } => {
            s.tick_rate = tick_rate;
            s.connected = true;
            s.stats.connects += 1;
            if let Some(r) = ready.take() {
                r.send(Ok(())).ok();
            }
            Some(Event::Connected)
        }
        ServerMsg::Subscribed {
            scene,
            scene_num,
            joints,
            ..
        } => {
            match joints {
                Some(set) => s.joint_sets.insert(scene.clone(), set),
                None => s.joint_sets.remove(&scene),
            };
            s.scene_nums.insert(scene_num, scene);
            None
        }
        ServerMsg::Unsubscribed { scene } => {
            s.avatars.retain(|_, a| a.scene != scene);
            None
        }
        ServerMsg::Description { scene, avatar } => match avatar.to_skeleton() {
            Ok(skeleton) => {
                let id = avatar.id.clone();
                let tick_rate = s.tick_rate;
                let selection = s
                    .joint_sets
                    .get(&scene)
                    .map(|set| set.select(&avatar))
                    .filter(|sel| !sel.is_all());
                s.by_num.insert(avatar.num, id.clone());
                s.avatars.insert(
                    id.clone(),
                    AvatarView {
                        scene,
                        description: Arc::new(*avatar),
                        skeleton: Arc::new(skeleton),
                        latest: None,
                        jitter: JitterBuffer::new(tick_rate),
                        selection,
                    },
                );
                Some(Event::Description(id))
            }
            Err(e) => {
                warn!(error = %e, "invalid description");
                None
            }
        },
        ServerMsg::AvatarRemoved { avatar, .. } => {
            s.avatars.remove(&avatar);
            Some(Event::AvatarRemoved(avatar))
        }
        ServerMsg::Pong {
            id, server_time_us, ..
        } => {
            if let Some(t0) = s.pings.remove(&id) {
                s.clock.add(t0, server_time_us, received);
            }
            None
        }
        ServerMsg::Ack { id, result } => {
            if let Some(tx) = s.pending.remove(&id) {
                tx.send(Ok(result)).ok();
            }
            None
        }
        ServerMsg::Error(e) => {
            if let Some(tx) = e.id.and_then(|id| s.pending.remove(&id)) {
                tx.send(Err(e)).ok();
                None
            } else if s.connected {
                s.stats.last_error = Some(e.clone());
                Some(Event::Error(e))
            } else if may_downgrade && e.code == ErrorCode::UnsupportedVersion {
                // A server that predates this version: `run` says hello again with the one
                // before.
                return Err(ClientError::Server(e));
            } else {
                // Refused before the welcome (bad version, bad token): the first connect fails.
                drop(s);
                if let Some(r) = ready.take() {
                    r.send(Err(ClientError::Server(e.clone()))).ok();
                }
                events.send(Event::Error(e.clone())).ok();
                return Err(ClientError::Server(e));
            }
        }
        ServerMsg::Frame(frame) => on_json_frame(&mut s, frame, len, received),
        // Scene and avatar changes (for dashboards); this client follows poses only.
        ServerMsg::Scenes { .. }
        | ServerMsg::SceneCreated { .. }
        | ServerMsg::SceneDeleted { .. }
        | ServerMsg::AvatarChanged { .. }
        | ServerMsg::Viewers { .. } => None,
    };
    drop(s);
    if let Some(e) = event {
        events.send(e).ok();
    }
    Ok(())
}

/// Ticks back a pose may be and still be an old one (a keyframe sent again, a datagram
/// overtaken) rather than a new stream's (a server restarted: its ticks count from 0).
const OLD_POSE_TICKS: u64 = 120;

/// Whether a pose of tick `seq` is older than (or the same as) the avatar's newest, of tick
/// `newest`, which it must not replace: over WebTransport a keyframe comes again before each
/// delta until it is acknowledged, and datagrams may be overtaken.
fn is_old(newest: Option<u64>, seq: u64) -> bool {
    newest.is_some_and(|n| seq <= n && n - seq <= OLD_POSE_TICKS)
}

fn record(s: &mut Shared, id: &AvatarId, sample: PoseSample) {
    let newest = s
        .avatars
        .get(id)
        .and_then(|a| a.latest.as_ref().map(|l| l.seq));
    if is_old(newest, sample.seq) {
        return;
    }
    let (server_time_us, received) = (sample.server_time_us, sample.received_us);
    // Latency needs the clock offset: frames that arrive before the first pong are not
    // counted (they would mix two clocks). An avatar's first pose is the join keyframe, which
    // the server may have made up to a second ago: its age is reported on its own.
    let joined = s.avatars.get(id).is_some_and(|a| a.latest.is_none());
    if s.clock.rtt_us().is_some() {
        let latency = received as f64 + s.clock.offset_us() - server_time_us as f64;
        if joined {
            s.stats.join_age_us = Some(latency);
        } else {
            s.stats.latency_sum_us += latency;
            s.stats.latency_count += 1;
            s.stats.latency_max_us = s.stats.latency_max_us.max(latency);
        }
    }
    if let Some(a) = s.avatars.get_mut(id) {
        // The jitter buffer interpolates placed poses: placement and pose of the same tick.
        a.jitter
            .push(server_time_us, received, sample.placed_locals(&a.skeleton));
        a.latest = Some(sample);
    }
}

/// Local transforms from a decoded pose: rest everywhere, then the streamed parts — of every
/// joint, or of the joints of `selection` when the pose carries only those.
fn locals_from(
    view: &AvatarView,
    selection: Option<&Selection>,
    rotations: &[glam::Quat],
    translations: &[glam::Vec3],
    scales: &[glam::Vec3],
) -> Option<Vec<Transform>> {
    let d = &view.description;
    let all = |n: usize| (0..n).collect::<Vec<usize>>();
    let (joints, translated, scaled) = match selection {
        Some(sel) if sel.joint_count == view.skeleton.len() => (
            sel.joint_indices().collect(),
            Selection::pick(&d.translated_joints, sel.translations.iter().copied()),
            Selection::pick(&d.scaled_joints, sel.scales.iter().copied()),
        ),
        Some(_) => return None,
        None => (
            all(view.skeleton.len()),
            d.translated_joints.clone(),
            d.scaled_joints.clone(),
        ),
    };
    if rotations.len() != joints.len()
        || translations.len() != translated.len()
        || scales.len() != scaled.len()
    {
        return None;
    }
    let mut locals = view.skeleton.rest().to_vec();
    for (&j, q) in joints.iter().zip(rotations) {
        locals[j].rotation = *q;
    }
    for (&j, t) in translated.iter().zip(translations) {
        locals[usize::from(j)].translation = *t;
    }
    for (&j, v) in scaled.iter().zip(scales) {
        locals[usize::from(j)].scale = *v;
    }
    Some(locals)
}

/// Drops the v2 decoder's frames of a scene left or an avatar gone (before `msg` is handled,
/// while the numbers are still known): a long-lived client holds frames of live avatars only.
fn forget_frames(shared: &Mutex<Shared>, decoder: &mut Decoders, msg: &ServerMsg) {
    let s = lock(shared);
    let scene_num = |scene: &SceneId| {
        s.scene_nums
            .iter()
            .find(|(_, id)| *id == scene)
            .map(|(n, _)| *n)
    };
    match msg {
        ServerMsg::Unsubscribed { scene } => {
            if let Some(n) = scene_num(scene) {
                decoder.v2.forget_scene(n);
            }
        }
        ServerMsg::AvatarRemoved { scene, avatar } => {
            if let (Some(n), Some(view)) = (scene_num(scene), s.avatars.get(avatar)) {
                decoder.v2.forget_avatar(n, view.description.num);
            }
        }
        _ => {}
    }
}

/// Both wires' decoders: a frame's first byte says which it is.
#[derive(Debug, Default)]
struct Decoders {
    v1: FrameDecoder,
    v2: Frame2Decoder,
}

impl Decoders {
    fn decode(&mut self, bytes: &[u8]) -> Result<Frame, String> {
        if bytes.first() == Some(&frame2::MAGIC) {
            self.v2.decode(bytes).map_err(|e| e.to_string())
        } else {
            self.v1.decode(bytes).map_err(|e| e.to_string())
        }
    }
}

/// Decodes a binary frame into the avatars' poses; returns what a WebTransport link
/// acknowledges of it: a v1 keyframe, every v2 frame (protocol version 8).
fn on_binary(
    shared: &Arc<Mutex<Shared>>,
    events: &broadcast::Sender<Event>,
    decoder: &mut Decoders,
    bytes: &[u8],
    received: u64,
) -> Option<Ack> {
    let mut s = lock(shared);
    let frame = match decoder.decode(bytes) {
        Ok(f) => f,
        Err(e) => {
            debug!(error = %e, "undecodable frame");
            s.stats.undecodable += 1;
            return None;
        }
    };
    s.stats.frames += 1;
    s.stats.frame_bytes += bytes.len() as u64;
    let key = frame.header.kind == posecast_proto::frame::FrameKind::Key;
    s.stats.keyframes += u64::from(key);
    for AvatarPose {
        avatar_num,
        hash,
        rotations,
        translations,
        scales,
        placement,
        weights,
    } in &frame.avatars
    {
        let Some(id) = s.by_num.get(avatar_num).cloned() else {
            continue;
        };
        let Some(view) = s.avatars.get(&id) else {
            continue;
        };
        if view.description.hash_u64() != *hash {
            s.stats.stale += 1;
            continue;
        }
        if let Some(locals) = locals_from(
            view,
            view.selection.as_ref(),
            rotations,
            translations,
            scales,
        ) {
            let sample = PoseSample {
                seq: frame.header.seq,
                server_time_us: frame.header.server_time_us,
                received_us: received,
                locals,
                placement: *placement,
                weights: weights.clone(),
            };
            record(&mut s, &id, sample);
        } else {
            s.stats.undecodable += 1;
        }
    }
    drop(s);
    events
        .send(Event::Frame {
            scene_num: frame.header.scene_num,
            seq: frame.header.seq,
            key,
            bytes: bytes.len(),
        })
        .ok();
    let v2 = bytes.first() == Some(&frame2::MAGIC);
    (key || v2).then(|| Ack {
        whole_frame: v2,
        scene_num: frame.header.scene_num,
        seq: frame.header.seq,
        avatars: frame.avatars.iter().map(|a| a.avatar_num).collect(),
    })
}

fn on_json_frame(s: &mut Shared, frame: FrameJson, len: usize, received: u64) -> Option<Event> {
    s.stats.frames += 1;
    s.stats.keyframes += 1;
    s.stats.frame_bytes += len as u64;
    for pose in &frame.avatars {
        let Some(view) = s.avatars.get(&pose.avatar) else {
            continue;
        };
        if view.description.hash != pose.hash {
            s.stats.stale += 1;
            continue;
        }
        let q: Vec<glam::Quat> = pose
            .rotations
            .iter()
            .map(|r| glam::Quat::from_array(*r).normalize())
            .collect();
        let t: Vec<glam::Vec3> = pose
            .translations
            .iter()
            .map(|v| glam::Vec3::from_array(*v))
            .collect();
        let sc: Vec<glam::Vec3> = pose
            .scales
            .iter()
            .map(|v| glam::Vec3::from_array(*v))
            .collect();
        let listed = match &pose.joints {
            Some(joints) => Selection::of_joints(&view.description, joints),
            None => None,
        };
        if pose.joints.is_some() && listed.is_none() {
            s.stats.undecodable += 1;
            continue;
        }
        if let Some(locals) = locals_from(view, listed.as_ref(), &q, &t, &sc) {
            let weights = view
                .description
                .morph_targets
                .iter()
                .map(|c| pose.weights.get(c).copied().unwrap_or(0.0))
                .collect();
            let sample = PoseSample {
                seq: frame.seq,
                server_time_us: frame.server_time_us,
                received_us: received,
                locals,
                placement: pose.placement,
                weights,
            };
            record(s, &pose.avatar, sample);
        } else {
            s.stats.undecodable += 1;
        }
    }
    let scene_num = s
        .scene_nums
        .iter()
        .find(|(_, id)| **id == frame.scene)
        .map_or(0, |(n, _)| *n);
    Some(Event::Frame {
        scene_num,
        seq: frame.seq,
        key: true,
        bytes: len,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A keyframe sent again (an older tick) or the same tick twice does not replace the
    /// newest pose; a newer tick does, and so does a restarted server's tick 0.
    #[test]
    fn an_older_pose_never_replaces_the_newest() {
        assert!(!is_old(None, 5));
        assert!(is_old(Some(100), 97));
        assert!(is_old(Some(100), 100));
        assert!(!is_old(Some(100), 101));
        assert!(!is_old(Some(10_000), 0));
    }
}
