//! The server pushes changes; the page never polls. Changes made by someone else (REST) show on
//! the page within a second, while the page sends no command at all: it never sends
//! `list_scenes`, and nothing while idle.

use crate::browser::*;
use crate::common::{self, CONTROL};
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Runs `body` on the server, then measures how long the page takes to satisfy `expr`.
async fn shows_within(
    b: &fantoccini::Client,
    server: &posecast_server::startup::Server,
    body: Value,
    expr: &str,
) -> Duration {
    let (status, answer) = command(server, body.clone()).await;
    assert_eq!(status, 200, "{body}: {answer}");
    let t0 = Instant::now();
    wait_js(b, 60, expr).await;
    t0.elapsed()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_pushes_changes_and_the_page_never_polls() {
    let server = common::server(60.0).await;
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.selected === 'avatar' && window.posecast.frames > 10").await;
    // Settled: what the page sent to start (the rig list, nothing else).
    tokio::time::sleep(Duration::from_millis(500)).await;
    let sent_at_start = wait_js(&b, 60, "window.posecast.sent").await;
    assert_eq!(
        sent_at_start,
        json!({"list_assets": 1}),
        "commands the page sent to start"
    );

    let mut delays = Vec::new();
    let before = wait_js(&b, 60, "window.posecast.camera").await;
    delays.push(shows_within(&b, &server,
        json!({"op": "add_avatar", "scene": "default", "asset": "avatar", "avatar": "newcomer", "position": [1.5, 0, 0]}),
        "document.querySelector('#scene-list button[data-avatar=\"newcomer\"]') !== null && window.posecast.drawn.length === 2").await);
    // The camera frames the scene again with the newcomer (1.5 m to the side): its target
    // moves toward it.
    let framed = wait_js(
        &b,
        60,
        "window.posecast.camera.target[0] > 0.5 && window.posecast.camera",
    )
    .await;
    assert!(
        framed["distance"].as_f64() > before["distance"].as_f64(),
        "the camera backed off to show both: {before} → {framed}"
    );
    delays.push(
        shows_within(
            &b,
            &server,
            json!({"op": "pause", "avatar": "avatar"}),
            "document.querySelector('[data-field=state]')?.textContent.startsWith('paused')",
        )
        .await,
    );
    delays.push(shows_within(&b, &server,
        json!({"op": "play", "avatar": "newcomer", "clip": "wave"}),
        "document.querySelector('#scene-list button[data-avatar=\"newcomer\"] .avatar-summary')?.textContent.startsWith('wave')").await);
    delays.push(
        shows_within(
            &b,
            &server,
            json!({"op": "create_scene", "scene": "annex"}),
            "document.querySelector('#scene-list [data-scene=\"annex\"]') !== null",
        )
        .await,
    );
    delays.push(
        shows_within(
            &b,
            &server,
            json!({"op": "add_avatar", "scene": "annex", "asset": "avatar", "avatar": "visitor"}),
            "document.querySelector('#scene-list button[data-avatar=\"visitor\"]') !== null",
        )
        .await,
    );
    // The clip picker follows what the selected avatar plays, whoever started it.
    delays.push(
        shows_within(
            &b,
            &server,
            json!({"op": "play", "avatar": "avatar", "clip": "walk"}),
            "document.getElementById('clip-select').value === '[null,\"walk\"]'",
        )
        .await,
    );
    delays.push(shows_within(&b, &server,
        json!({"op": "remove_avatar", "avatar": "newcomer"}),
        "document.querySelector('#scene-list [data-avatar=\"newcomer\"]') === null && window.posecast.drawn.length === 1").await);
    delays.push(
        shows_within(
            &b,
            &server,
            json!({"op": "delete_scene", "scene": "annex"}),
            "document.querySelector('#scene-list [data-scene=\"annex\"]') === null",
        )
        .await,
    );

    // Idle for 2.5 s: not one command.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let sent = wait_js(&b, 60, "window.posecast.sent").await;
    assert_eq!(sent, sent_at_start, "the page sent commands of its own");
    assert_eq!(errors(&b).await, json!([]));
    println!("push: shown after {delays:?}; commands sent {sent}");
    b.close().await.unwrap();
    server.stop().await;
}

/// Presence on the page: a user joining with a minted token shows under the scene ("watched
/// by"), their drive on the avatar ("driven by alice (websocket)"); the operator ends the
/// drive from the page; both go when they leave — pushed by the server, the page asking nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_shows_who_watches_and_who_drives() {
    use futures_util::SinkExt;
    // Alice's drive sends no pose: it must outlast the test, not the 2 s drive timeout (a
    // silent drive's end is announced and would take the "driven by" away).
    let server = common::kit_builder(30.0)
        .configure(|c| c.drive_timeout = Duration::from_secs(600))
        .start()
        .await
        .unwrap()
        .into_server();
    let minter = server.state.config.access.mint.clone().unwrap();
    let alice = minter
        .mint(
            posecast_proto::tokens::MintRequest {
                name: "alice".into(),
                rights: vec![
                    posecast_proto::tokens::Right::View,
                    posecast_proto::tokens::Right::Drive,
                ],
                scenes: None,
                avatars: None,
                ttl_s: Some(600),
                max_bytes: None,
                max_objects: None,
            },
            |_| false,
        )
        .unwrap();
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && window.posecast.frames > 5",
    )
    .await;
    let viewers = "document.querySelector('[data-viewers=\"default\"]')?.textContent ?? ''";
    // The page itself watches the scene (with the control token, named `test`).
    wait_js(&b, 60, &format!("({viewers}).includes('watched by test')")).await;

    let mut ws = common::raw_as(
        &server,
        posecast_proto::msg::Encoding::Json,
        Some(&alice.token),
    )
    .await;
    let send = |v: Value| tokio_tungstenite::tungstenite::Message::Text(v.to_string().into());
    ws.send(send(json!({"type": "subscribe", "scene": "default"})))
        .await
        .unwrap();
    wait_js(&b, 60, &format!("({viewers}).includes('alice')")).await;
    ws.send(send(
        json!({"type": "command", "id": 1, "command": {"op": "drive", "avatar": "avatar"}}),
    ))
    .await
    .unwrap();
    let summary = "document.querySelector('#scene-list button[data-avatar=\"avatar\"] .avatar-summary')?.textContent ?? ''";
    wait_js(
        &b,
        60,
        &format!("({summary}).includes('driven by alice (websocket)')"),
    )
    .await;

    // The operator ends the drive from the page; alice may take it again.
    find(&b, "#release-drive").await.click().await.unwrap();
    wait_js(
        &b,
        60,
        &format!(
            "!({summary}).includes('driven by') && document.getElementById('release-drive').hidden"
        ),
    )
    .await;
    ws.send(send(
        json!({"type": "command", "id": 2, "command": {"op": "drive", "avatar": "avatar"}}),
    ))
    .await
    .unwrap();
    wait_js(
        &b,
        60,
        &format!("({summary}).includes('driven by alice (websocket)')"),
    )
    .await;

    ws.close(None).await.unwrap();
    wait_js(
        &b,
        60,
        &format!("!({summary}).includes('driven by') && !({viewers}).includes('alice')"),
    )
    .await;
    assert_eq!(errors(&b).await, json!([]));
}

