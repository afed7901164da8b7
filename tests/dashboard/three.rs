//! posecast inside three.js (`/sdk/three.js`) in headless Chromium, with three.js and three-vrm
//! as a web team installs them (npm, under `target/npm`, served from the page's own origin
//! through an import map): the server's `mesh.glb` loaded with three's `GLTFLoader` and bound
//! with `SkeletonBinding`, and the same mesh made a three-vrm `VRMHumanoid` and bound with
//! `VRMBinding`. The page reports the pose it applied and three's own world matrices; the
//! reference is posecast-proto's forward kinematics of that pose in Rust.

use crate::browser::*;
use crate::common;
use posecast_client::net::{AvatarView, Client, ClientOptions};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::msg::AvatarPoseJson;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The npm packages the page imports (scripts/test installs them, pinned, into target/npm).
fn node_modules() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/npm/node_modules");
    for package in [
        "three/build/three.module.js",
        "@pixiv/three-vrm/lib/three-vrm.module.js",
    ] {
        if !dir.join(package).exists() {
            posecast_proto::testing::skip(&format!(
                "tests/dashboard/three.rs: target/npm/node_modules/{package} is missing (scripts/test installs three and @pixiv/three-vrm)"
            ));
            return None;
        }
    }
    Some(dir)
}

/// The test page: binds every avatar asked for twice (a `SkeletonBinding` on one copy of its
/// `mesh.glb`, a `VRMBinding` on another made a `VRMHumanoid` at its bind pose) and, on
/// `check(id)`, applies the client's played-out pose to both and reports three's world
/// positions and rotations.
fn page(server: &str) -> String {
    r#"<!doctype html>
<script type="importmap">
{"imports": {
  "three": "/node_modules/three/build/three.module.js",
  "three/addons/": "/node_modules/three/examples/jsm/",
  "@pixiv/three-vrm": "/node_modules/@pixiv/three-vrm/lib/three-vrm.module.js"
}}
</script>
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMHumanoid, VRMLoaderPlugin } from "@pixiv/three-vrm";
import { Client } from "http://SERVER/sdk/posecast.js";
import { SkeletonBinding, VRMBinding, meshUrl, poseAtBind, vrmHumanBones, findJoints } from "http://SERVER/sdk/three.js";

const client = new Client({ url: "ws://SERVER/ws" });
client.subscribe("default");
client.connect();
const loader = new GLTFLoader();
const bound = new Map();
window.errors = [];
window.addEventListener("error", (e) => window.errors.push(String(e.message)));

window.known = (id) => !!client.avatar(id) && !!client.pose(id);
window.bind = async (id) => {
  const desc = client.avatar(id).description;
  const plain = await loader.loadAsync(meshUrl(client, desc));
  const skeleton = new SkeletonBinding(desc, plain.scene);
  const b = { desc, plain, skeleton, vrm: null };
  const bones = vrmHumanBones(desc, plain.scene);
  if (bones.hips) {
    // A VRM is at rest in its bind pose: so is this copy when it becomes a humanoid.
    const asVrm = await loader.loadAsync(meshUrl(client, desc));
    poseAtBind(desc, asVrm.scene);
    asVrm.scene.updateMatrixWorld(true);
    const humanoid = new VRMHumanoid(vrmHumanBones(desc, asVrm.scene));
    asVrm.scene.add(humanoid.normalizedHumanBonesRoot);
    b.vrm = { asVrm, humanoid, binding: new VRMBinding(desc, { humanoid, scene: asVrm.scene }) };
  }
  bound.set(id, b);
  return { missing: skeleton.missing, humanoid: Object.keys(bones) };
};

const world = (object) => {
  const p = new THREE.Vector3(), q = new THREE.Quaternion(), s = new THREE.Vector3();
  object.matrixWorld.decompose(p, q, s);
  return { p: p.toArray(), q: q.toArray() };
};

