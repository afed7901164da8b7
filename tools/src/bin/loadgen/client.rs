//! One lightweight load client: hello (in the protocol version the run asks for: 1 gets v1
//! frames, 2 and 3 wire v2 ones), subscribe, then read frames and keep only the header's `seq`
//! and `server_time_us` (no pose decoding: the point is the server's fan-out, and a full decode
//! per frame would make this process the bottleneck sooner).
//!
//! A client speaks over a websocket or over WebTransport ([`Endpoint`]), through the client
//! library's [`Link`]. Over WebTransport frames come as datagrams — wire v1 before protocol
//! version 8, wire v2 from it — and the client does what the client library does there: it
//! answers the server's pings and acknowledges every v1 keyframe, or from version 8 every
//! frame (or part of one) it receives, naming its avatars from the chunks' heads, so the server
//! sends deltas against it. (It does not decode: a version 8 frame that comes always decodes,
//! as its deltas name only frames acknowledged.)
use anyhow::{Context, Result, bail};
use futures_util::{SinkExt, StreamExt};
use posecast_client::net::transport::{Ack, Link, QuicOffer};
use posecast_proto::frame::{FrameHeader, FrameKind};
use posecast_proto::frame2::{self, FrameClock};
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, SceneId, ServerMsg};
use std::sync::atomic::{AtomicU8, AtomicUsize, Ordering};
use tokio::sync::{Semaphore, watch};
use tokio_tungstenite::tungstenite::Message;

/// Where the run is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Connecting and settling: frames are not counted.
    Warmup = 0,
    /// Counting.
    Measure = 1,
    /// Stop reading and close.
    Done = 2,
}

/// State shared by every client.
#[derive(Debug)]
pub struct Shared {
    phase: AtomicU8,
    done: watch::Sender<bool>,
    connecting: Semaphore,
    /// Clients that received `subscribed`.
    pub ready: AtomicUsize,
    /// Clients that failed to connect or subscribe.
    pub failed: AtomicUsize,
    /// Whether clients keep every frame's arrival (`--link`).
    record_arrivals: bool,
    /// The protocol version the clients say hello with.
    version: u32,
}

impl Shared {
    /// `parallel` connections may be in their handshake at once.
    pub fn new(parallel: usize, record_arrivals: bool) -> Self {
        Self {
            record_arrivals,
            version: PROTOCOL_VERSION,
            phase: AtomicU8::new(Phase::Warmup as u8),
            done: watch::Sender::new(false),
            connecting: Semaphore::new(parallel.max(1)),
            ready: AtomicUsize::new(0),
            failed: AtomicUsize::new(0),
        }
    }

    /// The same, with clients saying hello in protocol version `version`.
    #[must_use]
    pub fn with_version(mut self, version: u32) -> Self {
        self.version = version;
        self
    }

    /// Moves every client to `phase`.
    pub fn set_phase(&self, phase: Phase) {
        self.phase.store(phase as u8, Ordering::SeqCst);
        if phase == Phase::Done {
            self.done.send_replace(true);
        }
    }

    fn measuring(&self) -> bool {
        self.phase.load(Ordering::Relaxed) == Phase::Measure as u8
    }
}

/// What one client saw during the measurement.
#[derive(Debug, Default)]
pub struct ClientStats {
    /// Binary frames received.
    pub frames: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Keyframes among them.
    pub keys: u64,
    /// Tick→receive latency of each frame, µs.
    pub latencies_us: Vec<u32>,
    /// Frames whose time could not be read (packed deltas before the first keyframe, from
    /// the reference server): counted, without a latency.
    pub untimed: u64,
    /// Ticks missing between consecutive frames (`seq` gaps).
    pub missed: u64,
    /// Frames whose `seq` was not above the previous one.
    pub out_of_order: u64,
    /// Why the client failed, if it did.
    pub failure: Option<String>,
    /// The connection ended before the run did.
    pub closed_early: bool,
    /// Every frame's arrival, when the run records them (`--link`).
    pub arrivals: Vec<Arrival>,
}

/// One frame as it arrived.
#[derive(Debug, Clone, Copy, Default)]
pub struct Arrival {
    /// When, µs since the Unix epoch.
    pub arrival_us: u64,
    /// The frame's `server_time_us`.
    pub stamp_us: u64,
    /// Its tick.
    pub seq: u64,
    /// The keyframe it refers to.
    pub base_seq: u64,
    /// Whether it is a keyframe.
    pub key: bool,
}

