//! posecast inside three.js (`/sdk/three.js`) in headless Chromium, with three.js and three-vrm
//! as a web team installs them (npm, under `target/npm`, served from the page's own origin
//! through an import map): the server's `mesh.glb` loaded with three's `GLTFLoader` and bound
//! with `SkeletonBinding`, and the same mesh made a three-vrm `VRMHumanoid` and bound with
//! `VRMBinding`. The page reports the pose it applied and three's own world matrices; the
//! reference is posecast-proto's forward kinematics of that pose in Rust. A take of the whole
//! scene (`/api/takes/{take}.glb`) played by three's `AnimationMixer` is checked against the
//! take's own frames the same way, in scene space.

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
// The face: the pose (and its morph weights) applied by the binding, then every vertex of
// every mesh with morph targets as three computes it on the CPU (morph, then skin:
// `getVertexPosition`), in world space, beside its unmorphed bind-space position.
window.face = (id) => {
  const b = bound.get(id);
  const pose = client.pose(id);
  if (!b || !pose || !pose.weights) return null;
  b.skeleton.apply(pose);
  b.plain.scene.updateMatrixWorld(true);
  const v = new THREE.Vector3();
  const rest = [], world = [];
  for (const m of b.skeleton.morphMeshes) {
    const pos = m.geometry.attributes.position;
    for (let i = 0; i < pos.count; i++) {
      rest.push(pos.getX(i), pos.getY(i), pos.getZ(i));
      m.getVertexPosition(i, v);
      v.applyMatrix4(m.matrixWorld);
      world.push(v.x, v.y, v.z);
    }
  }
  return { pose, meshes: b.skeleton.morphMeshes.length, rest, world };
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

/// A face drawn by three.js matches posecast's CPU reference (issue 30 goal 5, the independent
/// reference): Ready Player Me's avatar walking (the built-in walk retargeted), placed, with
/// three morph weights set; the SDK's `SkeletonBinding` applies the streamed pose and weights
/// to the server's `mesh.glb` in three.js, whose own CPU path (`getVertexPosition`: morph, then
/// skin) gives every vertex; the reference is `morph_cpu` then `skin_cpu` of the same pose on
/// the mesh as posecast's client reads it (vertices matched by their bind-space position).
/// posecast's GPU paths equal that CPU reference (`client/tests/render_morph.rs`), so the
/// native renderer's faces are three.js's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_js_draws_the_face_posecast_computes() {
    let Some(modules) = node_modules() else {
        return;
    };
    let Some(rpm) = common::testdata_bytes("gltf/ReadyPlayerMe/PreviewMesh.glb") else {
        return;
    };
    let server = common::server(60.0).await;
    let (status, body) =
        common::upload_files(server.addr, "/api/assets/rpm", &[("rpm.glb", &rpm)]).await;
    assert_eq!(status, 200, "{body}");
    for c in [
        serde_json::json!({"op": "add_avatar", "scene": "default", "asset": "rpm", "avatar": "face",
            "position": [0.5, 0, -0.25], "rotation": [0, 0.38268343, 0, 0.9238795]}),
        serde_json::json!({"op": "play", "avatar": "face", "clip": "walk", "from_asset": "avatar"}),
        serde_json::json!({"op": "set_morph_weights", "avatar": "face",
            "weights": {"mouthOpen": 0.6, "eyesClosed": 0.9, "mouthSmile": 0.35}}),
    ] {
        let (status, body) = command(&server, c.clone()).await;
        assert_eq!(status, 200, "{c} → {body}");
    }
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    let rust = Client::connect(options).await.unwrap();
    assert!(
        common::wait_for(60.0, || rust
            .avatars()
            .iter()
            .any(|a| a.description.id.0 == "face"))
        .await
    );
    let view = rust
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == "face")
        .unwrap();
    // The meshes `mesh.glb` is written from: the rig's, in bind space.
    let rig = server.state.world.library.get("rpm").unwrap();
    let meshes: Vec<&posecast_proto::SkinnedMesh> =
        rig.asset.meshes.iter().map(|m| &m.mesh).collect();
    // Bind-space position → the (mesh, vertex) there (seams repeat a position).
    let mut at: std::collections::HashMap<[u32; 3], Vec<(usize, usize)>> = Default::default();
    for (m, mesh) in meshes.iter().enumerate() {
        for (i, p) in mesh.positions().iter().enumerate() {
            at.entry(p.to_array().map(f32::to_bits))
                .or_default()
                .push((m, i));
        }
    }
    let size = model_size(&view);

    let page_url = serve_origin(page(&server.addr.to_string()), Some(modules), Vec::new()).await;
    let (_driver, b) = browser().await;
    b.goto(&page_url).await.unwrap();
    wait_js(&b, 60, "window.ready === true").await;
    wait_js(&b, 60, "window.known(\"face\")").await;
    b.execute("return await window.bind(\"face\");", vec![])
        .await
        .unwrap();
    let mut worst = 0.0f32;
    let mut moved = 0.0f32;
    let mut compared = 0usize;
    for _ in 0..3 {
        tokio::time::sleep(Duration::from_millis(131)).await;
        let report = wait_js(&b, 60, "window.face(\"face\")").await;
        assert!(
            report["meshes"].as_u64().unwrap() > 0,
            "no morph meshes in three"
        );
        let pose: AvatarPoseJson = serde_json::from_value(report["pose"].clone()).unwrap();
        let weights = pose.weights.clone();
        assert!(
            (weights["eyesClosed"] - 0.9).abs() <= posecast_proto::morph::MAX_WEIGHT_ERROR,
            "{weights:?}"
        );
        let world = reference(&view, &report["pose"]);
        let mut skinning = vec![glam::Mat4::IDENTITY; world.len()];
        posecast_proto::fk::skinning_matrices(&view.skeleton, &world, &mut skinning);
        // Per mesh: morphed (bind space) and then skinned (world) positions.
        let mut morphed = Vec::new();
        let mut skinned = Vec::new();
        for mesh in &meshes {
            let by_target: Vec<f32> = mesh
                .targets()
                .iter()
                .map(|t| weights.get(&t.name).copied().unwrap_or(0.0))
                .collect();
            let n = mesh.vertex_count();
            let (mut p, mut nrm) = (vec![glam::Vec3::ZERO; n], vec![glam::Vec3::ZERO; n]);
            posecast_proto::morph::morph_cpu(mesh, &by_target, &mut p, &mut nrm);
            let as_mesh = posecast_proto::SkinnedMesh::new(
                p.clone(),
                nrm,
                mesh.indices().to_vec(),
                mesh.influences(),
                mesh.joints().to_vec(),
                mesh.weights().to_vec(),
                view.skeleton.len(),
            )
            .unwrap();
            let (mut w, mut wn) = (vec![glam::Vec3::ZERO; n], vec![glam::Vec3::ZERO; n]);
            posecast_proto::skinning::skin_cpu(&as_mesh, &skinning, &mut w, &mut wn);
            morphed.push(p);
            skinned.push(w);
        }
        let numbers =
            |key: &str| -> Vec<f32> { serde_json::from_value(report[key].clone()).unwrap() };
        let (rest, three) = (numbers("rest"), numbers("world"));
        for (r, t) in rest.chunks_exact(3).zip(three.chunks_exact(3)) {
            let key = [r[0], r[1], r[2]].map(f32::to_bits);
            let Some(candidates) = at.get(&key) else {
                panic!("three's vertex at {r:?} is not in posecast's mesh");
            };
            let t = glam::Vec3::new(t[0], t[1], t[2]);
            let e = candidates
                .iter()
                .map(|&(m, i)| skinned[m][i].distance(t))
                .fold(f32::INFINITY, f32::min);
            worst = worst.max(e / size);
            moved = moved.max(
                candidates
                    .iter()
                    .map(|&(m, i)| (morphed[m][i] - meshes[m].positions()[i]).length())
                    .fold(0.0, f32::max),
            );
            compared += 1;
        }
    }
    println!(
        "face: {compared} vertices compared over 3 poses, worst {worst:.2e} of the model's size \
         (largest morph displacement {moved:.4} m)"
    );
    assert!(moved > 0.002, "the weights moved no vertex ({moved} m)");
    assert!(
        worst <= 1e-5,
        "three.js's face is {worst:e} of the size from posecast's"
    );
    b.close().await.ok();
}

