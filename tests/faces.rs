//! Faces end to end (issue 30): a Ready Player Me avatar's morph weights set by
//! `set_morph_weights` / `set_expression` (by its own channel names and by standard names),
//! as viewers decode them — binary frames of protocol version 4, JSON frames, and version 3
//! frames that leave them out — through `get_avatar`, and across a SIGKILL. The reference is
//! the weight each command gave, within the wire's stated bound (half of 1/1023).

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::{command_to, testdata_bytes, upload_files};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::morph::MAX_WEIGHT_ERROR;
use posecast_proto::msg::Encoding;
use serde_json::{Value, json};
use std::net::SocketAddr;

const RPM: &str = "gltf/ReadyPlayerMe/PreviewMesh.glb";

async fn ok(addr: SocketAddr, body: Value) -> Value {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_eq!(status, 200, "{body} → {answer}");
    answer["result"].clone()
}

async fn refused(addr: SocketAddr, body: Value) -> (u16, String, String) {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_ne!(status, 200, "{body} must be refused: {answer}");
    (
        status,
        answer["code"].as_str().unwrap_or_default().to_owned(),
        answer["message"].as_str().unwrap_or_default().to_owned(),
    )
}

/// Uploads Ready Player Me's avatar as asset `rpm` and adds avatar `face` of it to `default`.
/// `false` (a failure under `CI=true`) without the shared test data.
async fn add_face(addr: SocketAddr) -> bool {
    let Some(bytes) = testdata_bytes(RPM) else {
        return false;
    };
    let (status, body) = upload_files(addr, "/api/assets/rpm", &[("rpm.glb", &bytes)]).await;
    assert_eq!(status, 200, "{body}");
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "rpm", "avatar": "face"}),
    )
    .await;
    true
}

async fn viewer(addr: SocketAddr, encoding: Encoding, version: u32) -> Client {
    let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "default");
    options.reconnect = false;
    options.encoding = encoding;
    options.version = version;
    Client::connect(options).await.unwrap()
}

/// The face's latest decoded weights by channel name, once they are `want` (within the wire's
/// bound); fails the test when they never are.
async fn weights_become(client: &Client, want: &[(&str, f32)]) -> Vec<(String, f32)> {
    common::weights_become(client, "face", "viewer", want).await
}

#[tokio::test]
async fn weights_set_by_name_reach_every_viewer_within_the_bound() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let v4 = viewer(addr, Encoding::Binary, 4).await;
    let json_viewer = viewer(addr, Encoding::Json, 3).await;
    let v3 = viewer(addr, Encoding::Binary, 3).await;

    // Its own channel names and standard ones (VRM `blink` → eyesClosed) alike.
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face",
               "weights": {"mouthOpen": 0.5, "blink": 0.3}}),
    )
    .await;
    let want = [("mouthOpen", 0.5), ("eyesClosed", 0.3)];
    for (label, client) in [("v4 binary", &v4), ("JSON", &json_viewer)] {
        let got = weights_become(client, &want).await;
        for (name, w) in &want {
            let have = got.iter().find(|(n, _)| n == name).map(|(_, w)| *w);
            let have = have.unwrap_or_else(|| panic!("{label}: no {name} in {got:?}"));
            assert!(
                (have - w).abs() <= MAX_WEIGHT_ERROR,
                "{label} {name}: {have}"
            );
        }
        assert!(
            got.iter().filter(|(_, w)| *w > 0.0).count() == 2,
            "{label}: {got:?}"
        );
    }
    // Version 3 frames leave weights out and still decode: its poses keep arriving.
    let seen = v3.stats().frames;
    assert!(common::wait_for(120.0, || v3.stats().frames > seen + 3).await);
    let face = v3
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == "face")
        .unwrap();
    assert!(face.latest.unwrap().weights.is_empty());
    assert_eq!(v3.stats().undecodable, 0);

    // get_avatar lists the weights above 0 by channel.
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    let listed = &state["morph_weights"];
    assert!(
        (listed["mouthOpen"].as_f64().unwrap() - 0.5).abs() < 1e-3,
        "{state}"
    );
    assert!(
        (listed["eyesClosed"].as_f64().unwrap() - 0.3).abs() < 1e-3,
        "{state}"
    );

    // set_expression (ARKit's jawOpen is mouthOpen here), weight 1 by default; reset clears.
    ok(
        addr,
        json!({"op": "set_expression", "avatar": "face", "expression": "happy"}),
    )
    .await;
    weights_become(
        &v4,
        &[("mouthOpen", 0.5), ("eyesClosed", 0.3), ("mouthSmile", 1.0)],
    )
    .await;
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {"jawOpen": 0.25},
               "reset": true}),
    )
    .await;
    let got = weights_become(&v4, &[("mouthOpen", 0.25)]).await;
    let nonzero: Vec<_> = got.iter().filter(|(_, w)| *w > 0.0).collect();
    assert_eq!(nonzero.len(), 1, "{got:?}");
    assert!((nonzero[0].1 - 0.25).abs() <= MAX_WEIGHT_ERROR, "{got:?}");
}

