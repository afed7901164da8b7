//! The reference server posecast's fan-out is measured against (`loadgen --server reference`):
//! the plain design a competent engineer would write first — one `tokio::sync::broadcast`
//! channel of encoded frames, one task per client that says hello, then forwards every frame
//! into its tokio-tungstenite websocket (a client that lags skips what it missed).
//!
//! Its frames are posecast's own: an in-process posecast scene of the same avatars playing
//! the same clips, ticked by posecast's ticker and encoded once per tick by its feed, is read
//! through one outbox and broadcast. So both servers send the same bytes at the same rate and
//! the comparison is of the fan-out alone: per-client work, wake-ups, syscalls, locking.
//! It speaks just enough of the protocol for `loadgen`'s clients: `hello` → `welcome`,
//! `subscribe` → `subscribed`, then binary frames.

use anyhow::{Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use posecast_proto::command::Command;
use posecast_proto::msg::{Access, AvatarId, ClientMsg, Encoding, SceneId, ServerMsg};
use posecast_server::builtin::{BUILTIN_ASSET, rig};
use posecast_server::metrics::Metrics;
use posecast_server::quota::Quotas;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::{Next, Outbox};
use posecast_server::world::{World, command};
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::sync::broadcast;
use tokio_tungstenite::tungstenite::Message;

/// Frames a client may fall behind before it skips to the newest (tokio broadcast's lag).
const LAG_FRAMES: usize = 4;

/// Serves on `listen` until the process is killed: `avatars` built-in avatars playing `clips`
/// in turn, ticked at `tick_rate`.
pub fn serve(listen: SocketAddr, avatars: usize, clips: &[String], tick_rate: f32) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let frames = frame_source(avatars, clips, tick_rate)?;
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

/// posecast's scene, ticking, with its binary frames broadcast (see the module doc).
fn frame_source(
    avatars: usize,
    clips: &[String],
    tick_rate: f32,
) -> Result<broadcast::Sender<Bytes>> {
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
    let outbox = Arc::new(Outbox::new());
    handle.subscribe(Subscriber::new(
        0,
        outbox.clone(),
        Encoding::Binary,
        None,
        1,
    ))?;
    let (frames, _) = broadcast::channel(LAG_FRAMES);
    let sender = frames.clone();
    tokio::spawn(async move {
        // The world lives as long as its only reader: the scene keeps ticking.
        let _world = world;
        while let Next::Send(messages) = outbox.next().await {
            for m in messages {
                if let axum::extract::ws::Message::Binary(bytes) = m {
                    sender.send(bytes).ok();
                }
            }
        }
    });
    Ok(frames)
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
    loop {
        tokio::select! {
            frame = frames.recv() => match frame {
                Ok(bytes) => sink.send(Message::Binary(bytes)).await?,
                Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => return Ok(()),
            },
            message = stream.next() => match message {
                Some(Ok(Message::Close(_)) | Err(_)) | None => return Ok(()),
                Some(Ok(_)) => {}
            },
        }
    }
}
