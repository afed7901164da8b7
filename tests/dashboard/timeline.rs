//! The timeline moves with the stream: the time display and the scrubber change with (nearly)
//! every frame, not once a second, and agree with the server's clip time; the clip's range is
//! marked; a cross-fade shows while it runs and goes when it ends; scrubbing seeks.

use crate::browser::*;
use crate::common::{self, CONTROL, http};
use serde_json::{Value, json};
use std::collections::BTreeSet;
use std::time::{Duration, Instant};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_timeline_moves_with_the_stream() {
    let server = common::server(60.0).await;
    let (_, assets) = http(&server, "GET", "/api/assets", None).await;
    let assets: Value = serde_json::from_str(&assets).unwrap();
    let walk = assets[0]["clips"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "walk")
        .unwrap()["duration"]
        .as_f64()
        .unwrap();
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.access?.control === true && window.posecast.selected === 'avatar' && window.posecast.frames > 10").await;

    // Walk, with a 1.5 s cross-fade from idle.
    find(&b, "#clip-select")
        .await
        .select_by_value(r#"[null,"walk"]"#)
        .await
        .unwrap();
    let fade = find(&b, "#fade").await;
    fade.clear().await.unwrap();
    fade.send_keys("1.5").await.unwrap();
    find(&b, "#play").await.click().await.unwrap();
    // The fade shows, names the clip fading out and grows; the band spans clip times.
    let first = wait_js(
        &b,
        60,
        "!document.getElementById('tl-fade').hidden && window.posecast.timeline.fade",
    )
    .await
    .as_f64()
    .unwrap();
    let text = wait_js(
        &b,
        60,
        "document.getElementById('tl-fade-text').textContent",
    )
    .await;
    assert!(
        text.as_str().unwrap().starts_with("Cross-fade from idle"),
        "{text}"
    );
    wait_js(&b, 60, "!document.getElementById('tl-fade-band').hidden && parseFloat(document.getElementById('tl-fade-band').style.width) > 0").await;
    let later = wait_js(
        &b,
        60,
        &format!("window.posecast.timeline.fade > {first} + 0.2 && window.posecast.timeline.fade"),
    )
    .await;
    // … and goes when the fade is over.
    wait_js(&b, 60, "document.getElementById('tl-fade').hidden && document.getElementById('tl-fade-band').hidden && window.posecast.timeline.fade === null").await;

    // Range markers: from 0 to the clip's duration, labelled at both ends.
    let labels = wait_js(&b, 60, "[...document.querySelectorAll('#tl-markers .marker.labelled')].map((m) => m.dataset.label)").await;
    let end = format!("{} s", (walk * 100.0).round() / 100.0);
    assert_eq!(labels, json!(["0 s", end]), "walk lasts {walk} s");
    let count = wait_js(
        &b,
        60,
        "document.querySelectorAll('#tl-markers .marker').length",
    )
    .await;
    assert!(count.as_u64().unwrap() >= 4, "{count} markers");
    assert_eq!(
        wait_js(&b, 60, "document.getElementById('seek').max").await,
        json!(walk.to_string())
    );

    // The display and the scrubber change with the frames: sampled every 20 ms for 1 s.
    let samples = b
        .execute_async(
            "const done = arguments[0]; const out = []; const t0 = performance.now();
             const id = setInterval(() => {
               out.push([document.getElementById('tl-time').textContent, document.getElementById('seek').value, window.posecast.timeline.renders]);
               if (performance.now() - t0 > 1000) { clearInterval(id); done(out); }
             }, 20);",
            vec![],
        )
        .await
        .unwrap();
    let samples = samples.as_array().unwrap();
    // How often each changed from one sample to the next: a display that follows the frames
    // changes between most samples (a loaded browser may take fewer than 50 of them).
    let changes = |k: usize| {
        samples
            .windows(2)
            .filter(|w| w[0][k].as_str() != w[1][k].as_str())
            .count()
    };
    let texts: BTreeSet<&str> = samples.iter().map(|s| s[0].as_str().unwrap()).collect();
    let values: BTreeSet<&str> = samples.iter().map(|s| s[1].as_str().unwrap()).collect();
    let renders = samples.last().unwrap()[2].as_u64().unwrap() - samples[0][2].as_u64().unwrap();
    let gaps = samples.len() - 1;
    assert!(
        // At least 10 changes, or every gap when a loaded browser sampled fewer times.
        changes(0) >= gaps.min(10)
            && changes(1) >= gaps.min(10)
            && 2 * changes(0) >= gaps
            && 2 * changes(1) >= gaps
            && renders >= 30,
        "in 1 s ({} samples) the time display changed {} times, the scrubber {}, {renders} timeline updates",
        samples.len(),
        changes(0),
        changes(1)
    );

    // It agrees with the server's clock: the page's time, read between two reads of the
    // server's, lies between them (modulo the clip), give or take the ticks a frame takes to
    // arrive.
    let wrap = |d: f64| {
        let d = d.rem_euclid(walk);
        if d > walk / 2.0 { d - walk } else { d }
    };
    let (mut behind, mut ahead) = (0.0f64, 0.0f64);
    for _ in 0..5 {
        let before = avatar_state(&server, "avatar").await["time"]
            .as_f64()
            .unwrap();
        let page = b
            .execute("return window.posecast.timeline.time;", vec![])
            .await
            .unwrap()
            .as_f64()
            .unwrap();
        let after = avatar_state(&server, "avatar").await["time"]
            .as_f64()
            .unwrap();
        behind = behind.max(wrap(before - page));
        ahead = ahead.max(wrap(page - after));
        assert!(
            wrap(before - page) < 0.05 && wrap(page - after) < 0.02,
            "page shows {page:.3} s, the server {before:.3} s before and {after:.3} s after"
        );
        tokio::time::sleep(Duration::from_millis(150)).await;
    }

    // Scrubbing (paused, so the time stays put): the server seeks to the scrubber's value.
    find(&b, "#pause").await.click().await.unwrap();
    let t0 = Instant::now();
    while avatar_state(&server, "avatar").await["paused"] != true {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "pause never arrived"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let target = walk * 0.4;
    b.execute(
        "const s = document.getElementById('seek'); s.value = arguments[0];
         s.dispatchEvent(new Event('input', {bubbles: true})); s.dispatchEvent(new Event('change', {bubbles: true}));",
        vec![json!(target)],
    )
    .await
    .unwrap();
    let t0 = Instant::now();
    loop {
        let time = avatar_state(&server, "avatar").await["time"]
            .as_f64()
            .unwrap();
        if (time - target).abs() < 0.002 {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "seek to {target} never arrived ({time})"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    wait_js(&b, 60, &format!("Math.abs(window.posecast.timeline.time - {target}) < 0.002 && document.getElementById('tl-state').textContent.startsWith('paused')")).await;
    assert_eq!(errors(&b).await, json!([]));
    println!(
        "timeline: {} distinct times and {} scrubber positions in 1 s ({renders} updates); page behind the server by at most {behind:.3} s, ahead by {ahead:.3} s; fade {first:.2} → {later}",
        texts.len(),
        values.len()
    );
    b.close().await.unwrap();
    server.stop().await;
}