impl ClientStats {
    /// A client that failed for `why`.
    pub fn failed(why: &str) -> Self {
        Self {
            failure: Some(why.to_owned()),
            ..Self::default()
        }
    }
}

/// Where a client connects, and over which transport.
#[derive(Debug, Clone)]
pub enum Endpoint {
    /// A websocket URL, `ws://host:port/ws`.
    WebSocket(String),
    /// A WebTransport endpoint (its `https://` URL and certificate hash).
    WebTransport(QuicOffer),
}

impl Endpoint {
    /// The transport's name, as tables print it.
    pub fn transport(&self) -> &'static str {
        match self {
            Self::WebSocket(_) => "websocket",
            Self::WebTransport(_) => "webtransport",
        }
    }

    async fn open(&self) -> Result<Link> {
        match self {
            Self::WebSocket(url) => Link::websocket(url)
                .await
                .map_err(|e| anyhow::anyhow!("connect to {url}: {e}")),
            Self::WebTransport(offer) => Link::webtransport(offer)
                .await
                .map_err(|e| anyhow::anyhow!("connect to {}: {e}", offer.url)),
        }
    }
}

/// Connects, subscribes to `scene` and reads until the run is done.
pub async fn run(
    index: usize,
    endpoint: &Endpoint,
    scene: &str,
    rate: Option<f32>,
    shared: &Shared,
) -> ClientStats {
    let mut done = shared.done.subscribe();
    let connected = {
        // The permit bounds handshakes in flight (the server's accept backlog is finite).
        let _permit = shared.connecting.acquire().await;
        connect(index, endpoint, scene, rate, shared.version).await
    };
    let mut ws = match connected {
        Ok(ws) => ws,
        Err(e) => {
            shared.failed.fetch_add(1, Ordering::Relaxed);
            return ClientStats::failed(&format!("{e:#}"));
        }
    };
    shared.ready.fetch_add(1, Ordering::Relaxed);
    let mut stats = ClientStats::default();
    let mut last_seq: Option<u64> = None;
    let mut clock = FrameClock::default();
    loop {
        let message = tokio::select! {
            m = ws.stream.next() => m,
            _ = done.wait_for(|d| *d) => break,
        };
        match message {
            Some(Ok(Message::Binary(bytes))) => {
                let now = crate::unix_micros();
                let Some((header, timed)) = frame_header(&bytes, &mut clock) else {
                    stats.failure = Some("a binary message is not a pose frame".into());
                    break;
                };
                if ws.answers_pings() {
                    // Over WebTransport: a v1 keyframe, or (protocol version 8) every v2 frame,
                    // naming the avatars of its chunks. A lost acknowledgement is made up for
                    // by the next frame's.
                    let v2 = bytes.first() == Some(&frame2::MAGIC);
                    let avatars = if v2 {
                        frame2::split_by_avatar(&bytes, usize::MAX)
                            .ok()
                            .and_then(|mut parts| parts.pop())
                            .map(|(_, avatars)| avatars)
                    } else if header.kind == FrameKind::Key {
                        posecast_proto::frame::avatars_of(&bytes)
                            .ok()
                            .map(|(_, avatars)| avatars)
                    } else {
                        None
                    };
                    if let Some(avatars) = avatars {
                        ws.acknowledge(&Ack {
                            whole_frame: v2,
                            scene_num: header.scene_num,
                            seq: header.seq,
                            avatars,
                        });
                    }
                }
                let measuring = shared.measuring();
                match last_seq {
                    Some(prev) if header.seq <= prev => {
                        stats.out_of_order += u64::from(measuring);
                    }
                    Some(prev) if measuring => stats.missed += header.seq - prev - 1,
                    _ => {}
                }
                last_seq = Some(last_seq.map_or(header.seq, |p| p.max(header.seq)));
                if measuring {
                    stats.frames += 1;
                    stats.bytes += bytes.len() as u64;
                    stats.keys += u64::from(header.kind == FrameKind::Key);
                    if !timed {
                        stats.untimed += 1;
                        continue;
                    }
                    let latency = now.saturating_sub(header.server_time_us);
                    stats
                        .latencies_us
                        .push(u32::try_from(latency).unwrap_or(u32::MAX));
                    if shared.record_arrivals {
                        stats.arrivals.push(Arrival {
                            arrival_us: now,
                            stamp_us: header.server_time_us,
                            seq: header.seq,
                            base_seq: header.base_seq,
                            key: header.kind == FrameKind::Key,
                        });
                    }
                }
            }
            Some(Ok(Message::Text(text))) => {
                if let Ok(ServerMsg::Error(e)) = serde_json::from_str::<ServerMsg>(&text) {
                    stats.failure = Some(format!("server error: {e}"));
                }
            }
            Some(Ok(Message::Ping(payload))) if ws.answers_pings() => {
                if ws.sink.send(Message::Pong(payload)).await.is_err() {
                    stats.closed_early = true;
                    break;
                }
            }
            Some(Ok(Message::Close(_))) | None => {
                stats.closed_early = true;
                break;
            }
            Some(Ok(_)) => {}
            Some(Err(e)) => {
                stats.failure = Some(format!("read failed: {e}"));
                stats.closed_early = true;
                break;
            }
        }
    }
    // The run is over: a close that fails (the server went first) changes nothing measured.
    ws.sink.send(Message::Close(None)).await.ok();
    stats
}