/// One avatar at one frame of a take: its description then and its decoded pose.
type TakeAvatar = (
    std::sync::Arc<posecast_proto::description::AvatarDescription>,
    posecast_proto::frame::AvatarPose,
);

/// The take's own frames (as `tests/takes.rs` reads them for its exports): each frame's time,
/// seconds from the take's first frame, and every avatar's description and decoded pose.
fn take_frames(
    server: &posecast_server::startup::Server,
    take: &str,
) -> Vec<(f64, std::collections::BTreeMap<String, TakeAvatar>)> {
    let index = server.state.takes.index(take).unwrap();
    let source = server.state.takes.source(take).unwrap();
    let first = index.first_seq().unwrap();
    let rate = f64::from(index.header.tick_rate);
    let mut reader = posecast_server::stream::take::TakeReader::new(source, index.clone());
    (0..index.frames.len())
        .map(|i| {
            let t = (index.frames[i].seq - first) as f64 / rate;
            let poses = reader
                .poses(i)
                .unwrap()
                .iter()
                .map(|p| {
                    (
                        p.description.id.0.clone(),
                        (p.description.clone(), p.pose.clone()),
                    )
                })
                .collect();
            (t, poses)
        })
        .collect()
}

/// Every joint's world matrix in scene space as the take has it: the description's rest, the
/// frame's rotations, translations and scales, forward kinematics, then the placement
/// (`P · FK`, the way a client draws a placed avatar; the export folds `P` into the roots).
fn take_world(
    d: &posecast_proto::description::AvatarDescription,
    pose: &posecast_proto::frame::AvatarPose,
) -> Vec<glam::Mat4> {
    let skeleton = d.to_skeleton().unwrap();
    let mut locals = skeleton.rest().to_vec();
    for (l, q) in locals.iter_mut().zip(&pose.rotations) {
        l.rotation = *q;
    }
    for (&j, t) in d.translated_joints.iter().zip(&pose.translations) {
        locals[usize::from(j)].translation = *t;
    }
    for (&j, s) in d.scaled_joints.iter().zip(&pose.scales) {
        locals[usize::from(j)].scale = *s;
    }
    let mut world = vec![glam::Mat4::IDENTITY; skeleton.len()];
    forward_kinematics(&skeleton, &locals, &mut world);
    let placement = pose.placement.to_mat4();
    world.iter().map(|m| placement * *m).collect()
}

