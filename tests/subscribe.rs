//! Subscribing: scenes of many avatars, what a subscriber's first frame holds, avatar filters,
//! and JSON written only for JSON subscribers — read off the wire (raw websockets, frames
//! decoded by `posecast_proto::frame`) or off a scene's outboxes.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use axum::extract::ws::Message as AxumMessage;
use common::{Ws, client, raw, server};
use futures_util::{SinkExt, StreamExt};
use glam::Quat;
use posecast_proto::command::Command;
use posecast_proto::frame::FrameDecoder;
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, FrameJson, SceneId, ServerMsg};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_server::avatar::Avatar;
use posecast_server::metrics::Metrics;
use posecast_server::scene::Scene;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::{Next, Outbox};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

/// One avatar's pose in a frame.
#[derive(Debug, Clone)]
struct Pose {
    avatar: AvatarId,
    rotations: Vec<Quat>,
}

/// A frame as received, whatever the encoding.
#[derive(Debug, Clone)]
struct Frame {
    seq: u64,
    avatars: Vec<Pose>,
}

/// A server message as a subscriber sees it.
#[derive(Debug)]
enum Got {
    Description(AvatarId),
    Frame(Frame),
    Other(ServerMsg),
    Closed(String),
}

/// Turns server messages into [`Got`]: JSON as is, binary through a frame decoder that knows
/// avatar numbers from the descriptions seen.
#[derive(Default)]
struct Reader {
    decoder: FrameDecoder,
    ids: HashMap<u32, AvatarId>,
}

impl Reader {
    fn text(&mut self, text: &str) -> Got {
        match serde_json::from_str::<ServerMsg>(text).unwrap() {
            ServerMsg::Description { avatar, .. } => {
                self.ids.insert(avatar.num, avatar.id.clone());
                Got::Description(avatar.id)
            }
            ServerMsg::Frame(FrameJson { seq, avatars, .. }) => Got::Frame(Frame {
                seq,
                avatars: avatars
                    .into_iter()
                    .map(|a| Pose {
                        avatar: a.avatar,
                        rotations: a.rotations.iter().map(|&r| Quat::from_array(r)).collect(),
                    })
                    .collect(),
            }),
            other => Got::Other(other),
        }
    }

    fn binary(&mut self, bytes: &[u8]) -> Got {
        let frame = self.decoder.decode(bytes).expect("an undecodable frame");
        Got::Frame(Frame {
            seq: frame.header.seq,
            avatars: frame
                .avatars
                .into_iter()
                .map(|a| Pose {
                    // An avatar nobody described shows up as such.
                    avatar: self
                        .ids
                        .get(&a.avatar_num)
                        .cloned()
                        .unwrap_or_else(|| AvatarId(format!("undescribed #{}", a.avatar_num))),
                    rotations: a.rotations,
                })
                .collect(),
        })
    }
}

/// A raw websocket subscriber.
struct Watcher {
    ws: Ws,
    reader: Reader,
    /// Bytes of text messages received.
    text_bytes: usize,
}

impl Watcher {
    async fn subscribe(
        server: &posecast_server::startup::Server,
        encoding: Encoding,
        scene: &str,
        avatars: Option<Vec<AvatarId>>,
    ) -> Self {
        let mut ws = raw(server, encoding).await;
        let sub = ClientMsg::Subscribe {
            scene: SceneId(scene.into()),
            avatars,
            rate: None,
            joints: None,
            morph_weights: None,
            precision: None,
        };
        ws.send(Message::Text(serde_json::to_string(&sub).unwrap().into()))
            .await
            .unwrap();
        Self {
            ws,
            reader: Reader::default(),
            text_bytes: 0,
        }
    }