/// The header of a v1 or a v2 frame (told apart by the first byte), and whether its time is
/// known; `clock` holds the v2 frames read before (a packed delta's time is read against its
/// base frame's, which a client of the reference server that joined between keyframes lacks:
/// such frames count, untimed, until the next keyframe).
pub fn frame_header(bytes: &[u8], clock: &mut FrameClock) -> Option<(FrameHeader, bool)> {
    if bytes.first() == Some(&frame2::MAGIC) {
        let (header, _, timed) = clock.read_untimed(bytes).ok()?;
        if timed {
            clock.record(&header);
        }
        Some((header, timed))
    } else {
        posecast_proto::frame::read_header(bytes)
            .ok()
            .map(|(h, _)| (h, true))
    }
}

/// Opens a connection at `endpoint` and says hello (binary encoding, protocol `version`);
/// returns once `welcome` arrived.
async fn hello(
    endpoint: &Endpoint,
    name: String,
    token: Option<&str>,
    version: u32,
) -> Result<Link> {
    let mut ws = endpoint.open().await?;
    let hello = ClientMsg::Hello {
        version,
        encoding: Encoding::Binary,
        token: token.map(str::to_owned),
        client: Some(name),
    };
    send(&mut ws, &hello).await?;
    expect(&mut ws, |m| matches!(m, ServerMsg::Welcome { .. })).await?;
    Ok(ws)
}

/// A connection for commands (hello with the control token, no subscription).
pub async fn connect_control(url: &str, token: &str) -> Result<Link> {
    hello(
        &Endpoint::WebSocket(url.to_owned()),
        "loadgen-control".into(),
        Some(token),
        PROTOCOL_VERSION,
    )
    .await
}

/// Opens a connection, says hello in protocol `version` and subscribes (at `rate` frames per
/// second, or every tick); returns once `subscribed` arrived.
pub async fn connect(
    index: usize,
    endpoint: &Endpoint,
    scene: &str,
    rate: Option<f32>,
    version: u32,
) -> Result<Link> {
    let mut ws = hello(endpoint, format!("loadgen-{index}"), None, version).await?;
    send(
        &mut ws,
        &ClientMsg::Subscribe {
            scene: SceneId(scene.to_owned()),
            avatars: None,
            rate,
            joints: None,
            morph_weights: None,
            precision: None,
        },
    )
    .await?;
    expect(&mut ws, |m| matches!(m, ServerMsg::Subscribed { .. })).await?;
    Ok(ws)
}

/// Sends a client message as JSON text.
pub async fn send(ws: &mut Link, msg: &ClientMsg) -> Result<()> {
    let text = serde_json::to_string(msg)?;
    ws.sink
        .send(Message::text(text))
        .await
        .map_err(|e| anyhow::anyhow!("send: {e}"))
}

/// Reads text messages until one satisfies `want`; a server error fails.
pub async fn expect(ws: &mut Link, want: impl Fn(&ServerMsg) -> bool) -> Result<ServerMsg> {
    loop {
        let message = tokio::time::timeout(std::time::Duration::from_secs(20), ws.stream.next())
            .await
            .context("no answer within 20 s")?;
        match message {
            Some(Ok(Message::Text(text))) => {
                let msg: ServerMsg = serde_json::from_str(&text)
                    .with_context(|| format!("not a server message: {text}"))?;
                if let ServerMsg::Error(e) = &msg {
                    bail!("server error: {e}");
                }
                if want(&msg) {
                    return Ok(msg);
                }
            }
            Some(Ok(Message::Close(frame))) => bail!("server closed: {frame:?}"),
            Some(Ok(_)) => {}
            Some(Err(e)) => bail!("read failed: {e}"),
            None => bail!("connection ended"),
        }
    }
}
