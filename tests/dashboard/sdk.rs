//! The JavaScript client (`/sdk/posecast.js`) in headless Chromium, from pages served on
//! another origin that import only it: its binary decoding against a Rust client's on the same
//! ticks (all joints, and a joint subset made whole), its typed command errors, and the guide's
//! "Build your own dashboard" page as written.

use crate::browser::*;
use crate::common::{self, CONTROL};
use posecast_client::net::{Client, ClientOptions, Event};
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// Serves `html` on another origin than the posecast server's ([`serve_origin`]).
async fn serve_page(html: String) -> String {
    serve_origin(html, None, Vec::new()).await
}

/// A page that imports only the client and records, per tick, the decoded rotations and
/// placement of `avatar` (and whether the frame was a keyframe): its default client (protocol
/// version 9, on a websocket version 7's wire v2 frames with packed deltas), one asking for
/// version 1, one for JSON and one for a joint subset (v1 frames on a version-2 connection).
fn recording_page(addr: std::net::SocketAddr) -> String {
    format!(
        r#"<!doctype html><meta charset="utf-8"><title>posecast.js</title>
<script type="module">
import * as sdk from "http://{addr}/sdk/posecast.js";
window.sdk = sdk;
window.url = "ws://{addr}/ws";
const client = new sdk.Client({{ url: window.url }});
window.client = client;
window.recorded = {{}};
window.recordedCount = 0;
client.on("frame", (f) => {{
  const p = f.avatars.find((a) => a.avatar === "avatar");
  if (p && window.recordedCount < 600) {{
    window.recorded[f.seq] = {{ key: f.key, rotations: p.rotations, placement: p.placement }};
    window.recordedCount++;
  }}
}});
client.subscribe("default");
client.connect();
// The same stream in v1 frames (protocol version 1).
const v1 = new sdk.Client({{ url: window.url, version: 1 }});
window.v1Client = v1;
window.v1 = {{}};
v1.on("frame", (f) => {{
  const p = f.avatars.find((a) => a.avatar === "avatar");
  if (p && Object.keys(window.v1).length < 600) window.v1[f.seq] = {{ key: f.key, rotations: p.rotations, placement: p.placement }};
}});
v1.subscribe("default");
v1.connect();
// The same stream as JSON (float rotations, every frame complete), in the same shape.
const json = new sdk.Client({{ url: window.url, encoding: "json" }});
window.jsonClient = json;
window.json = {{}};
json.on("frame", (f) => {{
  const p = f.avatars.find((a) => a.avatar === "avatar");
  if (p && Object.keys(window.json).length < 600) window.json[f.seq] = {{ key: f.key, rotations: p.rotations }};
}});
json.subscribe("default");
json.connect();
// Binary (v2) frames of the left arm's chain only (a joint subset), made whole by the client.
const arm = new sdk.Client({{ url: window.url }});
window.armClient = arm;
window.arm = {{}};
arm.on("frame", (f) => {{
  const p = f.avatars.find((a) => a.avatar === "avatar");
  if (p && Object.keys(window.arm).length < 600) window.arm[f.seq] = {{ key: f.key, rotations: p.rotations }};
}});
arm.subscribe("default", {{ joints: {{ names: ["l_wrist"] }} }});
arm.connect();
// Binary (v2) frames at a precision of 0.1° (protocol version 5): coarser, smaller.
const coarse = new sdk.Client({{ url: window.url }});
window.coarseClient = coarse;
window.coarse = {{}};
coarse.on("frame", (f) => {{
  const p = f.avatars.find((a) => a.avatar === "avatar");
  if (p && Object.keys(window.coarse).length < 600) window.coarse[f.seq] = {{ key: f.key, rotations: p.rotations }};
}});
coarse.subscribe("default", {{ precision: {{ degrees: 0.1 }} }});
coarse.connect();
</script>"#
    )
}

fn quat(v: &Value) -> glam::Quat {
    let a: Vec<f32> = v
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect();
    glam::Quat::from_xyzw(a[0], a[1], a[2], a[3])
}

/// How a page client's recorded ticks compare with the Rust client's.
struct Compared {
    ticks: usize,
    deltas: usize,
    rotations: usize,
    worst: f64,
    worst_place: f32,
}