/// A viewer over WebTransport gets frames as datagrams — wire v2 (protocol versions 9 and 8),
/// or wire v1 before — whose chunks carry the morph weights too, so the face shows as on a
/// websocket, within the wire's bound; a viewer that leaves them out gets none.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn weights_reach_a_webtransport_viewer() {
    let server = common::kit_builder(30.0)
        .configure(|c| c.quic_listen = Some("127.0.0.1:0".parse().unwrap()))
        .start()
        .await
        .unwrap()
        .into_server();
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let over_quic = |weights: bool, version: u32| {
        let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "default");
        options.reconnect = false;
        options.quic_timeout = common::watch::PATIENCE;
        options.morph_weights = weights;
        options.version = version;
        Client::connect(options)
    };
    let quic = over_quic(true, 9).await.unwrap();
    let v1 = over_quic(true, 7).await.unwrap();
    let faceless = over_quic(false, 8).await.unwrap();
    for c in [&quic, &v1, &faceless] {
        assert_eq!(
            c.transport(),
            Some(posecast_client::net::Transport::WebTransport)
        );
    }
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face",
               "weights": {"mouthOpen": 0.5, "blink": 0.3}}),
    )
    .await;
    let want = [("mouthOpen", 0.5), ("eyesClosed", 0.3)];
    for viewer in [&quic, &v1] {
        let got = weights_become(viewer, &want).await;
        assert_eq!(got.iter().filter(|(_, w)| *w > 0.0).count(), 2, "{got:?}");
    }
    // Version 9 acknowledges every frame, version 7 its keyframes.
    let (q, v) = (quic.stats(), v1.stats());
    assert!(q.acks >= q.frames && v.acks <= v.keyframes, "{q:?} {v:?}");
    let latest = faceless.latest(&posecast_proto::msg::AvatarId("face".into()));
    assert!(
        latest.is_some_and(|p| p.weights.is_empty()),
        "the faceless viewer got weights"
    );
    server.stop().await;
}

#[tokio::test]
async fn bad_weights_are_refused_and_change_nothing() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {"mouthSmile": 0.75}}),
    )
    .await;
    let before = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    for (weights, code) in [
        (
            json!({"mouthOpen": 0.5, "noSuchShape": 0.5}),
            "unknown_expression",
        ),
        (json!({"mouthOpen": 1.5}), "invalid_value"),
        (json!({"mouthOpen": -0.01}), "invalid_value"),
        (json!({"mouthOpen": 1e38, "blink": 0.5}), "invalid_value"),
    ] {
        let body = json!({"op": "set_morph_weights", "avatar": "face", "weights": weights,
                          "reset": true});
        let (status, got, message) = refused(addr, body).await;
        assert_eq!(got, code, "{weights}: {message}");
        assert!(status == 404 || status == 400, "{status}");
        let after = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
        assert_eq!(after["morph_weights"], before["morph_weights"], "{weights}");
    }
    // NaN is not JSON; a weight that is not a number is a bad message.
    let (_, code, _) = refused(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {"mouthOpen": "NaN"}}),
    )
    .await;
    assert_eq!(code, "bad_message");
    // The built-in avatar has no morph targets: the error says so.
    let (status, code, message) = refused(
        addr,
        json!({"op": "set_expression", "avatar": "avatar", "expression": "blink"}),
    )
    .await;
    assert_eq!((status, code.as_str()), (404, "unknown_expression"));
    assert!(message.contains("no morph targets"), "{message}");
}

