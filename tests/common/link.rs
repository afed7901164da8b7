//! Viewers behind an emulated link (`posecast-linkemu`): a server with a scene of built-in
//! avatars, lightweight websocket viewers that connect through a proxy and keep each frame's
//! stamp and arrival, and the figures the link tests assert on.

use futures_util::{SinkExt, StreamExt};
use posecast_proto::frame::read_header;
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, SceneId};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::task::JoinHandle;
use tokio_tungstenite::tungstenite::Message;

/// One link test at a time in a test binary: each measures frame ages in milliseconds on two
/// shared cores, so two at once would measure each other.
pub async fn one_at_a_time() -> tokio::sync::MutexGuard<'static, ()> {
    static TURN: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());
    TURN.lock().await
}

/// Microseconds since the Unix epoch: frames' `server_time_us` are on this clock (server and
/// viewers share the machine, so a frame's age is `arrival − stamp`).
pub fn unix_micros() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// A server at 60 Hz whose `default` scene holds `avatars` built-in avatars (the one it starts
/// with plays `idle`; the others `walk`, `wave`, `idle` in turn).
pub async fn scene_server(avatars: usize) -> Server {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: 60.0,
        access: super::test_access(),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    super::add_extras(&server, 1..avatars).await;
    server
}

/// What one viewer saw.
#[derive(Debug, Default, Clone)]
pub struct Seen {
    /// From connecting to the welcome.
    pub welcome_after: Option<Duration>,
    /// From connecting to the first frame (the join keyframe).
    pub joined_after: Option<Duration>,
    /// Every frame after the first that the viewer would show: (arrival µs, server time µs).
    /// Not among them: a keyframe that came (within 2 ms) together with the delta right behind
    /// it that refers to it, only as its reference (a paced viewer that skipped the keyframe's tick gets it just before its next delta,
    /// which is newer and shown instead) — counted in `references`.
    pub frames: Vec<(u64, u64)>,
    /// Keyframes received only as the reference of the next delta.
    pub references: u64,
    /// Why it stopped early, if it did.
    pub failure: Option<String>,
}

impl Seen {
    /// Frames that arrived in `[from, to)` (µs).
    pub fn frames_between(&self, from: u64, to: u64) -> impl Iterator<Item = &(u64, u64)> {
        self.frames
            .iter()
            .filter(move |(a, _)| *a >= from && *a < to)
    }
}

/// A viewer connected through `addr` (a proxy or the server), subscribed to `default`.
#[derive(Debug)]
pub struct Viewer {
    /// What it saw so far.
    pub seen: Arc<Mutex<Seen>>,
    task: JoinHandle<()>,
}

impl Drop for Viewer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// How a viewer reads its socket.
#[derive(Debug, Clone, Copy)]
pub enum Reading {
    /// Every message as it comes.
    Prompt,
    /// A reader that gets the CPU now and then (a client on a loaded machine): it reads what
    /// came for about a millisecond, then does not run for the pause. It keeps up (it reads
    /// everything each time it runs) but answers pings up to the pause late.
    InBursts(Duration),
    /// A reader that can take at most this many messages a second.
    AtMost(u32),
}

impl Viewer {
    /// Connects and keeps reading until dropped.
    pub fn spawn(addr: SocketAddr, encoding: Encoding) -> Self {
        Self::spawn_reading(addr, encoding, Reading::Prompt)
    }

    /// Connects and keeps reading as `reading` says until dropped.
    pub fn spawn_reading(addr: SocketAddr, encoding: Encoding, reading: Reading) -> Self {
        let seen = Arc::new(Mutex::new(Seen::default()));
        let s = seen.clone();
        let task = tokio::spawn(async move {
            if let Err(e) = view(addr, encoding, reading, &s).await {
                s.lock().unwrap().failure = Some(e);
            }
        });
        Self { seen, task }
    }

    /// A copy of what it saw.
    pub fn seen(&self) -> Seen {
        self.seen.lock().unwrap().clone()
    }
}

async fn view(
    addr: SocketAddr,
    encoding: Encoding,
    reading: Reading,
    seen: &Mutex<Seen>,
) -> Result<(), String> {
    let began = tokio::time::Instant::now();
    let stream = tokio::net::TcpStream::connect(addr)
        .await
        .map_err(|e| e.to_string())?;
    stream.set_nodelay(true).ok();
    let (mut ws, _) = tokio_tungstenite::client_async(format!("ws://{addr}/ws"), stream)
        .await
        .map_err(|e| e.to_string())?;
    for msg in [
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding,
            token: None,
            client: Some("link-test".into()),
        },
        ClientMsg::Subscribe {
            scene: SceneId("default".into()),
            avatars: None,
            rate: None,
            joints: None,
            morph_weights: None,
            precision: None,
        },
    ] {
        ws.send(Message::text(serde_json::to_string(&msg).unwrap()))
            .await
            .map_err(|e| e.to_string())?;
    }
    let mut last_key: Option<u64> = None;
    let mut awake = tokio::time::Instant::now();
    while let Some(m) = ws.next().await {
        match reading {
            Reading::Prompt => {}
            Reading::InBursts(pause) => {
                if awake.elapsed() >= Duration::from_millis(1) {
                    tokio::time::sleep(pause).await;
                    awake = tokio::time::Instant::now();
                }
            }
            Reading::AtMost(per_second) => {
                tokio::time::sleep(Duration::from_secs(1) / per_second).await;
            }
        }
        let m = m.map_err(|e| e.to_string())?;
        let arrival = unix_micros();
        let stamp = match &m {
            Message::Binary(bytes) => Some(read_header(bytes).map_err(|e| e.to_string())?.0),
            Message::Text(t) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                match v["type"].as_str() {
                    Some("welcome") => {
                        seen.lock().unwrap().welcome_after = Some(began.elapsed());
                        None
                    }
                    Some("frame") => Some(posecast_proto::frame::FrameHeader {
                        kind: posecast_proto::frame::FrameKind::Key,
                        scene_num: 0,
                        seq: v["seq"].as_u64().unwrap(),
                        server_time_us: v["server_time_us"].as_u64().unwrap(),
                        base_seq: 0,
                    }),
                    _ => None,
                }
            }
            Message::Close(_) => return Err("closed by the server".into()),
            _ => None,
        };
        if let Some(header) = stamp {
            let mut s = seen.lock().unwrap();
            if s.joined_after.is_none() {
                s.joined_after = Some(began.elapsed());
            } else {
                // A delta whose keyframe came just before it: that keyframe was its reference.
                if header.kind == posecast_proto::frame::FrameKind::Delta
                    && last_key == Some(header.base_seq)
                    && s.frames.last().is_some_and(|(a, _)| arrival - a <= 2_000)
                    && s.frames.pop().is_some()
                {
                    s.references += 1;
                }
                s.frames.push((arrival, header.server_time_us));
            }
            last_key = (header.kind == posecast_proto::frame::FrameKind::Key
                && matches!(m, Message::Binary(_)))
            .then_some(header.seq);
        }
    }
    Err("connection ended".into())
}

/// The `q`-quantile (0–1) of `values` (sorted in place), nearest rank.
pub fn quantile(values: &mut [f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let rank = ((values.len() as f64 * q).ceil() as usize).clamp(1, values.len());
    values[rank - 1]
}
