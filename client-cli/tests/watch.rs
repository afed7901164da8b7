//! `posecast-client watch` on a scene the server does not have says so at once and exits
//! with an error, instead of showing 0 frames/s for ever.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::time::{Duration, Instant};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_on_an_unknown_scene_says_so_and_exits() {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    let url = server.ws_url();
    let began = Instant::now();
    let output = tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_posecast-client"))
            .args([
                "watch",
                "--url",
                &url,
                "--scene",
                "nowhere",
                "--seconds",
                "20",
            ])
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let took = began.elapsed();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("no scene nowhere"), "{stderr}");
    assert!(took < Duration::from_secs(5), "took {took:?}");
    server.stop().await;
}