/// The take page: `load()` fetches `/take.glb`, parses it with three's `GLTFLoader` and plays
/// its first animation on an `AnimationMixer` of the scene (once, clamped at its end, so the
/// last frame is reachable); `sample(t)` sets the mixer's time and reports, per avatar (its
/// root node found by name, its joints as its skin lists them), every joint's local quaternion
/// and world position. Errors and warnings logged by three are kept.
const TAKE_PAGE: &str = r#"<!doctype html>
<script type="importmap">
{"imports": {
  "three": "/node_modules/three/build/three.module.js",
  "three/addons/": "/node_modules/three/examples/jsm/"
}}
</script>
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

window.errors = [];
window.warnings = [];
window.addEventListener("error", (e) => window.errors.push(String(e.message)));
window.addEventListener("unhandledrejection", (e) => window.errors.push(String(e.reason)));
const logError = console.error.bind(console), logWarn = console.warn.bind(console);
console.error = (...a) => { window.errors.push(a.map(String).join(" ")); logError(...a); };
console.warn = (...a) => { window.warnings.push(a.map(String).join(" ")); logWarn(...a); };

let gltf, mixer, action;
const figures = new Map();
window.load = async (ids) => {
  const bytes = await (await fetch("/take.glb")).arrayBuffer();
  gltf = await new Promise((resolve, reject) => new GLTFLoader().parse(bytes, "", resolve, reject));
  const json = gltf.parser.json;
  const byNode = new Map();
  gltf.scene.traverse((o) => {
    const a = gltf.parser.associations.get(o);
    if (a && a.nodes !== undefined && !byNode.has(a.nodes)) byNode.set(a.nodes, o);
  });
  const found = {};
  for (const id of ids) {
    const rootIndex = json.nodes.findIndex((n) => n.name === id);
    const skin = (json.skins || []).find((s) => s.name === id);
    const root = byNode.get(rootIndex);
    const joints = skin ? skin.joints.map((n) => byNode.get(n)) : [];
    let skinned = 0;
    gltf.scene.traverse((o) => {
      if (o.isSkinnedMesh && joints.length && o.skeleton.bones[0] === joints[0]) skinned += 1;
    });
    found[id] = {
      root: root ? root.name : null,
      rootIsSceneChild: !!root && root.parent === gltf.scene,
      joints: joints.map((o) => (o ? o.name : null)),
      bones: joints.filter((o) => o && o.isBone).length,
      under: joints.filter((o) => { for (let p = o; p; p = p.parent) if (p === root) return true; return false; }).length,
      skinned,
    };
    figures.set(id, { root, joints });
  }
  mixer = new THREE.AnimationMixer(gltf.scene);
  const clip = gltf.animations[0];
  action = mixer.clipAction(clip);
  action.setLoop(THREE.LoopOnce, 1);
  action.clampWhenFinished = true;
  action.play();
  return { found, animations: gltf.animations.length, name: clip.name, duration: clip.duration, tracks: clip.tracks.length };
};

