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

/// A multipart body of file parts and text fields.
fn multipart(files: &[(&str, &[u8])], fields: &[(&str, &str)]) -> (String, Vec<u8>) {
    let boundary = "posecast-options-boundary-31c9";
    let mut body = Vec::new();
    for (name, bytes) in files {
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{name}\"\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(bytes);
        body.extend_from_slice(b"\r\n");
    }
    for (name, text) in fields {
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n{text}\r\n"
            )
            .as_bytes(),
        );
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

async fn upload(
    addr: SocketAddr,
    path: &str,
    files: &[(&str, &[u8])],
    fields: &[(&str, &str)],
) -> (u16, Value) {
    let (content_type, body) = multipart(files, fields);
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

/// The built-in avatar's `.glb` as a VRM 1.0 file: its JSON chunk gains a `VRMC_vrm` humanoid
/// naming every joint but `sacroiliac` (VRM has no such bone).
fn builtin_as_vrm() -> Vec<u8> {
    let glb = posecast_server::builtin::AVATAR_GLB;
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let mut doc: Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bones: serde_json::Map<String, Value> = doc["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .filter_map(|(i, node)| {
            let bone = match node["name"].as_str()? {
                "humanoid_root" => "hips",
                "vl5" => "spine",
                "vt10" => "chest",
                "vt1" => "upperChest",
                "vc4" => "neck",
                "skullbase" => "head",
                "l_shoulder" => "leftUpperArm",
                "l_elbow" => "leftLowerArm",
                "l_wrist" => "leftHand",
                "r_shoulder" => "rightUpperArm",
                "r_elbow" => "rightLowerArm",
                "r_wrist" => "rightHand",
                "l_hip" => "leftUpperLeg",
                "l_knee" => "leftLowerLeg",
                "l_ankle" => "leftFoot",
                "r_hip" => "rightUpperLeg",
                "r_knee" => "rightLowerLeg",
                "r_ankle" => "rightFoot",
                _ => return None,
            };
            Some((bone.to_owned(), json!({ "node": i })))
        })
        .collect();
    doc["extensionsUsed"] = json!(["VRMC_vrm"]);
    doc["extensions"] =
        json!({"VRMC_vrm": {"specVersion": "1.0", "humanoid": {"humanBones": bones}}});
    let mut json = serde_json::to_vec(&doc).unwrap();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let bin = &glb[20 + json_len..];
    let mut out = b"glTF".to_vec();
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&((12 + 8 + json.len() + bin.len()) as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(bin);
    out
}

/// `.vrm` files upload as multipart parts and raw bodies (issue 18, item 6); the file's
/// humanoid bones are the mapping (joints it does not name stay unmapped).
#[tokio::test]
async fn vrm_uploads_take_the_files_humanoid_bones() {
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path()).await;
    let addr = server.addr;
    let vrm = builtin_as_vrm();
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