/// On every tick both decoded, the page client's rotations equal the Rust client's within
/// float rounding (the same 48 bits), and its placement too.
fn compare(
    rust_ticks: &BTreeMap<u64, (Vec<glam::Quat>, [f32; 7])>,
    recorded: &serde_json::Map<String, Value>,
    wire: &str,
) -> Compared {
    let (mut ticks, mut deltas, mut rotations, mut worst, mut worst_place) =
        (0, 0, 0, 0.0f64, 0.0f32);
    for (seq, (want, want_place)) in rust_ticks {
        let Some(got) = recorded.get(&seq.to_string()) else {
            continue;
        };
        ticks += 1;
        if got["key"] == json!(false) {
            deltas += 1;
        }
        let got_rotations = got["rotations"].as_array().unwrap();
        assert_eq!(got_rotations.len(), want.len(), "joints at tick {seq}");
        for (j, (g, w)) in got_rotations.iter().zip(want).enumerate() {
            let angle = angle_between_degrees(quat(g), *w);
            worst = worst.max(angle);
            rotations += 1;
            assert!(
                angle <= SAME_BITS_DEGREES,
                "{wire} tick {seq} joint {j}: the page decoded {g}, the Rust client {w:?} ({angle}°)"
            );
        }
        let p = &got["placement"];
        let got_place: Vec<f32> = p["position"]
            .as_array()
            .unwrap()
            .iter()
            .chain(p["rotation"].as_array().unwrap())
            .map(|x| x.as_f64().unwrap() as f32)
            .collect();
        for (g, w) in got_place.iter().zip(want_place) {
            worst_place = worst_place.max((g - w).abs());
            assert!(
                (g - w).abs() <= 1e-5,
                "{wire} tick {seq}: placement {p} vs {want_place:?}"
            );
        }
    }
    assert!(
        worst <= MAX_ERROR_DEGREES,
        "{wire}: {worst}° over the quantisation bound"
    );
    Compared {
        ticks,
        deltas,
        rotations,
        worst,
        worst_place,
    }
}

/// Both decoders read the same 48 bits per rotation, so they differ by float rounding only
/// (f64 in JavaScript, f32 in Rust: measured 1.5e-5°); one 15-bit level off is about 0.005°,
/// inside the quantisation bound but not this.
const SAME_BITS_DEGREES: f64 = 5e-4;

