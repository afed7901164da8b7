//! A reader that falls behind gets fresh frames, not a stale backlog (issue 22, item 1): with
//! `TCP_NOTSENT_LOWAT` the kernel holds only a few frames of a connection's unsent bytes, so
//! the backlog waits in its outbox, where newer frames replace older ones. Without the bound
//! the kernel's send buffer grows to take the whole backlog, and the client reads seconds of
//! stale frames once it reads again.
//!
//! The client stands for a thin link: a small receive buffer, and a 2 s stall.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use futures_util::StreamExt;
use posecast_proto::frame::read_header;
use posecast_proto::msg::Encoding;
use posecast_server::config::{Config, NetLimits};
use posecast_server::startup::Server;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

/// Frames older than this when read count as stale (the stall is 2 s).
const STALE_US: u64 = 500_000;

/// Stale frames a reader with a small receive buffer gets after a 2 s stall, from a server
/// whose connections may hold `lowat` unsent bytes in the kernel (0: no bound).
async fn stale_frames_after_a_stall(lowat: u32) -> (usize, usize) {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: 60.0,
        access: common::test_access(),
        net: NetLimits {
            tcp_notsent_lowat: lowat,
            ..NetLimits::default()
        },
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    // Twenty avatars: frames of a few kilobytes, as a busy scene sends.
    common::add_extras(&server, 0..20).await;
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let stream = socket.connect(server.addr).await.unwrap();
    let (mut ws, _) = tokio_tungstenite::client_async(server.ws_url(), stream)
        .await
        .unwrap();
    common::hello_and_subscribe(&mut ws, Encoding::Binary, "default", Some("thin")).await;
    // Read for a moment, then stop reading for 2 s while the server keeps ticking.
    let until = tokio::time::Instant::now() + Duration::from_millis(500);
    while tokio::time::timeout_at(until, ws.next()).await.is_ok() {}
    tokio::time::sleep(Duration::from_secs(2)).await;
    // Read again for a second: how many of the frames are stale?
    let (mut stale, mut frames) = (0, 0);
    let until = tokio::time::Instant::now() + Duration::from_secs(1);
    while let Ok(Some(Ok(m))) = tokio::time::timeout_at(until, ws.next()).await {
        if let Message::Binary(bytes) = m {
            let (header, _) = read_header(&bytes).unwrap();
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_micros() as u64;
            frames += 1;
            if now.saturating_sub(header.server_time_us) > STALE_US {
                stale += 1;
            }
        }
    }
    drop(ws);
    server.stop().await;
    (stale, frames)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_reader_gets_fresh_frames_not_a_stale_backlog() {
    let (bounded, bounded_frames) =
        stale_frames_after_a_stall(posecast_server::config::DEFAULT_TCP_NOTSENT_LOWAT).await;
    let (unbounded, unbounded_frames) = stale_frames_after_a_stall(0).await;
    eprintln!(
        "after a 2 s stall: {bounded} of {bounded_frames} frames stale with the bound, \
         {unbounded} of {unbounded_frames} without"
    );
    assert!(
        bounded <= 30,
        "{bounded} stale frames with TCP_NOTSENT_LOWAT (a few kilobytes of kernel queue)"
    );
    assert!(
        unbounded >= 2 * bounded.max(10),
        "without the bound the kernel should have held the backlog: {unbounded} stale"
    );
}
