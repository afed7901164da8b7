//! The web dashboard in a real headless Chromium, driven over WebDriver (chromedriver +
//! fantoccini) against an in-process server: the page loads without errors and lists the
//! avatars; its buttons and sliders change the avatars' state and the pose stream (checked by a
//! separate Rust websocket client); the preview draws the avatar (screenshot pixel count), and
//! every avatar of a scene where it stands (drawn roots, screenshot columns).
//!
//! Needs `/usr/bin/chromium` and `/usr/bin/chromedriver` (`scripts/test` installs them).
//! Set `POSECAST_UPDATE_SCREENSHOT=1` to also write `docs/dashboard.png` for the README.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{http, wait_for};
use fantoccini::key::Key;
use fantoccini::{Client as Browser, ClientBuilder, Locator};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_server::auth::{Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use serde_json::{Value, json};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// A chromedriver child process in a process group of its own, with the Chromium it starts:
/// the whole group is killed on drop (also when a test panics before closing the session).
struct Driver {
    child: Child,
    profile: PathBuf,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let group = format!("-{}", self.child.id());
        let _ = Command::new("kill")
            .args(["-KILL", "--", &group])
            .stderr(Stdio::null())
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.profile);
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Starts chromedriver and a headless Chromium session at 1280×800.
async fn browser() -> (Driver, Browser) {
    assert!(
        Path::new(CHROMEDRIVER).exists() && Path::new(CHROMIUM).exists(),
        "chromium and chromedriver are needed (scripts/test installs them)"
    );
    let port = free_port();
    let child = Command::new(CHROMEDRIVER)
        .arg(format!("--port={port}"))
        .process_group(0)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromedriver");
    let profile =
        std::env::temp_dir().join(format!("posecast-dashboard-{}-{port}", std::process::id()));
    let driver = Driver { child, profile };
    let deadline = Instant::now() + Duration::from_secs(20);
    while tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .is_err()
    {
        assert!(Instant::now() < deadline, "chromedriver did not start");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": CHROMIUM,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--window-size=1280,800", "--force-device-scale-factor=1",
                format!("--user-data-dir={}", driver.profile.display()),
            ],
        }),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    let client = ClientBuilder::new(connector)
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{port}"))
        .await
        .expect("start a Chromium session");
    (driver, client)
}

