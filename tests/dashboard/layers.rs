//! Clip layers from the dashboard: the Playback panel plays the chosen clip on a named layer
//! over the avatar's clip, on the joints typed (`-name` takes a subtree out), replacing or
//! additive; the server's state and the panel's state list show it; Stop layer removes it.

use crate::browser::*;
use crate::common::{self, CONTROL};
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Polls the avatar's `layers` until `check` holds, for at most a minute.
async fn wait_layers(
    server: &posecast_server::startup::Server,
    what: &str,
    check: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let state = avatar_state(server, "avatar").await;
        if check(&state["layers"]) {
            return state["layers"].clone();
        }
        assert!(Instant::now() < deadline, "{what}: state {state}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_plays_and_stops_a_clip_layer() {
    let server = common::server(30.0).await;
    let (s, b) = command(
        &server,
        json!({"op": "play", "avatar": "avatar", "clip": "walk"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    find(&b, r#"#scene-list button[data-avatar="avatar"]"#)
        .await
        .click()
        .await
        .unwrap();
    wait_js(
        &b,
        60,
        "[...document.getElementById('clip-select').options].some((o) => o.value === '[null,\"wave\"]')",
    )
    .await;
    // The right arm but the hand waves over the walk; clicked from the page's script (a
    // WebDriver click scrolls the layout).
    b.execute(
        "document.getElementById('clip-select').value = '[null,\"wave\"]'; \
         document.getElementById('layer-name').value = 'arm'; \
         document.getElementById('layer-mask').value = 'r_sternoclavicular, -r_wrist'; \
         document.getElementById('play-layer').click();",
        vec![],
    )
    .await
    .unwrap();
    let layers = wait_layers(&server, "the arm layer plays", |l| {
        l.as_array().is_some_and(|l| l.len() == 1)
    })
    .await;
    assert_eq!(layers[0]["layer"], "arm", "{layers}");
    assert_eq!(layers[0]["clip"], "wave", "{layers}");
    assert_eq!(layers[0]["additive"], false, "{layers}");
    // r_sternoclavicular, r_shoulder, r_elbow (the wrist's subtree taken out).
    assert_eq!(layers[0]["joints"], 3, "{layers}");
    assert_eq!(avatar_state(&server, "avatar").await["clip"], "walk");
    wait_js(
        &b,
        60,
        "document.querySelector('[data-field=layers]')?.textContent.startsWith('arm: wave')",
    )
    .await;

    // An additive layer at half weight over every joint.
    b.execute(
        "document.getElementById('clip-select').value = '[null,\"idle\"]'; \
         document.getElementById('layer-name').value = 'breath'; \
         document.getElementById('layer-mask').value = ''; \
         document.getElementById('layer-additive').checked = true; \
         document.getElementById('layer-weight').value = '0.5'; \
         document.getElementById('play-layer').click();",
        vec![],
    )
    .await
    .unwrap();
    let layers = wait_layers(&server, "the breathing layer plays", |l| {
        l.as_array().is_some_and(|l| l.len() == 2)
    })
    .await;
    assert_eq!(layers[1]["additive"], true, "{layers}");
    assert_eq!(layers[1]["joints"], 23, "{layers}");

    // Stop layer (named in the field) fades the arm out.
    b.execute(
        "document.getElementById('layer-name').value = 'arm'; \
         document.getElementById('stop-layer').click();",
        vec![],
    )
    .await
    .unwrap();
    wait_layers(&server, "the arm layer is gone", |l| {
        l.as_array()
            .is_some_and(|l| l.len() == 1 && l[0]["layer"] == "breath")
    })
    .await;
    assert_eq!(errors(&b).await, json!([]), "page errors");
    b.close().await.ok();
}
