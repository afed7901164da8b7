//! The reference server posecast's fan-out is measured against (`loadgen --server reference`):
//! the plain design done plainly. Frames are recorded up front and replayed at the tick rate
//! into one `tokio::sync::broadcast`; per client, one task writes every frame into its
//! tokio-tungstenite websocket (a client that lags skips what it missed) and one reads it
//! (for the close; tungstenite answers pings as it reads). Nothing else per client: no timers,
//! no `select!`, no pacing, no encoding.
//!
//! Its frames are posecast's own bytes: before serving, an in-process posecast scene of the
//! same avatars playing the same clips runs for [`RECORD_SECONDS`] and the frames its feed
//! gives a full-rate binary subscriber of the run's protocol version are kept — wire v1, or
//! wire v2 (deltas against the previous frame). They are replayed in a loop, each header
//! restamped (tick, time, base tick), so both servers send the same sizes at the same rate and
//! the comparison is of the fan-out alone. (A lagging v2 client here gets deltas it could not
//! decode; loadgen's clients do not decode, and posecast's re-keying of such a client is work
//! only posecast does.)
//!
//! It speaks just enough of the protocol for `loadgen`'s clients: `hello` → `welcome`,
//! `subscribe` → `subscribed`, then binary frames.

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use posecast_proto::command::Command;
use posecast_proto::frame::{self, FrameHeader, HEADER_BYTES};
use posecast_proto::frame2::{self, FrameClock};
use posecast_proto::msg::{Access, AvatarId, ClientMsg, Encoding, SceneId, ServerMsg};
use posecast_server::builtin::{BUILTIN_ASSET, rig};
use posecast_server::metrics::Metrics;
use posecast_server::quota::Quotas;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::{Next, Outbox};
use posecast_server::world::{World, command};
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast;
use tokio_tungstenite::tungstenite::Message;

/// Frames a client may fall behind before it skips to the newest (tokio broadcast's lag):
/// about a second at 60 Hz.
const LAG_FRAMES: usize = 64;

/// Seconds of posecast's frames replayed, recorded from a subscription made
/// [`SETTLE_SECONDS`] after the clips started (their first moments are not typical): its
/// keyframe, then what a subscriber gets (on wire v2, deltas: a v2 reader that keeps up gets a
/// keyframe every 10 s, so the loop's one keyframe a replay is where a client that joined
/// between keyframes can start reading packed deltas' times).
pub const RECORD_SECONDS: f64 = 3.0;
/// Seconds the clips play before the recording subscribes.
pub const SETTLE_SECONDS: f64 = 1.0;

/// Serves on `listen` until the process is killed: `avatars` built-in avatars playing `clips`
/// in turn, ticked at `tick_rate`, in the frames of protocol `protocol`.
pub fn serve(
    listen: SocketAddr,
    avatars: usize,
    clips: &[String],
    tick_rate: f32,
    protocol: u32,
) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let recorded = record(avatars, clips, tick_rate, protocol).await?;
        let (frames, _) = broadcast::channel(LAG_FRAMES);
        tokio::spawn(replay(recorded, tick_rate, frames.clone()));
        let listener = tokio::net::TcpListener::bind(listen)
            .await
            .with_context(|| format!("bind {listen}"))?;
        loop {
            let (tcp, _) = listener.accept().await?;
            let frames = frames.subscribe();
            tokio::spawn(async move {
                // A client that fails only ends itself.
                client(tcp, frames, tick_rate).await.ok();
            });
        }
    })
}

/// One recorded frame: its header, and the bytes after it.
#[derive(Debug, Clone)]
struct Recorded {
    header: FrameHeader,
    avatars: usize,
    body: Bytes,
    v2: bool,
    /// A packed delta (protocol version 7), whose time is sent against its base frame's.
    packed: bool,
}

