//! Scale-out through NATS: three `posecast` processes and a `nats-server` on loopback. A scene
//! created on one server is ticked there and served by all: the same bytes on every server, a
//! late joiner's current pose at once, commands through any server reaching the owner, and
//! another server taking the scene over from its last acknowledged state when the owner is
//! killed.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::nats::Nats;
use common::{CONTROL, Ws, command_to, metric, raw_at};
use futures_util::{SinkExt, StreamExt};
use posecast_proto::frame::{FrameDecoder, FrameKind, read_header};
use posecast_proto::msg::Encoding;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

/// Ticks per second of every server here: 50 ms a tick.
const RATE: f32 = 20.0;
const TICK: Duration = Duration::from_millis(50);

fn node(nats: &Nats, name: &str, lease: &str) -> Posecast {
    node_at(nats, name, lease, RATE)
}

fn node_at(nats: &Nats, name: &str, lease: &str, rate: f32) -> Posecast {
    node_with(nats, name, lease, rate, &[])
}

fn node_with(nats: &Nats, name: &str, lease: &str, rate: f32, more: &[&str]) -> Posecast {
    let url = nats.url();
    let rate = rate.to_string();
    let mut args = vec![
        "--nats",
        &url,
        "--node",
        name,
        "--lease",
        lease,
        "--no-persist",
        "--tick-rate",
        &rate,
        "--control-token",
        CONTROL,
    ];
    args.extend_from_slice(more);
    Posecast::start(&args, &[])
}

async fn ok(addr: SocketAddr, json: &str) -> serde_json::Value {
    let (status, body) = command_to(addr, json).await;
    assert_eq!(status, 200, "{json}: {body}");
    body
}