/// An acknowledged `set_morph_weights` survives SIGKILL: the restarted server streams and
/// lists the same weights.
#[tokio::test]
async fn weights_survive_a_sigkill() {
    let data = tempfile::tempdir().unwrap();
    let start = || Posecast::on_data(data.path());
    let server = start();
    if !add_face(server.addr).await {
        return;
    }
    ok(
        server.addr,
        json!({"op": "set_morph_weights", "avatar": "face",
               "weights": {"eyesLookUp": 0.6, "aa": 0.2}}),
    )
    .await;
    server.kill();
    let server = start();
    let state = ok(server.addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    let listed = state["morph_weights"].as_object().unwrap();
    assert_eq!(listed.len(), 2, "{state}");
    assert!(
        (listed["eyesLookUp"].as_f64().unwrap() - 0.6).abs() < 1e-3,
        "{state}"
    );
    assert!(
        (listed["mouthOpen"].as_f64().unwrap() - 0.2).abs() < 1e-3,
        "{state}"
    );
    let v4 = viewer(server.addr, Encoding::Binary, 4).await;
    weights_become(&v4, &[("eyesLookUp", 0.6), ("mouthOpen", 0.2)]).await;
    server.kill();
}

/// A VMC performer's blend shapes (`/VMC/Ext/Blend/Val` + `Apply`, VRM 0.x names as VSeeFace
/// sends them) drive the face's morph channels: `Joy` → happy → mouthSmile, `A` → aa →
/// mouthOpen, `Blink` → blink → eyesClosed; a name the face lacks is kept in `blend_shapes`
/// only, and a NaN is refused as before.
#[tokio::test]
async fn vmc_blend_shapes_drive_the_morph_channels() {
    use common::vmc::{bundle, message, sender};
    use rosc::OscType;
    let server = common::vmc::server(30.0, &["face"], Vec::new()).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let val = |name: &str, v: f32| {
        message(
            "/VMC/Ext/Blend/Val",
            vec![OscType::String(name.into()), OscType::Float(v)],
        )
    };
    let packet = bundle(vec![
        val("Joy", 0.75),
        val("A", 0.25),
        val("Blink", 1.0),
        val("Fun", 0.5),
        val("Blink_L", f32::NAN),
        message("/VMC/Ext/Blend/Apply", vec![]),
    ]);
    let udp = sender().await;
    let v4 = viewer(addr, Encoding::Binary, 4).await;
    let want = [
        ("mouthSmile", 0.75),
        ("mouthOpen", 0.25),
        ("eyesClosed", 1.0),
    ];
    let to = server.vmc.inputs[0];
    let bytes = rosc::encoder::encode(&packet).unwrap();
    // The same packet three times: one datagram lost on loopback changes nothing.
    for _ in 0..3 {
        udp.send_to(&bytes, to).await.unwrap();
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let got = weights_become(&v4, &want).await;
    for (name, w) in want {
        let have = got.iter().find(|(n, _)| n == name).map(|(_, w)| *w);
        assert!(
            have.is_some_and(|h| (h - w).abs() <= MAX_WEIGHT_ERROR),
            "{name}: {got:?}"
        );
    }
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    assert_eq!(state["blend_shapes"]["Fun"], 0.5, "{state}");
    assert_eq!(
        state["morph_weights"].as_object().unwrap().len(),
        3,
        "{state}"
    );
}

/// VMC out sends the face's weights in every bundle: each channel by its own name, and the
/// VRM 0.x clip names VMC receivers compare (exact case) that the face's expressions map onto
/// a channel — `Blink` (blink → eyesClosed), `Joy` (happy → mouthSmile), `A` (aa → mouthOpen)
/// — then `/VMC/Ext/Blend/Apply`.
#[tokio::test]
async fn vmc_out_sends_the_faces_weights_by_channel_and_vrm_names() {
    use rosc::{OscPacket, OscType};
    use std::collections::BTreeMap;
    let listener = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let out = posecast_server::vmc::VmcOut {
        avatar: posecast_proto::msg::AvatarId("face".into()),
        addr: listener.local_addr().unwrap(),
    };
    let server = common::vmc::server(30.0, &[], vec![out]).await;
    if !add_face(server.addr).await {
        return;
    }
    ok(
        server.addr,
        json!({"op": "set_morph_weights", "avatar": "face",
               "weights": {"blink": 1.0, "mouthSmile": 0.5}}),
    )
    .await;
    /// A bundle's blend shape values and whether `Apply` follows the last of them.
    fn blends(packet: &OscPacket) -> (BTreeMap<String, f32>, bool) {
        let mut values = BTreeMap::new();
        let mut applied = false;
        if let OscPacket::Bundle(b) = packet {
            for p in &b.content {
                let OscPacket::Message(m) = p else { continue };
                match (m.addr.as_str(), m.args.as_slice()) {
                    ("/VMC/Ext/Blend/Val", [OscType::String(n), OscType::Float(v)]) => {
                        applied = false;
                        values.insert(n.clone(), *v);
                    }
                    ("/VMC/Ext/Blend/Apply", []) => applied = true,
                    _ => {}
                }
            }
        }
        (values, applied)
    }
    let mut buf = vec![0u8; 65_536];
    let (values, applied) = tokio::time::timeout(std::time::Duration::from_secs(120), async {
        loop {
            let (n, _) = listener.recv_from(&mut buf).await.unwrap();
            let (_, packet) = rosc::decoder::decode_udp(&buf[..n]).unwrap();
            let (values, applied) = blends(&packet);
            if values.get("eyesClosed") == Some(&1.0) && values.get("mouthSmile") == Some(&0.5) {
                return (values, applied);
            }
        }
    })
    .await
    .expect("VMC out never sent the weights");
    assert!(
        applied,
        "no /VMC/Ext/Blend/Apply after the values: {values:?}"
    );
    for channel in [
        "mouthOpen",
        "mouthSmile",
        "eyesClosed",
        "eyesLookUp",
        "eyesLookDown",
    ] {
        assert!(
            values.contains_key(channel),
            "{channel} missing: {values:?}"
        );
    }
    assert_eq!(values.get("Blink"), Some(&1.0), "{values:?}");
    assert_eq!(values.get("Joy"), Some(&0.5), "{values:?}");
    assert_eq!(values.get("A"), Some(&0.0), "{values:?}");
    // VMC names are case-sensitive: only the VRM 0.x spelling is sent.
    assert!(
        !values.contains_key("blink") && !values.contains_key("joy"),
        "{values:?}"
    );
}

/// Weights survive recording, export and replay: a take of the face while its weights are
/// set (eyes closed 0.8, then the mouth opened 0.6 too) holds a morph track per channel that
/// moved; its glTF passes the Khronos validator (a `weights` channel on the mesh node) and
/// imports back with those weights at its start and end; played back on the face once its set
/// weights are reset, the stream carries the recorded weights (the clip's end, held).
#[tokio::test]
async fn weights_are_recorded_exported_and_replayed() {
    use posecast_proto::morph::{weight_level, weight_value};
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let v4 = viewer(addr, Encoding::Binary, 4).await;
    let set =
        |weights: Value| json!({"op": "set_morph_weights", "avatar": "face", "weights": weights});
    ok(addr, set(json!({"eyesClosed": 0.8}))).await;
    weights_become(&v4, &[("eyesClosed", 0.8)]).await;
    ok(
        addr,
        json!({"op": "record", "avatar": "face", "clip": "take"}),
    )
    .await;
    tokio::time::sleep(std::time::Duration::from_millis(400)).await;
    ok(addr, set(json!({"mouthOpen": 0.6}))).await;
    weights_become(&v4, &[("eyesClosed", 0.8), ("mouthOpen", 0.6)]).await;
    tokio::time::sleep(std::time::Duration::from_millis(400)).await;
    let info = ok(addr, json!({"op": "stop_recording", "avatar": "face"})).await;
    assert_eq!(info["clip"], "take", "{info}");

    let (status, glb) = common::get_bytes(addr, "/api/assets/rpm/clips/take.glb").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&glb));
    posecast_proto::testing::assert_valid_gltf(&[("face-take-weights", glb.clone())]);
    let back = posecast_server::import::gltf::from_slice("take.glb", &glb)
        .unwrap()
        .remove(0);
    let clip = back.clips.iter().find(|c| c.name() == "take").unwrap();
    let track = |name: &str| {
        clip.morphs()
            .iter()
            .find(|m| m.channel == name)
            .unwrap_or_else(|| panic!("no {name} track in {:?}", clip.morphs()))
    };
    // As streamed: quantised to 10 bits.
    let q = |w: f32| weight_value(weight_level(w));
    let (start, end) = (clip.start(), clip.end());
    assert!((track("eyesClosed").sample(start) - q(0.8)).abs() < 1e-6);
    assert!((track("eyesClosed").sample(end) - q(0.8)).abs() < 1e-6);
    assert_eq!(track("mouthOpen").sample(start), 0.0);
    assert!((track("mouthOpen").sample(end) - q(0.6)).abs() < 1e-6);
    // glTF's weights channel covers every target: the others come back held at 0.
    for m in clip.morphs() {
        if m.channel != "eyesClosed" && m.channel != "mouthOpen" {
            assert!(m.track.is_constant() && m.sample(start) == 0.0, "{m:?}");
        }
    }

    // Replayed: the set weights back to 0, the take held at its end.
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {}, "reset": true}),
    )
    .await;
    weights_become(&v4, &[]).await;
    ok(
        addr,
        json!({"op": "play", "avatar": "face", "clip": "take", "looping": false, "fade": 0}),
    )
    .await;
    weights_become(&v4, &[("eyesClosed", 0.8), ("mouthOpen", 0.6)]).await;
    // The state shows them too (the larger of set and clip weights, per channel).
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    assert_eq!(
        state["morph_weights"]["eyesClosed"],
        f64::from(q(0.8)),
        "{state}"
    );
}