window.check = (id) => {
  const b = bound.get(id);
  const pose = client.pose(id);
  if (!b || !pose) return null;
  b.skeleton.apply(pose);
  b.plain.scene.updateMatrixWorld(true);
  const joints = findJoints(b.desc, b.plain.scene).map((o) => (o ? world(o) : null));
  const vrm = {};
  if (b.vrm) {
    b.vrm.binding.apply(pose);
    b.vrm.humanoid.update();
    b.vrm.asVrm.scene.updateMatrixWorld(true);
    for (const { node } of Object.values(b.vrm.humanoid.humanBones)) vrm[node.name] = world(node);
  }
  return { pose, joints, vrm };
};
// A VRM file loaded by three-vrm's own loader, bound by VRMBinding; each raw bone's rest
// world rotation kept to report the rotation it turned through.
const files = new Map();
window.bindVrmFile = async (id, url) => {
  const desc = client.avatar(id).description;
  const vrmLoader = new GLTFLoader();
  vrmLoader.register((parser) => new VRMLoaderPlugin(parser));
  const vrm = (await vrmLoader.loadAsync(url)).userData.vrm;
  vrm.scene.updateMatrixWorld(true);
  const rest = new Map();
  for (const { node } of Object.values(vrm.humanoid.rawHumanBones)) {
    rest.set(node, new THREE.Quaternion().setFromRotationMatrix(node.matrixWorld));
  }
  const binding = new VRMBinding(desc, vrm);
  files.set(id, { vrm, rest, binding });
  return { unmatched: binding.unmatched, metaVersion: vrm.meta?.metaVersion ?? null };
};
window.checkVrmFile = (id) => {
  const f = files.get(id);
  const pose = client.pose(id);
  if (!f || !pose) return null;
  f.binding.apply(pose);
  f.vrm.update(0);
  f.vrm.scene.updateMatrixWorld(true);
  const bones = {};
  for (const [node, rest] of f.rest) {
    const w = world(node);
    const turned = new THREE.Quaternion().fromArray(w.q).multiply(rest.clone().invert());
    bones[node.name] = { p: w.p, turned: turned.toArray() };
  }
  return { pose, bones };
};
window.ready = true;
</script>
"#
    .replace("SERVER", server)
}

/// posecast-proto's forward kinematics of the page's pose: rest, then the streamed parts, with
/// the placement composed into the roots.
fn reference(view: &AvatarView, pose: &Value) -> Vec<glam::Mat4> {
    let pose: AvatarPoseJson = serde_json::from_value(pose.clone()).unwrap();
    let mut locals = view
        .locals_of(&pose)
        .expect("the page's pose fits the avatar");
    pose.placement
        .place_roots(view.skeleton.parents(), &mut locals);
    let mut world = vec![glam::Mat4::IDENTITY; view.skeleton.len()];
    forward_kinematics(&view.skeleton, &locals, &mut world);
    world
}

fn vec3(v: &Value) -> glam::Vec3 {
    let a: Vec<f32> = serde_json::from_value(v.clone()).unwrap();
    glam::Vec3::new(a[0], a[1], a[2])
}

fn quat(v: &Value) -> glam::Quat {
    let a: Vec<f32> = serde_json::from_value(v.clone()).unwrap();
    glam::Quat::from_xyzw(a[0], a[1], a[2], a[3]).normalize()
}

/// The model's size: the largest distance between two joints at rest.
fn model_size(view: &AvatarView) -> f32 {
    let rest: Vec<_> = view.skeleton.rest().to_vec();
    let mut world = vec![glam::Mat4::IDENTITY; rest.len()];
    forward_kinematics(&view.skeleton, &rest, &mut world);
    let points: Vec<glam::Vec3> = world.iter().map(|m| m.w_axis.truncate()).collect();
    let mut size = 0.0f32;
    for a in &points {
        for b in &points {
            size = size.max(a.distance(*b));
        }
    }
    size
}

