//! Faces in the dashboard: the Face panel shows a standard expression and moves a morph channel
//! of a Ready Player Me avatar; the server's state takes them, the page's client reads them
//! from the stream (protocol version 4), and the WebGL preview morphs the mesh (the eyes and
//! mouth move on screen while the body, playing nothing, stays still).

use crate::browser::*;
use crate::common::{self, CONTROL, testdata_bytes, upload_files};
use fantoccini::Client as Browser;
use posecast_server::startup::Server;
use serde_json::{Value, json};
use std::time::{Duration, Instant};

const RPM: &str = "gltf/ReadyPlayerMe/PreviewMesh.glb";

/// Polls the avatar's state until `check` holds of its `morph_weights`, for at most a minute.
async fn wait_state(server: &Server, avatar: &str, what: &str, check: impl Fn(&Value) -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let state = avatar_state(server, avatar).await;
        if check(&state["morph_weights"]) {
            return;
        }
        assert!(Instant::now() < deadline, "{what}: state {state}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Holds the preview's pixels in the page as `window[name]`, after a few more renders (so
/// what the page holds is on screen). The canvas keeps its drawing buffer, so a 2D copy reads it.
async fn grab(b: &Browser, name: &str) {
    let rendered = wait_js(b, 60, "window.posecast.rendered")
        .await
        .as_u64()
        .unwrap();
    wait_js(b, 60, &format!("window.posecast.rendered > {rendered} + 3")).await;
    b.execute(
        &format!(
            "const c = document.getElementById('preview'); \
             const o = document.createElement('canvas'); o.width = c.width; o.height = c.height; \
             const x = o.getContext('2d'); x.drawImage(c, 0, 0); \
             window['{name}'] = x.getImageData(0, 0, c.width, c.height);"
        ),
        vec![],
    )
    .await
    .unwrap();
}

/// Pixels whose summed RGB difference between two grabs exceeds 30 (8-bit steps).
async fn changed_pixels(b: &Browser, a: &str, c: &str) -> u64 {
    b.execute(
        &format!(
            "const a = window['{a}'], b = window['{c}']; \
             if (a.width !== b.width || a.height !== b.height) return -1; \
             let n = 0; \
             for (let i = 0; i < a.data.length; i += 4) {{ \
               const d = Math.abs(a.data[i] - b.data[i]) + Math.abs(a.data[i + 1] - b.data[i + 1]) \
                 + Math.abs(a.data[i + 2] - b.data[i + 2]); \
               if (d > 30) n++; \
             }} \
             return n;"
        ),
        vec![],
    )
    .await
    .unwrap()
    .as_u64()
    .expect("the preview changed size between grabs")
}

/// Clicks an element from the page's script (a WebDriver click scrolls it into view, and the
/// layout with it).
async fn click(b: &Browser, id: &str) {
    b.execute(&format!("document.getElementById('{id}').click();"), vec![])
        .await
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_face_panel_sets_expressions_the_preview_shows() {
    let Some(bytes) = testdata_bytes(RPM) else {
        return;
    };
    let server = common::server(60.0).await;
    let (status, body) = upload_files(server.addr, "/api/assets/rpm", &[("rpm.glb", &bytes)]).await;
    assert_eq!(status, 200, "{body}");
    // The face alone in the scene, so it fills the preview.
    for body in [
        json!({"op": "remove_avatar", "avatar": "avatar"}),
        json!({"op": "add_avatar", "scene": "default", "asset": "rpm", "avatar": "face"}),
    ] {
        let (s, answer) = command(&server, body.clone()).await;
        assert_eq!(s, 200, "{body}: {answer}");
    }
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    find(&b, r#"#scene-list button[data-avatar="face"]"#)
        .await
        .click()
        .await
        .unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.renderer === 'webgl2' && window.posecast.meshLoaded \
         && document.querySelectorAll('#face-sliders input').length === 5 \
         && !document.getElementById('face-controls').disabled",
    )
    .await;
    // A preview of fixed size (scroll bars coming and going must not resize it between grabs),
    // close up on the face, from the front.
    b.execute(
        "const w = document.querySelector('.canvas-wrap'); \
         w.style.width = '480px'; w.style.height = '360px'; w.style.flex = 'none';",
        vec![],
    )
    .await
    .unwrap();
    wait_js(&b, 60, "window.posecast.aimAtJoint('face', 'Head', 0.7)").await;
    grab(&b, "neutral").await;

    // A standard name from the picker: `blink` is the rig's eyesClosed.
    b.execute(
        "document.getElementById('face-expression').value = 'blink';",
        vec![],
    )
    .await
    .unwrap();
    click(&b, "face-expression-set").await;
    wait_state(&server, "face", "blink shown", |w| w["eyesClosed"] == 1.0).await;
    // A channel's slider.
    b.execute(
        "const i = document.getElementById('face-mouthOpen'); i.value = '1'; \
         i.dispatchEvent(new Event('input'));",
        vec![],
    )
    .await
    .unwrap();
    wait_state(&server, "face", "mouth opened", |w| {
        w["eyesClosed"] == 1.0 && w["mouthOpen"] == 1.0
    })
    .await;
    // The page's client decodes both from the binary stream.
    wait_js(
        &b,
        60,
        "(window.posecast.weights('face')?.eyesClosed ?? 0) > 0.999 \
         && (window.posecast.weights('face')?.mouthOpen ?? 0) > 0.999",
    )
    .await;
    grab(&b, "expression").await;
    let moved = changed_pixels(&b, "neutral", "expression").await;

    // Neutral: every weight back to 0, and the picture back to the first one.
    click(&b, "face-reset").await;
    wait_state(&server, "face", "neutral", |w| {
        w.as_object().is_none_or(|m| m.values().all(|v| v == 0.0))
    })
    .await;
    wait_js(
        &b,
        60,
        "(window.posecast.weights('face')?.eyesClosed ?? 1) === 0 \
         && (window.posecast.weights('face')?.mouthOpen ?? 1) === 0",
    )
    .await;
    grab(&b, "back").await;
    let residue = changed_pixels(&b, "neutral", "back").await;
    let shot = b.screenshot().await.unwrap();
    let save = || {
        let path = artifacts().join("dashboard-face.png");
        std::fs::write(&path, &shot).unwrap();
        format!("screenshot {}", path.display())
    };
    assert!(
        moved >= 20,
        "the expression changed only {moved} pixels of the preview; {}",
        save()
    );
    assert!(
        residue * 10 <= moved,
        "neutral again differs from neutral by {residue} pixels (the expression by {moved}); {}",
        save()
    );
    assert_eq!(errors(&b).await, json!([]), "errors on the page");
    println!("face panel: the expression changed {moved} pixels, neutral again {residue}");
    b.close().await.unwrap();
}
