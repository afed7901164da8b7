//! Presence (issue 39): the scene list says who watches each scene (by token name) and who
//! drives each avatar and how, and tells its watchers when that changes.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, http, raw_as, server};
use futures_util::SinkExt;
use posecast_proto::command::{DriveVia, Driver, SceneInfo, Viewer};
use posecast_proto::msg::{Encoding, ServerMsg};
use posecast_proto::tokens::{MintRequest, Right};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;

/// The next text message of `ws` that `pick` accepts (others skipped); `None` when the socket
/// closes or nothing accepted comes within a minute (far above what a busy machine needs: the
/// server gathers viewer changes for a second).
async fn next_where<T>(
    ws: &mut common::Ws,
    mut pick: impl FnMut(ServerMsg) -> Option<T>,
) -> Option<T> {
    use futures_util::StreamExt;
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        let msg = tokio::time::timeout_at(deadline, ws.next())
            .await
            .ok()??
            .ok()?;
        if let Message::Text(t) = msg
            && let Some(found) = pick(serde_json::from_str(t.as_str()).unwrap())
        {
            return Some(found);
        }
    }
}

async fn send(ws: &mut common::Ws, msg: serde_json::Value) {
    ws.send(Message::Text(msg.to_string().into()))
        .await
        .unwrap();
}

#[tokio::test]
async fn watchers_see_who_watches_and_who_drives() {
    let server = server(30.0).await;
    let minter = server.state.config.access.mint.clone().unwrap();
    let alice = minter
        .mint(
            MintRequest {
                name: "alice".into(),
                rights: vec![Right::View, Right::Drive],
                scenes: None,
                avatars: None,
                ttl_s: Some(600),
                max_bytes: None,
                max_objects: None,
            },
            |_| false,
        )
        .unwrap();

    let mut dashboard = raw_as(&server, Encoding::Json, Some(CONTROL)).await;
    send(&mut dashboard, json!({"type": "watch_scenes"})).await;
    let scenes = next_where(&mut dashboard, |m| match m {
        ServerMsg::Scenes { scenes } => Some(scenes),
        _ => None,
    })
    .await
    .unwrap();
    assert!(scenes[0].viewers.is_empty(), "{:?}", scenes[0].viewers);

    // Alice and an anonymous viewer subscribe: one `viewers` message tells both.
    let mut a = raw_as(&server, Encoding::Json, Some(&alice.token)).await;
    send(&mut a, json!({"type": "subscribe", "scene": "default"})).await;
    let mut anon = raw_as(&server, Encoding::Json, None).await;
    send(&mut anon, json!({"type": "subscribe", "scene": "default"})).await;
    let both = vec![
        Viewer {
            name: Some("alice".into()),
            connections: 1,
        },
        Viewer {
            name: None,
            connections: 1,
        },
    ];
    let seen = next_where(&mut dashboard, |m| match m {
        ServerMsg::Viewers { scene, viewers } if scene.0 == "default" && viewers == both => {
            Some(())
        }
        _ => None,
    })
    .await;
    assert!(
        seen.is_some(),
        "no viewers message with alice and an anonymous viewer"
    );
    let (_, listed) = http(&server, "GET", "/api/scenes", None).await;
    let listed: Vec<SceneInfo> = serde_json::from_str(&listed).unwrap();
    assert_eq!(listed[0].viewers, both);

    // Alice drives the avatar: the dashboard sees who and how.
    send(
        &mut a,
        json!({"type": "command", "id": 1, "command": {"op": "drive", "avatar": "avatar"}}),
    )
    .await;
    let driver = next_where(&mut dashboard, |m| match m {
        ServerMsg::AvatarChanged { avatar, .. } if avatar.driven => Some(avatar.driver),
        _ => None,
    })
    .await
    .unwrap();
    assert_eq!(
        driver,
        Some(Driver {
            name: "alice".into(),
            via: DriveVia::Websocket
        })
    );

    // Alice leaves: the avatar is free again and she no longer watches.
    a.close(None).await.unwrap();
    let released = next_where(&mut dashboard, |m| match m {
        ServerMsg::AvatarChanged { avatar, .. } if !avatar.driven => Some(avatar.driver),
        _ => None,
    })
    .await;
    assert_eq!(released, Some(None));
    let only_anonymous = vec![Viewer {
        name: None,
        connections: 1,
    }];
    let seen = next_where(&mut dashboard, |m| match m {
        ServerMsg::Viewers { viewers, .. } if viewers == only_anonymous => Some(()),
        _ => None,
    })
    .await;
    assert!(seen.is_some(), "no viewers message without alice");
    server.stop().await;
}

/// A scene's subscribers hear who watches it too (not only the scene list's watchers), and a
/// driver that goes silent past `--drive-timeout` while staying connected is announced like
/// one that leaves: `avatar_changed` with no driver.
#[tokio::test]
async fn subscribers_hear_who_watches_and_when_a_silent_drive_ends() {
    let server = common::kit_builder(30.0)
        .configure(|c| c.drive_timeout = std::time::Duration::from_secs(1))
        .start()
        .await
        .unwrap()
        .into_server();
    let mut viewer = raw_as(&server, Encoding::Json, None).await;
    send(
        &mut viewer,
        json!({"type": "subscribe", "scene": "default"}),
    )
    .await;
    let mut driver = raw_as(&server, Encoding::Json, Some(CONTROL)).await;
    send(
        &mut driver,
        json!({"type": "subscribe", "scene": "default"}),
    )
    .await;
    let both = vec![
        Viewer {
            name: Some("test".into()),
            connections: 1,
        },
        Viewer {
            name: None,
            connections: 1,
        },
    ];
    let seen = next_where(&mut viewer, |m| match m {
        ServerMsg::Viewers { scene, viewers } if scene.0 == "default" && viewers == both => {
            Some(())
        }
        _ => None,
    })
    .await;
    assert!(seen.is_some(), "the subscriber was not told who watches");

    // The driver takes the avatar and then sends nothing, its socket open.
    send(
        &mut driver,
        json!({"type": "command", "id": 1, "command": {"op": "drive", "avatar": "avatar"}}),
    )
    .await;
    let driven = next_where(&mut viewer, |m| match m {
        ServerMsg::AvatarChanged { avatar, .. } if avatar.driven => Some(()),
        _ => None,
    })
    .await;
    assert!(driven.is_some(), "the drive was not announced");
    let ended = next_where(&mut viewer, |m| match m {
        ServerMsg::AvatarChanged { avatar, .. } if !avatar.driven => Some(avatar.driver),
        _ => None,
    })
    .await;
    assert_eq!(
        ended,
        Some(None),
        "the silent drive's end was not announced"
    );
    drop(driver);
    server.stop().await;
}
