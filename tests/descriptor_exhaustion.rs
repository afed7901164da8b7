//! Issue 13: a server out of file descriptors (accept fails with EMFILE) backs off instead of
//! spinning, keeps streaming to the clients it has, warns once (not per failure), and serves again as soon as
//! descriptors are free. The real binary runs as a child whose descriptor limit the test
//! lowers (prlimit) after start, below its connection cap, so `accept` really fails.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use futures_util::{SinkExt, StreamExt};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::Message;

/// User + system CPU time of process `pid` so far (`/proc/<pid>/stat`, 100 ticks a second).
fn cpu_time(pid: u32) -> Duration {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    let after_name = stat.rsplit_once(')').unwrap().1;
    let fields: Vec<u64> = after_name
        .split_whitespace()
        .skip(11)
        .take(2)
        .map(|v| v.parse().unwrap())
        .collect();
    Duration::from_millis((fields[0] + fields[1]) * 10)
}

fn open_descriptors(pid: u32) -> u64 {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .count() as u64
}

async fn healthz(addr: std::net::SocketAddr) -> Option<String> {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.ok()?;
    tcp.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .await
        .ok()?;
    let mut response = String::new();
    tokio::time::timeout(
        Duration::from_millis(500),
        tcp.read_to_string(&mut response),
    )
    .await
    .ok()?
    .ok()?;
    response.starts_with("HTTP/1.1 200").then_some(response)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn out_of_descriptors_the_accept_loop_backs_off_keeps_streaming_and_recovers() {
    const ATTACKERS: usize = 100;
    let mut server = Posecast::start(
        &[
            "--no-persist",
            "--header-read-timeout",
            "1",
            "--max-connections-per-address",
            "1000",
        ],
        &[("RUST_LOG", "info")],
    );
    let (addr, pid) = (server.addr, server.pid());

    // A viewer, connected while descriptors are plenty.
    let (mut viewer, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    for m in [
        r#"{"type":"hello","version":1,"encoding":"binary"}"#,
        r#"{"type":"subscribe","scene":"default"}"#,
    ] {
        viewer.send(Message::Text(m.into())).await.unwrap();
    }
    let frames = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counted = frames.clone();
    let reader = tokio::spawn(async move {
        while let Some(Ok(m)) = viewer.next().await {
            if matches!(m, Message::Binary(_)) {
                counted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
    });
    tokio::time::sleep(Duration::from_millis(300)).await;

    // Leave the server 20 descriptors, then take them with silent sockets: the rest of the
    // attackers wait in the listen backlog while every accept fails.
    let limit = open_descriptors(pid) + 20;
    rlimit::prlimit(
        i32::try_from(pid).unwrap(),
        rlimit::Resource::NOFILE,
        Some((limit, limit)),
        None,
    )
    .unwrap();
    let mut attackers = Vec::new();
    for _ in 0..ATTACKERS {
        attackers.push(tokio::net::TcpStream::connect(addr).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(
        healthz(addr).await.is_none(),
        "the server still had descriptors: the test proves nothing"
    );

    // Exhausted for a second: little CPU (a spinning accept loop burns a whole core), and the
    // viewer still gets its frames.
    let (cpu_before, frames_before) = (
        cpu_time(pid),
        frames.load(std::sync::atomic::Ordering::Relaxed),
    );
    let window = Duration::from_secs(1);
    tokio::time::sleep(window).await;
    let cpu = cpu_time(pid) - cpu_before;
    let streamed = frames.load(std::sync::atomic::Ordering::Relaxed) - frames_before;

    // The attackers leave (or the header timeout would close them): service resumes.
    drop(attackers);
    let left = Instant::now();
    let mut recovered = None;
    while left.elapsed() < Duration::from_secs(5) {
        if healthz(addr).await.is_some() {
            recovered = Some(left.elapsed());
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    reader.abort();
    server.terminate();
    tokio::task::spawn_blocking(move || server.wait_exit(Duration::from_secs(5)).map(|_| server))
        .await
        .unwrap()
        .map(|server| {
            let output = server.output();
            let warnings = output
                .iter()
                .filter(|l| l.contains("accept failed"))
                .count();
            eprintln!(
                "out of descriptors for {window:?}: server CPU {cpu:?}, {streamed} frames \
                 streamed to the viewer; /healthz again {recovered:?} after the attackers left; \
                 {warnings} warning(s)"
            );
            assert_eq!(warnings, 1, "one warning, not one per failure: {output:#?}");
        })
        .expect("the server did not exit on SIGTERM");
    assert!(
        cpu < window / 4,
        "the server used {cpu:?} of CPU in {window:?} while out of descriptors"
    );
    assert!(
        streamed >= 30,
        "the viewer got {streamed} frames in {window:?}"
    );
    let recovered = recovered.expect("/healthz still failing 5 s after the attackers left");
    assert!(recovered < Duration::from_millis(1500), "{recovered:?}");
}
