//! Tokens: refused ones leave the page watching and saying why; a `#control=…` link restores control.

use crate::browser::*;
use crate::common::{self, http_as};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::msg::AvatarId;
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::time::Duration;

/// A wrong control token is refused visibly and the page keeps watching: anonymously while
/// anyone may watch, with the view token when views are private. Nothing changes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_control_token_is_refused_and_changes_nothing() {
    for open_view in [true, false] {
        let mut access = common::test_access();
        access.open_view = open_view;
        access
            .add(TokenRule::new(
                "viewer",
                Secret::new("view-token"),
                Role::View,
            ))
            .unwrap();
        let server = common::server_with(60.0, access).await;
        let (_driver, b) = browser().await;
        b.goto(&format!("{}/?debug", server.http_url()))
            .await
            .unwrap();
        wait_js(&b, 60, "window.posecast.state").await;
        find(&b, "#token-view")
            .await
            .send_keys("view-token")
            .await
            .unwrap();
        find(&b, "#token-control")
            .await
            .send_keys("wrong-token")
            .await
            .unwrap();
        find(&b, "#token-apply").await.click().await.unwrap();
        // The refusal is shown, with the server's reason; the page watches.
        wait_js(
            &b,
            60,
            "/refused the control token \\(unauthorized: the token is not valid on this server\\)/.test(document.getElementById('auth-status').textContent)",
        )
        .await;
        find(&b, r#"#scene-list button[data-avatar="avatar"]"#).await;
        wait_js(
            &b,
            60,
            "window.posecast.state === 'online' && window.posecast.frames > 5 \
             && document.getElementById('conn-state').textContent === 'watching' \
             && document.getElementById('playback-controls').disabled",
        )
        .await;
        let name = wait_js(&b, 60, "window.posecast.access").await["name"].clone();
        let expected = if open_view {
            serde_json::Value::Null
        } else {
            "viewer".into()
        };
        assert_eq!(name, expected, "open views: {open_view}");
        // Playing is not offered (and would be refused): the avatar keeps idling.
        find(&b, "#clip-select")
            .await
            .select_by_value(r#"[null,"walk"]"#)
            .await
            .unwrap();
        let _ = find(&b, "#play").await.click().await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        let mut o = ClientOptions::new(server.ws_url(), "default");
        o.token = Some("view-token".into());
        o.reconnect = false;
        let watcher = Client::connect(o).await.unwrap();
        let state = watcher
            .command(posecast_proto::command::Command::GetAvatar {
                avatar: AvatarId("avatar".into()),
            })
            .await
            .unwrap()
            .to_value();
        assert_eq!(state["clip"], "idle", "{state}");
        assert_eq!(errors(&b).await, serde_json::json!([]));
        b.close().await.unwrap();
        server.stop().await;
    }
}

/// Access rules with one control token, as a server that generated `token` has.
fn access_with(token: &str) -> AccessConfig {
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new(
            "generated",
            Secret::new(token),
            Role::Control,
        ))
        .unwrap();
    access
}