impl Recorded {
    /// A v1 or v2 frame's header and body; `None` for anything else. `clock` holds the frames
    /// read before (a packed delta's time is read against its base frame's).
    fn parse(bytes: &Bytes, clock: &mut FrameClock) -> Option<Self> {
        if bytes.first() == Some(&frame2::MAGIC) {
            let base_time = |h: &FrameHeader| clock.time_of(h.scene_num, h.base_seq);
            let (header, avatars) = clock.read(bytes).ok()?;
            let packed = bytes.get(1) == Some(&3);
            // v2 headers are varints: the body starts where the same header, written, ends.
            let mut head = Vec::new();
            if packed {
                frame2::write_packed_header(&header, base_time(&header)?, avatars, &mut head);
            } else {
                frame2::write_header(&header, avatars, &mut head);
            }
            clock.record(&header);
            bytes.starts_with(&head).then(|| Self {
                header,
                avatars,
                body: bytes.slice(head.len()..),
                v2: true,
                packed,
            })
        } else {
            let (header, avatars) = frame::read_header(bytes).ok()?;
            Some(Self {
                header,
                avatars: usize::from(avatars),
                body: bytes.slice(HEADER_BYTES..),
                v2: false,
                packed: false,
            })
        }
    }

    /// The frame as tick `seq` at `server_time_us`, referring as far back as it did; a packed
    /// delta's base frame was sent at `base_time_us`.
    fn stamped(&self, seq: u64, server_time_us: u64, base_time_us: u64) -> Bytes {
        let back = self.header.seq.saturating_sub(self.header.base_seq);
        let header = FrameHeader {
            seq,
            server_time_us,
            base_seq: seq.saturating_sub(back),
            ..self.header
        };
        let mut out = Vec::with_capacity(HEADER_BYTES + self.body.len());
        if self.packed {
            frame2::write_packed_header(&header, base_time_us, self.avatars, &mut out);
        } else if self.v2 {
            frame2::write_header(&header, self.avatars, &mut out);
        } else {
            let count = u16::try_from(self.avatars).unwrap_or(u16::MAX);
            frame::write_header(&header, count, &mut out);
        }
        out.extend_from_slice(&self.body);
        Bytes::from(out)
    }
}

/// [`RECORD_SECONDS`] of posecast's frames of the scene (see the module doc), in tick order.
async fn record(
    avatars: usize,
    clips: &[String],
    tick_rate: f32,
    protocol: u32,
) -> Result<Vec<Recorded>> {
    let world = World::new(tick_rate, Quotas::default(), Arc::new(Metrics::new()));
    world.library.insert(rig()?);
    let scene = SceneId("default".into());
    let handle = world.create_scene(scene.clone())?;
    for i in 0..avatars {
        let avatar = AvatarId(format!("{BUILTIN_ASSET}-{i}"));
        world.add_avatar(&scene, BUILTIN_ASSET, Some(avatar.clone()))?;
        if let Some(clip) = clips.get(i % clips.len().max(1)) {
            command::apply(
                &world,
                &Command::Play {
                    avatar,
                    clip: clip.clone(),
                    from_asset: None,
                    speed: None,
                    looping: None,
                    start: None,
                    fade: None,
                    root_motion: None,
                },
            )?;
        }
    }
    tokio::time::sleep(Duration::from_secs_f64(SETTLE_SECONDS)).await;
    let outbox = Arc::new(Outbox::new());
    handle.subscribe(
        Subscriber::new(0, outbox.clone(), Encoding::Binary, None, 1).with_version(protocol),
    )?;
    let per_second = f64::from(tick_rate);
    let wanted = (RECORD_SECONDS * per_second).ceil().max(1.0) as usize;
    // Enough to find the first keyframe and a whole run of `wanted` from it.
    let total = 2 * wanted;
    let mut recorded: Vec<Recorded> = Vec::with_capacity(total);
    let mut clock = FrameClock::default();
    // Read as the frames come (every tick, in order): a reader this prompt gets every one.
    let deadline = tokio::time::Instant::now()
        + Duration::from_secs_f64(4.0 * (SETTLE_SECONDS + 2.0 * RECORD_SECONDS));
    while recorded.len() < total {
        let next = tokio::time::timeout_at(deadline, outbox.next()).await;
        let Ok(Next::Send(messages)) = next else {
            bail!(
                "the recording scene gave {} of {wanted} frames",
                recorded.len()
            );
        };
        for m in messages {
            if let axum::extract::ws::Message::Binary(bytes) = m
                && let Some(frame) = Recorded::parse(&bytes, &mut clock)
            {
                recorded.push(frame);
            }
        }
    }
    // Start the loop on the first keyframe (the subscription's own), as a subscriber's
    // stream does.
    let first_key = recorded
        .iter()
        .position(|r| r.header.seq == r.header.base_seq)
        .unwrap_or(0)
        .min(recorded.len() - wanted);
    Ok(recorded.drain(first_key..first_key + wanted).collect())
}

