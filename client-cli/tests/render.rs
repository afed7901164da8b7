//! `posecast-client render`: `--clip/--seek` render a private copy of the avatar (other viewers
//! see no change, no control token needed), and an unknown scene or avatar is said at once.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_proto::command::Command;
use posecast_server::config::Config;
use posecast_server::startup::Server;
use posecast_server::world::command::apply;
use std::time::{Duration, Instant};

async fn render(url: &str, args: &[&str]) -> (std::process::Output, Duration) {
    let mut all = vec!["render", "--url", url];
    all.extend_from_slice(args);
    let all: Vec<String> = all.into_iter().map(str::to_owned).collect();
    let began = Instant::now();
    let output = tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_posecast-client"))
            .args(&all)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    (output, began.elapsed())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_with_a_clip_changes_nothing_others_see() {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    let url = server.ws_url();
    let dir = std::env::temp_dir().join(format!("posecast-render-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("walk.png");
    let state = || {
        let avatar = posecast_proto::msg::AvatarId("avatar".into());
        apply(&server.state.world, &Command::GetAvatar { avatar })
            .unwrap()
            .to_value()
    };
    let before = state();
    // No token: the server generated one, so this connection may only watch.
    let (output, _) = render(
        &url,
        &[
            "--clip",
            "walk",
            "--seek",
            "0.25",
            "--width",
            "160",
            "--height",
            "120",
            "--timed-frames",
            "1",
            "--out",
            out.to_str().unwrap(),
        ],
    )
    .await;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "render failed: {stderr}");
    assert!(stderr.contains("sampled privately"), "{stderr}");
    let png = std::fs::read(&out).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    let after = state();
    for field in ["clip", "paused", "speed", "overrides"] {
        assert_eq!(before[field], after[field], "{field} changed");
    }
    assert_eq!(
        (&after["clip"], &after["paused"]),
        (&"idle".into(), &false.into())
    );

    // Unknown scene and avatar: said at once, not after the 10 s wait.
    let (output, took) = render(
        &url,
        &["--scene", "nowhere", "--out", out.to_str().unwrap()],
    )
    .await;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("no scene nowhere"),
        "{stderr}"
    );
    assert!(took < Duration::from_secs(5), "took {took:?}");
    let (output, took) = render(
        &url,
        &[
            "--avatar",
            "nobody",
            "--clip",
            "walk",
            "--out",
            out.to_str().unwrap(),
        ],
    )
    .await;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("no avatar nobody"),
        "{stderr}"
    );
    assert!(took < Duration::from_secs(5), "took {took:?}");
    std::fs::remove_dir_all(&dir).ok();
    server.stop().await;
}