/// A subscription can leave the weights out (`morph_weights: false`): its v4 binary frames
/// carry none (the same bytes a version-3 viewer gets) and its JSON frames no `weights`, while
/// a viewer of the same scene that wants them still gets them.
#[tokio::test]
async fn a_subscription_can_leave_the_weights_out() {
    use futures_util::{SinkExt, StreamExt};
    use posecast_proto::msg::{ClientMsg, SceneId};
    use tokio_tungstenite::tungstenite::Message;
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    ok(
        addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {"mouthOpen": 0.7}}),
    )
    .await;
    let with = viewer(addr, Encoding::Binary, 4).await;
    let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "default");
    options.reconnect = false;
    options.morph_weights = false;
    let without = Client::connect(options).await.unwrap();
    weights_become(&with, &[("mouthOpen", 0.7)]).await;
    let face = posecast_proto::msg::AvatarId("face".into());
    assert!(
        common::wait_for(120.0, || without.latest(&face).is_some()).await,
        "the viewer without weights never got a pose"
    );
    let sample = without.latest(&face).unwrap();
    assert!(sample.weights.is_empty(), "{:?}", sample.weights);

    // JSON: the frames' avatar objects have no `weights`.
    let mut ws = common::raw(&server, Encoding::Json).await;
    let subscribe = ClientMsg::Subscribe {
        scene: SceneId("default".into()),
        avatars: None,
        rate: None,
        joints: None,
        morph_weights: Some(false),
        precision: None,
    };
    ws.send(Message::text(serde_json::to_string(&subscribe).unwrap()))
        .await
        .unwrap();
    let frame = tokio::time::timeout(std::time::Duration::from_secs(120), async {
        loop {
            let t = match ws.next().await {
                Some(Ok(Message::Text(t))) => t,
                Some(Ok(_)) => continue,
                other => panic!("connection closed: {other:?}"),
            };
            let v: Value = serde_json::from_str(&t).unwrap();
            if v["type"] == "frame" && v["avatars"].as_array().is_some_and(|a| !a.is_empty()) {
                return v;
            }
        }
    })
    .await
    .expect("no JSON frame");
    let pose = frame["avatars"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["avatar"] == "face")
        .expect("the face in the frame");
    assert!(pose.get("weights").is_none(), "{pose}");
    assert!(
        pose["rotations"].as_array().is_some_and(|r| !r.is_empty()),
        "{pose}"
    );
}

