//! Every avatar of the watched scene drawn where it stands.

use crate::browser::*;
use crate::common;
use serde_json::json;

/// Two built-in avatars placed 2 m apart in one scene are both drawn, each where it stands, by
/// the WebGL2 preview and by the 2D fallback: the root joint the page draws is at the avatar's
/// placement, and the screenshot shows two separate figures (runs of non-background columns),
/// each holding its root's projection. With placement ignored both stand at the origin.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_preview_draws_every_avatar_where_it_stands() {
    let server = common::server(60.0).await;
    let base = server.http_url();
    let placed = [("left", -1.0), ("right", 1.0)];
    let (s, b) = command(&server, json!({"op": "create_scene", "scene": "row"})).await;
    assert_eq!(s, 200, "{b}");
    for (name, x) in placed {
        let (s, b) = command(
            &server,
            json!({"op": "add_avatar", "scene": "row", "asset": "avatar", "avatar": name,
                   "position": [x, 0.0, 0.0]}),
        )
        .await;
        assert_eq!(s, 200, "{b}");
    }
    let (_driver, b) = browser().await;
    let mut report = Vec::new();
    for (renderer, query) in [("webgl2", ""), ("2d", "&renderer=2d")] {
        b.goto(&format!("{base}/?debug{query}")).await.unwrap();
        find(&b, r#"#scene-list button[data-avatar="left"]"#)
            .await
            .click()
            .await
            .unwrap();
        let ready = if renderer == "webgl2" {
            "window.posecast.meshLoaded"
        } else {
            "true"
        };
        wait_js(
            &b,
            60,
            &format!(
                "window.posecast.renderer === '{renderer}' && window.posecast.drawn.length === 2 \
                 && {ready}"
            ),
        )
        .await;
        // A few more renders, so the mesh that just arrived is on screen.
        let rendered = wait_js(&b, 60, "window.posecast.rendered")
            .await
            .as_u64()
            .unwrap();
        wait_js(
            &b,
            60,
            &format!("window.posecast.rendered > {rendered} + 2"),
        )
        .await;
        b.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
        let drawn = b
            .execute("return window.posecast.drawn;", vec![])
            .await
            .unwrap();
        let shot = b.screenshot().await.unwrap();
        let rect = find(&b, "#preview").await.rectangle().await.unwrap();
        let runs = column_runs(&shot, rect);
        let failed = || {
            let path = artifacts().join(format!("dashboard-placement-{renderer}.png"));
            std::fs::write(&path, &shot).unwrap();
            format!(
                "drawn {drawn}, column runs {runs:?}; screenshot {}",
                path.display()
            )
        };
        let mut holding = Vec::new();
        for (name, x) in placed {
            let d = drawn
                .as_array()
                .unwrap()
                .iter()
                .find(|d| d["avatar"] == name)
                .unwrap_or_else(|| panic!("{renderer}: {name} not drawn; {}", failed()));
            let root: Vec<f64> = serde_json::from_value(d["root"].clone()).unwrap();
            // The root stands over its placement (the rig's rest root is on the Y axis).
            assert!(
                (root[0] - x).abs() < 0.25 && root[2].abs() < 0.25,
                "{renderer}: {name}'s root drawn at {root:?}, placed at x = {x}; {}",
                failed()
            );
            let column = rect.0 + d["screen"][0].as_f64().unwrap();
            let run = runs
                .iter()
                .position(|&(a, b)| (a as f64 - 2.0..=b as f64 + 3.0).contains(&column))
                .unwrap_or_else(|| {
                    panic!(
                        "{renderer}: nothing drawn at {name}'s root column {column:.0}; {}",
                        failed()
                    )
                });
            holding.push(run);
        }
        assert_ne!(
            holding[0],
            holding[1],
            "{renderer}: both avatars in one figure; {}",
            failed()
        );
        assert_eq!(
            errors(&b).await,
            json!([]),
            "{renderer}: errors while drawing"
        );
        report.push(format!("{renderer}: {} runs {runs:?}", runs.len()));
    }
    println!("placed avatars: {}", report.join("; "));
    b.close().await.unwrap();
}