/// On every tick both decoded, the page's rotations — its default client's, wire v2, and a
/// version-1 client's — equal the Rust client's (v1 frames) within the quantisation bound —
/// within float rounding, in fact — and its placements within float rounding; the page's JSON
/// client's float rotations are within the quantisation bound of them — keyframes and deltas
/// (the avatar walks while it is moved, so deltas carry small and full rotation changes and
/// placements). v2 frames are smaller than v1 frames, which are several times smaller than
/// JSON; the joint-subset client, on a version-2 connection, decodes its v1 frames; a client
/// asking for 0.1° (protocol version 5) decodes smaller frames within that bound.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_javascript_client_decodes_binary_frames_as_the_rust_client_does() {
    let server = common::server(60.0).await;
    for body in [
        json!({"op": "play", "avatar": "avatar", "clip": "walk", "fade": 0}),
        json!({"op": "place_avatar", "avatar": "avatar", "position": [3, 0, -2], "rotation": glam::Quat::from_rotation_y(1.5).to_array(), "duration": 30}),
    ] {
        let (status, answer) = command(&server, body).await;
        assert_eq!(status, 200, "{answer}");
    }
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.encoding = Encoding::Binary;
    options.reconnect = false;
    let rust = Client::connect(options).await.unwrap();
    let avatar = AvatarId("avatar".into());

    let page = serve_page(recording_page(server.addr)).await;
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();
    wait_js(&b, 60, "window.recordedCount > 0").await;

    // The Rust client's pose of every tick it decoded, for 3 s.
    let mut rust_ticks: BTreeMap<u64, (Vec<glam::Quat>, [f32; 7])> = BTreeMap::new();
    let mut events = rust.events();
    let end = Instant::now() + Duration::from_secs(3);
    while Instant::now() < end {
        let Ok(Ok(event)) = tokio::time::timeout(Duration::from_millis(200), events.recv()).await
        else {
            continue;
        };
        if let Event::Frame { seq, .. } = event
            && let Some(p) = rust.latest(&avatar)
            && p.seq == seq
        {
            let pl = p.placement;
            let placement = [
                pl.position.x,
                pl.position.y,
                pl.position.z,
                pl.rotation.x,
                pl.rotation.y,
                pl.rotation.z,
                pl.rotation.w,
            ];
            let rotations = p.locals.iter().map(|t| t.rotation).collect();
            rust_ticks.insert(seq, (rotations, placement));
        }
    }
    let recorded = wait_js(&b, 60, "window.recordedCount >= 200 && window.recorded").await;
    let recorded = recorded.as_object().unwrap();

    let v2 = compare(&rust_ticks, recorded, "v2");
    let v1_recorded = wait_js(&b, 60, "Object.keys(window.v1).length > 60 && window.v1").await;
    let v1 = compare(&rust_ticks, v1_recorded.as_object().unwrap(), "v1");
    let Compared {
        ticks,
        deltas,
        rotations,
        worst,
        worst_place,
    } = v2;
    assert!(
        v1.ticks >= 60 && v1.deltas >= 30,
        "only {} ticks ({} deltas) decoded by the v1 page client and the Rust client",
        v1.ticks,
        v1.deltas
    );
    // The JSON client's float rotations: the binary ones are within the quantisation bound.
    let json_frames = wait_js(&b, 60, "window.json").await;
    let (mut json_ticks, mut worst_json) = (0, 0.0f64);
    for (seq, (want, _)) in &rust_ticks {
        let Some(got) = json_frames.get(seq.to_string()) else {
            continue;
        };
        json_ticks += 1;
        assert_eq!(got["key"], json!(true), "JSON frames are complete");
        for (j, (g, w)) in got["rotations"]
            .as_array()
            .unwrap()
            .iter()
            .zip(want)
            .enumerate()
        {
            let angle = angle_between_degrees(quat(g), *w);
            worst_json = worst_json.max(angle);
            assert!(
                angle <= MAX_ERROR_DEGREES,
                "tick {seq} joint {j}: JSON {g}, binary {w:?} ({angle}°)"
            );
        }
    }
    assert!(
        json_ticks >= 60,
        "only {json_ticks} ticks in JSON and binary"
    );
    // The arm-only client: the chain to the left wrist as the full stream decodes it (the same
    // bits), every other joint at its rest rotation — whole poses, from fewer bytes.
    let description = rust.avatar(&avatar).unwrap().description.clone();
    let chain =
        posecast_proto::subset::JointSet::Names(vec!["l_wrist".into()]).select(&description);
    let arm_frames = wait_js(&b, 60, "Object.keys(window.arm).length > 60 && window.arm").await;
    let mut arm_ticks = 0;
    for (seq, (want, _)) in &rust_ticks {
        let Some(got) = arm_frames.get(seq.to_string()) else {
            continue;
        };
        arm_ticks += 1;
        let got = got["rotations"].as_array().unwrap();
        assert_eq!(got.len(), want.len(), "whole poses at tick {seq}");
        for (j, (g, w)) in got.iter().zip(want).enumerate() {
            let expected = if chain.joints.contains(&(j as u16)) {
                *w
            } else {
                glam::Quat::from_array(description.rest_rotations[j])
            };
            let angle = angle_between_degrees(quat(g), expected);
            assert!(
                angle <= SAME_BITS_DEGREES,
                "tick {seq} joint {j}: the arm-only page has {g}, expected {expected:?} ({angle}°)"
            );
        }
    }
    assert!(
        arm_ticks >= 60,
        "only {arm_ticks} ticks of the arm-only client"
    );
    // The 0.1° client: every rotation within the grid's bound (step 11) of the finest
    // stream's, which is itself within the finest bound of the server's.
    let coarse_frames = wait_js(
        &b,
        60,
        "Object.keys(window.coarse).length > 60 && window.coarse",
    )
    .await;
    let bound = posecast_proto::precision::rotation_bound_degrees(11)
        + posecast_proto::precision::rotation_bound_degrees(1);
    let (mut coarse_ticks, mut coarse_worst) = (0, 0.0f64);
    for (seq, (want, _)) in &rust_ticks {
        let Some(got) = coarse_frames.get(seq.to_string()) else {
            continue;
        };
        coarse_ticks += 1;
        for (j, (g, w)) in got["rotations"]
            .as_array()
            .unwrap()
            .iter()
            .zip(want)
            .enumerate()
        {
            let angle = angle_between_degrees(quat(g), *w);
            coarse_worst = coarse_worst.max(angle);
            assert!(
                angle <= bound,
                "tick {seq} joint {j}: 0.1° page client {angle}° off"
            );
        }
    }
    assert!(
        coarse_ticks >= 60,
        "only {coarse_ticks} ticks of the 0.1° client"
    );
    // Coarser than the finest (not the same frames under another name).
    assert!(
        coarse_worst > 0.01,
        "the 0.1° client's worst is {coarse_worst}°"
    );
    // Binary is what browsers should get: several times smaller than JSON, and v2 (the
    // default) smaller than v1 (bytes per frame, keyframes included).
    let sizes = b
        .execute(
            "return [client.stats.frameBytes / client.stats.frames, \
                     jsonClient.stats.frameBytes / jsonClient.stats.frames, \
                     armClient.stats.frameBytes / armClient.stats.frames, \
                     armClient.stats.undecodable, \
                     v1Client.stats.frameBytes / v1Client.stats.frames, \
                     [client, v1Client, armClient].map((c) => c.welcome.version), \
                     client.stats.undecodable, v1Client.stats.undecodable, \
                     coarseClient.stats.frameBytes / coarseClient.stats.frames, \
                     coarseClient.stats.undecodable];",
            vec![],
        )
        .await
        .unwrap();
    let (binary_bytes, json_bytes) = (sizes[0].as_f64().unwrap(), sizes[1].as_f64().unwrap());
    let (arm_bytes, v1_bytes) = (sizes[2].as_f64().unwrap(), sizes[4].as_f64().unwrap());
    assert_eq!(sizes[3], json!(0), "arm-only frames all decoded");
    assert_eq!(sizes[5], json!([9, 1, 9]), "protocol versions welcomed");
    assert_eq!(sizes[9], json!(0), "0.1° frames all decoded");
    let coarse_bytes = sizes[8].as_f64().unwrap();
    assert!(
        coarse_bytes < binary_bytes,
        "0.1° frames {coarse_bytes} B against {binary_bytes} B at the finest"
    );
    assert_eq!(sizes[6], json!(0), "v2 frames all decoded");
    assert_eq!(sizes[7], json!(0), "v1 frames all decoded");
    // The arm's chain comes as v2 frames cut to it: smaller than v2 frames of every joint.
    assert!(
        arm_bytes < binary_bytes,
        "arm-only {arm_bytes:.0} B, all joints {binary_bytes:.0} B a v2 frame"
    );
    assert!(
        binary_bytes < v1_bytes,
        "bytes per frame: v2 {binary_bytes:.0}, v1 {v1_bytes:.0}"
    );
    assert!(
        v1_bytes * 3.0 < json_bytes,
        "bytes per frame: v1 {v1_bytes:.0}, JSON {json_bytes:.0}"
    );
    // 3 s at 60 Hz: most ticks reach both (a loaded machine may skip some).
    assert!(
        ticks >= 60 && deltas >= 30,
        "only {ticks} ticks ({deltas} deltas) decoded by both; the Rust client had {}, the page {}",
        rust_ticks.len(),
        recorded.len()
    );
    // The avatar moved: the compared poses are not one pose repeated. (Over every tick: the
    // first, middle and last alone can fall on the same phase of the walk cycle.)
    let moved = rust_ticks.values().map(|(r, _)| r[1]).collect::<Vec<_>>();
    let farthest = moved
        .iter()
        .map(|q| angle_between_degrees(moved[0], *q))
        .fold(0.0f64, f64::max);
    assert!(
        farthest > 0.5,
        "the avatar did not move: joint 1 at most {farthest}° from its first pose"
    );
    println!(
        "posecast.js vs posecast_client: {ticks} ticks ({deltas} deltas), {rotations} rotations, \
         largest difference {worst:.2e}° (bound {MAX_ERROR_DEGREES}°), placement {worst_place:.1e}; \
         v1 page client: {} ticks ({} deltas), largest difference {:.2e}°; \
         JSON vs binary on {json_ticks} ticks: {worst_json:.2e}°; bytes per frame: v2 \
         {binary_bytes:.1}, v1 {v1_bytes:.1}, JSON {json_bytes:.0}, v2 of the left arm's chain \
         ({} joints, {arm_ticks} ticks compared) {arm_bytes:.0}",
        v1.ticks,
        v1.deltas,
        v1.worst,
        chain.joints.len()
    );
}