/// Binary live poses carry weights (flag bit 2: channel index into the `drive` answer's
/// `morph_targets`, 10-bit level): they reach the stream within the wire's bound; a channel
/// past the list is refused with a typed error and changes nothing.
#[tokio::test]
async fn binary_live_poses_carry_weights() {
    use futures_util::SinkExt;
    use posecast_proto::command::CommandResult;
    use posecast_proto::live::BinaryPose;
    use posecast_proto::morph::weight_level;
    use posecast_proto::msg::{ErrorCode, ServerMsg};
    use tokio_tungstenite::tungstenite::Message;
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let v4 = viewer(addr, Encoding::Binary, 4).await;
    let mut ws = common::raw(&server, Encoding::Json).await;
    ws.send(Message::text(
        json!({"type": "command", "id": 1, "command": {"op": "drive", "avatar": "face"}})
            .to_string(),
    ))
    .await
    .unwrap();
    let info = loop {
        match common::next_text(&mut ws).await.expect("drive answered") {
            ServerMsg::Ack {
                id: 1,
                result: CommandResult::Drive(info),
                ..
            } => break info,
            ServerMsg::Error(e) => panic!("drive: {e:?}"),
            _ => {}
        }
    };
    assert_eq!(
        info.morph_targets,
        [
            "mouthOpen",
            "mouthSmile",
            "eyesClosed",
            "eyesLookUp",
            "eyesLookDown"
        ]
    );
    assert_eq!(
        info.expressions.get("blink").map(String::as_str),
        Some("eyesClosed")
    );
    let channel = |name: &str| info.morph_targets.iter().position(|n| n == name).unwrap() as u16;
    let pose = |time_us: u64, weights: Vec<(u16, u16)>| {
        let p = BinaryPose {
            avatar_num: info.avatar_num,
            time_us: Some(time_us),
            root_position: None,
            rotations: Vec::new(),
            weights,
            trackers: Vec::new(),
        };
        Message::binary(p.encode())
    };
    ws.send(pose(
        1000,
        vec![
            (channel("eyesClosed"), weight_level(0.9)),
            (channel("mouthOpen"), weight_level(0.35)),
        ],
    ))
    .await
    .unwrap();
    weights_become(&v4, &[("eyesClosed", 0.9), ("mouthOpen", 0.35)]).await;
    // Channel 5 of 5: refused, and the weights stay.
    ws.send(pose(2000, vec![(0, 0), (5, 1023)])).await.unwrap();
    loop {
        let msg = common::next_text(&mut ws).await;
        if let ServerMsg::Error(e) = msg.expect("the bad pose answered") {
            assert_eq!(e.code, ErrorCode::UnknownExpression, "{e:?}");
            break;
        }
    }
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    assert!(
        state["morph_weights"]["mouthOpen"].as_f64().is_some(),
        "{state}"
    );
}

