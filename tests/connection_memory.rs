//! Issue 13: what an idle websocket costs the server, measured on the real binary as a child
//! process (its resident memory from `/proc/<pid>/status`, which the test's own clients cannot
//! pollute), and that the memory is given back when the clients leave.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use futures_util::{SinkExt, StreamExt};
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

const CLIENTS: usize = 1_000;
/// The budget per connected client (issue 13).
const MAX_BYTES_PER_CLIENT: f64 = 64.0 * 1024.0;

/// The `posecast` binary's allocator (the package features of this build).
fn allocator() -> &'static str {
    if cfg!(feature = "jemalloc") {
        "jemalloc"
    } else if cfg!(feature = "mimalloc") {
        "mimalloc"
    } else {
        "glibc"
    }
}

/// Resident memory of process `pid`, bytes (`VmRSS`).
fn rss(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("no VmRSS");
    kb * 1024.0
}

/// A websocket that said hello (and subscribed to `default` when `subscribe`), with a task
/// that reads everything (as a viewer does) until the server closes or `stop` fires.
async fn idle_client(
    addr: SocketAddr,
    subscribe: bool,
    stop: tokio::sync::watch::Receiver<bool>,
) -> tokio::task::JoinHandle<()> {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    ws.send(Message::Text(
        r#"{"type":"hello","version":1,"encoding":"binary"}"#.into(),
    ))
    .await
    .unwrap();
    if subscribe {
        ws.send(Message::Text(
            r#"{"type":"subscribe","scene":"default"}"#.into(),
        ))
        .await
        .unwrap();
    }
    // Ready once the server answered what was asked (welcome, and subscribed).
    let mut answers = 0;
    let wanted = if subscribe { 2 } else { 1 };
    while answers < wanted {
        match tokio::time::timeout(Duration::from_secs(10), ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                if t.contains("\"welcome\"") || t.contains("\"subscribed\"") {
                    answers += 1;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("no answer to hello/subscribe: {other:?}"),
        }
    }
    let mut stop = stop;
    tokio::spawn(async move {
        loop {
            tokio::select! {
                m = ws.next() => if !matches!(m, Some(Ok(_))) { return },
                _ = stop.changed() => break,
            }
        }
        ws.close(None).await.ok();
        // Read until the server's answer so the closing handshake completes.
        while let Ok(Some(Ok(_))) = tokio::time::timeout(Duration::from_secs(2), ws.next()).await {}
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idle_websocket_costs_at_most_64_kib_and_gives_it_back_when_it_leaves() {
    let (_, soft, hard) = posecast_server::service::limits::raise_nofile_limit().unwrap();
    if soft < (CLIENTS + 500) as u64 {
        posecast_proto::testing::skip(&format!(
            "{CLIENTS} websockets need more open files than the hard limit {hard}"
        ));
        return;
    }
    let per_address = (CLIENTS + 100).to_string();
    let server = Posecast::start(
        &[
            "--no-persist",
            "--max-connections-per-address",
            &per_address,
        ],
        &[("RUST_LOG", "warn")],
    );
    let pid = server.pid();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);

    // Warm up what every server has after its first client (worker threads' caches, lazily
    // built descriptions), so the start level is a serving server's.
    let warm = idle_client(server.addr, true, stop_rx.clone()).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let start = rss(pid);

    let mut clients = Vec::with_capacity(CLIENTS);
    for i in 0..CLIENTS {
        clients.push(idle_client(server.addr, i % 2 == 0, stop_rx.clone()).await);
    }
    // Half of them receive 60 frames a second; let that run.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let held = rss(pid);
    let per_client = (held - start) / CLIENTS as f64;

    stop_tx.send(true).unwrap();
    for c in clients {
        c.await.unwrap();
    }
    warm.await.unwrap();
    let closed = Instant::now();
    let mut after = rss(pid);
    while after > start * 1.1 && closed.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(200)).await;
        after = rss(pid);
    }
    let returned_in = closed.elapsed();
    eprintln!(
        "{} allocator, {CLIENTS} idle websockets (half subscribed): start {:.1} MB, held {:.1} MB, \
         {:.1} KiB per client; after close {:.1} MB ({:+.1} %) within {returned_in:?}",
        allocator(),
        start / 1e6,
        held / 1e6,
        per_client / 1024.0,
        after / 1e6,
        (after / start - 1.0) * 100.0
    );
    assert!(
        per_client <= MAX_BYTES_PER_CLIENT,
        "{:.1} KiB per idle websocket",
        per_client / 1024.0
    );
    assert!(
        after <= start * 1.1,
        "resident memory {:.1} MB 10 s after every client left; it started at {:.1} MB",
        after / 1e6,
        start / 1e6
    );
}