/// Sends the recorded frames in a loop at `tick_rate`, each stamped with its tick and the
/// time (ticks the process was too late for are skipped).
async fn replay(recorded: Vec<Recorded>, tick_rate: f32, frames: broadcast::Sender<Bytes>) {
    let mut ticks = tokio::time::interval(Duration::from_secs_f64(1.0 / f64::from(tick_rate)));
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // The times of the frames sent, newest first, for packed deltas' base frames.
    let mut sent: VecDeque<(u64, u64)> = VecDeque::with_capacity(RING);
    const RING: usize = 64;
    for seq in 1u64.. {
        ticks.tick().await;
        let frame = &recorded[(seq as usize - 1) % recorded.len()];
        let now = crate::unix_micros();
        let back = frame.header.seq.saturating_sub(frame.header.base_seq);
        let base_time = sent
            .iter()
            .find(|(s, _)| *s == seq.saturating_sub(back))
            .map_or(now, |(_, t)| *t);
        frames.send(frame.stamped(seq, now, base_time)).ok();
        sent.push_front((seq, now));
        sent.truncate(RING);
    }
}

/// One client: hello, subscribe, then every broadcast frame.
async fn client(
    tcp: tokio::net::TcpStream,
    mut frames: broadcast::Receiver<Bytes>,
    tick_rate: f32,
) -> Result<()> {
    tcp.set_nodelay(true)?;
    let mut ws = tokio_tungstenite::accept_async(tcp).await?;
    let reply =
        |msg: &ServerMsg| -> Result<Message> { Ok(Message::text(serde_json::to_string(msg)?)) };
    // Hello, then subscribe: loadgen's clients send exactly these.
    while let Some(message) = ws.next().await {
        let Message::Text(text) = message? else {
            continue;
        };
        match serde_json::from_str::<ClientMsg>(&text)? {
            ClientMsg::Hello { version, .. } => {
                ws.send(reply(&ServerMsg::Welcome {
                    version,
                    encoding: Encoding::Binary,
                    server: "loadgen reference".into(),
                    tick_rate,
                    server_time_us: 0,
                    access: Access::default(),
                })?)
                .await?;
            }
            ClientMsg::Subscribe { scene, .. } => {
                ws.send(reply(&ServerMsg::Subscribed {
                    scene,
                    scene_num: 1,
                    rate: Some(tick_rate),
                    joints: None,
                    precision: None,
                })?)
                .await?;
                break;
            }
            _ => {}
        }
    }
    // Drop everything queued before the subscription: frames start now.
    frames = frames.resubscribe();
    let (mut sink, mut stream) = ws.split();
    // The reader: until the client closes (its messages are otherwise ignored).
    tokio::spawn(async move {
        while let Some(Ok(message)) = stream.next().await {
            if matches!(message, Message::Close(_)) {
                break;
            }
        }
    });
    // The writer: every frame, until the socket fails.
    loop {
        match frames.recv().await {
            Ok(bytes) => sink.send(Message::Binary(bytes)).await?,
            Err(broadcast::error::RecvError::Lagged(_)) => {}
            Err(broadcast::error::RecvError::Closed) => return Ok(()),
        }
    }
}
