//! The Takes panel (issue 32): a take of the whole `default` scene recorded with its Record /
//! Stop button while the page counts stream frames, listed with the duration the server gives;
//! replayed as a new scene that the page then watches; the replay's timeline moves with the
//! stream and agrees with the server's `control_replay` state; Pause holds it; the scrubber
//! seeks; Delete is refused while the take is replayed and works once the replay is gone.
//! Every wait is for an event (frames, answers, the server's state), bounded generously.

use crate::browser::*;
use crate::common::{self, CONTROL, http};
use serde_json::{Value, json};
use std::time::{Duration, Instant};

/// Bound on every wait (a loaded machine): the test waits for events, never for a duration.
const PATIENCE: u64 = 120;

/// The replay's state as the server says (`control_replay` with no fields, over HTTP).
async fn replay_state(server: &posecast_server::startup::Server, scene: &str) -> Value {
    let (status, body) = command(server, json!({"op": "control_replay", "scene": scene})).await;
    assert_eq!(status, 200, "{body}");
    body["result"].clone()
}

/// Polls the server's replay state until `done` holds.
async fn until_state(
    server: &posecast_server::startup::Server,
    scene: &str,
    what: &str,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let t0 = Instant::now();
    loop {
        let state = replay_state(server, scene).await;
        if done(&state) {
            return state;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(PATIENCE),
            "{what} never arrived: {state}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Clicks an element of the page as a user would (from script: the panel's own handlers run).
async fn click(b: &fantoccini::Client, css: &str) {
    wait_js(b, PATIENCE, &format!("document.querySelector({css:?})")).await;
    b.execute(
        "document.querySelector(arguments[0]).click();",
        vec![json!(css)],
    )
    .await
    .unwrap();
}

/// `t` into `[-d/2, d/2)`: a difference of times on a looping timeline of `d` seconds.
fn wrap(t: f64, d: f64) -> f64 {
    let t = t.rem_euclid(d);
    if t >= d / 2.0 { t - d } else { t }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_takes_panel_records_replays_seeks_and_deletes() {
    let server = common::server(60.0).await;
    let (_driver, b) = browser().await;

    // Watching only: the panel lists, but records, replays and deletes nothing.
    b.goto(&format!("{}/?debug", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, PATIENCE, "window.posecast.state === 'online' && window.posecast.access?.control === false && window.posecast.watched === 'default'").await;
    wait_js(&b, PATIENCE, "document.getElementById('takes-record').disabled && document.getElementById('replay-controls').disabled && !document.getElementById('takes-empty').hidden").await;

    b.goto(&format!(
        "{}/?debug&control#control={CONTROL}",
        server.http_url()
    ))
    .await
    .unwrap();
    wait_js(&b, PATIENCE, "window.posecast.state === 'online' && window.posecast.access?.control === true && window.posecast.watched === 'default' && window.posecast.frames > 10 && !document.getElementById('takes-record').disabled").await;
    assert_eq!(
        wait_js(&b, PATIENCE, "JSON.stringify(window.posecast.takes.list)").await,
        json!("[]")
    );

    // Record: the name, Record; the running duration and frames show while it records.
    b.execute(
        "document.getElementById('takes-name').value = 'rehearsal';",
        vec![],
    )
    .await
    .unwrap();
    click(&b, "#takes-record").await;
    wait_js(
        &b,
        PATIENCE,
        "window.posecast.takes.recording?.take === 'rehearsal' && document.getElementById('takes-record').textContent === 'Stop'",
    )
    .await;
    let f0 = wait_js(&b, PATIENCE, "window.posecast.frames").await;
    let f0 = f0.as_u64().unwrap();
    // Two seconds of the scene, counted in the frames the page receives (60 Hz).
    wait_js(
        &b,
        PATIENCE,
        &format!("window.posecast.frames >= {f0} + 120"),
    )
    .await;
    let running = wait_js(
        &b,
        PATIENCE,
        "window.posecast.takes.recording?.frames >= 60 && document.getElementById('takes-recording').textContent",
    )
    .await;
    let running = running.as_str().unwrap().to_owned();
    assert!(
        running.contains("Recording rehearsal") && running.contains(" frames"),
        "{running}"
    );
    click(&b, "#takes-record").await;
    wait_js(&b, PATIENCE, "window.posecast.takes.recording === null && window.posecast.takes.list.length === 1 && window.posecast.takes.list[0].recording === false && document.getElementById('takes-record').textContent === 'Record'").await;

    // The list shows it, with the duration the server gives.
    let shown = wait_js(
        &b,
        PATIENCE,
        "document.querySelector('[data-duration=\"rehearsal\"]')?.textContent",
    )
    .await;
    let shown: f64 = shown
        .as_str()
        .unwrap()
        .trim_end_matches(" s")
        .parse()
        .unwrap();
    let (status, body) = http(&server, "GET", "/api/takes/rehearsal", None).await;
    assert_eq!(status, 200, "{body}");
    let info: Value = serde_json::from_str(&body).unwrap();
    let duration = info["duration"].as_f64().unwrap();
    assert!(
        (shown - duration).abs() < 0.3,
        "the list shows {shown} s, get_take says {duration} s"
    );
    assert!(duration >= 1.5, "two seconds of frames made {info}");
    assert_eq!(info["scene"], "default");
    assert_eq!(info["avatars"], json!(["avatar"]));
    let facts = wait_js(
        &b,
        PATIENCE,
        "document.querySelector('li[data-take=\"rehearsal\"] .take-facts').textContent",
    )
    .await;
    assert!(
        facts.as_str().unwrap().contains("scene default")
            && facts.as_str().unwrap().contains("1 avatar (avatar)"),
        "{facts}"
    );
    let glb = wait_js(
        &b,
        PATIENCE,
        "document.querySelector('a[data-glb=\"rehearsal\"]').getAttribute('href')",
    )
    .await;
    assert_eq!(glb, json!("/api/takes/rehearsal.glb"));

    // Replay: it asks for the scene (default `<take>-replay`), starts it and watches it.
    click(&b, "button[data-replay=\"rehearsal\"]").await;
    assert_eq!(
        wait_js(
            &b,
            PATIENCE,
            "document.querySelector('input[data-replay-scene=\"rehearsal\"]').value"
        )
        .await,
        json!("rehearsal-replay")
    );
    click(&b, "button[data-replay-start=\"rehearsal\"]").await;
    wait_js(&b, PATIENCE, "window.posecast.watched === 'rehearsal-replay' && window.posecast.takes.replay?.scene === 'rehearsal-replay' && !document.getElementById('replay').hidden").await;
    let (_, scenes) = command(&server, json!({"op": "list_scenes"})).await;
    assert!(
        scenes["result"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s["scene"] == "rehearsal-replay"),
        "{scenes}"
    );
    let scene = "rehearsal-replay";

    // Loop, at a quarter speed (the take is ~2 s): set from the panel, seen by the server.
    click(&b, "#replay-loop").await;
    b.execute(
        "const s = document.getElementById('replay-speed'); s.value = '0.25'; s.dispatchEvent(new Event('change', {bubbles: true}));",
        vec![],
    )
    .await
    .unwrap();
    until_state(&server, scene, "loop at ×0.25", |s| {
        s["loop"] == true && s["speed"].as_f64() == Some(0.25)
    })
    .await;
    wait_js(&b, PATIENCE, "window.posecast.takes.replay.loop === true && window.posecast.takes.replay.speed === 0.25 && document.getElementById('replay-state').textContent === 'playing ×0.25 · loop'").await;

    // The shown time and the scrubber move with the frames: sampled every 20 ms for 1 s.
    let samples = b
        .execute_async(
            "const done = arguments[0]; const out = []; const t0 = performance.now();
             const id = setInterval(() => {
               out.push([window.posecast.takes.shownTime, document.getElementById('replay-seek').value, window.posecast.takes.renders, window.posecast.frames]);
               if (performance.now() - t0 > 1000) { clearInterval(id); done(out); }
             }, 20);",
            vec![],
        )
        .await
        .unwrap();
    let samples = samples.as_array().unwrap();
    let changes = |k: usize| samples.windows(2).filter(|w| w[0][k] != w[1][k]).count();
    let gaps = samples.len() - 1;
    let n = |i: usize, k: usize| samples[i][k].as_f64().unwrap();
    let renders = n(gaps, 2) - n(0, 2);
    let frames = n(gaps, 3) - n(0, 3);
    let advanced = wrap(n(gaps, 0) - n(0, 0), duration);
    assert!(
        changes(0) >= gaps.min(10)
            && changes(1) >= gaps.min(10)
            && 2 * changes(0) >= gaps
            && renders >= 30.0
            && frames >= 30.0
            && advanced > 0.1,
        "in 1 s ({} samples, {frames} frames) the shown time changed {} times (by {advanced:.3} s), the scrubber {}, {renders} updates",
        samples.len(),
        changes(0),
        changes(1)
    );
    // … and agrees with the server's: read between two reads of the server's state.
    let mut worst = 0.0f64;
    for _ in 0..5 {
        let before = replay_state(&server, scene).await["time"].as_f64().unwrap();
        let page = wait_js(&b, PATIENCE, "window.posecast.takes.shownTime").await;
        let page = page.as_f64().unwrap();
        let after = replay_state(&server, scene).await["time"].as_f64().unwrap();
        let (behind, ahead) = (wrap(before - page, duration), wrap(page - after, duration));
        worst = worst.max(behind).max(ahead);
        assert!(
            behind < 0.1 && ahead < 0.1,
            "page shows {page:.3} s, the server {before:.3} s before and {after:.3} s after"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    // Pause: the server says paused, and the shown time holds while frames go on.
    click(&b, "#replay-pause").await;
    let paused = until_state(&server, scene, "pause", |s| s["paused"] == true).await;
    let held = wait_js(&b, PATIENCE, "window.posecast.takes.replay.paused === true && document.getElementById('replay-pause').textContent === 'Resume' && window.posecast.takes.shownTime").await;
    let held = held.as_f64().unwrap();
    let f1 = wait_js(&b, PATIENCE, "window.posecast.frames").await;
    let r1 = wait_js(&b, PATIENCE, "window.posecast.takes.renders").await;
    wait_js(
        &b,
        PATIENCE,
        &format!(
            "window.posecast.frames >= {f1} + 30 && window.posecast.takes.renders >= {r1} + 30"
        ),
    )
    .await;
    let still = wait_js(&b, PATIENCE, "window.posecast.takes.shownTime").await;
    assert_eq!(
        still.as_f64().unwrap(),
        held,
        "paused, the shown time moved"
    );
    let server_time = replay_state(&server, scene).await["time"].as_f64().unwrap();
    assert!(
        (server_time - held).abs() < 0.01 && (paused["time"].as_f64().unwrap() - held).abs() < 0.01,
        "paused at {held} on the page, {server_time} on the server"
    );

    // Seek: the scrubber set to the middle (input, change) moves the server's replay there.
    let target = duration / 2.0;
    let sent = wait_js(&b, PATIENCE, "window.posecast.sent.control_replay").await;
    b.execute(
        "const s = document.getElementById('replay-seek'); s.value = arguments[0];
         s.dispatchEvent(new Event('input', {bubbles: true})); s.dispatchEvent(new Event('change', {bubbles: true}));",
        vec![json!(target)],
    )
    .await
    .unwrap();
    wait_js(
        &b,
        PATIENCE,
        &format!(
            "window.posecast.sent.control_replay > {sent} && !window.posecast.takes.seeking && window.posecast.takes.scrubbing === false"
        ),
    )
    .await;
    let sought = replay_state(&server, scene).await;
    let time = sought["time"].as_f64().unwrap();
    assert!(
        (time - target).abs() < 0.1 && sought["paused"] == true,
        "the scrubber asked for {target:.3} s, the server's replay is at {time:.3} s: {sought}"
    );
    let page = wait_js(&b, PATIENCE, "window.posecast.takes.shownTime").await;
    assert!(
        (page.as_f64().unwrap() - time).abs() < 0.01,
        "after the seek the page shows {page}, the server {time}"
    );

    // Delete while the take is replayed: refused, and the panel says why.
    b.execute(
        "const d = document.querySelector('button[data-delete-take=\"rehearsal\"]'); d.click(); d.click();",
        vec![],
    )
    .await
    .unwrap();
    let refusal = wait_js(&b, PATIENCE, "document.getElementById('takes-result').classList.contains('error') && document.getElementById('takes-result').textContent").await;
    assert!(refusal.as_str().unwrap().contains("conflict"), "{refusal}");
    let (status, _) = http(&server, "GET", "/api/takes/rehearsal", None).await;
    assert_eq!(status, 200, "a refused delete deleted the take");
    assert_eq!(
        wait_js(&b, PATIENCE, "window.posecast.takes.list.length").await,
        json!(1)
    );

    // The replay's scene deleted (over HTTP): the page forgets the replay; Delete works.
    let (status, body) = command(&server, json!({"op": "delete_scene", "scene": scene})).await;
    assert_eq!(status, 200, "{body}");
    wait_js(&b, PATIENCE, "window.posecast.watched !== 'rehearsal-replay' && window.posecast.takes.replay === null && document.getElementById('replay').hidden").await;
    b.execute(
        "const d = document.querySelector('button[data-delete-take=\"rehearsal\"]'); d.click(); d.click();",
        vec![],
    )
    .await
    .unwrap();
    wait_js(&b, PATIENCE, "window.posecast.takes.list.length === 0 && !document.getElementById('takes-empty').hidden && document.querySelector('li[data-take]') === null && document.getElementById('takes-result').textContent === 'Take rehearsal deleted.'").await;
    let (_, list) = http(&server, "GET", "/api/takes", None).await;
    assert_eq!(serde_json::from_str::<Value>(&list).unwrap(), json!([]));
    assert_eq!(errors(&b).await, json!([]));
    println!(
        "takes: recorded {duration:.2} s ({} frames), shown as {shown:.2} s; replay at ×0.25 advanced {advanced:.3} s in 1 s ({} changes in {gaps} gaps); page within {worst:.3} s of the server; seek to {target:.3} → {time:.3}",
        info["frames"],
        changes(0)
    );
    b.close().await.unwrap();
    server.stop().await;
}