/// Checks `id` over several played-out poses: the `SkeletonBinding`'s bone world positions
/// against posecast's forward kinematics (every joint, placement included), and the
/// `VRMBinding`'s humanoid bones, moved by three-vrm from the normalised bones, against the
/// same: world rotations of every humanoid bone, positions of those whose every ancestor is a
/// humanoid bone (a joint three-vrm does not drive keeps its bind pose under its parent).
/// Returns the worst errors: positions per model size, rotations in degrees.
async fn check_avatar(b: &fantoccini::Client, rust: &Client, id: &str) -> (f32, f32, f32, usize) {
    let view = rust
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == id)
        .expect("the Rust client knows the avatar");
    let size = model_size(&view);
    let bound = b
        .execute(&format!("return await window.bind({id:?});"), vec![])
        .await
        .unwrap();
    assert_eq!(bound["missing"], serde_json::json!([]), "{bound}");
    let names = view.skeleton.names().to_vec();
    let (mut worst_skeleton, mut worst_vrm_position, mut worst_vrm_angle) =
        (0.0f32, 0.0f32, 0.0f32);
    let mut checked_vrm_positions = 0;
    for round in 0..12 {
        tokio::time::sleep(Duration::from_millis(97)).await;
        let report = wait_js(b, 60, &format!("window.check({id:?})")).await;
        let placed = reference(&view, &report["pose"]);
        for (j, m) in placed.iter().enumerate() {
            let p = vec3(&report["joints"][j]["p"]);
            let e = p.distance(m.w_axis.truncate()) / size;
            worst_skeleton = worst_skeleton.max(e);
        }
        for (j, name) in names.iter().enumerate() {
            let Some(node) = report["vrm"].get(name.as_str()) else {
                continue;
            };
            // The bone's world rotation: the rotation its joint turned through from the bind
            // pose (G = W_j · B_j⁻¹, what the binding hands three-vrm) applied to its rest, the
            // bind pose B_j — so the joint's own world rotation, placement included.
            let (_, expected, _) = placed[j].to_scale_rotation_translation();
            let got = quat(&node["q"]);
            // In f64 and from the difference's vector part: f32 `acos` near 1 reads 0.05° of noise.
            let d = expected.as_dquat().inverse() * got.as_dquat();
            let angle = (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees() as f32;
            worst_vrm_angle = worst_vrm_angle.max(angle);
            let humanoid_chain = std::iter::successors(Some(j), |&k| view.skeleton.parents()[k])
                .all(|k| report["vrm"].get(names[k].as_str()).is_some());
            if humanoid_chain {
                let e = vec3(&node["p"]).distance(placed[j].w_axis.truncate()) / size;
                worst_vrm_position = worst_vrm_position.max(e);
                checked_vrm_positions += 1;
            }
        }
        if round == 0 {
            let errors = b.execute("return window.errors;", vec![]).await.unwrap();
            assert_eq!(errors, serde_json::json!([]), "page errors");
        }
    }
    (
        worst_skeleton,
        worst_vrm_position,
        worst_vrm_angle,
        checked_vrm_positions,
    )
}