    /// The next message, or `None` after `secs` seconds. The server's keep-alive pings (every
    /// 15 s; a slow machine can take that long here) are answered by tungstenite and skipped.
    async fn next_within(&mut self, secs: f32) -> Option<Got> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs_f32(secs);
        let msg = loop {
            let msg = tokio::time::timeout_at(deadline, self.ws.next())
                .await
                .ok()?;
            if !matches!(msg, Some(Ok(Message::Ping(_) | Message::Pong(_)))) {
                break msg;
            }
        };
        Some(match msg {
            None => Got::Closed("end of stream".into()),
            Some(Err(e)) => Got::Closed(e.to_string()),
            Some(Ok(Message::Text(t))) => {
                self.text_bytes += t.len();
                self.reader.text(t.as_str())
            }
            Some(Ok(Message::Binary(b))) => self.reader.binary(&b),
            Some(Ok(Message::Close(c))) => Got::Closed(format!("{c:?}")),
            Some(Ok(other)) => panic!("unexpected {other:?}"),
        })
    }

    /// `subscribed`, then the descriptions, up to the first frame, which must come within
    /// `secs` seconds. Returns the described avatars and that frame.
    async fn first_frame(&mut self, secs: f32) -> (Vec<AvatarId>, Frame) {
        let mut described = Vec::new();
        let mut subscribed = false;
        loop {
            match self.next_within(secs).await {
                Some(Got::Other(ServerMsg::Subscribed { .. })) => subscribed = true,
                Some(Got::Description(id)) => described.push(id),
                Some(Got::Frame(f)) => {
                    assert!(subscribed, "a frame before `subscribed`");
                    return (described, f);
                }
                Some(Got::Closed(why)) => {
                    panic!("closed after {} descriptions: {why}", described.len())
                }
                // Who watches the scene: sent as the other subscribers come, in any order
                // with this one's descriptions.
                Some(Got::Other(ServerMsg::Viewers { .. })) => {}
                Some(Got::Other(other)) => panic!("unexpected {other:?}"),
                None => panic!(
                    "no frame within {secs} s ({} descriptions)",
                    described.len()
                ),
            }
        }
    }

    /// The next frame (skipping other messages), within `secs` seconds.
    async fn frame(&mut self, secs: f32) -> Frame {
        loop {
            match self.next_within(secs).await {
                Some(Got::Frame(f)) => return f,
                Some(Got::Closed(why)) => panic!("closed: {why}"),
                Some(_) => {}
                None => panic!("no frame within {secs} s"),
            }
        }
    }
}

fn sorted(mut ids: Vec<AvatarId>) -> Vec<AvatarId> {
    ids.sort();
    ids
}