/// The control room records: Record and Stop recording on the selected avatar make a clip of
/// its rig, and the page links the take as glTF and BVH, which the server serves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_records_a_take_and_links_its_downloads() {
    let server = common::server(30.0).await;
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.selected === 'avatar' && window.posecast.frames > 5").await;
    let name = find(&b, "#take-name").await;
    name.clear().await.unwrap();
    name.send_keys("rehearsal").await.unwrap();
    find(&b, "#record").await.click().await.unwrap();
    wait_js(&b, 60, "document.querySelector('#scene-list button[data-avatar=\"avatar\"] .avatar-summary')?.textContent.includes('recording rehearsal')").await;
    // A few frames into the take (waited for, not slept).
    let frames = wait_js(&b, 60, "window.posecast.frames")
        .await
        .as_u64()
        .unwrap();
    wait_js(&b, 60, &format!("window.posecast.frames > {frames} + 10")).await;
    find(&b, "#stop-recording").await.click().await.unwrap();
    let href = wait_js(
        &b,
        60,
        "document.querySelector('#take-links a[data-take=\"glb\"]')?.getAttribute('href')",
    )
    .await;
    assert_eq!(href, "/api/assets/avatar/clips/rehearsal.glb");
    let (status, glb) = common::get_bytes(server.addr, href.as_str().unwrap()).await;
    assert_eq!(status, 200);
    assert_eq!(&glb[..4], b"glTF");
    let bvh = wait_js(
        &b,
        60,
        "document.querySelector('#take-links a[data-take=\"bvh\"]').getAttribute('href')",
    )
    .await;
    let (status, text) = common::get_bytes(server.addr, bvh.as_str().unwrap()).await;
    assert_eq!(status, 200);
    assert!(text.starts_with(b"HIERARCHY"));
    assert_eq!(errors(&b).await, json!([]));
}