/// Commands whose promises reject with the typed error: `play` without a token is
/// `unauthorized` (and changes nothing), `get_avatar` of an unknown avatar `unknown_avatar`; a
/// control token the server does not know leaves the client watching, the refusal recorded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn command_promises_reject_with_the_typed_error() {
    let server = common::server(60.0).await;
    let page = serve_page(recording_page(server.addr)).await;
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();
    wait_js(&b, 60, "window.client && window.client.state === 'online'").await;
    let script = format!(
        r#"const done = arguments[0];
(async () => {{
  const {{ Client, PosecastError }} = window.sdk;
  const online = (c) => new Promise((resolve) => {{
    c.on("state", (s) => s === "online" && resolve(c));
    c.connect();
  }});
  const refusal = async (c, command) => {{
    try {{
      return {{ resolved: await c.command(command) }};
    }} catch (e) {{
      return {{ typed: e instanceof PosecastError, name: e.name, code: e.code, message: e.message, id: e.id ?? null, details: e.details ?? null }};
    }}
  }};
  const viewer = await online(new Client({{ url: window.url, reconnect: false }}));
  const controller = await online(new Client({{ url: window.url, reconnect: false, token: "{CONTROL}" }}));
  const wrong = await online(new Client({{ url: window.url, reconnect: false, token: "not-a-token" }}));
  await new Promise((r) => setTimeout(r, 300)); // the refusal's reason follows the welcome
  const out = {{
    play: await refusal(viewer, {{ op: "play", avatar: "avatar", clip: "wave" }}),
    unknown: await refusal(controller, {{ op: "get_avatar", avatar: "nobody" }}),
    known: await refusal(controller, {{ op: "get_avatar", avatar: "avatar" }}),
    wrong: {{ state: wrong.state, access: wrong.access, refusals: wrong.refusals }},
  }};
  for (const c of [viewer, controller, wrong]) c.close();
  done(out);
}})().catch((e) => done({{ failed: String(e) }}));"#
    );
    let out = b.execute_async(&script, vec![]).await.unwrap();
    assert_eq!(out["play"]["typed"], json!(true), "{out}");
    assert_eq!(out["play"]["name"], "PosecastError", "{out}");
    assert_eq!(out["play"]["code"], "unauthorized", "{out}");
    assert!(
        out["play"]["id"].is_u64(),
        "the error names its command: {out}"
    );
    assert_eq!(out["unknown"]["typed"], json!(true), "{out}");
    assert_eq!(out["unknown"]["code"], "unknown_avatar", "{out}");
    assert_eq!(
        out["unknown"]["details"],
        json!({"avatar": "nobody"}),
        "the error names what was not found: {out}"
    );
    assert_eq!(out["play"]["details"], json!(null), "{out}");
    assert_eq!(
        out["known"]["resolved"]["clip"], "idle",
        "a command that succeeds resolves with its result: {out}"
    );
    assert_eq!(out["wrong"]["state"], "online", "{out}");
    assert_eq!(out["wrong"]["access"]["control"], json!(false), "{out}");
    assert_eq!(out["wrong"]["refusals"][0]["code"], "unauthorized", "{out}");
    // The refused play changed nothing.
    assert_eq!(avatar_state(&server, "avatar").await["clip"], "idle");
}