fn ids(frame: &Frame) -> Vec<AvatarId> {
    sorted(frame.avatars.iter().map(|a| a.avatar.clone()).collect())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_of_1000_avatars_streams_to_every_subscriber() {
    let server = server(10.0).await;
    let scene = SceneId("crowd".into());
    server.state.world.create_scene(scene.clone()).unwrap();
    let crowd: Vec<AvatarId> = (0..1000).map(|i| AvatarId(format!("c{i:04}"))).collect();
    for id in &crowd {
        server
            .state
            .world
            .add_avatar(&scene, "avatar", Some(id.clone()))
            .unwrap();
    }
    let joints = posecast_server::builtin::rig().unwrap().skeleton().len();
    let mut watchers = Vec::new();
    for encoding in [Encoding::Binary, Encoding::Json, Encoding::Binary] {
        watchers.push((
            encoding,
            Watcher::subscribe(&server, encoding, "crowd", None).await,
        ));
    }
    for (encoding, w) in &mut watchers {
        // Every description and then, at once, the current pose of all.
        let (described, first) = w.first_frame(20.0).await;
        assert_eq!(sorted(described), crowd, "{encoding:?}");
        if *encoding == Encoding::Binary {
            println!(
                "1,000 descriptions and `subscribed`: {} bytes",
                w.text_bytes
            );
        }
        assert_eq!(ids(&first), crowd, "{encoding:?}: first frame");
        // Then regular frames of all 1,000, and no close.
        let mut last = first.seq;
        for _ in 0..3 {
            let f = w.frame(20.0).await;
            assert!(f.seq > last, "{encoding:?}: seq {} after {last}", f.seq);
            last = f.seq;
            assert_eq!(ids(&f), crowd, "{encoding:?}: frame {}", f.seq);
            assert!(f.avatars.iter().all(|a| a.rotations.len() == joints));
        }
    }
    println!(
        "1,000 avatars at 10 Hz: {} ticks, {} missed",
        server.state.metrics.ticks(),
        server.state.metrics.missed()
    );
    server.stop().await;
}

#[tokio::test]
async fn the_first_frame_after_subscribing_carries_every_described_avatar() {
    // One tick every 5 s: no tick falls between adding an avatar and subscribing, so the scene's
    // cached keyframe predates the avatar every time.
    let server = server(0.2).await;
    let control = client(&server, Encoding::Binary).await;
    for i in 0..30 {
        let added = AvatarId(format!("n{i}"));
        control
            .command(Command::AddAvatar {
                scene: SceneId("default".into()),
                asset: "avatar".into(),
                avatar: Some(added.clone()),
                clip: (i % 2 == 1).then(|| "walk".into()),
                position: None,
                rotation: None,
            })
            .await
            .unwrap();
        for encoding in [Encoding::Binary, Encoding::Json] {
            let mut w = Watcher::subscribe(&server, encoding, "default", None).await;
            // "At once": well before the next tick.
            let (described, first) = w.first_frame(2.0).await;
            assert_eq!(described.len(), i + 2, "{encoding:?} try {i}");
            assert!(described.contains(&added));
            assert_eq!(
                ids(&first),
                sorted(described),
                "{encoding:?} try {i}: the first frame (tick {}) lacks a described avatar",
                first.seq
            );
        }
    }
    server.stop().await;
}

#[tokio::test]
async fn a_filtered_subscription_gets_only_its_avatars_with_the_same_poses() {
    let server = server(30.0).await;
    let control = client(&server, Encoding::Binary).await;
    let rig = posecast_server::builtin::rig().unwrap();
    let scene = SceneId("trio".into());
    control
        .command(Command::CreateScene {
            scene: scene.clone(),
        })
        .await
        .unwrap();
    // Three avatars frozen (speed 0) at known clip times: their poses are known exactly.
    let setup = [
        ("t0", "walk", 0.2f32),
        ("t1", "wave", 0.7),
        ("t2", "idle", 1.3),
    ];
    for (id, clip, time) in setup {
        let avatar = AvatarId(id.into());
        control
            .command(Command::AddAvatar {
                scene: scene.clone(),
                asset: "avatar".into(),
                avatar: Some(avatar.clone()),
                clip: None,
                position: None,
                rotation: None,
            })
            .await
            .unwrap();
        control
            .command(Command::Play {
                avatar,
                clip: clip.into(),
                from_asset: None,
                speed: Some(0.0),
                looping: Some(true),
                start: Some(time),
                fade: Some(0.0),
                root_motion: None,
            })
            .await
            .unwrap();
    }
    let wanted = AvatarId("t1".into());
    let expected = {
        let clip = rig.clip("wave").unwrap();
        let mut out = rig.skeleton().rest().to_vec();
        clip.sample(clip.start() + 0.7, rig.skeleton().rest(), &mut out);
        out
    };
    let mut all = Watcher::subscribe(&server, Encoding::Binary, "trio", None).await;
    let (described, first) = all.first_frame(2.0).await;
    assert_eq!(described.len(), 3);
    // A tick after the set-up: from now on the scene's cached frames show the frozen poses.
    let settled = all.frame(2.0).await;
    assert!(settled.seq > first.seq);
    let mut unfiltered: HashMap<u64, Pose> = HashMap::new();
    let mut keep = |f: &Frame| {
        let p = f.avatars.iter().find(|a| a.avatar == wanted).unwrap();
        unfiltered.insert(f.seq, p.clone());
    };
    keep(&settled);
    let mut only = Watcher::subscribe(
        &server,
        Encoding::Binary,
        "trio",
        Some(vec![wanted.clone()]),
    )
    .await;
    let mut only_json =
        Watcher::subscribe(&server, Encoding::Json, "trio", Some(vec![wanted.clone()])).await;
    let mut filtered = Vec::new();
    for (name, w) in [("binary", &mut only), ("json", &mut only_json)] {
        let (described, first) = w.first_frame(2.0).await;
        assert_eq!(
            described,
            std::slice::from_ref(&wanted),
            "{name}: descriptions"
        );
        filtered.push((name, first));
    }
    for _ in 0..30 {
        keep(&all.frame(2.0).await);
        filtered.push(("binary", only.frame(2.0).await));
        filtered.push(("json", only_json.frame(2.0).await));
    }
    let mut compared = 0;
    for (name, f) in &filtered {
        assert_eq!(
            ids(f),
            std::slice::from_ref(&wanted),
            "{name} frame {}: other avatars",
            f.seq
        );
        let got = &f.avatars[0].rotations;
        // The pose is the clip's, sampled here.
        for (q, e) in got.iter().zip(&expected) {
            let err = angle_between_degrees(*q, e.rotation);
            assert!(err <= MAX_ERROR_DEGREES, "{name} frame {}: {err}°", f.seq);
        }
        // Binary: the very same chunk as the unfiltered stream's, so the same decoded pose.
        if *name == "binary"
            && let Some(p) = unfiltered.get(&f.seq)
        {
            assert_eq!(got, &p.rotations, "frame {}", f.seq);
            compared += 1;
        }
    }
    assert!(compared >= 10, "only {compared} frames seen by both");
    server.stop().await;
}

/// Everything an outbox holds now, as [`Got`]s.
async fn drain(outbox: &Outbox, reader: &mut Reader) -> Vec<Got> {
    let next = tokio::time::timeout(Duration::from_secs(1), outbox.next())
        .await
        .expect("nothing queued");
    let Next::Send(messages) = next else {
        panic!("outbox closed")
    };
    messages
        .into_iter()
        .map(|m| match m {
            AxumMessage::Text(t) => reader.text(t.as_str()),
            AxumMessage::Binary(b) => reader.binary(&b),
            other => panic!("unexpected {other:?}"),
        })
        .collect()
}

fn frames(got: Vec<Got>) -> Vec<Frame> {
    got.into_iter()
        .filter_map(|g| match g {
            Got::Frame(f) => Some(f),
            _ => None,
        })
        .collect()
}

fn subscriber(conn: u64, outbox: &Arc<Outbox>, encoding: Encoding) -> Subscriber {
    Subscriber::new(conn, outbox.clone(), encoding, None, 1)
}

#[tokio::test]
async fn json_is_written_only_for_json_subscribers_and_a_json_late_joiner_gets_the_cached_keyframe()
{
    let metrics = Arc::new(Metrics::new());
    let scene = Scene::new(SceneId("s".into()), 1, metrics.clone(), 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    let (a, b) = (AvatarId("a".into()), AvatarId("b".into()));
    scene
        .add_avatar(Avatar::new(a.clone(), 1, rig.clone()))
        .unwrap();
    scene
        .add_avatar(Avatar::new(b.clone(), 2, rig.clone()))
        .unwrap();
    // Poses known independently: the rest pose, one joint of `a` overridden.
    let elbow = rig.skeleton().find("l_elbow").unwrap();
    let (q1, q2) = (Quat::from_rotation_y(0.6), Quat::from_rotation_x(-0.4));
    scene
        .lock()
        .avatar_mut(&a)
        .unwrap()
        .set_rotation(elbow, q1)
        .unwrap();
    let binary = Arc::new(Outbox::new());
    scene
        .subscribe(subscriber(1, &binary, Encoding::Binary))
        .unwrap();
    // Keyframes every 3 ticks: 1 and 4 are keyframes, 5 a delta.
    for seq in 1..=5 {
        scene.tick(seq, seq as f64 / 60.0, seq * 1000, 3);
    }
    assert_eq!(
        metrics.json_poses_encoded(),
        0,
        "poses were written as JSON with no JSON subscriber"
    );
    // After the cached frames were made, the pose changes: a joiner must still get the
    // cached tick's pose, not the current one.
    scene
        .lock()
        .avatar_mut(&a)
        .unwrap()
        .set_rotation(elbow, q2)
        .unwrap();
    let json = Arc::new(Outbox::new());
    scene
        .subscribe(subscriber(2, &json, Encoding::Json))
        .unwrap();
    let got = frames(drain(&json, &mut Reader::default()).await);
    let seqs: Vec<u64> = got.iter().map(|f| f.seq).collect();
    assert_eq!(
        seqs,
        [4, 5],
        "the cached keyframe, then the newest delta, at once"
    );
    let rest = rig.skeleton().rest();
    for f in &got {
        assert_eq!(ids(f), [a.clone(), b.clone()]);
        for pose in &f.avatars {
            for (j, (got, r)) in pose.rotations.iter().zip(rest).enumerate() {
                let want = if pose.avatar == a && j == elbow {
                    q1
                } else {
                    r.rotation
                };
                let err = angle_between_degrees(*got, want);
                assert!(
                    err < 1e-4,
                    "frame {} {} joint {j}: {err}°",
                    f.seq,
                    pose.avatar
                );
            }
        }
    }
    // The same content the binary subscriber decoded for that keyframe.
    let mut reader = Reader::default();
    let decoded = frames(drain(&binary, &mut reader).await);
    let key = decoded.iter().find(|f| f.seq == 4).unwrap();
    for (j, q) in key.avatars[0].rotations.iter().enumerate() {
        let err = angle_between_degrees(*q, got[0].avatars[0].rotations[j]);
        assert!(
            err <= MAX_ERROR_DEGREES,
            "joint {j}: binary and JSON differ by {err}°"
        );
    }
    // Written once for the joiner (two avatars in two cached frames), then once per tick
    // while a JSON subscriber stays, and no more after it left.
    assert_eq!(metrics.json_poses_encoded(), 4);
    scene.tick(6, 6.0 / 60.0, 6000, 3);
    assert_eq!(metrics.json_poses_encoded(), 6);
    assert!(scene.unsubscribe(2));
    scene.tick(7, 7.0 / 60.0, 7000, 3);
    assert_eq!(metrics.json_poses_encoded(), 6);
}

#[tokio::test]
async fn a_keyframe_made_for_a_joiner_leaves_every_stream_decodable() {
    let metrics = Arc::new(Metrics::new());
    let scene = Scene::new(SceneId("s".into()), 1, metrics, 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    let (a, b) = (AvatarId("a".into()), AvatarId("b".into()));
    scene
        .add_avatar(Avatar::new(a.clone(), 1, rig.clone()))
        .unwrap();
    let early = Arc::new(Outbox::new());
    scene
        .subscribe(subscriber(1, &early, Encoding::Binary))
        .unwrap();
    let mut early_reader = Reader::default();
    let mut early_frames = Vec::new();
    for seq in 1..=3 {
        scene.tick(seq, seq as f64 / 60.0, seq * 1000, 60);
        early_frames.extend(frames(drain(&early, &mut early_reader).await));
    }
    // `b` arrives between ticks; a subscriber joins before the next tick.
    scene
        .add_avatar(Avatar::new(b.clone(), 2, rig.clone()))
        .unwrap();
    let late = Arc::new(Outbox::new());
    scene
        .subscribe(subscriber(2, &late, Encoding::Binary))
        .unwrap();
    let mut late_reader = Reader::default();
    let first = frames(drain(&late, &mut late_reader).await);
    assert_eq!(first.len(), 1);
    assert_eq!(ids(&first[0]), [a.clone(), b.clone()]);
    assert_eq!(first[0].seq, 3, "labelled with the last tick");
    // Every frame after it decodes for both (the readers panic on an undecodable frame).
    let mut late_frames = first;
    for seq in 4..=8 {
        scene.tick(seq, seq as f64 / 60.0, seq * 1000, 60);
        early_frames.extend(frames(drain(&early, &mut early_reader).await));
        late_frames.extend(frames(drain(&late, &mut late_reader).await));
    }
    let seqs = |f: &[Frame]| f.iter().map(|f| f.seq).collect::<Vec<_>>();
    assert_eq!(seqs(&early_frames), (1..=8).collect::<Vec<_>>());
    assert_eq!(seqs(&late_frames), (3..=8).collect::<Vec<_>>());
    for f in &late_frames {
        assert_eq!(ids(f), [a.clone(), b.clone()]);
    }
    // A third joiner, with nothing changed since: the cached keyframe and newest delta.
    let third = Arc::new(Outbox::new());
    scene
        .subscribe(subscriber(3, &third, Encoding::Binary))
        .unwrap();
    let got = frames(drain(&third, &mut Reader::default()).await);
    assert_eq!(seqs(&got), [4, 8]);
}

/// Subscribers at a third and a quarter of the tick rate get every third and fourth tick,
/// each decodable on its own (a keyframe they skipped comes before their next delta), with
/// the poses the full-rate subscriber got for those ticks, for fewer bytes.
#[tokio::test]
async fn lower_rate_subscribers_get_every_nth_tick_decodable_and_equal() {
    let metrics = Arc::new(Metrics::new());
    let scene = Scene::new(SceneId("s".into()), 1, metrics, 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    scene
        .add_avatar(common::feed::walking(&rig, "a", 1, 0.0))
        .unwrap();
    let outboxes: Vec<(u32, Arc<Outbox>)> = [1, 3, 4]
        .into_iter()
        .map(|every| (every, Arc::new(Outbox::new())))
        .collect();
    for (i, (every, outbox)) in outboxes.iter().enumerate() {
        scene
            .subscribe(Subscriber::new(
                i as u64,
                outbox.clone(),
                Encoding::Binary,
                None,
                *every,
            ))
            .unwrap();
    }
    let mut readers: Vec<Reader> = outboxes.iter().map(|_| Reader::default()).collect();
    let mut got: Vec<Vec<Frame>> = vec![Vec::new(); outboxes.len()];
    let mut bytes = vec![0usize; outboxes.len()];
    // Keyframes every 10 ticks, which the slower subscribers mostly skip.
    for seq in 1..=120u64 {
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 10);
        for (i, (_, outbox)) in outboxes.iter().enumerate() {
            if outbox.pending_frames() == 0 {
                continue;
            }
            let Ok(Next::Send(messages)) =
                tokio::time::timeout(Duration::from_secs(1), outbox.next()).await
            else {
                panic!("outbox closed")
            };
            for m in messages {
                match m {
                    AxumMessage::Text(t) => {
                        readers[i].text(t.as_str());
                    }
                    AxumMessage::Binary(b) => {
                        bytes[i] += b.len();
                        if let Got::Frame(f) = readers[i].binary(&b) {
                            got[i].push(f);
                        }
                    }
                    other => panic!("unexpected {other:?}"),
                }
            }
        }
    }
    let full: HashMap<u64, &Frame> = got[0].iter().map(|f| (f.seq, f)).collect();
    assert_eq!(full.len(), 120);
    for (i, (every, _)) in outboxes.iter().enumerate().skip(1) {
        let seqs: Vec<u64> = got[i].iter().map(|f| f.seq).collect();
        // Every n-th tick (plus the skipped keyframes, which arrive just before).
        let sent: Vec<u64> = seqs
            .iter()
            .copied()
            .filter(|s| s % u64::from(*every) == 0)
            .collect();
        assert_eq!(sent.len(), 120 / *every as usize, "every {every}: {seqs:?}");
        for f in &got[i] {
            let want = full[&f.seq];
            for (g, w) in f.avatars[0]
                .rotations
                .iter()
                .zip(&want.avatars[0].rotations)
            {
                assert!(angle_between_degrees(*g, *w) < 1e-6, "tick {}", f.seq);
            }
        }
        assert!(
            bytes[i] * 2 < bytes[0],
            "every {every} tick costs {} bytes against {} for all",
            bytes[i],
            bytes[0]
        );
        eprintln!(
            "every {every}th tick: {} frames, {} bytes ({:.0} % of full rate)",
            got[i].len(),
            bytes[i],
            100.0 * bytes[i] as f64 / bytes[0] as f64
        );
    }
}