/// Evaluates `expr` in the page until it is truthy, for at most `secs`; returns its value.
async fn wait_js(b: &Browser, secs: u64, expr: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let v = b
            .execute(&format!("return ({expr});"), vec![])
            .await
            .unwrap();
        let truthy =
            !matches!(&v, Value::Null | Value::Bool(false)) && v != json!(0) && v != json!("");
        if truthy {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for `{expr}`");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn find(b: &Browser, css: &str) -> fantoccini::elements::Element {
    b.wait()
        .at_most(Duration::from_secs(10))
        .for_element(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no element {css}: {e}"))
}

async fn errors(b: &Browser) -> Value {
    b.execute("return window.posecast.errors;", vec![])
        .await
        .unwrap()
}

async fn command(server: &Server, body: Value) -> (u16, Value) {
    let (status, text) = http(server, "POST", "/api/commands", Some(&body.to_string())).await;
    (status, serde_json::from_str(&text).unwrap_or(Value::Null))
}

async fn avatar_state(server: &Server, avatar: &str) -> Value {
    let (status, body) = command(server, json!({"op": "get_avatar", "avatar": avatar})).await;
    assert_eq!(status, 200, "{body}");
    body["result"].clone()
}

/// Largest angle (degrees) of `joint`'s streamed local rotation from identity over `secs`.
async fn max_angle(c: &Client, avatar: &AvatarId, joint: usize, secs: f32) -> f32 {
    let end = Instant::now() + Duration::from_secs_f32(secs);
    let mut max = 0.0f32;
    while Instant::now() < end {
        if let Some(p) = c.latest(avatar) {
            max = max.max(
                p.locals[joint]
                    .rotation
                    .angle_between(glam::Quat::IDENTITY)
                    .to_degrees(),
            );
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    max
}

/// Non-background pixels of a screenshot inside the CSS-pixel rectangle `(x, y, w, h)`.
fn count_avatar_pixels(png_bytes: &[u8], rect: (f64, f64, f64, f64)) -> (usize, usize) {
    let (pixels, area) = avatar_pixels(png_bytes, rect, GRID_DIFFERENCE);
    (pixels.len(), area)
}

/// Connected runs `(first, last)` of screenshot columns (CSS px) holding an avatar pixel inside
/// `rect`: one per figure drawn apart from the others. Stricter than [`count_avatar_pixels`]:
/// the grid's nearest lines (80 from the background) span the whole preview and would join
/// the figures; the lit mesh and the skeleton overlay are far brighter.
fn column_runs(png_bytes: &[u8], rect: (f64, f64, f64, f64)) -> Vec<(usize, usize)> {
    let (pixels, _) = avatar_pixels(png_bytes, rect, 150);
    let mut columns: Vec<usize> = pixels.iter().map(|&(x, _)| x).collect();
    columns.sort_unstable();
    columns.dedup();
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for x in columns {
        match runs.last_mut() {
            Some(run) if run.1 + 1 == x => run.1 = x,
            _ => runs.push((x, x)),
        }
    }
    runs
}

/// Summed RGB difference from the preview's background above which a pixel is no grid.
const GRID_DIFFERENCE: i32 = 60;

/// `(x, y)` of the pixels of a screenshot inside the CSS-pixel rectangle `(x, y, w, h)` whose
/// summed RGB difference from the background exceeds `threshold`, and the rectangle's area.
fn avatar_pixels(
    png_bytes: &[u8],
    rect: (f64, f64, f64, f64),
    threshold: i32,
) -> (Vec<(usize, usize)>, usize) {
    let decoder = png::Decoder::new(png_bytes);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    // The preview's clear colour (viewer.js BACKGROUND); most of the grid is within 60 of it (its nearest lines reach 80).
    let bg = [27i32, 30, 36];
    let (x0, y0) = (rect.0.max(0.0) as usize, rect.1.max(0.0) as usize);
    let x1 = ((rect.0 + rect.2) as usize).min(info.width as usize);
    let y1 = ((rect.1 + rect.3) as usize).min(info.height as usize);
    let mut pixels = Vec::new();
    for y in y0..y1 {
        for x in x0..x1 {
            let i = (y * info.width as usize + x) * channels;
            let d: i32 = (0..3).map(|c| (i32::from(buf[i + c]) - bg[c]).abs()).sum();
            if d > threshold {
                pixels.push((x, y));
            }
        }
    }
    (pixels, (x1 - x0) * (y1 - y0))
}

fn artifacts() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A server with the built-in avatar plus the CSE169 `test.skel` rig (DOF limits on `knee_r`).
async fn server_with_limited_rig() -> (Server, PathBuf) {
    let dir =
        std::env::temp_dir().join(format!("posecast-dashboard-assets-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let skel = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/testdata/cse169/test.skel");
    std::fs::copy(&skel, dir.join("test.skel")).expect("../shared/testdata/cse169/test.skel");
    let config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: 60.0,
        asset_dirs: vec![dir.clone()],
        access: common::test_access(),
        ..Config::default()
    };
    let server = Server::start(config).await.unwrap();
    server.ready().await.unwrap();
    (server, dir)
}

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
    wait_js(&b, 10, "window.posecast.state === 'online' && window.posecast.frames > 10 && window.posecast.rendered > 10").await;
    let renderer = wait_js(&b, 5, "window.posecast.renderer").await;
    wait_js(&b, 10, "window.posecast.meshLoaded").await;
    assert_eq!(errors(&b).await, json!([]), "errors while loading");
    let fps = wait_js(
        &b,
        5,
        "/^[1-9][0-9]* frames/.test(document.getElementById('fps').textContent) && document.getElementById('fps').textContent",
    )
    .await;
    let rtt = wait_js(&b, 5, "window.posecast.rtt").await;

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
            t0.elapsed() < Duration::from_secs(5),
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
        5,
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
    wait_js(&b, 5, "document.getElementById('dof-0').min === '-115' && document.getElementById('dof-0').max === '0' && document.getElementById('dof-1').min === '0' && document.getElementById('dof-1').max === '0' && Math.abs(Number(document.getElementById('dof-0').value) + 114.6) < 0.6").await;
    slider.send_keys(&Key::End.to_string()).await.unwrap();
    let t0 = Instant::now();
    loop {
        if avatar_state(&server, "skel").await["overrides"] == json!(["knee_r"]) {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "the slider never set an override"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The page shows the value the server applied.
    wait_js(&b, 5, "document.getElementById('dof-0-out').textContent === '0.0°' && document.getElementById('dof-0').max === '0'").await;
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
    wait_js(&b, 10, "window.posecast.meshLoaded").await;
    let rendered = wait_js(&b, 5, "window.posecast.rendered")
        .await
        .as_u64()
        .unwrap();
    wait_js(&b, 5, &format!("window.posecast.rendered > {rendered} + 5")).await;
    b.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    let png_bytes = b.screenshot().await.unwrap();
    std::fs::write(artifacts().join("dashboard.png"), &png_bytes).unwrap();
    if std::env::var_os("POSECAST_UPDATE_SCREENSHOT").is_some() {
        std::fs::write(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/dashboard.png"),
            &png_bytes,
        )
        .unwrap();
    }
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
            let v = wait_js(&b, 20, "(() => { const t = document.getElementById('upload-result').textContent; return /^(Imported|Upload refused|Upload failed)/.test(t) ? t : null; })()").await;
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
    wait_js(&b, 5, "window.innerWidth <= 400").await;
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
        10,
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
    wait_js(&b, 10, "document.getElementById('conn-state').textContent.startsWith('offline') && !document.getElementById('offline').hidden").await;
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
        15,
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
        10,
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

/// A wrong control token is refused visibly, the page keeps watching with the view token, and
/// nothing changes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_control_token_is_refused_and_changes_nothing() {
    let mut access = common::test_access();
    access
        .add(TokenRule::new(
            "viewer",
            Secret::new("view-token"),
            Role::View,
        ))
        .unwrap();
    let server = common::server_with(60.0, access).await;
    let (_driver, b) = browser().await;
    b.goto(&format!("{}/?debug", server.http_url()))
        .await
        .unwrap();
    wait_js(&b, 10, "window.posecast.state").await;
    find(&b, "#token-view")
        .await
        .send_keys("view-token")
        .await
        .unwrap();
    find(&b, "#token-control")
        .await
        .send_keys("wrong-token")
        .await
        .unwrap();
    find(&b, "#token-apply").await.click().await.unwrap();
    // The refusal is shown; the page falls back to the view token and can still watch.
    wait_js(
        &b,
        10,
        "/unauthorized/.test(document.getElementById('auth-status').textContent)",
    )
    .await;
    find(&b, r#"#scene-list button[data-avatar="avatar"]"#).await;
    wait_js(
        &b,
        10,
        "window.posecast.state === 'online' && window.posecast.frames > 5",
    )
    .await;
    // Playing is refused (or not offered): the avatar keeps idling.
    find(&b, "#clip-select")
        .await
        .select_by_value(r#"[null,"walk"]"#)
        .await
        .unwrap();
    let _ = find(&b, "#play").await.click().await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut o = ClientOptions::new(server.ws_url(), "default");
    o.token = Some("view-token".into());
    o.reconnect = false;
    let watcher = Client::connect(o).await.unwrap();
    let state = watcher
        .command(posecast_proto::command::Command::GetAvatar {
            avatar: AvatarId("avatar".into()),
        })
        .await
        .unwrap();
    assert_eq!(state["clip"], "idle", "{state}");
    b.close().await.unwrap();
}

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
            15,
            &format!(
                "window.posecast.renderer === '{renderer}' && window.posecast.drawn.length === 2 \
                 && {ready}"
            ),
        )
        .await;
        // A few more renders, so the mesh that just arrived is on screen.
        let rendered = wait_js(&b, 5, "window.posecast.rendered")
            .await
            .as_u64()
            .unwrap();
        wait_js(&b, 5, &format!("window.posecast.rendered > {rendered} + 2")).await;
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
