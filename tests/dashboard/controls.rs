//! The page drives avatars: play, DOF sliders, uploads, narrow screens, the 2D fallback, offline and back.

use crate::browser::*;
use crate::common::{self, http, wait_for};
use fantoccini::key::Key;
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_controls_avatars_in_a_real_browser() {
    let started = Instant::now();
    let (server, asset_dir) = server_with_limited_rig().await;
    let base = server.http_url();

    // The limited rig goes into a scene of its own.
    let (_, assets) = http(&server, "GET", "/api/assets", None).await;
    let assets: Value = serde_json::from_str(&assets).unwrap();
    let skel_asset = assets
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] != "avatar")
        .expect("test.skel loaded")["name"]
        .as_str()
        .unwrap()
        .to_string();
    let (s, b) = command(&server, json!({"op": "create_scene", "scene": "lab"})).await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command(
        &server,
        json!({"op": "add_avatar", "scene": "lab", "asset": skel_asset, "avatar": "skel"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");

    // Rust clients watching both scenes.
    let watch = |scene: &str| {
        let mut o = ClientOptions::new(server.ws_url(), scene);
        o.encoding = Encoding::Json;
        o.reconnect = false;
        Client::connect(o)
    };
    let main = watch("default").await.unwrap();
    let lab = watch("lab").await.unwrap();
    let avatar = AvatarId("avatar".into());
    let skel = AvatarId("skel".into());
    assert!(
        wait_for(5.0, || main.latest(&avatar).is_some()
            && lab.latest(&skel).is_some())
        .await
    );
    let knee = main
        .avatar(&avatar)
        .unwrap()
        .skeleton
        .find("l_knee")
        .unwrap();
    let idle_knee = max_angle(&main, &avatar, knee, 0.5).await;

    let (_driver, b) = browser().await;
    let mut phases = vec![("browser", started.elapsed())];

    // 1. The page loads, connects, lists the built-in avatar and draws frames; no errors.
    // The control token arrives the way the server's start-up link gives it: in the fragment.
    b.goto(&format!("{base}/?debug#control={}", common::CONTROL))
        .await
        .unwrap();
    find(&b, r#"#scene-list button[data-avatar="avatar"]"#).await;
    find(&b, r#"#scene-list button[data-avatar="skel"]"#).await;
    wait_js(&b, 60, "window.posecast.state === 'online' && window.posecast.frames > 10 && window.posecast.rendered > 10").await;
    let renderer = wait_js(&b, 60, "window.posecast.renderer").await;
    wait_js(&b, 60, "window.posecast.meshLoaded").await;
    assert_eq!(errors(&b).await, json!([]), "errors while loading");
    let fps = wait_js(
        &b,
        60,
        "/^[1-9][0-9]* frames/.test(document.getElementById('fps').textContent) && document.getElementById('fps').textContent",
    )
    .await;
    let rtt = wait_js(&b, 60, "window.posecast.rtt").await;

    phases.push(("load", started.elapsed()));
    // 2. Play "walk": the avatar's state and the pose stream change.
    let clip = find(&b, "#clip-select").await;
    clip.select_by_value(r#"[null,"walk"]"#).await.unwrap();
    find(&b, "#play").await.click().await.unwrap();
    let t0 = Instant::now();
    loop {
        if avatar_state(&server, "avatar").await["clip"] == "walk" {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "play from the page never reached the server"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let walk_knee = max_angle(&main, &avatar, knee, 1.2).await;
    assert!(
        walk_knee > idle_knee + 15.0,
        "knee swing idle {idle_knee:.1}° vs walk {walk_knee:.1}°: the stream did not change"
    );
    wait_js(
        &b,
        60,
        "document.querySelector('[data-field=clip]')?.textContent === 'walk'",
    )
    .await;

    phases.push(("play", started.elapsed()));
    // 3. A DOF slider of a limited joint: the stream follows, clamped to the joint's limits
    //    (test.skel: knee_r rotx in [-2, 0], roty and rotz fixed at 0).
    find(&b, r#"#scene-list button[data-avatar="skel"]"#)
        .await
        .click()
        .await
        .unwrap();
    find(&b, r#"#joint-tree button[data-joint="knee_r"]"#)
        .await
        .click()
        .await
        .unwrap();
    let slider = find(&b, "#dof-0").await;
    let knee_r = lab.avatar(&skel).unwrap().skeleton.find("knee_r").unwrap();
    let before = lab.latest(&skel).unwrap().locals[knee_r].rotation;
    // The sliders span the limits `get_joint` reports from test.skel: rotx [−2, 0] rad
    // (−114.6°…0°), roty and rotz locked at 0; they start at the pose, rotx −2 (−114.6°).
    wait_js(&b, 60, "document.getElementById('dof-0').min === '-115' && document.getElementById('dof-0').max === '0' && document.getElementById('dof-1').min === '0' && document.getElementById('dof-1').max === '0' && Math.abs(Number(document.getElementById('dof-0').value) + 114.6) < 0.6").await;
    slider.send_keys(&Key::End.to_string()).await.unwrap();
    let t0 = Instant::now();
    loop {
        if avatar_state(&server, "skel").await["overrides"] == json!(["knee_r"]) {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the slider never set an override"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The page shows the value the server applied.
    wait_js(&b, 60, "document.getElementById('dof-0-out').textContent === '0.0°' && document.getElementById('dof-0').max === '0'").await;
    // The same values again over REST (changes nothing): the rotation the server sets for them.
    let (s, r) = command(
        &server,
        json!({"op": "set_joint_dofs", "avatar": "skel", "joint": "knee_r", "values": [0.0, 0.0, 0.0]}),
    )
    .await;
    assert_eq!(s, 200, "{r}");
    let r = &r["result"];
    assert_eq!(r["values"], json!([0.0, 0.0, 0.0]));
    let expected = glam::Quat::from_slice(
        &r["rotation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap() as f32)
            .collect::<Vec<_>>(),
    );
    assert!(
        wait_for(2.0, || lab.latest(&skel).is_some_and(|p| p.locals[knee_r]
            .rotation
            .angle_between(expected)
            .to_degrees()
            < 0.05))
        .await,
        "the streamed knee_r rotation is not the clamped one"
    );
    assert!(
        before.angle_between(expected).to_degrees() > 10.0,
        "the slider did not move the joint"
    );

    phases.push(("dof", started.elapsed()));
    // 4. Screenshot of the built-in avatar walking: the preview shows it.
    find(&b, r#"#scene-list button[data-avatar="avatar"]"#)
        .await
        .click()
        .await
        .unwrap();
    wait_js(&b, 60, "window.posecast.meshLoaded").await;
    let rendered = wait_js(&b, 60, "window.posecast.rendered")
        .await
        .as_u64()
        .unwrap();
    wait_js(
        &b,
        60,
        &format!("window.posecast.rendered > {rendered} + 5"),
    )
    .await;
    b.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    let png_bytes = b.screenshot().await.unwrap();
    std::fs::write(artifacts().join("dashboard.png"), &png_bytes).unwrap();
    let rect = find(&b, "#preview").await.rectangle().await.unwrap();
    let (avatar_px, area) = count_avatar_pixels(&png_bytes, rect);
    assert!(
        avatar_px * 100 > area,
        "the preview shows only {avatar_px} avatar pixels of {area}"
    );

    phases.push(("screenshot", started.elapsed()));

    // 4b. Uploads through the form: the server's import error is shown verbatim and nothing
    // is added; a real BVH, then .anim clips for an uploaded .skel, are imported and listed.
    let upload = |files: Vec<PathBuf>, name: &'static str| {
        let b = b.clone();
        async move {
            let name_box = find(&b, "#upload-name").await;
            name_box.clear().await.unwrap();
            name_box.send_keys(name).await.unwrap();
            let input = find(&b, "#upload-files").await;
            input.clear().await.ok();
            let paths: Vec<String> = files.iter().map(|p| p.display().to_string()).collect();
            input.send_keys(&paths.join("\n")).await.unwrap();
            find(&b, "#upload-submit").await.click().await.unwrap();
            let v = wait_js(&b, 60, "(() => { const t = document.getElementById('upload-result').textContent; return /^(Imported|Upload refused|Upload failed)/.test(t) ? t : null; })()").await;
            v.as_str().unwrap_or_default().to_owned()
        }
    };
    let garbage = artifacts().join("garbage.glb");
    std::fs::write(&garbage, b"glTF this is not a binary glTF").unwrap();
    let text = upload(vec![garbage], "junk").await;
    assert!(text.starts_with("Upload refused (422): "), "{text}");
    assert!(
        text.contains("garbage.glb"),
        "the importer's message names the file: {text}"
    );
    let (_, listed) = http(&server, "GET", "/api/assets", None).await;
    assert!(!listed.contains("\"junk\""), "{listed}");
    // Chromedriver wants canonical paths for file inputs.
    let testdata =
        std::fs::canonicalize(Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/testdata"))
            .expect("../shared/testdata");
    let text = upload(vec![testdata.join("bvh/fairmotion/sinusoidal.bvh")], "sine").await;
    assert!(text.starts_with("Imported sine ("), "{text}");
    // The classification reaches the page (four generic joints are not a humanoid).
    assert!(text.contains("not humanoid"), "{text}");
    let text = upload(
        vec![
            testdata.join("cse169/wasp.skel"),
            testdata.join("cse169/wasp.skin"),
        ],
        "wasp",
    )
    .await;
    assert!(text.starts_with("Imported wasp ("), "{text}");
    let text = upload(vec![testdata.join("cse169/wasp_walk.anim")], "wasp").await;
    assert!(text.contains("wasp_walk"), "{text}");
    let (_, listed) = http(&server, "GET", "/api/assets", None).await;
    assert!(
        listed.contains("\"sine\"") && listed.contains("wasp_walk"),
        "{listed}"
    );
    phases.push(("uploads", started.elapsed()));
    // 5. Narrow screens: no horizontal scrolling at 400 px.
    b.set_window_size(400, 800).await.unwrap();
    wait_js(&b, 60, "window.innerWidth <= 400").await;
    let overflow = b
        .execute(
            "return document.documentElement.scrollWidth - window.innerWidth;",
            vec![],
        )
        .await
        .unwrap();
    assert!(
        overflow.as_i64().unwrap() <= 0,
        "horizontal overflow of {overflow} px at 400 px"
    );
    b.set_window_size(1280, 800).await.unwrap();

    // The 2D-canvas fallback (used when WebGL2 is unavailable) draws the skeleton.
    b.goto(&format!("{base}/?debug&renderer=2d")).await.unwrap();
    wait_js(
        &b,
        60,
        "window.posecast.renderer === '2d' && window.posecast.rendered > 10",
    )
    .await;
    let shot = b.screenshot().await.unwrap();
    let rect = find(&b, "#preview").await.rectangle().await.unwrap();
    let (skeleton_px, _) = count_avatar_pixels(&shot, rect);
    assert!(
        skeleton_px > 200,
        "the 2D preview shows {skeleton_px} skeleton pixels"
    );
    phases.push(("narrow+2d", started.elapsed()));
    // 6. Server gone: the page says offline.
    assert_eq!(errors(&b).await, json!([]), "errors during the session");
    let addr = server.addr;
    server.stop().await;
    wait_js(&b, 60, "document.getElementById('conn-state').textContent.startsWith('offline') && !document.getElementById('offline').hidden").await;
    // Only the preview's overlay covers anything: the status pill (class `offline` too) stays
    // a pill in the header, and the page is not painted over.
    let pill = wait_js(&b, 60, "(() => { const p = getComputedStyle(document.getElementById('conn-state')); return [p.position, document.getElementById('conn-state').getBoundingClientRect().height < 60]; })()").await;
    assert_eq!(
        pill,
        serde_json::json!(["static", true]),
        "the status pill when offline"
    );
    phases.push(("offline", started.elapsed()));

    // 7. A server back on the same address: the page reconnects, resubscribes and streams.
    let server = Server::start(Config {
        listen: addr,
        tick_rate: 60.0,
        access: common::test_access(),
        ..Config::default()
    })
    .await
    .expect("restart on the same address");
    wait_js(
        &b,
        60,
        "window.posecast.state === 'online' && document.getElementById('offline').hidden",
    )
    .await;
    let frames = b
        .execute("return window.posecast.frames;", vec![])
        .await
        .unwrap();
    let frames = frames.as_u64().unwrap_or(0);
    wait_js(
        &b,
        60,
        &format!("window.posecast.frames > {frames} + 10 && document.querySelector('#scene-list button[data-avatar=\"avatar\"]') !== null"),
    )
    .await;
    server.stop().await;
    phases.push(("reconnected", started.elapsed()));
    let phases: Vec<String> = phases
        .iter()
        .map(|(name, t)| format!("{name} {:.1} s", t.as_secs_f32()))
        .collect();
    println!(
        "dashboard: renderer {renderer}, {fps}, RTT {rtt} ms, knee idle {idle_knee:.1}° walk \
         {walk_knee:.1}°, preview {avatar_px}/{area} px (2D: {skeleton_px}); done at: {}",
        phases.join(", ")
    );
    b.close().await.unwrap();
    let _ = std::fs::remove_dir_all(asset_dir);
}
