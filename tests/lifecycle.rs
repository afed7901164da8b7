//! The `posecast` binary as a child process: graceful shutdown on SIGTERM, start-up on an
//! unusable data folder, and what it logs at the most verbose level.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::{Posecast, run_to_exit};
use futures_util::{SinkExt, StreamExt};
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

/// A websocket to `addr` that said hello (with `token`) and subscribed to `default`, once the
/// subscription is confirmed.
async fn subscriber(addr: SocketAddr, token: Option<&str>) -> common::Ws {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    let hello = ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        encoding: Encoding::Binary,
        token: token.map(str::to_owned),
        client: None,
    };
    for msg in [
        serde_json::to_string(&hello).unwrap(),
        r#"{"type":"subscribe","scene":"default"}"#.to_owned(),
    ] {
        ws.send(Message::Text(msg.into())).await.unwrap();
    }
    loop {
        match common::next_text(&mut ws).await {
            Some(ServerMsg::Subscribed { .. }) => return ws,
            Some(ServerMsg::Error(e)) => panic!("{e:?}"),
            Some(_) => {}
            None => panic!("closed before subscribed"),
        }
    }
}

/// Reads until the close frame; its code, or `None` when the connection ended without one.
async fn close_code(mut ws: common::Ws) -> Option<u16> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while let Ok(Some(Ok(m))) = tokio::time::timeout_at(deadline, ws.next()).await {
        if let Message::Close(frame) = m {
            return frame.map(|f| u16::from(f.code));
        }
    }
    None
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_closes_every_websocket_with_1001_within_the_drain_time() {
    const CLIENTS: usize = 200;
    let drain = Duration::from_secs(2);
    let mut server = Posecast::start(&["--no-persist", "--shutdown-drain", "2"], &[]);
    let addr = server.addr;
    let mut clients = Vec::new();
    for _ in 0..CLIENTS {
        clients.push(subscriber(addr, None).await);
    }
    // Every client reads (frames, then the close) from now on, as a live viewer would.
    let readers: Vec<_> = clients
        .into_iter()
        .map(|ws| tokio::spawn(close_code(ws)))
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;

    server.terminate();
    let signalled = Instant::now();
    let exited = tokio::task::spawn_blocking(move || {
        let status = server.wait_exit(Duration::from_secs(10));
        (status, signalled.elapsed(), server)
    });
    let mut codes = Vec::new();
    for r in readers {
        codes.push(r.await.unwrap());
    }
    let (status, took, server) = exited.await.unwrap();
    let missing = codes.iter().filter(|c| c.is_none()).count();
    assert_eq!(
        missing,
        0,
        "{missing} of {CLIENTS} clients got no close frame; output: {:?}",
        server.output()
    );
    assert!(codes.iter().all(|c| *c == Some(1001)), "{codes:?}");
    let status = status.expect("still running 10 s after SIGTERM");
    assert!(status.success(), "{status:?}: {:?}", server.output());
    // The drain time plus process start-up of the exit path; clients that answer the close at
    // once let it finish well before the bound.
    assert!(
        took < drain + Duration::from_millis(1000),
        "exited {took:?} after SIGTERM"
    );
}

#[test]
fn an_unusable_data_folder_fails_start_up_and_names_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    // Tests run as root, so permissions cannot make a folder unwritable; a regular file where
    // the folder (or a parent of it) should be can.
    let file = dir.path().join("not-a-folder");
    std::fs::write(&file, b"x").unwrap();
    let under_file = file.join("data");
    for data in [&file, &under_file] {
        let data = data.to_str().unwrap();
        let (status, output) = run_to_exit(&["--data", data], &[]);
        assert!(!status.success(), "{data}: started anyway: {output}");
        assert!(
            output.contains(data) && output.contains("data folder"),
            "{data}: the error does not name the folder: {output}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_token_is_logged_even_at_trace_level() {
    const TOKEN: &str = "trace-secret-control-token-5e1f";
    let mut server = Posecast::start(
        &["--no-persist", "--control-token", TOKEN],
        &[("RUST_LOG", "trace")],
    );
    let addr = server.addr;
    let mut ws = subscriber(addr, Some(TOKEN)).await;
    ws.send(Message::Text(
        r#"{"type":"command","id":1,"command":{"op":"pause","avatar":"avatar"}}"#.into(),
    ))
    .await
    .unwrap();
    loop {
        match common::next_text(&mut ws).await {
            Some(ServerMsg::Ack { id: 1, .. }) => break,
            Some(ServerMsg::Error(e)) => panic!("{e:?}"),
            Some(_) => {}
            None => panic!("closed before the ack"),
        }
    }
    for scheme in ["Bearer", "bearer"] {
        let auth = format!("{scheme} {TOKEN}");
        let (status, _, body) = common::http_with_headers(
            addr,
            "POST",
            "/api/commands",
            &[("Authorization", &auth)],
            br#"{"op":"resume","avatar":"avatar"}"#,
        )
        .await;
        assert_eq!(status, 200, "{body}");
    }
    ws.close(None).await.ok();
    server.terminate();
    tokio::task::spawn_blocking(move || {
        assert!(server.wait_exit(Duration::from_secs(10)).is_some());
        // The reader threads may still be draining the pipes.
        std::thread::sleep(Duration::from_millis(200));
        let output = server.output();
        assert!(
            output.iter().any(|l| l.contains("TRACE")),
            "trace logging was not on, so this proves nothing: {output:?}"
        );
        let leaks: Vec<_> = output.iter().filter(|l| l.contains(TOKEN)).collect();
        assert!(leaks.is_empty(), "the token was printed: {leaks:#?}");
    })
    .await
    .unwrap();
}