/// A live driver's JSON `pose` messages carry weights by name (standard or the rig's own);
/// a bad one is refused with a typed error and changes neither the pose nor the weights.
#[tokio::test]
async fn live_poses_carry_weights() {
    use futures_util::SinkExt;
    use posecast_proto::msg::ServerMsg;
    use tokio_tungstenite::tungstenite::Message;
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let mut ws = common::raw(&server, Encoding::Json).await;
    let send = |msg: Value| Message::Text(msg.to_string().into());
    ws.send(send(json!({"type": "command", "id": 1,
                        "command": {"op": "drive", "avatar": "face"}})))
        .await
        .unwrap();
    loop {
        match common::next_text(&mut ws).await.expect("drive answered") {
            ServerMsg::Ack { id: 1, .. } => break,
            ServerMsg::Error(e) => panic!("drive: {e:?}"),
            _ => {}
        }
    }
    let pose = |time_us: u64, weights: Value| {
        send(
            json!({"type": "pose", "avatar": "face", "rotations": {}, "time_us": time_us,
                    "weights": weights}),
        )
    };
    ws.send(pose(1000, json!({"blink": 0.8, "mouthSmile": 0.4})))
        .await
        .unwrap();
    let weight_of = |state: &Value, name: &str| state["morph_weights"][name].as_f64();
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(120);
    let mut state = Value::Null;
    while tokio::time::Instant::now() < deadline {
        state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
        if weight_of(&state, "eyesClosed").is_some() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert!(
        (weight_of(&state, "eyesClosed").unwrap() - 0.8).abs() < 1e-3,
        "{state}"
    );
    assert!(
        (weight_of(&state, "mouthSmile").unwrap() - 0.4).abs() < 1e-3,
        "{state}"
    );
    // A pose older than the last applied is dropped with its weights: after a newer one shows,
    // the older one's blink never did.
    ws.send(pose(500, json!({"blink": 0.1}))).await.unwrap();
    ws.send(pose(2000, json!({"mouthOpen": 0.3})))
        .await
        .unwrap();
    while tokio::time::Instant::now() < deadline {
        state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
        if weight_of(&state, "mouthOpen").is_some() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert!(
        (weight_of(&state, "mouthOpen").unwrap() - 0.3).abs() < 1e-3,
        "{state}"
    );
    assert!(
        (weight_of(&state, "eyesClosed").unwrap() - 0.8).abs() < 1e-3,
        "{state}"
    );
    // An unknown name and an out-of-range weight: typed errors, nothing changed.
    for (weights, code) in [
        (
            json!({"blink": 0.1, "noSuchShape": 1.0}),
            "unknown_expression",
        ),
        (json!({"blink": 2.0}), "invalid_value"),
    ] {
        ws.send(pose(3000, weights.clone())).await.unwrap();
        loop {
            if let ServerMsg::Error(e) = common::next_text(&mut ws).await.expect("an error") {
                assert_eq!(serde_json::to_value(e.code).unwrap(), code, "{weights}");
                break;
            }
        }
    }
    let after = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    assert_eq!(after["morph_weights"], state["morph_weights"]);
}

/// Ready Player Me's avatar as a VRM 1.0 file whose `expressions` bind its morph targets with
/// weights and overrides (the file's own JSON, edited in memory; its buffers unchanged):
/// `aa` moves `mouthOpen` (head and teeth) by 0.8; `blink` moves `eyesClosed`; `happy` moves
/// `mouthSmile` by 1 and `eyesClosed` by 0.3, blocks the blink group and blends the mouth
/// group; custom `smirk` is binary and moves `mouthSmile` by 0.5; `happy` has a material
/// bind, which is not imported.
fn rpm_as_vrm(rpm: &[u8]) -> Vec<u8> {
    common::edit_glb_json(rpm, |doc| {
        let node = |name: &str| {
            doc["nodes"]
                .as_array()
                .unwrap()
                .iter()
                .position(|n| n["name"] == name)
                .unwrap()
        };
        let (head, teeth) = (node("Wolf3D_Head"), node("Wolf3D_Teeth"));
        let target = |name: &str| {
            let names = doc["meshes"][doc["nodes"][head]["mesh"].as_u64().unwrap() as usize]
                ["extras"]["targetNames"]
                .as_array()
                .unwrap();
            names.iter().position(|n| n == name).unwrap()
        };
        let (open, smile, closed) = (
            target("mouthOpen"),
            target("mouthSmile"),
            target("eyesClosed"),
        );
        doc["extensionsUsed"] = json!(["VRMC_vrm"]);
        doc["extensions"] = json!({"VRMC_vrm": {"specVersion": "1.0", "expressions": {
            "preset": {
                "aa": {"morphTargetBinds": [{"node": head, "index": open, "weight": 0.8},
                                            {"node": teeth, "index": open, "weight": 0.8}]},
                "blink": {"morphTargetBinds": [{"node": head, "index": closed, "weight": 1.0}]},
                "happy": {"morphTargetBinds": [{"node": head, "index": smile, "weight": 1.0},
                                               {"node": head, "index": closed, "weight": 0.3}],
                          "overrideBlink": "block", "overrideMouth": "blend",
                          "materialColorBinds": [{"material": 0, "type": "color",
                                                  "targetValue": [1, 0, 0, 1]}]}
            },
            "custom": {
                "smirk": {"isBinary": true,
                          "morphTargetBinds": [{"node": head, "index": smile, "weight": 0.5}]}
            }
        }}});
    })
}

/// A VRM's expressions (issue 30 goal 1): imported with weighted binds, `isBinary` and
/// overrides; set by name (and VRM 0.x name); streamed as the channel weights the VRM 1.0
/// specification's evaluation gives (values derived by hand below).
#[tokio::test]
async fn vrm_expressions_drive_weighted_channels_with_overrides() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    let Some(rpm) = testdata_bytes(RPM) else {
        return;
    };
    let (status, body) = upload_files(
        addr,
        "/api/assets/vrmface",
        &[("vrmface.vrm", &rpm_as_vrm(&rpm))],
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let notes = body.to_string();
    assert!(
        notes.contains("VRM 1.0 expressions: 4 kept (aa, blink, happy, smirk)"),
        "{notes}"
    );
    assert!(
        notes.contains("1 material/texture bind(s) not imported"),
        "{notes}"
    );
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "vrmface", "avatar": "face"}),
    )
    .await;
    let v = viewer(addr, Encoding::Binary, 4).await;
    assert!(
        common::wait_for(120.0, || v
            .avatars()
            .iter()
            .any(|a| a.description.id.0 == "face"))
        .await
    );
    let d = v
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == "face")
        .unwrap()
        .description;
    let names: Vec<&str> = d.expression_binds.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["aa", "blink", "happy", "smirk"]);
    // The file's names are not guessed again: `blink` is the file's, not `eyesClosed` alone.
    assert!(!d.expressions.contains_key("blink") && !d.expressions.contains_key("happy"));

    let set = |expression: &str, weight: f32| {
        json!({"op": "set_expression", "avatar": "face", "expression": expression,
               "weight": weight})
    };
    // aa 0.5: mouthOpen = 0.8 × 0.5 (head and teeth are one channel).
    ok(addr, set("aa", 0.5)).await;
    weights_become(&v, &[("mouthOpen", 0.4)]).await;
    ok(addr, set("blink", 1.0)).await;
    weights_become(&v, &[("mouthOpen", 0.4), ("eyesClosed", 1.0)]).await;
    // happy 0.5 blocks blink (0) and blends the mouth (aa × (1 − 0.5)): mouthOpen 0.2,
    // mouthSmile 0.5, eyesClosed only happy's own 0.3 × 0.5.
    ok(addr, set("happy", 0.5)).await;
    weights_become(
        &v,
        &[
            ("mouthOpen", 0.2),
            ("mouthSmile", 0.5),
            ("eyesClosed", 0.15),
        ],
    )
    .await;
    // smirk is binary: 0.4 shows nothing, 0.6 shows it whole (+0.5 on mouthSmile).
    ok(addr, set("smirk", 0.4)).await;
    ok(addr, set("aa", 0.5)).await; // a later command, so the 0.4 has been applied
    weights_become(
        &v,
        &[
            ("mouthOpen", 0.2),
            ("mouthSmile", 0.5),
            ("eyesClosed", 0.15),
        ],
    )
    .await;
    ok(addr, set("smirk", 0.6)).await;
    weights_become(
        &v,
        &[
            ("mouthOpen", 0.2),
            ("mouthSmile", 1.0),
            ("eyesClosed", 0.15),
        ],
    )
    .await;
    // A VRM 0.x name reaches the same expression: Joy 0 releases blink and the mouth.
    ok(addr, set("Joy", 0.0)).await;
    weights_become(
        &v,
        &[("mouthOpen", 0.4), ("mouthSmile", 0.5), ("eyesClosed", 1.0)],
    )
    .await;
}