/// The server restarts and generates a new control token: the page the old link opened
/// reconnects, watches (frames flow) and says why control is refused; opening the new
/// `#control=…` link in the same tab gives it control again, without reloading.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_restart_with_a_new_token_the_page_watches_until_the_new_link_is_opened() {
    let server = common::server_with(60.0, access_with("first-token-1111")).await;
    let addr = server.addr;
    let base = server.http_url();
    let (_driver, b) = browser().await;
    b.goto(&format!("{base}/?debug#control=first-token-1111"))
        .await
        .unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.access?.control === true \
         && location.hash === '' && document.getElementById('conn-state').textContent === 'online'",
    )
    .await;

    server.stop().await;
    wait_js(&b, 60, "window.posecast.state === 'offline'").await;
    let server = Server::start(Config {
        listen: addr,
        tick_rate: 60.0,
        access: access_with("second-token-2222"),
        ..Config::default()
    })
    .await
    .expect("restart on the same address");
    // Back, watching: frames flow and the page says why it may not control.
    let frames = wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.frames",
    )
    .await
    .as_u64()
    .unwrap();
    wait_js(
        &b,
        60,
        &format!(
            "window.posecast.frames > {frames} + 30 \
             && document.getElementById('conn-state').textContent === 'watching' \
             && document.getElementById('offline').hidden \
             && document.getElementById('playback-controls').disabled"
        ),
    )
    .await;
    let fps = wait_js(
        &b,
        60,
        "/^[1-9][0-9]* frames/.test(document.getElementById('fps').textContent) && document.getElementById('fps').textContent",
    )
    .await;
    let why = wait_js(&b, 60, "document.getElementById('auth-status').textContent").await;
    let why = why.as_str().unwrap();
    assert!(
        why.contains(
            "refused the control token (unauthorized: the token is not valid on this server)"
        ) && why.contains("#control="),
        "{why}"
    );

    // The new link, opened in this tab: control without a reload.
    b.execute("location.hash = '#control=second-token-2222';", vec![])
        .await
        .unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.access?.control === true \
         && document.getElementById('conn-state').textContent === 'online' \
         && document.getElementById('auth-status').textContent === '' \
         && location.hash === '' && !document.getElementById('playback-controls').disabled",
    )
    .await;
    find(&b, "#clip-select")
        .await
        .select_by_value(r#"[null,"walk"]"#)
        .await
        .unwrap();
    find(&b, "#play").await.click().await.unwrap();
    let t0 = std::time::Instant::now();
    let get = r#"{"op":"get_avatar","avatar":"avatar"}"#;
    let clip = async || {
        let (_, body) = http_as(
            &server,
            Some("second-token-2222"),
            "POST",
            "/api/commands",
            Some(get),
        )
        .await;
        serde_json::from_str::<serde_json::Value>(&body).unwrap()["result"]["clip"].clone()
    };
    while clip().await != "walk" {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "play with the new token never reached the server"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(errors(&b).await, serde_json::json!([]));
    println!("restart: watching at {fps} until the new link; refusal shown: {why}");
    b.close().await.unwrap();
    server.stop().await;
}

/// A stale link (`#control=` with a token the server no longer knows) on a server anyone may
/// watch: the page watches and draws the skinned mesh, not the skeleton only (the mesh is read
/// without the refused token).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stale_token_still_shows_the_mesh_where_anyone_may_watch() {
    let server = common::server(60.0).await;
    let (_driver, b) = browser().await;
    b.goto(&format!(
        "{}/?debug#control=stale-token-0000",
        server.http_url()
    ))
    .await
    .unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.frames > 5 \
         && document.getElementById('conn-state').textContent === 'watching'",
    )
    .await;
    wait_js(&b, 60, "window.posecast.meshLoaded === true").await;
    let notices = wait_js(
        &b,
        60,
        "document.querySelector('section.notices').textContent",
    )
    .await;
    assert!(
        !notices.as_str().unwrap_or("").contains("not shown"),
        "{notices}"
    );
    server.stop().await;
}

/// The page hands out a link: "control this scene" mints a token for `guest`, limited to the
/// watched scene for an hour, and the link opened (in this tab) controls that scene as guest.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_makes_a_link_with_a_minted_token_for_one_scene() {
    let server = common::server(60.0).await;
    let (_driver, b) = browser().await;
    b.goto(&format!(
        "{}/?debug#control={}",
        server.http_url(),
        common::CONTROL
    ))
    .await
    .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.watched === 'default' && window.posecast.access?.control === true").await;
    find(&b, "#share-rights")
        .await
        .select_by_value("control")
        .await
        .unwrap();
    find(&b, "#share-make").await.click().await.unwrap();
    let href = wait_js(
        &b,
        60,
        "document.querySelector('#share-link a')?.getAttribute('href')",
    )
    .await;
    let href = href.as_str().unwrap().to_owned();
    assert!(href.contains("#control=pc1."), "{href}");
    b.goto(&href.replacen("/#", "/?debug#", 1)).await.unwrap();
    let access = wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.access?.name === 'guest' && window.posecast.access",
    )
    .await;
    assert_eq!(access["control"], true, "{access}");
    assert_eq!(access["scenes"], serde_json::json!(["default"]), "{access}");
    assert!(access["expires_at"].as_u64().is_some(), "{access}");
    assert_eq!(errors(&b).await, serde_json::json!([]));
    server.stop().await;
}
