//! Correctable normalisation end to end (issue 18, items 2 and 3): pipeline options given
//! with an upload (multipart fields or query parameters), changed later with
//! `configure_asset` (stored, so a restart keeps them), the effective mapping read back with
//! `get_asset`; a rig that is not a humanoid refuses humanoid clips with `not_humanoid`.

#![allow(clippy::unwrap_used)]

mod common;

use common::{command_to, http_to};
use posecast_server::builtin::variants::{self, Naming, QUADRUPED_BVH};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use serde_json::{Value, json};
use std::net::SocketAddr;

async fn server(data: &std::path::Path) -> Server {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: Some(data.to_owned()),
        access: common::test_access(),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    server
}

async fn upload(
    addr: SocketAddr,
    path: &str,
    files: &[(&str, &[u8])],
    fields: &[(&str, &str)],
) -> (u16, Value) {
    let (content_type, body) = common::multipart_with_fields(files, fields);
    let (s, b) = http_to(addr, "POST", path, &content_type, &body).await;
    (s, serde_json::from_str(&b).unwrap_or(Value::Null))
}

async fn command(addr: SocketAddr, c: Value) -> (u16, Value) {
    command_to(addr, &c.to_string()).await
}

async fn detail(addr: SocketAddr, asset: &str) -> Value {
    let (s, b) = command(addr, json!({"op": "get_asset", "asset": asset})).await;
    assert_eq!(s, 200, "{b}");
    b["result"].clone()
}

/// The H-Anim name `get_asset` reports for `joint`.
fn hanim(detail: &Value, joint: &str) -> Value {
    detail["mapping"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["joint"] == joint)
        .unwrap_or_else(|| panic!("no joint {joint}"))["hanim"]
        .clone()
}