/// The guide's example page (`docs/src/how-to/javascript.md`), exactly as written but for the server's address, served from
/// another origin: it draws the avatar, its tick advances, its root is where the Rust client
/// has it, and its button shows the typed refusal.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_guides_example_page_shows_poses() {
    let readme = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/src/how-to/javascript.md"
    ))
    .unwrap();
    let section = readme
        .split("# Build your own dashboard")
        .nth(1)
        .expect("docs/src/how-to/javascript.md has a section \"Build your own dashboard\"");
    let example = section
        .split("```html\n")
        .nth(1)
        .and_then(|s| s.split("\n```").next())
        .expect("the section has an html example");
    assert!(
        example.contains("localhost:8080/sdk/posecast.js"),
        "{example}"
    );
    let server = common::server(60.0).await;
    let page = serve_page(example.replace("localhost:8080", &server.addr.to_string())).await;
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    let rust = Client::connect(options).await.unwrap();
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();

    let status = "document.getElementById('status').textContent.match(/^avatar: tick (\\d+), root at y = (-?[0-9.]+) m$/)";
    let first = wait_js(&b, 60, status).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let second = wait_js(&b, 60, status).await;
    let tick = |v: &Value| v[1].as_str().unwrap().parse::<u64>().unwrap();
    assert!(
        tick(&second) >= tick(&first) + 10,
        "the page's tick advances: {first} then {second}"
    );
    // Idle, in place: the root's height moves by millimetres between the page's (played-out)
    // tick and the Rust client's newest.
    let page_y: f32 = second[2].as_str().unwrap().parse().unwrap();
    let rust_y = rust.latest(&AvatarId("avatar".into())).unwrap().locals[0]
        .translation
        .y;
    assert!(
        (page_y - rust_y).abs() < 0.02,
        "root height: the page {page_y} m, the Rust client {rust_y} m"
    );
    // Something was drawn on the canvas.
    let drawn = b
        .execute(
            "const c = document.getElementById('view'); \
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
             let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n;",
            vec![],
        )
        .await
        .unwrap();
    assert!(drawn.as_u64().unwrap() > 100, "pixels drawn: {drawn}");
    find(&b, "#wave").await.click().await.unwrap();
    wait_js(
        &b,
        60,
        "document.getElementById('wave').textContent === 'refused: unauthorized'",
    )
    .await;
    assert_eq!(avatar_state(&server, "avatar").await["clip"], "idle");
}