/// The built-in avatar walking and a shared glTF rig (CesiumMan) playing its clip, bound in
/// three.js: skeleton positions within 1e-5 of the model's size of posecast's forward
/// kinematics; the VRM binding's bones within 1e-4 of the size and 0.001° of the rotations
/// their joints turned through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_js_and_three_vrm_models_follow_the_stream() {
    let Some(modules) = node_modules() else {
        return;
    };
    let Some(cesium) =
        posecast_proto::testing::require_testdata("gltf/CesiumMan/glTF-Binary/CesiumMan.glb")
    else {
        return;
    };
    let server = common::server(60.0).await;
    let mut asset = posecast_server::import::load_path(&cesium)
        .unwrap()
        .remove(0);
    asset.name = "cesium".into();
    server
        .state
        .world
        .library
        .insert(posecast_server::rig::Rig::from_asset(asset, &Default::default()).unwrap());
    let clip = server.state.world.library.get("cesium").unwrap().clips[0]
        .name()
        .to_string();
    let (status, body) = command(
        &server,
        serde_json::json!({"op": "add_avatar", "scene": "default", "asset": "cesium",
            "avatar": "cesium", "clip": clip, "position": [1.5, 0, 0.5], "rotation": [0, 0.38268343, 0, 0.9238795]}),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let (status, body) = command(
        &server,
        serde_json::json!({"op": "play", "avatar": "avatar", "clip": "walk"}),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let (status, body) = command(
        &server,
        serde_json::json!({"op": "place_avatar", "avatar": "avatar", "position": [-1.0, 0.0, 0.25],
            "rotation": [0.0, -0.5, 0.0, 0.8660254]}),
    )
    .await;
    assert_eq!(status, 200, "{body}");

    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    let rust = Client::connect(options).await.unwrap();
    common::wait_for(60.0, || rust.avatars().len() == 2).await;

    let url = serve_origin(page(&server.addr.to_string()), Some(modules), Vec::new()).await;
    let (_driver, b) = browser().await;
    b.goto(&url).await.unwrap();
    wait_js(&b, 60, "window.ready === true").await;
    for id in ["avatar", "cesium"] {
        wait_js(&b, 60, &format!("window.known({id:?})")).await;
        let (skeleton, vrm_position, vrm_angle, vrm_checked) = check_avatar(&b, &rust, id).await;
        println!(
            "{id}: SkeletonBinding positions {skeleton:.2e} of the model's size; \
             VRMBinding positions {vrm_position:.2e}, rotations {vrm_angle:.1e}°"
        );
        assert!(
            skeleton <= 1e-5,
            "{id}: SkeletonBinding off by {skeleton:e} of the size"
        );
        if id == "avatar" {
            assert!(
                vrm_checked > 0,
                "the built-in avatar is bound as a VRM humanoid"
            );
            assert!(
                vrm_position <= 1e-4,
                "{id}: VRMBinding off by {vrm_position:e} of the size"
            );
            assert!(
                vrm_angle <= 0.001,
                "{id}: VRMBinding rotations off by {vrm_angle}°"
            );
        }
    }
    b.close().await.ok();
}

/// `examples/web/three.html`, as written but for three's CDN address (npm's copy served from
/// the page's origin instead): it binds every avatar of the scene, an avatar added later too
/// and a removed one dropped, renders frames without errors, and the meshes are drawn (the
/// screenshot's lit pixels fall when the avatars are gone).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_three_js_example_page_shows_the_scene() {
    let Some(modules) = node_modules() else {
        return;
    };
    let html = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/examples/web/three.html"
    ))
    .unwrap();
    const CDN: &str = "https://cdn.jsdelivr.net/npm/three@0.187.0/";
    assert!(html.contains(CDN), "the page imports three from {CDN}");
    let three_version: Value =
        serde_json::from_slice(&std::fs::read(modules.join("three/package.json")).unwrap())
            .unwrap();
    assert_eq!(
        three_version["version"], "0.187.0",
        "the CDN's version is the one tested"
    );
    let server = common::server(60.0).await;
    let url = serve_origin(
        html.replace(CDN, "/node_modules/three/"),
        Some(modules),
        Vec::new(),
    )
    .await;
    let (_driver, b) = browser().await;
    b.goto(&format!("{url}?server={}", server.addr))
        .await
        .unwrap();
    let bound =
        "window.example && [...window.example.avatars.values()].filter((a) => a.binding).length";
    wait_js(&b, 60, &format!("{bound} === 1")).await;
    let (status, body) = command(
        &server,
        serde_json::json!({"op": "add_avatar", "scene": "default", "asset": "avatar",
            "avatar": "second", "clip": "wave", "position": [1.0, 0, 0]}),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    wait_js(&b, 60, &format!("{bound} === 2")).await;
    let frames = wait_js(&b, 60, "window.example.frames").await;
    wait_js(
        &b,
        60,
        &format!("window.example.frames >= {} + 10", frames.as_u64().unwrap()),
    )
    .await;
    let errors = b
        .execute("return window.example.errors;", vec![])
        .await
        .unwrap();
    assert_eq!(errors, serde_json::json!([]), "page errors");
    let lit = |png: &[u8]| {
        column_runs(png, (0.0, 0.0, 1280.0, 800.0))
            .iter()
            .map(|(a, z)| z - a + 1)
            .sum::<usize>()
    };
    let with_avatars = lit(&b.screenshot().await.unwrap());
    for avatar in ["avatar", "second"] {
        let (status, body) = command(
            &server,
            serde_json::json!({"op": "remove_avatar", "avatar": avatar}),
        )
        .await;
        assert_eq!(status, 200, "{body}");
    }
    wait_js(&b, 60, "window.example.avatars.size === 0").await;
    let frames = wait_js(&b, 60, "window.example.frames").await;
    wait_js(
        &b,
        60,
        &format!("window.example.frames >= {} + 3", frames.as_u64().unwrap()),
    )
    .await;
    let without = lit(&b.screenshot().await.unwrap());
    println!("lit columns: {with_avatars} with two avatars, {without} without");
    assert!(
        with_avatars >= without + 40,
        "the avatars are drawn: {with_avatars} lit columns with them, {without} without"
    );
}