#[tokio::test]
async fn options_with_the_upload_then_configure_asset() {
    let data = tempfile::tempdir().unwrap();
    let first = server(data.path()).await;
    let addr = first.addr;
    let bvh = variants::bvh(Naming::Mocapbank, "wave", None).unwrap();

    // Options as multipart fields: one joint unmapped by the user.
    let (s, b) = upload(
        addr,
        "/api/assets/mocap",
        &[("mocap.bvh", bvh.as_bytes())],
        &[("name_map", r#"{"LeftCollar": ""}"#)],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    assert_eq!(b["result"][0]["humanoid"], true, "{b}");
    assert_eq!(b["result"][0]["mapped"], 21, "{b}"); // all but LowerHips and LeftCollar
    let d = detail(addr, "mocap").await;
    assert_eq!(hanim(&d, "LeftCollar"), Value::Null);
    assert_eq!(
        hanim(&d, "LeftShoulder"),
        "l_shoulder",
        "the arm chain maps it"
    );
    assert_eq!(hanim(&d, "RightCollar"), "r_sternoclavicular");
    assert_eq!(d["options"]["name_map"], json!({"LeftCollar": ""}));
    assert_eq!(d["configurable"], true);
    assert_eq!(d["units"]["source"], "guessed");
    assert!((d["units"]["metres_per_unit"].as_f64().unwrap() - 0.01).abs() < 1e-9);

    // Changed later: another mapping, and declared not a humanoid.
    let (s, b) = command(
        addr,
        json!({"op": "configure_asset", "asset": "mocap",
               "options": {"name_map": {"LeftShoulder": ""}, "humanoid": false}}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    assert_eq!(b["result"][0]["humanoid"], false, "{b}");
    let d = detail(addr, "mocap").await;
    assert_eq!(hanim(&d, "LeftCollar"), "l_sternoclavicular");
    assert_eq!(hanim(&d, "LeftShoulder"), Value::Null);
    assert_eq!(d["humanoid"], false);
    assert_eq!(d["options"]["humanoid"], false);
    let meta: Value =
        serde_json::from_slice(&std::fs::read(data.path().join("assets/mocap/meta.json")).unwrap())
            .unwrap();
    assert_eq!(meta["options"]["humanoid"], false, "{meta}");

    // A humanoid clip onto it is refused, typed.
    let (s, b) = command(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "mocap", "avatar": "m"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let play = json!({"op": "play", "avatar": "m", "clip": "walk", "from_asset": "avatar"});
    let (s, b) = command(addr, play.clone()).await;
    assert_eq!((s, b["code"].clone()), (422, json!("not_humanoid")), "{b}");

    // Refusals change nothing.
    for (c, status, code) in [
        (
            json!({"op": "configure_asset", "asset": "avatar", "options": {}}),
            400,
            "not_allowed_now",
        ),
        (
            json!({"op": "configure_asset", "asset": "nope", "options": {}}),
            404,
            "unknown_asset",
        ),
        (
            json!({"op": "configure_asset", "asset": "mocap",
                   "options": {"name_map": {"NoSuchJoint": "l_hip"}}}),
            400,
            "invalid_value",
        ),
    ] {
        let (s, b) = command(addr, c).await;
        assert_eq!((s, b["code"].clone()), (status, json!(code)), "{b}");
    }
    assert_eq!(detail(addr, "mocap").await, d);
    first.stop().await;

    // A restart keeps the options.
    let second = server(data.path()).await;
    let addr = second.addr;
    assert_eq!(detail(addr, "mocap").await, d);
    // Declared a humanoid again, it takes the clip.
    let (s, b) = command(
        addr,
        json!({"op": "configure_asset", "asset": "mocap", "options": {}}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "mocap", "avatar": "m2"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command(
        addr,
        json!({"op": "play", "avatar": "m2", "clip": "walk", "from_asset": "avatar"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    second.stop().await;
}

#[tokio::test]
async fn options_as_query_parameters_and_a_quadruped() {
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path()).await;
    let addr = server.addr;
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/fox?format=bvh&metres_per_unit=0.02&up_axis=%2By",
        "application/octet-stream",
        QUADRUPED_BVH.as_bytes(),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let d = detail(addr, "fox").await;
    assert_eq!(d["humanoid"], false, "{d}");
    assert_eq!(d["units"]["source"], "configured");
    assert!((d["units"]["metres_per_unit"].as_f64().unwrap() - 0.02).abs() < 1e-7);
    assert_eq!(hanim(&d, "b_LeftUpperArm"), "l_shoulder", "names still map");
    assert!(
        d["pipeline"].as_array().unwrap().iter().any(|s| s
            .as_str()
            .unwrap()
            .starts_with("classification: not humanoid")),
        "{d}"
    );
    let (s, b) = command(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "fox", "avatar": "f"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command(
        addr,
        json!({"op": "play", "avatar": "f", "clip": "walk", "from_asset": "avatar"}),
    )
    .await;
    assert_eq!((s, b["code"].clone()), (422, json!("not_humanoid")), "{b}");
    // A rig without a mesh says so (it used to answer unknown_avatar).
    let (s, b) = http_to(
        addr,
        "GET",
        "/api/assets/fox/mesh.glb",
        "application/json",
        b"",
    )
    .await;
    let e: Value = serde_json::from_str(&b).unwrap();
    assert_eq!((s, e["code"].clone()), (404, json!("no_mesh")), "{b}");
    // A misspelt option is refused, not ignored.
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/fox2?format=bvh&humanoids=false",
        "application/octet-stream",
        QUADRUPED_BVH.as_bytes(),
    )
    .await;
    assert_eq!(s, 400, "{b}");
    server.stop().await;
}

/// What the importers skip or approximate reaches the uploader (issue 18, item 5).
#[tokio::test]
async fn upload_answers_carry_the_importers_notes() {
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path()).await;
    let addr = server.addr;
    let skel = "balljoint root {\n offset 0 0 0\n balljoint tip {\n offset 0 1 0\n }\n}\n";
    let channel = "channel {\n extrapolate constant constant\n keys 1 {\n 0 0 flat flat\n }\n}\n";
    let anim = format!(
        "animation {{\n range 0 1\n numchannels 6\n{}}}\n",
        channel.repeat(6)
    );
    let (s, b) = upload(
        addr,
        "/api/assets/short",
        &[
            ("arm.skel", skel.as_bytes()),
            ("wave.anim", anim.as_bytes()),
        ],
        &[],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let notes = b["result"][0]["notes"].to_string();
    assert!(notes.contains("6 of the skeleton's 9 channels"), "{b}");
    if let Some(cesium) = common::testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") {
        let (s, b) = upload(
            addr,
            "/api/assets/cesium",
            &[("CesiumMan.glb", &cesium)],
            &[],
        )
        .await;
        assert_eq!(s, 200, "{b}");
        let notes = b["result"][0]["notes"].to_string();
        assert!(notes.contains("materials not imported"), "{b}");
        // And the listing says so too.
        let d = detail(addr, "cesium").await;
        assert_eq!(d["notes"].to_string(), notes);
    }
    server.stop().await;
}

/// `.vrm` files upload as multipart parts and raw bodies (issue 18, item 6); the file's
/// humanoid bones are the mapping (joints it does not name stay unmapped).
#[tokio::test]
async fn vrm_uploads_take_the_files_humanoid_bones() {
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path()).await;
    let addr = server.addr;
    let vrm = common::builtin_as_vrm();
    let (s, b) = upload(addr, "/api/assets/vroid", &[("vroid.vrm", &vrm)], &[]).await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/vroid2?format=vrm",
        "application/octet-stream",
        &vrm,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    for name in ["vroid", "vroid2"] {
        let d = detail(addr, name).await;
        assert_eq!(d["humanoid"], true, "{d}");
        assert_eq!(d["mapped"], 18, "{d}");
        assert_eq!(hanim(&d, "l_shoulder"), "l_shoulder");
        assert_eq!(
            hanim(&d, "l_sternoclavicular"),
            Value::Null,
            "not a VRM bone here"
        );
        assert!(
            d["pipeline"][0]
                .as_str()
                .unwrap()
                .contains("the file's humanoid bone map"),
            "{d}"
        );
        assert!(
            d["notes"]
                .to_string()
                .contains("VRM 1.0 humanoid: 18 bones"),
            "{d}"
        );
    }
    server.stop().await;
}

/// World rotation of every joint from local rotations (`G_j = G_parent(j) · L_j`).
fn world_rotations(parents: &[Option<usize>], rotations: &[[f32; 4]]) -> Vec<glam::Quat> {
    let mut world: Vec<glam::Quat> = Vec::with_capacity(rotations.len());
    for (j, r) in rotations.iter().enumerate() {
        let local = glam::Quat::from_array(*r);
        world.push(match parents[j] {
            Some(p) => world[p] * local,
            None => local,
        });
    }
    world
}

/// A VRM animation (issue 33, goal 7) uploads as a rig of its own and plays on an avatar with
/// `play … from_asset`. The fixture is the built-in avatar's own file named `.vrma`, with its
/// 22 VRM bones in `VRMC_vrm_animation` (its rest pose is a T-pose, as the specification
/// wants): its skin and mesh are left out, its clips kept. Reference: played on the built-in
/// avatar itself, every mapped joint's world rotation equals the one of the avatar's own clip.
#[tokio::test]
async fn vrma_uploads_play_on_humanoid_avatars() {
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path()).await;
    let addr = server.addr;
    let vrma = common::builtin_with_bone_map("VRMC_vrm_animation", true);
    let (s, b) = upload(addr, "/api/assets/moves", &[("moves.vrma", &vrma)], &[]).await;
    assert_eq!(s, 200, "{b}");
    assert_eq!(b["result"][0]["humanoid"], true, "{b}");
    assert_eq!(b["result"][0]["mapped"], 22, "{b}");
    let notes = b["result"][0]["notes"].to_string();
    assert!(
        notes.contains("VRM animation (VRMC_vrm_animation 1.0)"),
        "{notes}"
    );
    assert!(
        notes.contains("1 mesh(es) and 1 skin(s) not imported"),
        "{notes}"
    );
    // As a raw body too.
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/moves2?format=vrma",
        "application/octet-stream",
        &vrma,
    )
    .await;
    assert_eq!(s, 200, "{b}");

    let (s, b) = command(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "avatar", "avatar": "p"}),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command(
        addr,
        json!({"op": "play", "avatar": "p", "clip": "walk", "from_asset": "moves", "fade": 0}),
    )
    .await;
    assert_eq!(s, 200, "{b}");

    let avatar =
        posecast_server::import::gltf::from_slice("avatar", posecast_server::builtin::AVATAR_GLB)
            .unwrap()
            .remove(0);
    let rig = posecast_server::rig::Rig::from_asset(avatar, &Default::default()).unwrap();
    let skeleton = &rig.asset.skeleton;
    let mapped: Vec<usize> = (0..skeleton.len())
        .filter(|&j| rig.hanim[j].as_deref().is_some_and(|h| h != "sacroiliac"))
        .collect();
    assert_eq!(mapped.len(), 22);
    let mut worst = 0.0f32;
    for time in [0.2f32, 0.5, 0.9] {
        let mut poses = Vec::new();
        for from in [Some("moves"), None] {
            let mut c = json!({"op": "sample_pose", "avatar": "p", "clip": "walk", "time": time});
            if let Some(f) = from {
                c["from_asset"] = json!(f);
            }
            let (s, b) = command(addr, c).await;
            assert_eq!(s, 200, "{b}");
            let rotations: Vec<[f32; 4]> =
                serde_json::from_value(b["result"]["rotations"].clone()).unwrap();
            poses.push(world_rotations(skeleton.parents(), &rotations));
        }
        for &j in &mapped {
            let d = poses[0][j].angle_between(poses[1][j]).to_degrees();
            worst = worst.max(d);
            assert!(d < 0.5, "{} at {time} s: {d}°", skeleton.names()[j]);
        }
    }
    println!("vrma walk on the built-in avatar: worst world rotation {worst:.4}° off its own walk");
    server.stop().await;
}