/// The client on its own (no dashboard around it): the server stops, the client goes offline
/// and keeps trying with back-off; a server back on the same address gets it online again,
/// subscribed as before (descriptions and frames of the same avatar flow), without the page
/// doing anything.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_reconnects_and_resubscribes_after_a_restart() {
    use posecast_server::config::Config;
    use posecast_server::startup::Server;
    let server = common::server(60.0).await;
    let addr = server.addr;
    let page = serve_page(format!(
        r#"<!doctype html><meta charset="utf-8"><title>reconnect</title>
<script type="module">
import {{ Client }} from "http://{addr}/sdk/posecast.js";
const client = new Client({{ url: "ws://{addr}/ws" }});
window.states = [];
window.frames = 0;
window.described = 0;
client.on("state", (s) => window.states.push(s));
client.on("description", () => window.described++);
client.on("frame", (f) => {{ if (f.avatars.some((a) => a.avatar === "avatar")) window.frames++; }});
client.subscribe("default");
client.connect();
window.client = client;
</script>"#
    ))
    .await;
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();
    wait_js(&b, 60, "window.frames > 30 && window.described >= 1").await;
    server.stop().await;
    wait_js(&b, 60, "window.client.state !== 'online'").await;
    // Down for a while: several attempts, none connecting.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let frames = b.execute("return window.frames;", vec![]).await.unwrap();
    let described = b.execute("return window.described;", vec![]).await.unwrap();
    let server = Server::start(Config {
        listen: addr,
        tick_rate: 60.0,
        access: common::test_access(),
        ..Config::default()
    })
    .await
    .expect("restart on the same address");
    server.ready().await.unwrap();
    let back = Instant::now();
    wait_js(
        &b,
        60,
        &format!(
            "window.client.state === 'online' && window.described > {described} && window.frames > {frames} + 30"
        ),
    )
    .await;
    let took = back.elapsed();
    let states = b.execute("return window.states;", vec![]).await.unwrap();
    let states: Vec<&str> = states
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert!(
        states.iter().filter(|s| **s == "online").count() >= 2,
        "online, then online again: {states:?}"
    );
    // Back-off is capped at 5 s: the restarted server is found within one more attempt.
    assert!(
        took < Duration::from_secs(8),
        "back after {took:?}: {states:?}"
    );
    server.stop().await;
}

/// Against a server of before protocol version 2 (it refuses `hello {version: 9}` down to `2`
/// with `unsupported_version`), the client — asking for 9 by default — says hello again
/// with the version before until it comes online with 1.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_falls_back_to_version_1_for_an_older_server() {
    // The posecast server only serves the SDK's files; the client talks to the old one.
    let server = common::server(60.0).await;
    let (old, hellos) = common::version_1_server().await;
    let page = serve_page(format!(
        r#"<!doctype html><meta charset="utf-8"><title>old server</title>
<script type="module">
import * as sdk from "http://{}/sdk/posecast.js";
const client = new sdk.Client({{ url: "ws://{old}/ws" }});
window.client = client;
client.connect();
</script>"#,
        server.addr
    ))
    .await;
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();
    wait_js(
        &b,
        60,
        "window.client && window.client.state === 'online' && window.client.version === 1 \
         && window.client.welcome.version === 1",
    )
    .await;
    assert_eq!(*hellos.lock().unwrap(), vec![9, 8, 7, 6, 5, 4, 3, 2, 1]);
    server.stop().await;
}