/// The expression map is correctable like the joint map (issue 30 goal 2): upload options and
/// `configure_asset` replace guesses, `""` unmaps, and a wrong name or target is refused with
/// a message, changing nothing.
#[tokio::test]
async fn the_expression_map_is_correctable() {
    let data = tempfile::tempdir().unwrap();
    let server = common::kit_builder(30.0)
        .data_dir(data.path())
        .start()
        .await
        .unwrap()
        .into_server();
    let addr = server.addr;
    let Some(rpm) = testdata_bytes(RPM) else {
        return;
    };
    let (ct, body) = common::multipart_with_fields(
        &[("rpm.glb", &rpm)],
        &[(
            "expression_map",
            r#"{"jawOpen": "mouthSmile", "blink": ""}"#,
        )],
    );
    let (status, answer) = common::http_to(addr, "POST", "/api/assets/rpm", &ct, &body).await;
    assert_eq!(status, 200, "{answer}");
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "rpm", "avatar": "face"}),
    )
    .await;
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "face"})).await;
    let described = ok(addr, json!({"op": "get_asset", "asset": "rpm"})).await;
    assert_eq!(
        described["options"]["expression_map"],
        json!({"jawOpen": "mouthSmile", "blink": ""}),
        "{described}"
    );
    let v = viewer(addr, Encoding::Json, 4).await;
    ok(
        addr,
        json!({"op": "set_expression", "avatar": "face", "expression": "jawOpen", "weight": 0.5}),
    )
    .await;
    weights_become(&v, &[("mouthSmile", 0.5)]).await;
    let (_, code, message) = refused(
        addr,
        json!({"op": "set_expression", "avatar": "face", "expression": "blink"}),
    )
    .await;
    assert_eq!(code, "unknown_expression", "{message} ({state})");

    // configure_asset: new avatars take the new map.
    ok(
        addr,
        json!({"op": "configure_asset", "asset": "rpm",
               "options": {"expression_map": {"happy": "mouthOpen"}}}),
    )
    .await;
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "rpm", "avatar": "face2"}),
    )
    .await;
    ok(
        addr,
        json!({"op": "set_expression", "avatar": "face2", "expression": "happy", "weight": 0.25}),
    )
    .await;
    let got = ok(addr, json!({"op": "get_avatar", "avatar": "face2"})).await;
    assert!(
        (got["morph_weights"]["mouthOpen"].as_f64().unwrap() - 0.25).abs() < 1e-3,
        "{got}"
    );
    // Refused, with the reason; the stored options stay.
    for (map, why) in [
        (
            json!({"notAName": "mouthOpen"}),
            "not a standard expression name",
        ),
        (
            json!({"jawOpen": "noSuchTarget"}),
            "not one of the rig's morph targets",
        ),
    ] {
        let (_, _, message) = refused(
            addr,
            json!({"op": "configure_asset", "asset": "rpm", "options": {"expression_map": map}}),
        )
        .await;
        assert!(message.contains(why), "{message}");
    }
    let described = ok(addr, json!({"op": "get_asset", "asset": "rpm"})).await;
    assert_eq!(
        described["options"]["expression_map"],
        json!({"happy": "mouthOpen"}),
        "{described}"
    );
}