/// Waits (at most 10 s) until `addr` lists scene `scene` with an owner; returns the owner.
async fn owner_seen_by(addr: SocketAddr, scene: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let body = ok(addr, r#"{"op":"list_scenes"}"#).await;
        let owner = body["result"]
            .as_array()
            .and_then(|scenes| scenes.iter().find(|s| s["scene"] == scene))
            .and_then(|s| s["owner"].as_str().map(str::to_owned));
        if let Some(owner) = owner {
            return owner;
        }
        assert!(
            Instant::now() < deadline,
            "{addr} never listed {scene}: {body}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Everything a subscriber receives, with arrival times, read by a task of its own.
#[derive(Clone, Default)]
struct Recorder(Arc<Mutex<Vec<(Instant, Message)>>>);

impl Recorder {
    async fn subscribe(addr: SocketAddr, encoding: Encoding, token: Option<&str>) -> (Self, Ws) {
        let mut ws = raw_at(addr, encoding, token).await;
        ws.send(Message::Text(
            r#"{"type":"subscribe","scene":"stage"}"#.into(),
        ))
        .await
        .unwrap();
        (Self::default(), ws)
    }

    fn spawn(self, mut ws: Ws) -> Self {
        let log = self.0.clone();
        tokio::spawn(async move {
            while let Some(Ok(m)) = ws.next().await {
                log.lock().unwrap().push((Instant::now(), m));
            }
        });
        self
    }

    fn messages(&self) -> Vec<(Instant, Message)> {
        self.0.lock().unwrap().clone()
    }

    /// Binary frames by tick number.
    fn frames(&self) -> BTreeMap<u64, Vec<u8>> {
        self.messages()
            .into_iter()
            .filter_map(|(_, m)| match m {
                Message::Binary(b) => Some((read_header(&b).unwrap().0.seq, b.to_vec())),
                _ => None,
            })
            .collect()
    }

    /// JSON frames by tick number.
    fn json_frames(&self) -> BTreeMap<u64, String> {
        self.texts("frame")
            .into_iter()
            .map(|t| {
                let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                (v["seq"].as_u64().unwrap(), t)
            })
            .collect()
    }

    /// The text messages of one type, as they came.
    fn texts(&self, kind: &str) -> Vec<String> {
        self.messages()
            .into_iter()
            .filter_map(|(_, m)| match m {
                Message::Text(t) if t.contains(&format!(r#""type":"{kind}""#)) => {
                    Some(t.to_string())
                }
                _ => None,
            })
            .collect()
    }
}

/// A scene `stage` created on `owner` with avatar `dancer` walking.
async fn stage(owner: SocketAddr) {
    ok(owner, r#"{"op":"create_scene","scene":"stage"}"#).await;
    ok(
        owner,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"dancer","clip":"walk"}"#,
    )
    .await;
}

/// The index of joint `name` in the description text.
fn joint_index(description: &str, name: &str) -> usize {
    let d: serde_json::Value = serde_json::from_str(description).unwrap();
    d["avatar"]["joint_names"]
        .as_array()
        .unwrap()
        .iter()
        .position(|j| j == name)
        .unwrap()
}

/// Rotations of joint `j` in every binary frame received after `after`, decoded.
fn rotations_after(rec: &Recorder, j: usize, after: Instant) -> Vec<(Instant, [f32; 4])> {
    let mut decoder = FrameDecoder::new();
    let mut out = Vec::new();
    for (at, m) in rec.messages() {
        if let Message::Binary(b) = m
            && let Ok(frame) = decoder.decode(&b)
            && at > after
        {
            // A frame without the avatar or joint holds no rotation: NaN never matches.
            let q = frame
                .avatars
                .first()
                .and_then(|a| a.rotations.get(j))
                .map_or([f32::NAN; 4], |q| q.to_array());
            out.push((at, q));
        }
    }
    out
}

fn same_rotation(a: [f32; 4], b: [f32; 4]) -> bool {
    let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    dot.abs() > 0.9999
}

/// A client on B gets byte-identical frames and descriptions to a client on the owner A; a
/// late joiner on C gets the description and a keyframe of the current pose before the next
/// tick, the same bytes as A's; every server lists the scene with its owner.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_server_serves_the_owners_bytes() {
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "2");
    let b = node(&nats, "b", "2");
    let c = node(&nats, "c", "2");
    stage(a.addr).await;
    for n in [&a, &b, &c] {
        assert_eq!(owner_seen_by(n.addr, "stage").await, "a");
        // The first server on a new NATS made the built-in `default` scene, once.
        assert_eq!(owner_seen_by(n.addr, "default").await, "a");
    }
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    let (on_b, ws) = Recorder::subscribe(b.addr, Encoding::Binary, None).await;
    let on_b = on_b.spawn(ws);
    let (json_a, ws) = Recorder::subscribe(a.addr, Encoding::Json, None).await;
    let json_a = json_a.spawn(ws);
    let (json_b, ws) = Recorder::subscribe(b.addr, Encoding::Json, None).await;
    let json_b = json_b.spawn(ws);
    // The counters of the window the frames are compared over.
    let published = metric(a.addr, "posecast_nats_published_bytes_total").await;
    let received = metric(b.addr, "posecast_nats_received_bytes_total").await;
    let window = Instant::now();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let published = metric(a.addr, "posecast_nats_published_bytes_total").await - published;
    let received = metric(b.addr, "posecast_nats_received_bytes_total").await - received;
    let seconds = window.elapsed().as_secs_f64();

    let (fa, fb) = (on_a.frames(), on_b.frames());
    let common: Vec<u64> = fa.keys().filter(|s| fb.contains_key(s)).copied().collect();
    assert!(
        common.len() >= 20,
        "{} ticks seen on both (A {}, B {})",
        common.len(),
        fa.len(),
        fb.len()
    );
    for seq in &common {
        assert_eq!(fa[seq], fb[seq], "frame {seq} differs between A and B");
    }
    // JSON too: the relay writes the same text from the same floats.
    let (ja, jb) = (json_a.json_frames(), json_b.json_frames());
    let common_json: Vec<u64> = ja.keys().filter(|s| jb.contains_key(s)).copied().collect();
    assert!(
        common_json.len() >= 20,
        "{} JSON ticks on both",
        common_json.len()
    );
    for seq in &common_json {
        assert_eq!(ja[seq], jb[seq], "JSON frame {seq} differs between A and B");
    }
    // Per node: A owns the scenes (`stage` and `default`) and publishes them, B and C relay
    // them and receive them; A
    // publishes at least the binary chunks of every tick (one avatar, 20 ticks a second).
    for (n, owned, relayed) in [(&a, 2.0, 0.0), (&b, 0.0, 2.0), (&c, 0.0, 2.0)] {
        assert_eq!(metric(n.addr, "posecast_cluster_scenes_owned").await, owned);
        assert_eq!(
            metric(n.addr, "posecast_cluster_scenes_relayed").await,
            relayed
        );
    }
    let chunk_bytes: usize = common.iter().map(|s| fa[s].len()).sum::<usize>() / common.len();
    assert!(
        published / seconds > f64::from(RATE) * 0.8 * chunk_bytes as f64,
        "A published {published} B in {seconds:.2} s"
    );
    assert!(
        received > 0.0 && received <= published * 1.05,
        "B received {received} B, A published {published} B"
    );
    println!(
        "NATS: owner published {:.0} B/s per scene (two scenes of one avatar at {RATE} Hz; binary frame {chunk_bytes} B), a relay received {:.0} B/s per scene",
        published / seconds / 2.0,
        received / seconds / 2.0
    );
    let description = on_a.texts("description");
    assert_eq!(description.len(), 1);
    assert_eq!(on_b.texts("description"), description);
    assert_eq!(on_b.texts("subscribed"), on_a.texts("subscribed"));

    // The late joiner on C: subscribed, the description, then at once the scene's last
    // keyframe and the newest delta after it — no older than the newest frame A had sent when
    // C asked — the same bytes as A's.
    let newest_on_a = *on_a.frames().keys().last().unwrap();
    let (on_c, mut ws) = Recorder::subscribe(c.addr, Encoding::Binary, None).await;
    let asked = Instant::now();
    let mut texts = Vec::new();
    let mut frames = Vec::new();
    while frames.len() < 2 {
        match tokio::time::timeout(Duration::from_secs(5), ws.next()).await {
            Ok(Some(Ok(Message::Binary(b)))) => frames.push((asked.elapsed(), b)),
            Ok(Some(Ok(Message::Text(t)))) => texts.push(t.to_string()),
            // The server's pings (round trips for the adaptive rate) come in between.
            Ok(Some(Ok(Message::Ping(_) | Message::Pong(_)))) => {}
            other => panic!("C: {other:?} after {texts:?}"),
        }
    }
    drop(on_c);
    assert!(texts[0].contains(r#""type":"subscribed""#), "{texts:?}");
    assert_eq!(
        texts[1..],
        description[..],
        "C's description differs from A's"
    );
    let key = read_header(&frames[0].1).unwrap().0;
    let next = read_header(&frames[1].1).unwrap().0;
    assert_eq!(key.kind, FrameKind::Key, "C's first frame is a keyframe");
    let current = if next.kind == FrameKind::Delta {
        assert_eq!(
            next.base_seq, key.seq,
            "the delta refers to the keyframe before it"
        );
        next.seq
    } else {
        key.seq
    };
    assert!(
        current + 2 >= newest_on_a,
        "C's current pose is tick {current}, A had sent {newest_on_a}"
    );
    // A has recorded those ticks by now (they may have reached C first).
    tokio::time::sleep(TICK * 4).await;
    let fa = on_a.frames();
    assert_eq!(
        frames[0].1[..],
        fa[&key.seq][..],
        "C's keyframe differs from A's"
    );
    if next.kind == FrameKind::Delta {
        assert_eq!(
            frames[1].1[..],
            fa[&next.seq][..],
            "C's delta differs from A's"
        );
    }
    println!(
        "late joiner on C: keyframe (tick {}) after {:.1} ms, current pose (tick {current}) after {:.1} ms",
        key.seq,
        frames[0].0.as_secs_f64() * 1e3,
        frames[1].0.as_secs_f64() * 1e3
    );
}

/// A late joiner on a relaying server gets the description and the current pose at once, not
/// at the next tick: with one tick a second, it subscribes just after a tick reached another
/// subscriber of that server and must have that tick's frame, the same bytes, long before the
/// next.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_joiner_on_a_relay_gets_the_current_pose_before_the_next_tick() {
    let Some(nats) = Nats::start() else { return };
    let a = node_at(&nats, "a", "2", 1.0);
    let c = node_at(&nats, "c", "2", 1.0);
    stage(a.addr).await;
    assert_eq!(owner_seen_by(c.addr, "stage").await, "a");
    let (_, mut reference) = Recorder::subscribe(c.addr, Encoding::Binary, None).await;
    let mut ticks = 0;
    let tick = loop {
        match tokio::time::timeout(Duration::from_secs(5), reference.next()).await {
            // The second tick seen: the relay has been running for a tick already.
            Ok(Some(Ok(Message::Binary(b)))) if ticks == 1 => break b,
            Ok(Some(Ok(Message::Binary(_)))) => ticks += 1,
            Ok(Some(Ok(_))) => {}
            other => panic!("reference: {other:?}"),
        }
    };
    let (_, mut joiner) = Recorder::subscribe(c.addr, Encoding::Binary, None).await;
    let asked = Instant::now();
    let mut texts = Vec::new();
    let first = loop {
        match tokio::time::timeout(Duration::from_secs(5), joiner.next()).await {
            Ok(Some(Ok(Message::Binary(b)))) => break b,
            Ok(Some(Ok(Message::Text(t)))) => texts.push(t.to_string()),
            Ok(Some(Ok(Message::Ping(_) | Message::Pong(_)))) => {}
            other => panic!("joiner: {other:?} after {texts:?}"),
        }
    };
    let waited = asked.elapsed();
    assert_eq!(texts.len(), 2, "subscribed and one description: {texts:?}");
    assert!(texts[1].contains(r#""type":"description""#), "{texts:?}");
    assert_eq!(
        first, tick,
        "the joiner's first frame is the tick the relay last sent"
    );
    assert!(
        waited < Duration::from_millis(500),
        "the current pose came {waited:?} after subscribing (ticks are 1 s apart)"
    );
    println!("late joiner on a relay: current pose after {waited:?}");
}

/// A command sent to C reaches the owner A, is acknowledged once through C, and its effect
/// is in B's stream within two ticks; a command refused at C (no token) or at the owner
/// (unknown joint, its error code carried back) changes nothing anywhere.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_through_any_server_reach_the_owner() {
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "2");
    let b = node(&nats, "b", "2");
    let c = node(&nats, "c", "2");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(c.addr, "stage").await, "a");
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let (on_b, ws) = Recorder::subscribe(b.addr, Encoding::Binary, None).await;
    let on_b = on_b.spawn(ws);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let description = on_b.texts("description");
    assert_eq!(description.len(), 1, "{:?}", on_b.texts("error"));
    let j = joint_index(&description[0], "l_elbow");

    // The command through C's websocket.
    let mut commander = raw_at(c.addr, Encoding::Json, Some(CONTROL)).await;
    let rotation = [0.5f32, 0.5, -0.5, 0.5];
    commander
        .send(Message::Text(
            format!(
                r#"{{"type":"command","id":7,"command":{{"op":"set_joint_rotation","avatar":"dancer","joint":"l_elbow","rotation":{rotation:?}}}}}"#
            )
            .into(),
        ))
        .await
        .unwrap();
    let mut acks = 0;
    let mut acked_at = None;
    let deadline = Instant::now() + Duration::from_secs(2);
    while let Ok(Some(Ok(m))) = tokio::time::timeout_at(deadline.into(), commander.next()).await {
        if let Message::Text(t) = m {
            let v: serde_json::Value = serde_json::from_str(&t).unwrap();
            assert_ne!(v["type"], "error", "{v}");
            if v["type"] == "ack" && v["id"] == 7 {
                acks += 1;
                acked_at.get_or_insert(Instant::now());
                let set: Vec<f32> =
                    serde_json::from_value(v["result"]["rotation"].clone()).unwrap();
                assert!(same_rotation(set.try_into().unwrap(), rotation), "{v}");
            }
        }
    }
    assert_eq!(acks, 1, "acknowledged once");
    let acked_at = acked_at.unwrap();
    let seen = rotations_after(&on_b, j, acked_at);
    let first_with = seen.iter().find(|(_, q)| same_rotation(*q, rotation));
    let (at, _) = first_with.unwrap_or_else(|| panic!("B never showed the rotation: {seen:?}"));
    // Two ticks, plus what a loaded machine adds to delivery: the advertised figure.
    assert!(
        at.duration_since(acked_at) <= TICK * 2 + Duration::from_millis(100),
        "B showed it {:?} after the ack",
        at.duration_since(acked_at)
    );
    // From then on every frame on B holds it.
    assert!(
        seen.iter()
            .skip_while(|(t, _)| t < at)
            .all(|(_, q)| same_rotation(*q, rotation))
    );

    // Refused at C: no token.
    let (status, body) = common::http_request(
        c.addr,
        None,
        "POST",
        "/api/commands",
        "application/json",
        br#"{"op":"set_joint_rotation","avatar":"dancer","joint":"l_elbow","rotation":[0,0,0,1]}"#,
    )
    .await;
    assert_eq!(status, 401, "{body}");
    // Refused at the owner: its error code comes back through C.
    let (status, body) = command_to(
        c.addr,
        r#"{"op":"set_joint_rotation","avatar":"dancer","joint":"no_such_joint","rotation":[0,0,0,1]}"#,
    )
    .await;
    assert_eq!(
        (status, body["code"].as_str()),
        (404, Some("unknown_joint")),
        "{body}"
    );
    let refused_at = Instant::now();
    tokio::time::sleep(TICK * 6).await;
    let after = rotations_after(&on_b, j, refused_at);
    assert!(after.len() >= 3, "{after:?}");
    assert!(
        after.iter().all(|(_, q)| same_rotation(*q, rotation)),
        "a refused command changed B's stream: {after:?}"
    );
    // And the owner still holds the acknowledged rotation.
    let joint = ok(
        a.addr,
        r#"{"op":"get_joint","avatar":"dancer","joint":"l_elbow"}"#,
    )
    .await;
    let local: Vec<f32> = serde_json::from_value(joint["result"]["rotation"].clone()).unwrap();
    assert!(
        same_rotation(local.try_into().unwrap(), rotation),
        "{joint}"
    );

    // Avatars added and removed through C: B's subscriber is told as A's would be — the new
    // avatar's description (A's bytes), frames holding both, then `avatar_removed`.
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    tokio::time::sleep(TICK * 4).await;
    ok(
        c.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"guest","clip":"wave"}"#,
    )
    .await;
    let added = Instant::now();
    let deadline = added + Duration::from_secs(5);
    while !on_b
        .texts("description")
        .iter()
        .any(|d| d.contains(r#""id":"guest""#))
    {
        assert!(
            Instant::now() < deadline,
            "B never described the new avatar"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(TICK * 4).await;
    let guest = |rec: &Recorder| {
        rec.texts("description")
            .into_iter()
            .find(|d| d.contains(r#""id":"guest""#))
            .unwrap()
    };
    assert_eq!(
        guest(&on_b),
        guest(&on_a),
        "the new avatar's description differs"
    );
    // Every frame goes through the decoder (a delta needs its keyframe, which may have reached
    // B before the ack reached this test); the scene had one avatar before, so a frame with
    // two is from after the add.
    let mut decoder = FrameDecoder::new();
    let both = on_b
        .messages()
        .into_iter()
        .filter_map(|(_, m)| match m {
            Message::Binary(b) => decoder.decode(&b).ok(),
            _ => None,
        })
        .filter(|f| f.avatars.len() == 2)
        .count();
    assert!(both >= 2, "{both} frames with both avatars on B");
    ok(b.addr, r#"{"op":"remove_avatar","avatar":"guest"}"#).await;
    let deadline = Instant::now() + Duration::from_secs(5);
    while on_b.texts("avatar_removed").is_empty() {
        assert!(Instant::now() < deadline, "B never said the avatar left");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(on_b.texts("avatar_removed")[0].contains(r#""avatar":"guest""#));
}

/// SIGKILL the owner: within the lease time and a second another server ticks the scene from
/// its last acknowledged state, and subscribers on the two others resume with a keyframe.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_server_takes_over_from_the_last_ack() {
    let Some(nats) = Nats::start() else { return };
    let lease = Duration::from_millis(1500);
    let a = node(&nats, "a", "1.5");
    let b = node(&nats, "b", "1.5");
    let c = node(&nats, "c", "1.5");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    assert_eq!(owner_seen_by(c.addr, "stage").await, "a");
    // The last acknowledged change, made through B.
    let rotation = [0.0f32, 0.70710677, 0.0, 0.70710677];
    ok(
        b.addr,
        &format!(
            r#"{{"op":"set_joint_rotation","avatar":"dancer","joint":"l_elbow","rotation":{rotation:?}}}"#
        ),
    )
    .await;
    let (on_b, ws) = Recorder::subscribe(b.addr, Encoding::Binary, None).await;
    let on_b = on_b.spawn(ws);
    let (on_c, ws) = Recorder::subscribe(c.addr, Encoding::Binary, None).await;
    let on_c = on_c.spawn(ws);
    tokio::time::sleep(Duration::from_millis(700)).await;
    let j = joint_index(&on_b.texts("description")[0], "l_elbow");

    let killed = Instant::now();
    a.kill();
    let new_owner = loop {
        let (status, body) = command_to(b.addr, r#"{"op":"list_scenes"}"#).await;
        let owner = body["result"]
            .as_array()
            .and_then(|scenes| scenes.iter().find(|s| s["scene"] == "stage"))
            .and_then(|s| s["owner"].as_str())
            .unwrap_or_default()
            .to_owned();
        if status == 200 && (owner == "b" || owner == "c") {
            break owner;
        }
        assert!(
            killed.elapsed() < Duration::from_secs(15),
            "no new owner: {body}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    // The new owner may restore, fence and start ticking some time after its lease shows
    // (longer on a loaded machine): wait for its stream rather than a fixed time.
    let seen = Instant::now();
    let binary_since = |rec: &Recorder| {
        rec.messages()
            .into_iter()
            .filter(|(t, m)| *t > seen && matches!(m, Message::Binary(_)))
            .count()
    };
    while binary_since(&on_b) < 30 || binary_since(&on_c) < 30 {
        assert!(
            seen.elapsed() < Duration::from_secs(60),
            "the stream did not resume after the takeover"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    for (name, rec) in [("B", &on_b), ("C", &on_c)] {
        // Frames still in flight from A may arrive after the kill (later still on a loaded
        // machine); the new owner's are the ones after the longest silence, the takeover.
        let frames: Vec<(Instant, Vec<u8>)> = rec
            .messages()
            .into_iter()
            .filter_map(|(t, m)| match m {
                Message::Binary(b) => Some((t, b.to_vec())),
                _ => None,
            })
            .collect();
        let gap_end = (1..frames.len())
            .filter(|&i| frames[i].0 > killed)
            .max_by_key(|&i| frames[i].0.duration_since(frames[i - 1].0))
            .unwrap_or(frames.len());
        let resumed = &frames[gap_end..];
        let (at, first) = resumed
            .first()
            .unwrap_or_else(|| panic!("{name}: no frame after the kill"));
        let header = read_header(first).unwrap().0;
        let around: Vec<String> = frames
            [gap_end.saturating_sub(3)..(gap_end + 5).min(frames.len())]
            .iter()
            .map(|(t, b)| {
                let h = read_header(b).unwrap().0;
                let ms = t.saturating_duration_since(killed).as_millis();
                format!("{ms} ms {:?} seq {}", h.kind, h.seq)
            })
            .collect();
        assert_eq!(
            header.kind,
            FrameKind::Key,
            "{name}: first frame after the takeover; frames around the gap: {around:?}"
        );
        let after = at.duration_since(killed);
        println!(
            "{name}: stream resumed {:.0} ms after the owner was killed (new owner {new_owner})",
            after.as_secs_f64() * 1e3
        );
        assert!(
            after <= lease + Duration::from_secs(1),
            "{name}: resumed after {after:?}"
        );
        // The acknowledged override is in the new owner's frames.
        let rotations = rotations_after(rec, j, *at - Duration::from_millis(1));
        assert!(!rotations.is_empty());
        assert!(
            rotations.iter().all(|(_, q)| same_rotation(*q, rotation)),
            "{name}: {rotations:?}"
        );
        // Nothing from A after the takeover: tick numbers only go up from the new owner's key.
        let seqs: Vec<u64> = resumed
            .iter()
            .map(|(_, b)| read_header(b).unwrap().0.seq)
            .collect();
        assert!(seqs.windows(2).all(|w| w[0] < w[1]), "{name}: {seqs:?}");
    }
}

/// NATS unreachable at start: the server does not start, and says which URLs it tried.
#[test]
fn an_unreachable_nats_fails_the_start_naming_the_urls() {
    let free = || {
        std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port()
    };
    let urls = format!("nats://127.0.0.1:{},nats://127.0.0.1:{}", free(), free());
    let (status, output) = common::child::run_to_exit(&["--nats", &urls, "--no-persist"], &[]);
    assert!(!status.success(), "{output}");
    assert!(
        output.contains(&format!("cannot join the cluster through NATS at {urls}")),
        "{output}"
    );
    assert!(!output.contains("panicked"), "{output}");
}

/// NATS lost while running, for longer than the lease: the owner keeps ticking its scene for
/// its own subscribers and reports `degraded`; once NATS is back both servers are healthy, one
/// of them owns the scene (the old owner again, or the other one, which may win the lapsed
/// lease), and both servers' subscribers get frames again without being unsubscribed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn servers_survive_a_nats_restart() {
    let Some(mut nats) = Nats::start() else {
        return;
    };
    let a = node(&nats, "a", "1");
    let b = node(&nats, "b", "1");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    let (on_b, ws) = Recorder::subscribe(b.addr, Encoding::Binary, None).await;
    let on_b = on_b.spawn(ws);
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(a.health(), Some((200, "ok".into())));

    nats.stop();
    let stopped = Instant::now();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let health = a.health();
        if health
            .as_ref()
            .is_some_and(|(status, body)| *status == 200 && body.contains(r#""status":"degraded""#))
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "A never said degraded: {health:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let recent = Instant::now() - Duration::from_millis(500);
    let served = on_a
        .messages()
        .iter()
        .filter(|(t, m)| *t > recent && m.is_binary())
        .count();
    assert!(
        served >= 5,
        "A's own subscriber got {served} frames in 0.5 s without NATS"
    );

    // Down for longer than the 1 s lease: it has lapsed when NATS is back.
    tokio::time::sleep(Duration::from_millis(2500).saturating_sub(stopped.elapsed())).await;
    nats.restart();
    let back = Instant::now();
    for n in [&a, &b] {
        let deadline = back + Duration::from_secs(20);
        while n.health() != Some((200, "ok".into())) {
            assert!(Instant::now() < deadline, "{:?}", n.health());
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
    for (name, rec) in [("A", &on_a), ("B", &on_b)] {
        let deadline = back + Duration::from_secs(20);
        loop {
            let resumed = rec
                .messages()
                .iter()
                .filter(|(t, m)| *t > back + Duration::from_secs(2) && m.is_binary())
                .count();
            if resumed >= 10 {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "{name}'s stream did not resume ({resumed} frames)"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert_eq!(rec.texts("unsubscribed"), Vec::<String>::new(), "{name}");
    }
    let owner = owner_seen_by(a.addr, "stage").await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, owner);
    println!(
        "streams resumed {:?} after NATS restarted; owner now {owner}",
        back.elapsed()
    );
}

/// The client library given several servers of a cluster: it connects to the first that
/// answers, and when that one dies goes on with the next, getting the scene's frames again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_library_fails_over_to_another_server() {
    use posecast_client::net::{Client, ClientOptions, Event};
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "1.5");
    let b = node(&nats, "b", "1.5");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let dead = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let mut options = ClientOptions::new(format!("ws://{dead}/ws"), "stage");
    options.fallback_urls = vec![format!("ws://{}/ws", a.addr), format!("ws://{}/ws", b.addr)];
    let client = Client::connect(options).await.unwrap();
    let mut events = client.events();
    let frames_before = {
        let deadline = Instant::now() + Duration::from_secs(5);
        let mut n = 0;
        while n < 5 {
            match tokio::time::timeout_at(deadline.into(), events.recv()).await {
                Ok(Ok(Event::Frame { .. })) => n += 1,
                Ok(Ok(_)) => {}
                other => panic!("no frames from A: {other:?}"),
            }
        }
        n
    };
    let killed = Instant::now();
    a.kill();
    // Disconnected, connected again (to B), then frames of the scene.
    let deadline = killed + Duration::from_secs(15);
    let mut reconnected = false;
    let mut frames_after = 0;
    while frames_after < 5 {
        match tokio::time::timeout_at(deadline.into(), events.recv()).await {
            Ok(Ok(Event::Connected)) => reconnected = true,
            Ok(Ok(Event::Frame { .. })) if reconnected => frames_after += 1,
            Ok(Ok(_)) | Ok(Err(_)) => {}
            Err(_) => panic!("no frames after the failover (reconnected: {reconnected})"),
        }
    }
    assert!(client.is_connected());
    assert!(
        client
            .latest(&posecast_proto::msg::AvatarId("dancer".into()))
            .is_some()
    );
    println!(
        "{frames_before} frames from A, then {frames_after} through B {:?} after A was killed",
        killed.elapsed()
    );
}

/// An owner whose lease another server took while it lived gives the scene up without
/// dropping its subscribers: they stay subscribed, get no frames while the scene is owned
/// elsewhere, and get a keyframe and the scene's frames again once a server ticks it here.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_owner_whose_lease_was_taken_keeps_its_subscribers() {
    let Some(nats) = Nats::start() else {
        return;
    };
    let a = node(&nats, "a", "1");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(a.addr, "stage").await, "a");
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    tokio::time::sleep(Duration::from_millis(500)).await;

    // "x" takes the lease, as a server would whose clock ran past A's lease, and keeps it
    // (as a live server renews it) until A has given the scene up: a lease put once lapses
    // after the lease time (1 s), and A, late on a busy machine, would find it lapsed and
    // take it back before anyone saw "x" own it.
    let client = async_nats::connect(nats.url()).await.unwrap();
    let leases = async_nats::jetstream::new(client)
        .get_key_value("posecast_leases")
        .await
        .unwrap();
    let key: String = "stage".bytes().map(|b| format!("{b:02x}")).collect();
    let (stop, mut stopped) = tokio::sync::oneshot::channel::<()>();
    let renewer = {
        let (leases, key) = (leases.clone(), key.clone());
        tokio::spawn(async move {
            loop {
                leases.put(&key, "x".into()).await.unwrap();
                tokio::select! {
                    _ = &mut stopped => return,
                    () = tokio::time::sleep(Duration::from_millis(200)) => {}
                }
            }
        })
    };
    let taken = Instant::now();
    let deadline = taken + Duration::from_secs(30);
    while owner_seen_by(a.addr, "stage").await != "x" {
        assert!(Instant::now() < deadline, "A never gave the scene up");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // "x" is no server: nothing ticks the scene until its lease lapses and A takes it back.
    stop.send(()).unwrap();
    renewer.await.unwrap();
    let given_up = Instant::now();
    leases.purge(&key).await.unwrap();
    let deadline = given_up + Duration::from_secs(30);
    while owner_seen_by(a.addr, "stage").await != "a" {
        assert!(Instant::now() < deadline, "A never took the scene back");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(on_a.texts("unsubscribed"), Vec::<String>::new());
    let frames: Vec<(Instant, Vec<u8>)> = on_a
        .messages()
        .into_iter()
        .filter_map(|(t, m)| match m {
            Message::Binary(b) => Some((t, b.to_vec())),
            _ => None,
        })
        .collect();
    let back: Vec<&(Instant, Vec<u8>)> = frames.iter().filter(|(t, _)| *t > given_up).collect();
    assert!(
        back.len() >= 5,
        "{} frames after A took the scene back",
        back.len()
    );
    let first = read_header(&back[0].1).unwrap().0;
    assert_eq!(
        first.kind,
        FrameKind::Key,
        "the first frame after the takeover"
    );
    // The descriptions were not sent again: the subscriber holds the same ones.
    assert_eq!(on_a.texts("description").len(), 1);
}

/// A scene-list watcher on B hears of a scene created, an avatar added and removed and the
/// scene deleted through A, as it would of changes made on B.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_on_another_server_hears_of_changes() {
    let Some(nats) = Nats::start() else {
        return;
    };
    let a = node(&nats, "a", "1");
    let b = node(&nats, "b", "1");
    let mut watcher = raw_at(b.addr, Encoding::Json, Some(CONTROL)).await;
    watcher
        .send(Message::Text(r#"{"type":"watch_scenes"}"#.into()))
        .await
        .unwrap();
    let mut next = async |kind: &str| -> serde_json::Value {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            match tokio::time::timeout_at(deadline.into(), watcher.next()).await {
                Ok(Some(Ok(Message::Text(t)))) => {
                    let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                    // B may hear of the default scene (relayed from A) after its first list.
                    if v["type"] == kind && v["scene"] != "default" {
                        return v;
                    }
                }
                Ok(Some(Ok(_))) => {}
                other => panic!("no {kind}: {other:?}"),
            }
        }
    };
    next("scenes").await;
    ok(a.addr, r#"{"op":"create_scene","scene":"later"}"#).await;
    assert_eq!(next("scene_created").await["scene"], "later");
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"later","asset":"avatar","avatar":"visitor","clip":"wave"}"#,
    )
    .await;
    let changed = next("avatar_changed").await;
    assert_eq!(changed["avatar"]["avatar"], "visitor", "{changed}");
    assert_eq!(changed["avatar"]["clip"], "wave", "{changed}");
    ok(a.addr, r#"{"op":"remove_avatar","avatar":"visitor"}"#).await;
    assert_eq!(next("avatar_removed").await["avatar"], "visitor");
    ok(a.addr, r#"{"op":"delete_scene","scene":"later"}"#).await;
    assert_eq!(next("scene_deleted").await["scene"], "later");
}

/// The description of avatar `avatar` among a recorder's description messages, once there.
async fn description_of(rec: &Recorder, avatar: &str) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let found = rec.texts("description").into_iter().find_map(|t| {
            let v: serde_json::Value = serde_json::from_str(&t).unwrap();
            (v["avatar"]["id"] == avatar).then_some(v)
        });
        if let Some(v) = found {
            return v;
        }
        assert!(Instant::now() < deadline, "no description of {avatar}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits (at most 15 s) until `addr` answers `get_asset` for `asset`; returns the answer.
async fn asset_seen_by(addr: SocketAddr, asset: &str) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(15);
    loop {
        let (status, body) =
            command_to(addr, &format!(r#"{{"op":"get_asset","asset":"{asset}"}}"#)).await;
        if status == 200 {
            return body["result"].clone();
        }
        assert!(
            Instant::now() < deadline,
            "{addr} never had asset {asset}: {body}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// An upload accepted by A is stored where every server reads it and imported by all of them
/// with its pipeline options: after the owner A is SIGKILLed, the server that takes the scene
/// over has the rig and streams the avatar made of it, with the description hash A gave it
/// (the options change the rig, so a server that imported it with the defaults would differ);
/// a server started after the upload has the asset, described exactly as A describes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_reach_every_server_and_survive_the_owner() {
    let Some(nats) = Nats::start() else { return };
    let Some(cesium) = common::testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") else {
        return;
    };
    let a = node(&nats, "a", "1.5");
    let b = node(&nats, "b", "1.5");
    let c = node(&nats, "c", "1.5");
    ok(a.addr, r#"{"op":"create_scene","scene":"stage"}"#).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    assert_eq!(owner_seen_by(c.addr, "stage").await, "a");
    let (status, body) = common::http_to(
        a.addr,
        "POST",
        "/api/assets/cesium?metres_per_unit=2",
        "model/gltf-binary",
        &cesium,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let uploaded: serde_json::Value = serde_json::from_str(&body).unwrap();
    let clip = uploaded["result"][0]["clips"][0]["name"]
        .as_str()
        .unwrap()
        .to_owned();
    // Through B, which forwards it to the owner A.
    ok(
        b.addr,
        &format!(
            r#"{{"op":"add_avatar","scene":"stage","asset":"cesium","avatar":"runner","clip":"{clip}"}}"#
        ),
    )
    .await;
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    let on_owner = description_of(&on_a, "runner").await;
    let hash = on_owner["avatar"]["hash"].as_str().unwrap().to_owned();
    let described = asset_seen_by(a.addr, "cesium").await;
    assert_eq!(described["options"]["metres_per_unit"], 2.0, "{described}");
    for other in [b.addr, c.addr] {
        assert_eq!(asset_seen_by(other, "cesium").await, described);
    }

    let killed = Instant::now();
    a.kill();
    let new_owner = loop {
        let (status, body) = command_to(b.addr, r#"{"op":"list_scenes"}"#).await;
        let owner = body["result"]
            .as_array()
            .and_then(|scenes| scenes.iter().find(|s| s["scene"] == "stage"))
            .and_then(|s| s["owner"].as_str())
            .unwrap_or_default()
            .to_owned();
        if status == 200 && (owner == "b" || owner == "c") {
            break owner;
        }
        assert!(
            killed.elapsed() < Duration::from_secs(15),
            "no new owner: {body}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let owner_addr = if new_owner == "b" { b.addr } else { c.addr };
    let (fresh, ws) = Recorder::subscribe(owner_addr, Encoding::Binary, None).await;
    let fresh = fresh.spawn(ws);
    let taken_over = description_of(&fresh, "runner").await;
    assert_eq!(taken_over["avatar"]["hash"], hash.as_str(), "{taken_over}");
    // Frames of the restored avatar, carrying that hash.
    let deadline = Instant::now() + Duration::from_secs(10);
    let hash = u64::from_str_radix(&hash, 16).unwrap();
    loop {
        let mut decoder = FrameDecoder::new();
        let streamed = fresh.messages().into_iter().any(|(_, m)| {
            matches!(m, Message::Binary(b) if decoder
                .decode(&b)
                .is_ok_and(|f| f.avatars.iter().any(|a| a.hash == hash && !a.rotations.is_empty())))
        });
        if streamed {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{new_owner} streams no frame of runner"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // A server started after the upload has it, described as A described it.
    let d = node(&nats, "d", "1.5");
    assert_eq!(asset_seen_by(d.addr, "cesium").await, described);
}

/// What the cluster's bucket holds that a server cannot use changes nothing there and is
/// logged: a malformed object, and an upload over its asset quota. A server lacking an
/// avatar's rig does not take the scene over when its owner dies (restoring would drop the
/// avatar, and its next snapshot lose it); a server started later that has the rig does, with
/// the avatar.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unusable_uploads_change_nothing_and_lose_nothing() {
    let Some(nats) = Nats::start() else { return };
    let Some(cesium) = common::testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") else {
        return;
    };
    let a = node(&nats, "a", "1");
    // Room for CesiumMan's 490,956 bytes on A, not on B.
    let b = node_with(&nats, "b", "1", RATE, &["--max-asset-bytes", "100000"]);
    let client = async_nats::connect(nats.url()).await.unwrap();
    let bucket = async_nats::jetstream::new(client)
        .get_object_store("posecast_assets")
        .await
        .unwrap();
    bucket
        .put("junk", &mut b"PCA1\xff\xff\xff\xffnot a bundle".as_slice())
        .await
        .unwrap();
    let (status, body) = common::http_to(
        a.addr,
        "POST",
        "/api/assets/cesium",
        "model/gltf-binary",
        &cesium,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    ok(a.addr, r#"{"op":"create_scene","scene":"stage"}"#).await;
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"cesium","avatar":"runner"}"#,
    )
    .await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let logged = |server: &Posecast, what: &str| {
        server
            .output()
            .iter()
            .any(|l| l.contains(what) && l.contains("not loaded here"))
    };
    assert!(
        common::wait_for(10.0, || logged(&b, "junk") && logged(&b, "cesium")).await,
        "{:#?}",
        b.output()
    );
    for name in ["junk", "cesium"] {
        let (status, body) =
            command_to(b.addr, &format!(r#"{{"op":"get_asset","asset":"{name}"}}"#)).await;
        assert_eq!(status, 404, "{body}");
    }
    assert!(logged(&a, "junk"), "{:#?}", a.output());

    a.kill();
    // Three lease times: B does not take the scene over.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let (status, body) = command_to(b.addr, r#"{"op":"list_scenes"}"#).await;
    assert_eq!(status, 200);
    let stage = body["result"]
        .as_array()
        .and_then(|scenes| scenes.iter().find(|s| s["scene"] == "stage"))
        .cloned();
    assert_ne!(
        stage.as_ref().and_then(|s| s["owner"].as_str()),
        Some("b"),
        "{body}"
    );
    assert!(
        b.output()
            .iter()
            .any(|l| l.contains("lacks assets") && l.contains("cesium")),
        "{:#?}",
        b.output()
    );
    assert_eq!(b.health().map(|(s, _)| s), Some(200));
    // C has room for the rig: it takes the scene over with the avatar.
    let c = node(&nats, "c", "1");
    assert_eq!(owner_seen_by(c.addr, "stage").await, "c");
    let (on_c, ws) = Recorder::subscribe(c.addr, Encoding::Binary, None).await;
    let on_c = on_c.spawn(ws);
    let runner = description_of(&on_c, "runner").await;
    assert_eq!(runner["avatar"]["name"], "cesium", "{runner}");
}

/// A scene-list watcher's first list on B shows a scene ticked by A with its avatars as A
/// lists them (ids, rigs, clips) and with its owner.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watchers_first_list_shows_relayed_scenes_with_their_avatars() {
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "1");
    let b = node(&nats, "b", "1");
    stage(a.addr).await;
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"greeter","clip":"wave"}"#,
    )
    .await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let on_a = ok(a.addr, r#"{"op":"list_scenes"}"#).await;
    let summary = |scene: &serde_json::Value| -> Vec<(String, String, String)> {
        scene["avatars"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| {
                (
                    a["avatar"].as_str().unwrap().to_owned(),
                    a["asset"].as_str().unwrap().to_owned(),
                    a["clip"].as_str().unwrap_or_default().to_owned(),
                )
            })
            .collect()
    };
    let find = |scenes: &serde_json::Value| {
        scenes
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["scene"] == "stage")
            .cloned()
            .unwrap_or_else(|| panic!("no stage in {scenes}"))
    };
    let expected = summary(&find(&on_a["result"]));
    assert_eq!(
        expected,
        [
            ("dancer".into(), "avatar".into(), "walk".into()),
            ("greeter".into(), "avatar".into(), "wave".into())
        ]
    );
    let mut watcher = raw_at(b.addr, Encoding::Json, Some(CONTROL)).await;
    watcher
        .send(Message::Text(r#"{"type":"watch_scenes"}"#.into()))
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let first = loop {
        match tokio::time::timeout_at(deadline.into(), watcher.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                if v["type"] == "scenes" {
                    break v;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("no scene list: {other:?}"),
        }
    };
    let listed = find(&first["scenes"]);
    assert_eq!(summary(&listed), expected, "{first}");
    assert_eq!(listed["owner"], "a", "{first}");
}

/// `--max-scenes` counts every scene the creating server holds, relayed ones included: every
/// server holds every scene of the cluster, so the limit is the cluster's as that server sees
/// it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn relayed_scenes_count_toward_max_scenes() {
    let Some(nats) = Nats::start() else { return };
    let a = node_with(&nats, "a", "1", RATE, &["--max-scenes", "2"]);
    let b = node(&nats, "b", "1");
    // `default` (made by the first server) and `elsewhere`, ticked by B.
    ok(b.addr, r#"{"op":"create_scene","scene":"elsewhere"}"#).await;
    assert_eq!(owner_seen_by(a.addr, "elsewhere").await, "b");
    owner_seen_by(a.addr, "default").await;
    let (status, body) = command_to(a.addr, r#"{"op":"create_scene","scene":"third"}"#).await;
    assert_eq!(status, 429, "{body}");
    assert_eq!(body["code"], "quota_exceeded", "{body}");
    // Refused before the name was claimed: the other servers never saw it (a claim given back
    // leaves its deletion in the bucket, and B, had it scanned meanwhile, would relay it).
    let scenes = async_nats::jetstream::new(async_nats::connect(nats.url()).await.unwrap())
        .get_key_value("posecast_scenes")
        .await
        .unwrap();
    let key: String = "third".bytes().map(|b| format!("{b:02x}")).collect();
    let entry = scenes.entry(&key).await.unwrap();
    assert!(entry.is_none(), "A claimed the refused scene: {entry:?}");
    // Nothing changed anywhere: B (no limit of its own) can still make it.
    ok(b.addr, r#"{"op":"create_scene","scene":"third"}"#).await;
}

/// A scene deleted and made again at once under the same name is relayed again by the other
/// servers: the relay that ended with the deletion does not stay registered and hide the new
/// one (`cluster_fuzz` once saw a server that never listed such a scene).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_made_again_after_its_deletion_is_relayed_again() {
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "1");
    let b = node(&nats, "b", "1");
    for round in 0..3 {
        ok(a.addr, r#"{"op":"create_scene","scene":"again"}"#).await;
        assert_eq!(owner_seen_by(b.addr, "again").await, "a", "round {round}");
        ok(a.addr, r#"{"op":"delete_scene","scene":"again"}"#).await;
        // B hears of the deletion; A makes the scene again at once.
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let body = ok(b.addr, r#"{"op":"list_scenes"}"#).await;
            let listed = body["result"]
                .as_array()
                .is_some_and(|scenes| scenes.iter().any(|s| s["scene"] == "again"));
            if !listed {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "B kept the deleted scene: {body}"
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
    ok(a.addr, r#"{"op":"create_scene","scene":"again"}"#).await;
    assert_eq!(owner_seen_by(b.addr, "again").await, "a");
}

/// A JSON connection to `addr` holding the control token that sent `drive` for `avatar` (as
/// command `id`), and the `drive` command's ack.
async fn driving(
    addr: std::net::SocketAddr,
    avatar: &str,
    id: u64,
) -> (common::Ws, serde_json::Value) {
    let mut driver = raw_at(addr, Encoding::Json, Some(CONTROL)).await;
    let command = serde_json::json!({"type": "command", "id": id,
        "command": {"op": "drive", "avatar": avatar}});
    driver
        .send(Message::Text(command.to_string().into()))
        .await
        .unwrap();
    let ack = common::next_of_type(&mut driver, "ack").await;
    (driver, ack)
}

/// A driver connected to B drives an avatar ticked by A: `drive` is acknowledged through B,
/// its JSON and binary poses show in A's frames (the rotations sent), a pose naming an
/// unknown joint or a weight the avatar lacks is refused at B, and when the driver leaves the
/// avatar goes back to its clip.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_driver_on_a_relay_drives_the_owners_avatar() {
    let Some(nats) = Nats::start() else { return };
    // A silent driver keeps its avatar for a minute: only its leaving releases it sooner.
    let a = node_with(&nats, "a", "1", RATE, &["--drive-timeout", "60"]);
    let b = node(&nats, "b", "1");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let (on_a, ws) = Recorder::subscribe(a.addr, Encoding::Binary, None).await;
    let on_a = on_a.spawn(ws);
    let description = description_of(&on_a, "dancer").await.to_string();
    let (elbow, knee) = (
        joint_index(&description, "l_elbow"),
        joint_index(&description, "r_knee"),
    );

    let (mut driver, ack) = driving(b.addr, "dancer", 7).await;
    assert_eq!(ack["id"], 7, "{ack}");
    let num = ack["result"]["avatar_num"].as_u64().unwrap();
    assert!(
        ack["result"]["joints"]
            .as_array()
            .unwrap()
            .iter()
            .any(|j| j == "l_elbow"),
        "{ack}"
    );
    let q = [0.0f32, 0.70710677, 0.0, 0.70710677];
    let sent = Instant::now();
    driver
        .send(Message::Text(
            format!(r#"{{"type":"pose","avatar":"dancer","rotations":{{"l_elbow":{q:?}}}}}"#)
                .into(),
        ))
        .await
        .unwrap();
    let seen = |j: usize, q: [f32; 4], after: Instant| {
        let on_a = on_a.clone();
        async move {
            common::wait_for(5.0, || {
                rotations_after(&on_a, j, after)
                    .iter()
                    .any(|(_, r)| same_rotation(*r, q))
            })
            .await
        }
    };
    assert!(
        seen(elbow, q, sent).await,
        "A's frames never showed the pose"
    );
    // The binary form, by joint index.
    let r = glam::Quat::from_rotation_x(-0.8);
    let pose = posecast_proto::live::BinaryPose {
        avatar_num: u32::try_from(num).unwrap(),
        time_us: None,
        root_position: None,
        rotations: vec![(u16::try_from(knee).unwrap(), r)],
        weights: Vec::new(),
        trackers: Vec::new(),
    };
    let sent = Instant::now();
    driver
        .send(Message::Binary(pose.encode().into()))
        .await
        .unwrap();
    assert!(
        seen(knee, r.to_array(), sent).await,
        "A's frames never showed the binary pose"
    );
    // Refused where the driver is.
    driver
        .send(Message::Text(
            r#"{"type":"pose","avatar":"dancer","rotations":{"no_such_joint":[0,0,0,1]}}"#.into(),
        ))
        .await
        .unwrap();
    let error = common::next_of_type(&mut driver, "error").await;
    assert_eq!(error["code"], "unknown_joint", "{error}");

    // A weight for an avatar without morph targets, refused where the driver is as on the
    // owner (the weights that arrive: `live_weights_through_a_relay_reach_every_viewer`).
    driver
        .send(Message::Text(
            r#"{"type":"pose","avatar":"dancer","rotations":{},"weights":{"blink":1.0}}"#.into(),
        ))
        .await
        .unwrap();
    let error = common::next_of_type(&mut driver, "error").await;
    assert_eq!(error["code"], "unknown_expression", "{error}");

    // The driver leaves: the walk takes the elbow again.
    drop(driver);
    let left = Instant::now();
    assert!(
        common::wait_for(5.0, || {
            rotations_after(&on_a, elbow, left + Duration::from_millis(300))
                .iter()
                .filter(|(_, r)| !same_rotation(*r, q))
                .count()
                > 5
        })
        .await,
        "the avatar stayed driven after its driver left"
    );
}

/// Ready Player Me's avatar `face` of scene `stage`, ticked by A, driven through B: a binary
/// pose's channel weights and a JSON pose's weight by a standard name (ARKit's `jawOpen`, which
/// this rig plays with its `mouthOpen`) reach viewers on A and on B as sent (levels of 1/1023;
/// within the wire's bound); a name the avatar lacks and a channel past its list are refused
/// at B with `unknown_expression` as on the owner, and the refused pose changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_weights_through_a_relay_reach_every_viewer() {
    use posecast_client::net::{Client, ClientOptions};
    use posecast_proto::morph::WEIGHT_LEVELS;
    let Some(nats) = Nats::start() else { return };
    let Some(rpm) = common::testdata_bytes("gltf/ReadyPlayerMe/PreviewMesh.glb") else {
        return;
    };
    let a = node_with(&nats, "a", "1", RATE, &["--drive-timeout", "60"]);
    let b = node(&nats, "b", "1");
    ok(a.addr, r#"{"op":"create_scene","scene":"stage"}"#).await;
    let (status, body) =
        common::upload_files(a.addr, "/api/assets/rpm", &[("rpm.glb", &rpm)]).await;
    assert_eq!(status, 200, "{body}");
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"rpm","avatar":"face"}"#,
    )
    .await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let viewer = |addr: SocketAddr| async move {
        let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "stage");
        options.reconnect = false;
        Client::connect(options).await.unwrap()
    };
    let (on_a, on_b) = (viewer(a.addr).await, viewer(b.addr).await);
    // B drives only an avatar whose relayed description it has.
    assert!(
        common::wait_for(120.0, || on_b
            .avatars()
            .iter()
            .any(|v| v.description.id.0 == "face"))
        .await,
        "B never described the face"
    );

    let (mut driver, ack) = driving(b.addr, "face", 1).await;
    let num = u32::try_from(ack["result"]["avatar_num"].as_u64().unwrap()).unwrap();
    let channels: Vec<String> =
        serde_json::from_value(ack["result"]["morph_targets"].clone()).unwrap();
    assert_eq!(
        ack["result"]["expressions"]["jawOpen"], "mouthOpen",
        "{ack}"
    );
    let channel = |name: &str| {
        let c = channels.iter().position(|c| c == name);
        u16::try_from(c.unwrap_or_else(|| panic!("no {name} in {channels:?}"))).unwrap()
    };
    let binary = |weights: Vec<(u16, u16)>| {
        let pose = posecast_proto::live::BinaryPose {
            avatar_num: num,
            time_us: None,
            root_position: None,
            rotations: Vec::new(),
            weights,
            trackers: Vec::new(),
        };
        Message::Binary(pose.encode().into())
    };
    let level = |l: u16| f32::from(l) / f32::from(WEIGHT_LEVELS);

    // (a) Binary, by channel index into the drive answer's list.
    driver
        .send(binary(vec![
            (channel("mouthSmile"), 767),
            (channel("eyesClosed"), 256),
        ]))
        .await
        .unwrap();
    let mut want = vec![("mouthSmile", level(767)), ("eyesClosed", level(256))];
    common::weights_become(&on_a, "face", "the viewer on A", &want).await;
    common::weights_become(&on_b, "face", "the viewer on B", &want).await;

    // (b) JSON, by a standard name B resolves; channels not named keep their weights.
    driver
        .send(Message::Text(
            r#"{"type":"pose","avatar":"face","rotations":{},"weights":{"jawOpen":0.25}}"#.into(),
        ))
        .await
        .unwrap();
    want.push(("mouthOpen", 0.25));
    common::weights_become(&on_a, "face", "the viewer on A", &want).await;
    common::weights_become(&on_b, "face", "the viewer on B", &want).await;

    // Refused at B, whole: a name the avatar lacks (beside a good one), a channel past the list.
    driver
        .send(Message::Text(
            r#"{"type":"pose","avatar":"face","rotations":{},"weights":{"mouthOpen":0.9,"noSuchShape":0.5}}"#
                .into(),
        ))
        .await
        .unwrap();
    let error = common::next_of_type(&mut driver, "error").await;
    assert_eq!(error["code"], "unknown_expression", "{error}");
    let past = u16::try_from(channels.len()).unwrap();
    driver.send(binary(vec![(past, 1023)])).await.unwrap();
    let error = common::next_of_type(&mut driver, "error").await;
    assert_eq!(error["code"], "unknown_expression", "{error}");
    // Poses pass on in order: once this one shows, mouthOpen is still 0.25, not 0.9.
    driver
        .send(binary(vec![(channel("eyesClosed"), 0)]))
        .await
        .unwrap();
    want.retain(|(n, _)| *n != "eyesClosed");
    common::weights_become(&on_a, "face", "the viewer on A", &want).await;
    common::weights_become(&on_b, "face", "the viewer on B", &want).await;
}

/// The owner of a scene whose avatar is driven through B is SIGKILLed; the driver goes on
/// sending poses to B, and they show in the frames of the server that took the scene over.
/// With two servers B takes it over and applies them itself; with three, C (B cannot load an
/// asset the scene uses, so it does not take it over) and B sends the `drive` again to C.
async fn driving_survives_a_takeover(through_another: bool) {
    let Some(nats) = Nats::start() else { return };
    let cesium = if through_another {
        match common::testdata_bytes("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") {
            Some(bytes) => Some(bytes),
            None => return,
        }
    } else {
        None
    };
    let a = node_with(&nats, "a", "1", RATE, &["--drive-timeout", "60"]);
    let b = node_with(
        &nats,
        "b",
        "1",
        RATE,
        &["--drive-timeout", "60", "--max-asset-bytes", "100000"],
    );
    let c = through_another.then(|| node_with(&nats, "c", "1", RATE, &["--drive-timeout", "60"]));
    stage(a.addr).await;
    if let Some(cesium) = &cesium {
        let (status, body) = common::http_to(
            a.addr,
            "POST",
            "/api/assets/cesium",
            "model/gltf-binary",
            cesium,
        )
        .await;
        assert_eq!(status, 200, "{body}");
        ok(
            a.addr,
            r#"{"op":"add_avatar","scene":"stage","asset":"cesium","avatar":"runner"}"#,
        )
        .await;
    }
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    let (mut driver, ack) = driving(b.addr, "dancer", 1).await;
    assert!(ack["result"]["avatar_num"].is_u64(), "{ack}");
    a.kill();
    let killed = Instant::now();
    let expected = if through_another { "c" } else { "b" };
    let new_owner = loop {
        let (_, body) = command_to(b.addr, r#"{"op":"list_scenes"}"#).await;
        let owner = body["result"]
            .as_array()
            .and_then(|scenes| scenes.iter().find(|s| s["scene"] == "stage"))
            .and_then(|s| s["owner"].as_str())
            .unwrap_or_default()
            .to_owned();
        if owner == "b" || owner == "c" {
            break owner;
        }
        assert!(
            killed.elapsed() < Duration::from_secs(15),
            "no new owner: {body}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(new_owner, expected);
    let owner_addr = c.as_ref().map_or(b.addr, |c| c.addr);
    let (on_owner, ws) = Recorder::subscribe(owner_addr, Encoding::Binary, None).await;
    let on_owner = on_owner.spawn(ws);
    let description = description_of(&on_owner, "dancer").await.to_string();
    let elbow = joint_index(&description, "l_elbow");
    // The walk does not hold the elbow there: only the driver's poses do.
    let q = [0.0f32, 0.70710677, 0.0, 0.70710677];
    let pose = format!(r#"{{"type":"pose","avatar":"dancer","rotations":{{"l_elbow":{q:?}}}}}"#);
    let began = Instant::now();
    let seen = loop {
        driver
            .send(Message::Text(pose.clone().into()))
            .await
            .unwrap();
        let held = rotations_after(&on_owner, elbow, began);
        if held.len() >= 5 && held.iter().rev().take(5).all(|(_, r)| same_rotation(*r, q)) {
            break true;
        }
        if began.elapsed() > Duration::from_secs(10) {
            break false;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(
        seen,
        "{new_owner} never showed the driver's poses after the takeover"
    );
    println!(
        "poses through B shown by the new owner {new_owner} {:.0} ms after it took over",
        began.elapsed().as_secs_f64() * 1e3
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn driving_through_a_relay_survives_it_taking_the_scene_over() {
    driving_survives_a_takeover(false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn driving_through_a_relay_survives_another_server_taking_the_scene_over() {
    driving_survives_a_takeover(true).await;
}

/// A clip recorded on A (`record` … `stop_recording`) reaches B's rig, and when A is
/// SIGKILLed B takes the scene over with the avatar still playing the recording.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recordings_reach_every_server_and_survive_the_owner() {
    let Some(nats) = Nats::start() else { return };
    let a = node(&nats, "a", "1");
    let b = node(&nats, "b", "1");
    stage(a.addr).await;
    assert_eq!(owner_seen_by(b.addr, "stage").await, "a");
    ok(
        a.addr,
        r#"{"op":"record","avatar":"dancer","clip":"take1"}"#,
    )
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let stopped = ok(a.addr, r#"{"op":"stop_recording","avatar":"dancer"}"#).await;
    assert_eq!(stopped["result"]["clip"], "take1", "{stopped}");
    let duration = stopped["result"]["duration"].as_f64().unwrap();
    ok(a.addr, r#"{"op":"play","avatar":"dancer","clip":"take1"}"#).await;
    // B's rig has it, as long as A's.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let asset = asset_seen_by(b.addr, "avatar").await;
        let take = asset["clips"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["name"] == "take1")
            .cloned();
        if let Some(take) = take {
            assert!(
                (take["duration"].as_f64().unwrap() - duration).abs() < 1e-3,
                "{take} vs {duration}"
            );
            break;
        }
        assert!(Instant::now() < deadline, "B never had take1: {asset}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    a.kill();
    let killed = Instant::now();
    loop {
        let (_, body) = command_to(b.addr, r#"{"op":"list_scenes"}"#).await;
        let stage = body["result"]
            .as_array()
            .and_then(|scenes| scenes.iter().find(|s| s["scene"] == "stage"))
            .cloned()
            .unwrap_or_default();
        // B lists itself as the owner only once the snapshot's avatars are restored (never
        // as the owner of an empty scene in between).
        if stage["owner"] == "b" {
            let dancer = stage["avatars"]
                .as_array()
                .and_then(|avatars| avatars.iter().find(|a| a["avatar"] == "dancer"));
            let Some(dancer) = dancer else {
                panic!("B listed itself as the owner before restoring the avatar: {stage}");
            };
            assert_eq!(dancer["clip"], "take1", "{stage}");
            break;
        }
        assert!(
            killed.elapsed() < Duration::from_secs(15),
            "B never took over: {body}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
