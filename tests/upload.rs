//! End-to-end uploads over REST: each format from the shared test files becomes a rig that
//! plays in a scene; bad uploads get typed errors and change nothing, in the library or on disk.

#![allow(clippy::unwrap_used)]

mod common;

use common::{command_to, http_to, list_tree, testdata_bytes, upload_files};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use serde_json::Value;
use std::net::SocketAddr;

/// A request body with its content type.
type Body = (String, Vec<u8>);

async fn server(data: &std::path::Path, max_upload_bytes: usize) -> Server {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: Some(data.to_owned()),
        max_upload_bytes,
        access: common::test_access(),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    server
}

async fn assets(addr: SocketAddr) -> Value {
    let (status, body) = http_to(addr, "GET", "/api/assets", "application/json", b"").await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

fn asset<'a>(list: &'a Value, name: &str) -> &'a Value {
    list.as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] == name)
        .unwrap_or_else(|| panic!("no asset {name} in {list}"))
}

/// Adds an avatar of `asset` playing its first clip and checks its clock moves.
async fn plays(addr: SocketAddr, asset: &str, clip: &str) {
    let avatar = format!("{asset}-test");
    let (s, b) = command_to(
        addr,
        &format!(r#"{{"op":"add_avatar","scene":"default","asset":"{asset}","avatar":"{avatar}","clip":"{clip}"}}"#),
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let get = format!(r#"{{"op":"get_avatar","avatar":"{avatar}"}}"#);
    let (_, first) = command_to(addr, &get).await;
    assert_eq!(first["result"]["clip"], clip, "{first}");
    tokio::time::sleep(std::time::Duration::from_millis(150)).await;
    let (_, later) = command_to(addr, &get).await;
    assert_ne!(
        first["result"]["time"], later["result"]["time"],
        "the clock of {avatar} does not move"
    );
}

/// `(name, joints, [(clip, duration)])` of a listed asset.
fn figures(list: &Value, name: &str) -> (u64, Vec<(String, f64)>) {
    let a = asset(list, name);
    let clips = a["clips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["name"].as_str().unwrap().to_owned(),
                c["duration"].as_f64().unwrap(),
            )
        })
        .collect();
    (a["joints"].as_u64().unwrap(), clips)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-3
}

#[tokio::test]
async fn each_format_uploads_lists_and_plays() {
    let (Some(cesium), Some(cmu), Some(sinus), Some(skel), Some(skin), Some(walk)) = (
        testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb"),
        testdata_bytes("bvh/cmu/01_01.bvh"),
        testdata_bytes("bvh/fairmotion/sinusoidal.bvh"),
        testdata_bytes("cse169/wasp.skel"),
        testdata_bytes("cse169/wasp.skin"),
        testdata_bytes("cse169/wasp_walk.anim"),
    ) else {
        return;
    };
    let (Some(simple_gltf), Some(simple_bin), Some(recursive)) = (
        testdata_bytes("gltf/RiggedSimple/glTF/RiggedSimple.gltf"),
        testdata_bytes("gltf/RiggedSimple/glTF/RiggedSimple0.bin"),
        testdata_bytes("gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb"),
    ) else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path(), 32 << 20).await;
    let addr = server.addr;

    // .glb, multipart: the response lists the new rig.
    let (s, b) = upload_files(addr, "/api/assets/cesium", &[("CesiumMan.glb", &cesium)]).await;
    assert_eq!(s, 200, "{b}");
    let result: Value = serde_json::from_str(&b).unwrap();
    assert_eq!(result["result"][0]["name"], "cesium", "{b}");
    // .glb, raw body (curl --data-binary).
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/cesium-raw",
        "model/gltf-binary",
        &cesium,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    // .gltf + external .bin, resolved inside the upload.
    let (s, b) = upload_files(
        addr,
        "/api/assets/simple",
        &[
            ("RiggedSimple.gltf", &simple_gltf),
            ("RiggedSimple0.bin", &simple_bin),
        ],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    // .bvh, multipart and raw.
    let (s, b) = upload_files(addr, "/api/assets/cmu", &[("01_01.bvh", &cmu)]).await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = http_to(
        addr,
        "POST",
        "/api/assets/sinus?format=bvh",
        "application/octet-stream",
        &sinus,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    // .skel + .skin + .anim.
    let (s, b) = upload_files(
        addr,
        "/api/assets/wasp",
        &[
            ("wasp.skel", &skel),
            ("wasp.skin", &skin),
            ("wasp_walk.anim", &walk),
        ],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    // A multi-skin glTF gives one rig per skeleton (its skins merged), all reported.
    let (s, b) = upload_files(
        addr,
        "/api/assets/rec",
        &[("RecursiveSkeletons.glb", &recursive)],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let rec: Value = serde_json::from_str(&b).unwrap();
    let rec = rec["result"].as_array().unwrap();
    assert_eq!(
        rec.len(),
        4,
        "RecursiveSkeletons has 84 skins on 4 skeletons: {b}"
    );
    assert!(
        rec.iter()
            .all(|r| r["name"].as_str().unwrap().starts_with("rec#")
                && r["joints"].as_u64() >= Some(210))
    );

    // The figures the files themselves state (testdata/SOURCES.md): joints, and clip ranges
    // (first to last key; BVH: (frames - 1) × frame time).
    let list = assets(addr).await;
    let (j, clips) = figures(&list, "cesium");
    assert_eq!(j, 19);
    assert!(
        clips.len() == 1 && close(clips[0].1, 2.0 - 0.0417),
        "{clips:?}"
    );
    assert_eq!(figures(&list, "cesium-raw"), figures(&list, "cesium"));
    let (j, clips) = figures(&list, "simple");
    assert_eq!(j, 2);
    assert!(
        clips.len() == 1 && close(clips[0].1, 2.0833 - 0.0417),
        "{clips:?}"
    );
    let (j, clips) = figures(&list, "cmu");
    assert_eq!(j, 31);
    assert!(
        clips.len() == 1 && close(clips[0].1, 2751.0 * 0.008_333_3),
        "{clips:?}"
    );
    assert_eq!(clips[0].0, "01_01");
    let (j, clips) = figures(&list, "sinus");
    assert_eq!(j, 4);
    assert!(close(clips[0].1, 119.0 / 60.0), "{clips:?}");
    let (j, clips) = figures(&list, "wasp");
    assert_eq!(j, 23);
    assert_eq!(clips, vec![("wasp_walk".to_owned(), 4.0)]);

    // Each plays in a scene.
    for (asset, clip) in [
        ("cesium", "animation0"),
        ("simple", "animation0"),
        ("cmu", "01_01"),
        ("wasp", "wasp_walk"),
    ] {
        let list = assets(addr).await;
        assert_eq!(asset_clip(&list, asset), clip);
        plays(addr, asset, clip).await;
    }

    // Stored as uploaded, with a meta file.
    let stored = list_tree(data.path());
    for f in [
        "assets/wasp/wasp.skel",
        "assets/wasp/wasp.skin",
        "assets/wasp/wasp_walk.anim",
        "assets/wasp/meta.json",
        "assets/simple/RiggedSimple0.bin",
        "assets/sinus/sinus.bvh",
    ] {
        assert!(stored.contains(&f.to_owned()), "{f} not in {stored:?}");
    }
    server.stop().await;
}

fn asset_clip(list: &Value, name: &str) -> String {
    asset(list, name)["clips"][0]["name"]
        .as_str()
        .unwrap()
        .to_owned()
}

#[tokio::test]
async fn clips_are_added_to_an_uploaded_skel() {
    let (Some(skel), Some(skin), Some(walk)) = (
        testdata_bytes("cse169/wasp.skel"),
        testdata_bytes("cse169/wasp.skin"),
        testdata_bytes("cse169/wasp_walk.anim"),
    ) else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let server = server(data.path(), 32 << 20).await;
    let addr = server.addr;
    let (s, b) = upload_files(
        addr,
        "/api/assets/w",
        &[("wasp.skel", &skel), ("wasp.skin", &skin)],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    assert_eq!(figures(&assets(addr).await, "w").1, vec![]);
    let (s, b) = upload_files(addr, "/api/assets/w/clips", &[("walk.anim", &walk)]).await;
    assert_eq!(s, 200, "{b}");
    let info: Value = serde_json::from_str(&b).unwrap();
    assert_eq!(info["result"]["clips"][0]["name"], "walk", "{b}");
    assert_eq!(
        figures(&assets(addr).await, "w").1,
        vec![("walk".to_owned(), 4.0)]
    );
    plays(addr, "w", "walk").await;
    assert!(list_tree(data.path()).contains(&"assets/w/walk.anim".to_owned()));

    // Typed refusals, nothing changed.
    let before = (assets(addr).await, list_tree(data.path()));
    for (path, files, status, code) in [
        (
            "/api/assets/w/clips",
            vec![("walk.anim", &walk)],
            409,
            "conflict",
        ),
        (
            "/api/assets/w/clips",
            vec![("x.bvh", &walk)],
            400,
            "invalid_value",
        ),
        (
            "/api/assets/avatar/clips",
            vec![("x.anim", &walk)],
            400,
            "invalid_value",
        ),
        (
            "/api/assets/nobody/clips",
            vec![("x.anim", &walk)],
            404,
            "unknown_asset",
        ),
        (
            "/api/assets/w/clips",
            vec![("bad.anim", &skin)],
            422,
            "import_failed",
        ),
    ] {
        let files: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (*n, b.as_slice())).collect();
        let (s, b) = upload_files(addr, path, &files).await;
        assert_eq!(s, status, "{path}: {b}");
        let e: Value = serde_json::from_str(&b).unwrap();
        assert_eq!(e["code"], code, "{b}");
    }
    assert_eq!((assets(addr).await, list_tree(data.path())), before);
    server.stop().await;
}

/// Clips are added to a `.skel` uploaded before a restart: the server keeps no upload bytes in
/// memory, so it reads the stored files again from `assets/<name>/`; the clip, stored beside
/// them, is there after the next restart too.
#[tokio::test]
async fn clips_are_added_to_a_skel_uploaded_before_a_restart() {
    let (Some(skel), Some(skin), Some(walk)) = (
        testdata_bytes("cse169/wasp.skel"),
        testdata_bytes("cse169/wasp.skin"),
        testdata_bytes("cse169/wasp_walk.anim"),
    ) else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let first = server(data.path(), 32 << 20).await;
    let (s, b) = upload_files(
        first.addr,
        "/api/assets/w",
        &[("wasp.skel", &skel), ("wasp.skin", &skin)],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    first.stop().await;

    let second = server(data.path(), 32 << 20).await;
    let addr = second.addr;
    assert_eq!(figures(&assets(addr).await, "w").1, vec![]);
    let (s, b) = upload_files(addr, "/api/assets/w/clips", &[("walk.anim", &walk)]).await;
    assert_eq!(s, 200, "{b}");
    // wasp_walk.anim's own range: 0 to 4 s.
    assert_eq!(
        figures(&assets(addr).await, "w").1,
        vec![("walk".to_owned(), 4.0)]
    );
    plays(addr, "w", "walk").await;
    second.stop().await;

    let third = server(data.path(), 32 << 20).await;
    assert_eq!(
        figures(&assets(third.addr).await, "w").1,
        vec![("walk".to_owned(), 4.0)]
    );
    third.stop().await;
}

#[tokio::test]
async fn failed_uploads_are_typed_and_change_nothing() {
    let (Some(cesium), Some(skin), Some(sinus)) = (
        testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb"),
        testdata_bytes("cse169/wasp.skin"),
        testdata_bytes("bvh/fairmotion/sinusoidal.bvh"),
    ) else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    // Room for CesiumMan (490,956 bytes) but not for much more.
    let server = server(data.path(), 600_000).await;
    let addr = server.addr;
    let (s, b) = upload_files(addr, "/api/assets/taken", &[("s.bvh", &sinus)]).await;
    assert_eq!(s, 200, "{b}");
    let before = (assets(addr).await, list_tree(data.path()));

    let truncated = &cesium[..cesium.len() / 2];
    let oversized = [cesium.as_slice(), cesium.as_slice()].concat();
    let garbage = b"this is not a model at all".repeat(10);
    let multi = |files: &[(&str, &[u8])]| common::multipart(files);
    let cases: Vec<(&str, Body, u16, &str)> = vec![
        (
            "/api/assets/trunc",
            multi(&[("CesiumMan.glb", truncated)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/trunc",
            ("model/gltf-binary".into(), truncated.to_vec()),
            422,
            "import_failed",
        ),
        (
            "/api/assets/junk",
            multi(&[("junk.glb", &garbage)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/junk",
            multi(&[("junk.bvh", &garbage)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/junk",
            multi(&[("junk.txt", &garbage)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/skin",
            multi(&[("wasp.skin", &skin)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/two",
            multi(&[("a.bvh", &sinus), ("b.bvh", &sinus)]),
            422,
            "import_failed",
        ),
        (
            "/api/assets/big",
            multi(&[("CesiumMan.glb", &oversized)]),
            413,
            "too_large",
        ),
        (
            "/api/assets/big",
            ("model/gltf-binary".into(), oversized.clone()),
            413,
            "too_large",
        ),
        (
            "/api/assets/taken",
            multi(&[("s.bvh", &sinus)]),
            409,
            "conflict",
        ),
        (
            "/api/assets/avatar",
            multi(&[("s.bvh", &sinus)]),
            409,
            "conflict",
        ),
        (
            "/api/assets/..",
            multi(&[("s.bvh", &sinus)]),
            400,
            "invalid_value",
        ),
        (
            "/api/assets/.hidden",
            multi(&[("s.bvh", &sinus)]),
            400,
            "invalid_value",
        ),
        (
            "/api/assets/raw",
            ("application/octet-stream".into(), sinus.clone()),
            400,
            "invalid_value",
        ),
        (
            "/api/assets/raw?format=obj",
            ("application/octet-stream".into(), sinus.clone()),
            400,
            "invalid_value",
        ),
    ];
    for (path, (content_type, body), status, code) in cases {
        let (s, b) = http_to(addr, "POST", path, &content_type, &body).await;
        assert_eq!(s, status, "{path} ({content_type}): {b}");
        let e: Value =
            serde_json::from_str(&b).unwrap_or_else(|_| panic!("{path}: untyped body {b:?}"));
        assert_eq!(e["code"], code, "{path}: {b}");
        if code == "import_failed" {
            // The importer's message names the file.
            let msg = e["message"].as_str().unwrap();
            assert!(msg.contains('.'), "{path}: {msg}");
        }
        assert_eq!(
            (assets(addr).await, list_tree(data.path())),
            before,
            "{path} changed something"
        );
    }
    server.stop().await;
}