const position = (o) => o.getWorldPosition(new THREE.Vector3()).toArray();
window.sample = (t) => {
  action.reset().play();
  mixer.setTime(t);
  gltf.scene.updateMatrixWorld(true);
  const out = {};
  for (const [id, { root, joints }] of figures) {
    out[id] = {
      root: { p: position(root), q: root.getWorldQuaternion(new THREE.Quaternion()).toArray() },
      joints: joints.map((o) => ({ q: o.quaternion.toArray(), p: position(o) })),
    };
  }
  return out;
};
window.ready = true;
</script>
"#;

/// A take of the scene (issue 32) loaded and played by three.js: the built-in avatar placed,
/// rotated and moved during the take, and a second avatar waving, recorded; the take's `.glb`
/// parsed by three's `GLTFLoader` and its one animation played by an `AnimationMixer`. At the
/// first, middle and last recorded frames every joint's local rotation is the take's (roots:
/// the placement's rotation folded in) within 1e-4 rad, and every joint stands where forward
/// kinematics of the take's frame, placed in the scene, puts it within 1e-4 m; the animation
/// lasts as long as the take, both avatars' roots are named after them and hold their joints.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_js_plays_a_take_of_the_scene_where_it_was_recorded() {
    let Some(modules) = node_modules() else {
        return;
    };
    let server = common::server(30.0).await;
    for body in [
        serde_json::json!({"op": "add_avatar", "scene": "default", "asset": "avatar", "avatar": "b",
            "position": [-1.0, 0.0, 0.5]}),
        serde_json::json!({"op": "play", "avatar": "b", "clip": "wave"}),
        serde_json::json!({"op": "place_avatar", "avatar": "avatar", "position": [1.5, 0.0, -0.75],
            "rotation": [0.0, 0.5, 0.0, 0.8660254]}),
    ] {
        let (status, answer) = command(&server, body.clone()).await;
        assert_eq!(status, 200, "{body} → {answer}");
    }
    let scene = server
        .state
        .world
        .scene(&posecast_proto::msg::SceneId("default".into()))
        .unwrap();
    let mut ticks = scene.ticks();
    let (status, answer) = command(
        &server,
        serde_json::json!({"op": "record_scene", "scene": "default", "take": "t"}),
    )
    .await;
    assert_eq!(status, 200, "{answer}");
    // Moved and turned further while recorded: the placement changes from frame to frame.
    let (status, answer) = command(
        &server,
        serde_json::json!({"op": "place_avatar", "avatar": "avatar", "position": [2.5, 0.0, 0.5],
            "rotation": [0.0, 0.8660254, 0.0, 0.5], "duration": 1}),
    )
    .await;
    assert_eq!(status, 200, "{answer}");
    for _ in 0..40 {
        ticks.changed().await.unwrap();
    }
    let (status, answer) = command(
        &server,
        serde_json::json!({"op": "stop_recording_scene", "scene": "default"}),
    )
    .await;
    assert_eq!(status, 200, "{answer}");
    let frames = take_frames(&server, "t");
    assert!(frames.len() >= 30, "{} frames", frames.len());
    let (status, glb) = common::get_bytes(server.addr, "/api/takes/t.glb").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&glb));

    let ids = ["avatar", "b"];
    let names = server
        .state
        .world
        .library
        .get("avatar")
        .unwrap()
        .skeleton()
        .names()
        .to_vec();
    let url = serve_origin(
        TAKE_PAGE.to_owned(),
        Some(modules),
        vec![("/take.glb", glb)],
    )
    .await;
    let (_driver, b) = browser().await;
    b.goto(&url).await.unwrap();
    wait_js(&b, 60, "window.ready === true").await;
    let loaded = b
        .execute(
            "return await window.load(arguments[0]);",
            vec![serde_json::json!(ids)],
        )
        .await
        .unwrap();
    assert_eq!(loaded["animations"], 1, "{loaded}");
    assert_eq!(loaded["name"], "t", "the animation is named after the take");
    let take_duration = frames.last().unwrap().0;
    let duration = loaded["duration"].as_f64().unwrap();
    assert!(
        (duration - take_duration).abs() <= 1e-3,
        "the animation lasts {duration} s, the take {take_duration} s"
    );
    for id in ids {
        let found = &loaded["found"][id];
        assert_eq!(found["root"], id, "a root node named after {id}: {loaded}");
        assert_eq!(found["rootIsSceneChild"], true, "{id}: {found}");
        let joints = found["joints"].as_array().unwrap();
        assert_eq!(joints.len(), names.len(), "{id}: {found}");
        assert_eq!(found["bones"], names.len(), "{id}: every joint a bone");
        assert_eq!(
            found["under"],
            names.len(),
            "{id}: the joints under its root"
        );
        assert!(
            found["skinned"].as_u64().unwrap() > 0,
            "{id}: a skinned mesh: {found}"
        );
    }

    let (mut worst_angle, mut worst_root_angle, mut worst_position, mut moved) =
        (0.0f64, 0.0f64, 0.0f32, 0.0f32);
    let last = frames.len() - 1;
    for i in [0, last / 3, last / 2, last] {
        let (t, poses) = &frames[i];
        // The key's own time as the file holds it (f32).
        let t = f64::from(*t as f32);
        let report = b
            .execute(
                "return window.sample(arguments[0]);",
                vec![serde_json::json!(t)],
            )
            .await
            .unwrap();
        for id in ids {
            let (d, pose) = &poses[id];
            let world = take_world(d, pose);
            let root = &report[id]["root"];
            assert!(
                vec3(&root["p"]).length() < 1e-6
                    && quat(&root["q"]).angle_between(glam::Quat::IDENTITY) < 1e-6,
                "{id}: its root node stays at the origin: {root}"
            );
            for (j, m) in world.iter().enumerate() {
                let joint = &report[id]["joints"][j];
                let expected = if d.parents[j] < 0 {
                    pose.placement.rotation * pose.rotations[j]
                } else {
                    pose.rotations[j]
                };
                let got = quat(&joint["q"]);
                let dq = expected.as_dquat().inverse() * got.as_dquat();
                let angle = 2.0 * dq.xyz().length().atan2(dq.w.abs());
                if d.parents[j] < 0 {
                    worst_root_angle = worst_root_angle.max(angle);
                } else {
                    worst_angle = worst_angle.max(angle);
                }
                let e = vec3(&joint["p"]).distance(m.w_axis.truncate());
                assert!(
                    e <= 1e-4,
                    "{id} {} at {t} s: three puts it at {}, the take at {} ({e} m)",
                    names[j],
                    joint["p"],
                    m.w_axis.truncate()
                );
                worst_position = worst_position.max(e);
            }
            moved = moved.max(pose.placement.position.length());
        }
    }
    let errors = b.execute("return window.errors;", vec![]).await.unwrap();
    assert_eq!(errors, serde_json::json!([]), "page errors");
    let warnings = b.execute("return window.warnings;", vec![]).await.unwrap();
    assert_eq!(warnings, serde_json::json!([]), "three's warnings");
    println!(
        "take in three.js: {} frames, {duration:.4} s (take {take_duration:.4} s); local rotations \
         within {worst_angle:.2e} rad (roots {worst_root_angle:.2e} rad), world positions within \
         {worst_position:.2e} m",
        frames.len()
    );
    assert!(
        worst_angle <= 1e-4,
        "local rotations off by {worst_angle} rad"
    );
    assert!(
        worst_root_angle <= 1e-4,
        "root rotations off by {worst_root_angle} rad"
    );
    assert!(
        moved > 1.0,
        "the placement moved the avatar away from the origin ({moved} m)"
    );
    b.close().await.ok();
}
