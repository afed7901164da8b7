//! The world managed from the page alone: a scene created, avatars added with rig, id, clip,
//! position and facing, all drawn where they stand; one picked by clicking it in the preview,
//! moved, followed by the camera, given a clip; one removed, the scene deleted. Every effect is
//! checked on the server (REST), not on the page's own word. Writes the multi-avatar
//! screenshot (`docs/src/images/dashboard.png` with `POSECAST_UPDATE_SCREENSHOT=1`).

use crate::browser::*;
use crate::common::{self, CONTROL, http};
use fantoccini::actions::{InputSource, MOUSE_BUTTON_LEFT, MouseActions, PointerAction};
use fantoccini::{Client as Browser, Locator};
use serde_json::{Value, json};
use std::path::Path;
use std::time::{Duration, Instant};

/// Sets an input's value as typing would (the forms read values on submit).
async fn set_value(b: &Browser, id: &str, value: &str) {
    b.execute(
        "const e = document.getElementById(arguments[0]); e.value = arguments[1]; \
         e.dispatchEvent(new Event('input', {bubbles: true})); \
         e.dispatchEvent(new Event('change', {bubbles: true}));",
        vec![json!(id), json!(value)],
    )
    .await
    .unwrap();
}

/// Waits until `check` holds for the server's state of `avatar` (REST `get_avatar`).
async fn wait_server(
    server: &posecast_server::startup::Server,
    avatar: &str,
    what: &str,
    check: impl Fn(&Value) -> bool,
) -> Value {
    let t0 = Instant::now();
    loop {
        let (status, body) = command(server, json!({"op": "get_avatar", "avatar": avatar})).await;
        if status == 200 && check(&body["result"]) {
            return body["result"].clone();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{avatar}: {what} never reached the server: {body}"
        );
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
}

fn near(v: &Value, want: &[f64], tolerance: f64) -> bool {
    v.as_array().is_some_and(|a| {
        a.len() == want.len()
            && a.iter()
                .zip(want)
                .all(|(x, w)| x.as_f64().is_some_and(|x| (x - w).abs() < tolerance))
    })
}

/// The drawn root of `avatar` on the page: `(world [x, y, z], canvas [x, y])`.
async fn drawn(b: &Browser, avatar: &str) -> (Vec<f64>, Vec<f64>) {
    let d = b
        .execute(
            "return window.posecast.drawn.find((d) => d.avatar === arguments[0]) ?? null;",
            vec![json!(avatar)],
        )
        .await
        .unwrap();
    assert!(!d.is_null(), "{avatar} is not drawn");
    (
        serde_json::from_value(d["root"].clone()).unwrap(),
        serde_json::from_value(d["screen"].clone()).unwrap(),
    )
}

async fn click(b: &Browser, css: &str) {
    find(b, css).await.click().await.unwrap();
}

/// A destructive button: the second click confirms. The first click is a real pointer click;
/// the confirming click is made in the page only while the button is still armed, because on a
/// loaded machine the webdriver round trip can outlast the page's confirmation window, and a
/// late second click would arm the button again instead of acting.
async fn click_twice(b: &Browser, css: &str) {
    let t0 = Instant::now();
    loop {
        click(b, css).await;
        let confirmed = b
            .execute(
                "const e = document.querySelector(arguments[0]); \
                 if (!e || e.dataset.armed !== '1') return false; \
                 e.click(); return e.dataset.armed === undefined;",
                vec![json!(css)],
            )
            .await
            .unwrap();
        if confirmed == json!(true) {
            return;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{css} was never armed and confirmed"
        );
        // Let an armed button time out so the next first click arms it afresh.
        wait_js(
            b,
            60,
            &format!("document.querySelector('{css}')?.dataset.armed === undefined"),
        )
        .await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_manages_scenes_and_avatars() {
    let server = common::server(60.0).await;
    let base = server.http_url();
    let (_driver, b) = browser().await;
    b.goto(&format!("{base}/?debug#control={CONTROL}"))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.access?.control === true && window.posecast.selected === 'avatar'").await;

    // A scene: created and watched.
    find(&b, "#scene-name")
        .await
        .send_keys("stage")
        .await
        .unwrap();
    click(&b, "#scene-create").await;
    wait_js(&b, 60, "window.posecast.watched === 'stage'").await;
    let (_, listed) = http(&server, "GET", "/api/scenes", None).await;
    assert!(listed.contains("\"stage\""), "{listed}");

    // Three avatars with clip, position and facing.
    let placed = [
        ("left", "walk", -1.2, 0.0, 0.0),
        ("right", "idle", 1.2, 0.0, 90.0),
        ("back", "", 0.0, -1.5, 180.0),
    ];
    for (id, clip, x, z, yaw) in placed {
        wait_js(&b, 60, "document.getElementById('add-scene').value === 'stage' && document.getElementById('add-rig').value === 'avatar'").await;
        set_value(&b, "add-id", id).await;
        set_value(&b, "add-clip", clip).await;
        set_value(&b, "add-x", &x.to_string()).await;
        set_value(&b, "add-z", &z.to_string()).await;
        set_value(&b, "add-yaw", &yaw.to_string()).await;
        click(&b, "#add-submit").await;
        let half = f64::to_radians(yaw) / 2.0;
        let state = wait_server(&server, id, "add_avatar", |s| s["scene"] == "stage").await;
        assert_eq!(
            state["clip"],
            if clip.is_empty() {
                Value::Null
            } else {
                clip.into()
            },
            "{state}"
        );
        assert!(
            near(&state["placement"]["position"], &[x, 0.0, z], 1e-4),
            "{state}"
        );
        assert!(
            near(
                &state["placement"]["rotation"],
                &[0.0, half.sin(), 0.0, half.cos()],
                1e-3
            ),
            "{state}"
        );
        // The page picks what it added.
        wait_js(&b, 60, &format!("window.posecast.selected === '{id}'")).await;
    }
    // All three drawn, each over its placement (the rest root is on the rig's Y axis).
    wait_js(
        &b,
        60,
        "window.posecast.drawn.length === 3 && window.posecast.meshLoaded",
    )
    .await;
    for (id, _, x, z, _) in placed {
        let (root, _) = drawn(&b, id).await;
        assert!(
            (root[0] - x).abs() < 0.25 && (root[2] - z).abs() < 0.25,
            "{id} drawn at {root:?}, placed at ({x}, {z})"
        );
    }

    // A click on "left" in the preview picks it.
    let rect = find(&b, "#preview").await.rectangle().await.unwrap();
    let (_, screen) = drawn(&b, "left").await;
    b.perform_actions(
        MouseActions::new("mouse".into())
            .then(PointerAction::MoveTo {
                duration: None,
                x: rect.0 + screen[0],
                y: rect.1 + screen[1] - 20.0,
            })
            .then(PointerAction::Down {
                button: MOUSE_BUTTON_LEFT,
            })
            .then(PointerAction::Up {
                button: MOUSE_BUTTON_LEFT,
            }),
    )
    .await
    .unwrap();
    wait_js(&b, 60, "window.posecast.selected === 'left' && document.querySelector('#scene-list button[data-avatar=\"left\"]').getAttribute('aria-pressed') === 'true'").await;

    // "right" picked from the list, moved with the placement form.
    click(&b, r#"#scene-list button[data-avatar="right"]"#).await;
    wait_js(&b, 60, "window.posecast.selected === 'right' && document.getElementById('place-x').value === '1.2'").await;
    set_value(&b, "place-x", "2").await;
    set_value(&b, "place-z", "0.5").await;
    click(&b, "#place-submit").await;
    wait_server(&server, "right", "place_avatar", |s| {
        near(&s["placement"]["position"], &[2.0, 0.0, 0.5], 1e-4)
    })
    .await;
    let t0 = Instant::now();
    loop {
        let (root, _) = drawn(&b, "right").await;
        if (root[0] - 2.0).abs() < 0.25 && (root[2] - 0.5).abs() < 0.25 {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "right still drawn at {root:?}"
        );
        tokio::time::sleep(Duration::from_millis(30)).await;
    }

    // The camera follows "right", then frames the whole scene again.
    click(&b, r#"#scene-list button[data-focus="right"]"#).await;
    let camera = wait_js(&b, 60, "window.posecast.camera.focus === 'right' && Math.abs(window.posecast.camera.target[0] - 2) < 0.3 && Math.abs(window.posecast.camera.target[2] - 0.5) < 0.3 && window.posecast.camera").await;
    click(&b, "#frame-all").await;
    wait_js(&b, 60, "window.posecast.camera.focus === null && Math.abs(window.posecast.camera.target[0] - 2) > 0.5").await;

    // "back" picked and given a clip; the others keep theirs.
    click(&b, r#"#scene-list button[data-avatar="back"]"#).await;
    wait_js(&b, 60, "window.posecast.selected === 'back'").await;
    find(&b, "#clip-select")
        .await
        .select_by_value(r#"[null,"wave"]"#)
        .await
        .unwrap();
    click(&b, "#play").await;
    wait_server(&server, "back", "play", |s| s["clip"] == "wave").await;
    assert_eq!(avatar_state(&server, "left").await["clip"], "walk");
    assert_eq!(avatar_state(&server, "right").await["clip"], "idle");

    // The screenshot of the scene: three avatars where they stand, "back" selected.
    let rendered = wait_js(&b, 60, "window.posecast.rendered")
        .await
        .as_u64()
        .unwrap();
    wait_js(
        &b,
        60,
        &format!("window.posecast.rendered > {rendered} + 10"),
    )
    .await;
    b.execute("document.querySelector('.col.left').scrollTop = 0;", vec![])
        .await
        .unwrap();
    let png_bytes = b.screenshot().await.unwrap();
    std::fs::write(artifacts().join("dashboard-world.png"), &png_bytes).unwrap();
    if std::env::var_os("POSECAST_UPDATE_SCREENSHOT").is_some() {
        write_small_png(
            &png_bytes,
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/src/images/dashboard.png"),
        );
    }
    let runs = column_runs(&png_bytes, rect);
    assert!(
        runs.len() >= 2,
        "the screenshot shows {} figures: {runs:?}",
        runs.len()
    );

    // "back" removed (a second click confirms), then the scene deleted.
    click_twice(&b, r#"#scene-list button[data-remove="back"]"#).await;
    let t0 = Instant::now();
    while command(&server, json!({"op": "get_avatar", "avatar": "back"}))
        .await
        .0
        != 404
    {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "remove never reached the server"
        );
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    wait_js(&b, 60, "window.posecast.drawn.length === 2 && !document.querySelector('#scene-list [data-avatar=\"back\"]')").await;
    click_twice(&b, r#"#scene-list button[data-delete-scene="stage"]"#).await;
    let t0 = Instant::now();
    loop {
        let (_, listed) = http(&server, "GET", "/api/scenes", None).await;
        if !listed.contains("\"stage\"") {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "delete never reached the server: {listed}"
        );
        tokio::time::sleep(Duration::from_millis(30)).await;
    }
    wait_js(&b, 60, "!document.querySelector('#scene-list [data-scene=\"stage\"]') && window.posecast.watched === 'default' && window.posecast.selected === 'avatar'").await;
    assert!(
        b.find(Locator::Css("#scene-list [data-avatar=\"left\"]"))
            .await
            .is_err()
    );
    assert_eq!(errors(&b).await, json!([]));
    println!("world: camera on right {camera}; screenshot figures {runs:?}");
    b.close().await.unwrap();
    server.stop().await;
}