/// The page drives an avatar live (issue 39): "Drive" takes it with the page's own token and
/// holds its pose; a rotation slider of the right shoulder moves that joint as a Rust viewer
/// sees it; the page's repeated poses keep the drive through several drive timeouts (1 s
/// here); "Release drive" ends it and the clip plays again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_drives_an_avatar_live_with_the_joint_sliders() {
    let server = common::kit_builder(30.0)
        .configure(|c| c.drive_timeout = Duration::from_secs(1))
        .start()
        .await
        .unwrap()
        .into_server();
    let mut options = posecast_client::net::ClientOptions::new(server.ws_url(), "default");
    options.encoding = posecast_proto::msg::Encoding::Json;
    options.reconnect = false;
    let viewer = posecast_client::net::Client::connect(options)
        .await
        .unwrap();
    let avatar = posecast_proto::msg::AvatarId("avatar".into());
    assert!(common::wait_for(60.0, || viewer.latest(&avatar).is_some()).await);
    let shoulder = viewer
        .avatar(&avatar)
        .unwrap()
        .skeleton
        .find("r_shoulder")
        .unwrap();

    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.selected === 'avatar' && window.posecast.frames > 5").await;
    find(&b, "#drive").await.click().await.unwrap();
    wait_js(&b, 60, "window.posecast.driving.avatar === 'avatar' && !document.getElementById('release-drive').hidden && document.getElementById('drive').hidden").await;
    let state = avatar_state(&server, "avatar").await;
    assert_eq!(state["driven"], true, "{state}");
    assert_eq!(state["driver"], json!({"name": "test", "via": "websocket"}));

    // The shoulder's sliders set its rotation in the live pose: X 0, Y 0, Z −60°.
    find(&b, r#"#joint-tree button[data-joint="r_shoulder"]"#)
        .await
        .click()
        .await
        .unwrap();
    wait_js(&b, 60, "document.getElementById('dof-note').textContent.startsWith('Driving live') && document.getElementById('dof-2') !== null").await;
    b.execute(
        "for (const [i, v] of [[0, 0], [1, 0], [2, -60]]) { const s = document.getElementById(`dof-${i}`); s.value = String(v); s.dispatchEvent(new Event('input')); }",
        vec![],
    )
    .await
    .unwrap();
    let want = glam::Quat::from_rotation_z(-60f32.to_radians());
    let angle_now = |viewer: &posecast_client::net::Client| {
        viewer.latest(&avatar).map_or(f64::MAX, |p| {
            posecast_proto::quant::angle_between_degrees(p.locals[shoulder].rotation, want)
        })
    };
    assert!(
        common::wait_for(60.0, || angle_now(&viewer) < 0.1).await,
        "the viewer never saw the shoulder at −60° about Z: {}° away",
        angle_now(&viewer)
    );

    // Three drive timeouts later the page still drives and the shoulder still holds: the
    // page repeats its pose (a silent drive would have ended after one).
    let sent = wait_js(&b, 60, "window.posecast.driving.sent").await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let state = avatar_state(&server, "avatar").await;
    assert_eq!(state["driven"], true, "the drive timed out: {state}");
    assert!(angle_now(&viewer) < 0.1, "{}°", angle_now(&viewer));
    let resent = wait_js(&b, 60, "window.posecast.driving.sent").await;
    assert!(
        resent.as_u64().unwrap() >= sent.as_u64().unwrap() + 3,
        "{sent} → {resent}"
    );

    // Released from the page: the clip plays again and the page stops sending.
    find(&b, "#release-drive").await.click().await.unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.driving.avatar === null && !document.getElementById('drive').hidden",
    )
    .await;
    let state = avatar_state(&server, "avatar").await;
    // (`driven` and `driver` are left out of an avatar's state when it is not driven.)
    assert!(
        state["driven"] != true && state["driver"].is_null(),
        "{state}"
    );
    assert_eq!(errors(&b).await, json!([]));
}