/// A VRM 1.0 file (the built-in avatar with a `VRMC_vrm` humanoid) uploaded to the server and
/// loaded in the page by three-vrm's own `VRMLoaderPlugin`, its avatar walking (the built-in
/// walk retargeted) and placed: bound with `VRMBinding`, three-vrm's raw bones turn through the
/// rotations posecast's joints turned through from the bind pose (rot(P · W_j · B_j⁻¹), within
/// 0.001°) and stand where posecast's forward kinematics puts them (within 1e-4 of the size).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vrm_file_follows_the_stream_through_three_vrm() {
    let Some(modules) = node_modules() else {
        return;
    };
    let server = common::server(60.0).await;
    let vrm = common::builtin_as_vrm();
    let (status, body) =
        common::upload_files(server.addr, "/api/assets/vroid", &[("vroid.vrm", &vrm)]).await;
    assert_eq!(status, 200, "{body}");
    for body in [
        serde_json::json!({"op": "add_avatar", "scene": "default", "asset": "vroid",
            "avatar": "vroid", "position": [0.5, 0.0, -1.0], "rotation": [0.0, 0.25881905, 0.0, 0.9659258]}),
        serde_json::json!({"op": "play", "avatar": "vroid", "clip": "walk", "from_asset": "avatar"}),
    ] {
        let (status, answer) = command(&server, body).await;
        assert_eq!(status, 200, "{answer}");
    }
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    let rust = Client::connect(options).await.unwrap();
    common::wait_for(60.0, || rust.avatars().len() == 2).await;
    let view = rust
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == "vroid")
        .unwrap();
    let size = model_size(&view);
    let names = view.skeleton.names().to_vec();

    let url = serve_origin(
        page(&server.addr.to_string()),
        Some(modules),
        vec![("/vroid.vrm", vrm)],
    )
    .await;
    let (_driver, b) = browser().await;
    b.goto(&url).await.unwrap();
    wait_js(&b, 60, "window.ready === true").await;
    wait_js(&b, 60, "window.known('vroid')").await;
    let bound = b
        .execute(
            "return await window.bindVrmFile('vroid', '/vroid.vrm');",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(bound["metaVersion"], "1", "{bound}");
    let (mut worst_position, mut worst_angle, mut compared) = (0.0f32, 0.0f64, 0);
    for _ in 0..12 {
        tokio::time::sleep(Duration::from_millis(97)).await;
        let report = wait_js(&b, 60, "window.checkVrmFile('vroid')").await;
        let placed = reference(&view, &report["pose"]);
        for (j, name) in names.iter().enumerate() {
            let Some(bone) = report["bones"].get(name.as_str()) else {
                continue;
            };
            let (_, expected, _) =
                (placed[j] * view.skeleton.inverse_bind()[j]).to_scale_rotation_translation();
            let d = expected.as_dquat().inverse() * quat(&bone["turned"]).as_dquat();
            worst_angle = worst_angle.max((2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees());
            let humanoid_chain = std::iter::successors(Some(j), |&k| view.skeleton.parents()[k])
                .all(|k| report["bones"].get(names[k].as_str()).is_some());
            if humanoid_chain {
                let e = vec3(&bone["p"]).distance(placed[j].w_axis.truncate()) / size;
                worst_position = worst_position.max(e);
                compared += 1;
            }
        }
    }
    let errors = b.execute("return window.errors;", vec![]).await.unwrap();
    assert_eq!(errors, serde_json::json!([]), "page errors");
    println!(
        "VRM file: {compared} bone positions within {worst_position:.2e} of the model's size, \
         rotations within {worst_angle:.1e}°"
    );
    assert!(compared > 0, "humanoid chains compared");
    assert!(
        worst_position <= 1e-4,
        "positions off by {worst_position:e} of the size"
    );
    assert!(worst_angle <= 0.001, "rotations off by {worst_angle}°");
}
