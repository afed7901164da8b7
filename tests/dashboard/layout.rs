//! Layout: at 1280×800 the joint sliders sit beside the preview, and with a slider scrolled
//! into view the whole preview is still on screen (the columns scroll on their own); at 400 px
//! one column without sideways scrolling, the preview kept on top (sticky) and nothing covering
//! the slider.

use crate::browser::*;
use crate::common::{self, CONTROL};
use serde_json::{Value, json};

/// The boxes `{x, y, w, h}` of the preview, the scrubber and control `arguments[0]`, after
/// scrolling that control into view as a user would (to the bottom of its scroll container);
/// whether it is the element found at its centre (nothing covers it); the viewport.
const GEOMETRY: &str = "
  const s = document.querySelector(arguments[0]);
  s.scrollIntoView({block: 'end', inline: 'nearest'});
  const r = (e) => { const b = e.getBoundingClientRect(); return {x: b.x, y: b.y, w: b.width, h: b.height}; };
  const slider = r(s);
  const cx = slider.x + slider.w / 2, cy = slider.y + slider.h / 2;
  return {
    preview: r(document.getElementById('preview')),
    timeline: r(document.getElementById('seek')),
    slider,
    hit: document.elementFromPoint(cx, cy) === s,
    vw: document.documentElement.clientWidth, vh: window.innerHeight,
    overflow: document.documentElement.scrollWidth - window.innerWidth,
  };";

fn inside(r: &Value, vw: f64, vh: f64) -> bool {
    let (x, y, w, h) = (
        r["x"].as_f64().unwrap(),
        r["y"].as_f64().unwrap(),
        r["w"].as_f64().unwrap(),
        r["h"].as_f64().unwrap(),
    );
    x >= -0.5 && y >= -0.5 && x + w <= vw + 0.5 && y + h <= vh + 0.5 && w > 0.0 && h > 0.0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn controls_sit_beside_the_preview_and_narrow_screens_still_work() {
    let server = common::server(60.0).await;
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug#control={CONTROL}", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.selected === 'avatar' && window.posecast.rendered > 5").await;
    find(&b, r#"#joint-tree button[data-joint="l_elbow"]"#)
        .await
        .click()
        .await
        .unwrap();
    find(&b, "#dof-2").await;

    // No column scrolls sideways: name what sticks out.
    let wide = b
        .execute(
            "return [...document.querySelectorAll('.col')].flatMap((c) => {
               const right = c.getBoundingClientRect().right;
               return c.scrollWidth > c.clientWidth
                 ? [...c.querySelectorAll('*')].filter((e) => e.getBoundingClientRect().right > right + 0.5)
                     .map((e) => `${e.tagName}#${e.id}.${e.className} ${e.getBoundingClientRect().right - right}`)
                 : [];
             });",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(wide, json!([]), "columns wider than their box");
    let mut report = Vec::new();
    for (width, height) in [(1280u32, 800u32), (400, 800)] {
        b.set_window_size(width, height).await.unwrap();
        wait_js(&b, 60, &format!("window.innerWidth <= {width}")).await;
        for slider in ["#dof-0", "#dof-2", "#place-submit", "#release-all"] {
            let g = b.execute(GEOMETRY, vec![json!(slider)]).await.unwrap();
            let (vw, vh) = (g["vw"].as_f64().unwrap(), g["vh"].as_f64().unwrap());
            assert!(
                g["overflow"].as_f64().unwrap() <= 0.0,
                "{width} px: sideways scrolling {g}"
            );
            assert!(
                inside(&g["slider"], vw, vh) && g["hit"] == true,
                "{width} px: {slider} not visible: {g}"
            );
            assert!(
                inside(&g["preview"], vw, vh),
                "{width} px: the preview left the screen with {slider} in view: {g}"
            );
            if width == 1280 {
                // Beside, not below: the control starts right of the preview.
                let p = &g["preview"];
                let right = p["x"].as_f64().unwrap() + p["w"].as_f64().unwrap();
                assert!(
                    g["slider"]["x"].as_f64().unwrap() >= right,
                    "{slider} is not beside the preview: {g}"
                );
                assert!(
                    inside(&g["timeline"], vw, vh),
                    "the timeline is off screen: {g}"
                );
            }
            report.push(format!("{width}px {slider}: preview {}", g["preview"]));
        }
        let shot = b.screenshot().await.unwrap();
        std::fs::write(artifacts().join(format!("dashboard-{width}px.png")), shot).unwrap();
    }
    assert_eq!(errors(&b).await, json!([]));
    println!("layout: {}", report.join("; "));
    b.close().await.unwrap();
    server.stop().await;
}