/// A VRM's expression weights are stored as expression weights, not flattened into channels:
/// after a SIGKILL, `happy` still blocks `blink`, and letting `happy` go shows the blink again.
#[tokio::test]
async fn vrm_expression_weights_survive_a_sigkill() {
    let data = tempfile::tempdir().unwrap();
    let start = || Posecast::on_data(data.path());
    let Some(rpm) = testdata_bytes(RPM) else {
        return;
    };
    let server = start();
    let (status, body) = upload_files(
        server.addr,
        "/api/assets/vrmface",
        &[("vrmface.vrm", &rpm_as_vrm(&rpm))],
    )
    .await;
    assert_eq!(status, 200, "{body}");
    ok(
        server.addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "vrmface", "avatar": "face"}),
    )
    .await;
    ok(
        server.addr,
        json!({"op": "set_morph_weights", "avatar": "face", "weights": {"blink": 1.0, "happy": 0.5}}),
    )
    .await;
    server.kill();
    let server = start();
    let v = viewer(server.addr, Encoding::Binary, 4).await;
    weights_become(&v, &[("mouthSmile", 0.5), ("eyesClosed", 0.15)]).await;
    ok(
        server.addr,
        json!({"op": "set_expression", "avatar": "face", "expression": "happy", "weight": 0.0}),
    )
    .await;
    weights_become(&v, &[("eyesClosed", 1.0)]).await;
    server.kill();
}

/// A take of the whole scene keeps the face: replayed, the replay's face shows the weights
/// the scene showed at that time of the take (the end, then the start after a seek).
#[tokio::test]
async fn a_scene_take_replays_the_face() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    if !add_face(addr).await {
        return;
    }
    let v4 = viewer(addr, Encoding::Binary, 4).await;
    let set =
        |weights: Value| json!({"op": "set_morph_weights", "avatar": "face", "weights": weights});
    ok(addr, set(json!({"eyesClosed": 0.8}))).await;
    weights_become(&v4, &[("eyesClosed", 0.8)]).await;
    let scene = server
        .state
        .world
        .scene(&posecast_proto::msg::SceneId("default".into()))
        .unwrap();
    let mut ticks = scene.ticks();
    ok(
        addr,
        json!({"op": "record_scene", "scene": "default", "take": "faces"}),
    )
    .await;
    for _ in 0..15 {
        ticks.changed().await.unwrap();
    }
    ok(addr, set(json!({"mouthOpen": 0.6}))).await;
    weights_become(&v4, &[("eyesClosed", 0.8), ("mouthOpen", 0.6)]).await;
    for _ in 0..15 {
        ticks.changed().await.unwrap();
    }
    ok(
        addr,
        json!({"op": "stop_recording_scene", "scene": "default"}),
    )
    .await;
    ok(
        addr,
        json!({"op": "replay", "take": "faces", "scene": "fr", "speed": 4}),
    )
    .await;
    let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "fr");
    options.reconnect = false;
    options.version = 4;
    let replay = Client::connect(options).await.unwrap();
    // At 4× the take ends within a second and holds its last frame.
    common::weights_become(
        &replay,
        "fr.face",
        "replay viewer",
        &[("eyesClosed", 0.8), ("mouthOpen", 0.6)],
    )
    .await;
    ok(
        addr,
        json!({"op": "control_replay", "scene": "fr", "time": 0, "paused": true}),
    )
    .await;
    common::weights_become(&replay, "fr.face", "replay viewer", &[("eyesClosed", 0.8)]).await;
}
