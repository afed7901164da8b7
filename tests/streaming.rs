//! End-to-end streaming: server in-process on port 0, real websocket clients.

#![allow(clippy::unwrap_used)]

mod common;

use axum::extract::ws::Message as AxumMessage;
use common::{client, next_text, raw, server, wait_for};
use futures_util::{Sink, SinkExt};
use glam::Quat;
use posecast_proto::Transform;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::frame::FrameDecoder;
use posecast_proto::msg::SceneId;
use posecast_proto::msg::{AvatarId, Encoding, ErrorCode, MAX_CLIENT_MESSAGE_BYTES, ServerMsg};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_server::avatar::Avatar;
use posecast_server::import;
use posecast_server::metrics::Metrics;
use posecast_server::scene::Scene;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::{MAX_CONTROL_BYTES, MAX_PENDING_DELTAS, Outbox};
use posecast_server::stream::writer::run_writer;
use posecast_testkit::DEFAULT_TIMEOUT;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

const AVATAR: &str = "avatar";

fn avatar() -> AvatarId {
    AvatarId(AVATAR.into())
}

/// How far (in distance) a streamed translation may be from the server's: binary frames of
/// wire v2 (the native client's default) quantise each component to 1/8192 m, so a
/// translation may be √3 half-steps off; v1 and JSON send f32.
const TRANSLATION: f32 = 1.733 * posecast_proto::frame2::MAX_TRANSLATION_ERROR as f32 + 1e-6;

/// The worst rotation error between two poses, degrees, and the worst translation error.
fn pose_error(a: &[Transform], b: &[Transform]) -> (f64, f32) {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).fold((0.0, 0.0), |(r, t), (x, y)| {
        (
            r.max(angle_between_degrees(x.rotation, y.rotation)),
            t.max(x.translation.distance(y.translation)),
        )
    })
}

/// Pauses `avatar` at clip time `time` and waits until the client holds a pose from a tick
/// after the command.
async fn pause_at(c: &posecast_client::net::Client, avatar: &AvatarId, time: f32) {
    c.command(Command::Pause {
        avatar: avatar.clone(),
    })
    .await
    .unwrap();
    c.command(Command::Seek {
        avatar: avatar.clone(),
        time,
    })
    .await
    .unwrap();
    let after = c.latest(avatar).map_or(0, |p| p.seq);
    assert!(
        wait_for(3.0, || c.latest(avatar).is_some_and(|p| p.seq > after + 1)).await,
        "no frame after the seek"
    );
}

/// Issue 38 (`--ws-direct-writes`): a reading client's frames go into its socket from the
/// tick's fan-out, with no task woken per frame. A writer task wakes only for a full socket or a close; a loopback
/// client that reads never fills its socket, so over hundreds of frames to four clients the
/// writers wake almost never (a writer woken per frame, or per batch as the websocket's
/// writer once was, would wake about once a frame).
#[tokio::test]
async fn frames_reach_reading_clients_without_a_writer_woken_per_frame() {
    let server = common::kit_builder(60.0)
        .configure(|c| c.net.ws_direct_writes = true)
        .start()
        .await
        .unwrap();
    let mut clients = Vec::new();
    for _ in 0..4 {
        let c = server.client().await.unwrap();
        c.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
        clients.push(c);
    }
    let (start_sent, start_wakes) = (
        common::metric(server.addr, "posecast_messages_sent_total").await,
        common::metric(server.addr, "posecast_writer_wakes_total").await,
    );
    let mut sent = start_sent;
    while sent < start_sent + 480.0 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        sent = common::metric(server.addr, "posecast_messages_sent_total").await;
    }
    let wakes = common::metric(server.addr, "posecast_writer_wakes_total").await - start_wakes;
    // Every client still decodes the stream (the bytes written are whole frames in order).
    for c in &clients {
        let seq = c.latest(&avatar()).unwrap().seq;
        assert!(wait_for(10.0, || c.latest(&avatar()).is_some_and(|p| p.seq > seq)).await);
    }
    assert!(
        wakes * 20.0 <= sent - start_sent,
        "{wakes} writer wake-ups for {} messages",
        sent - start_sent
    );
}

#[tokio::test]
async fn built_in_avatar_streams_the_clip_it_plays() {
    let server = common::kit_server(60.0).await;
    let c = server.client().await.unwrap();
    c.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    let view = c.avatar(&avatar()).unwrap();
    // The description is the server's rig.
    let rig = posecast_server::builtin::rig().unwrap();
    assert_eq!(view.skeleton.names(), rig.skeleton().names());
    assert_eq!(view.skeleton.parents(), rig.skeleton().parents());
    assert_eq!(view.skeleton.inverse_bind(), rig.skeleton().inverse_bind());
    assert_eq!(view.skeleton.rest(), rig.skeleton().rest());
    // Decoded poses equal the clip sampled independently at the same time.
    for (clip, time) in [("walk", 0.3f32), ("wave", 1.1), ("idle", 2.0)] {
        c.command(Command::Play {
            avatar: avatar(),
            clip: clip.into(),
            from_asset: None,
            speed: None,
            looping: None,
            start: None,
            fade: Some(0.0),
            // Authored root translation: compared with raw clip samples.
            root_motion: Some(posecast_proto::command::RootMotion::Accumulate),
        })
        .await
        .unwrap();
        c.command(Command::Pause { avatar: avatar() })
            .await
            .unwrap();
        c.command(Command::Seek {
            avatar: avatar(),
            time,
        })
        .await
        .unwrap();
        let got = c.fresh_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
        let expected = server.clip_pose(AVATAR, clip, time).unwrap();
        got.assert_near(&expected, MAX_ERROR_DEGREES).unwrap();
        let (_, trans) = pose_error(got.locals(), &expected);
        assert!(trans <= TRANSLATION, "{clip:?}: translation error {trans}");
    }
    server.stop().await;
}

#[tokio::test]
async fn a_testdata_rig_streams_its_clip() {
    let Some(path) =
        posecast_proto::testing::require_testdata("gltf/CesiumMan/glTF-Binary/CesiumMan.glb")
    else {
        return;
    };
    let server = server(60.0).await;
    let mut asset = import::load_path(&path).unwrap().remove(0);
    asset.name = "cesium".into();
    server
        .state
        .world
        .library
        .insert(posecast_server::rig::Rig::from_asset(asset, &Default::default()).unwrap());
    let c = client(&server, Encoding::Binary).await;
    let reply = c
        .command(Command::AddAvatar {
            scene: SceneId("default".into()),
            asset: "cesium".into(),
            avatar: Some(AvatarId("cesium-1".into())),
            clip: None,
            position: None,
            rotation: None,
        })
        .await
        .unwrap()
        .to_value();
    assert_eq!(reply["avatar"], "cesium-1");
    let id = AvatarId("cesium-1".into());
    let rig = server.state.world.library.get("cesium").unwrap();
    let clip_name = rig.clips[0].name().to_string();
    c.command(Command::Play {
        avatar: id.clone(),
        clip: clip_name,
        from_asset: None,
        speed: None,
        looping: None,
        start: None,
        fade: Some(0.0),
        // Authored root translation: compared with raw clip samples.
        root_motion: Some(posecast_proto::command::RootMotion::Accumulate),
    })
    .await
    .unwrap();
    assert!(wait_for(3.0, || c.latest(&id).is_some()).await);
    pause_at(&c, &id, 0.5).await;
    let got = c.latest(&id).unwrap().locals;
    let clip = &rig.clips[0];
    let mut expected = rig.skeleton().rest().to_vec();
    clip.sample(clip.start() + 0.5, rig.skeleton().rest(), &mut expected);
    let (rot, trans) = pose_error(&got, &expected);
    assert!(rot <= MAX_ERROR_DEGREES, "rotation error {rot}°");
    assert!(trans <= TRANSLATION + 1e-5, "translation error {trans}");
    server.stop().await;
}

#[tokio::test]
async fn a_late_joiner_gets_the_cached_frame_at_once_in_either_encoding() {
    // One tick every 5 s (key_interval rounds up to one tick, so every tick is a keyframe):
    // the first frame a late joiner gets must be the cached one — the last tick's seq, long
    // before the next tick could deliver one.
    let server = server(0.2).await;
    let first = client(&server, Encoding::Binary).await;
    assert!(wait_for(3.0, || first.latest(&avatar()).is_some()).await);
    for encoding in [Encoding::Binary, Encoding::Json] {
        let seen = first.latest(&avatar()).unwrap();
        let started = Instant::now();
        let late = client(&server, encoding).await;
        assert!(
            wait_for(2.0, || late.latest(&avatar()).is_some()).await,
            "{encoding:?} late joiner got no pose within 2 s of a 5 s tick"
        );
        let elapsed = started.elapsed();
        let got = late.latest(&avatar()).unwrap();
        let now_seen = first.latest(&avatar()).unwrap();
        // Normally `seen`; a tick may fall between the two reads on a slow machine, and then
        // the cached frame is that one.
        let cached = if got.seq == seen.seq {
            &seen
        } else {
            &now_seen
        };
        assert_eq!(
            got.seq, cached.seq,
            "{encoding:?} late joiner's first frame is tick {} (ticks seen: {}, {})",
            got.seq, seen.seq, now_seen.seq
        );
        assert_eq!(
            late.stats().frames,
            1,
            "{encoding:?}: exactly the cached frame"
        );
        assert!(elapsed < Duration::from_secs(2), "took {elapsed:?}");
        // Its content is that tick's pose (the binary client decoded the same tick).
        let (rot, trans) = pose_error(&got.locals, &cached.locals);
        assert!(
            rot <= MAX_ERROR_DEGREES,
            "{encoding:?}: {rot}° off the cached pose"
        );
        assert!(
            trans <= TRANSLATION,
            "{encoding:?}: translation {trans} off"
        );
        assert!(
            late.avatar(&avatar()).is_some(),
            "description arrived with the pose"
        );
    }
    server.stop().await;
}

/// A websocket peer that never reads: its sink is never ready.
struct NeverReady;

impl Sink<AxumMessage> for NeverReady {
    type Error = std::convert::Infallible;
    fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Pending
    }
    fn start_send(self: Pin<&mut Self>, _: AxumMessage) -> Result<(), Self::Error> {
        unreachable!("start_send without poll_ready")
    }
    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Pending
    }
    fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Pending
    }
}

/// A websocket peer that reads everything at once.
#[derive(Clone, Default)]
struct Reader(Arc<Mutex<Vec<AxumMessage>>>);

impl Sink<AxumMessage> for Reader {
    type Error = std::convert::Infallible;
    fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
    fn start_send(self: Pin<&mut Self>, m: AxumMessage) -> Result<(), Self::Error> {
        self.0.lock().unwrap().push(m);
        Ok(())
    }
    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
    fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
}

#[tokio::test]
async fn a_stalled_subscriber_loses_frames_not_memory_and_delays_no_one() {
    // The outbox and the real writer loop, against a peer whose sink is never ready — what a
    // client that stops reading looks like once the socket buffers are full.
    let metrics = Arc::new(Metrics::new());
    let scene = Scene::new(SceneId("s".into()), 1, metrics.clone(), 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    scene
        .add_avatar(Avatar::new(avatar(), 1, rig.clone()))
        .unwrap();
    let stalled = Arc::new(Outbox::new());
    let reading = Arc::new(Outbox::new());
    // A writer that never gets to run (a busy host): its frames replace each other too, but
    // no socket held it.
    let late = Arc::new(Outbox::new());
    for (conn, outbox, encoding) in [
        (1, &stalled, Encoding::Json),
        (2, &reading, Encoding::Binary),
        (3, &late, Encoding::Binary),
    ] {
        scene
            .subscribe(Subscriber::new(conn, outbox.clone(), encoding, None, 1))
            .unwrap();
    }
    let stalled_writer = tokio::spawn({
        let (outbox, metrics) = (stalled.clone(), metrics.clone());
        async move { run_writer(&outbox, NeverReady, &*metrics).await }
    });
    let received = Reader::default();
    let reading_writer = tokio::spawn({
        let (outbox, metrics, sink) = (reading.clone(), metrics.clone(), received.clone());
        async move { run_writer(&outbox, sink, &*metrics).await }
    });
    let ticks = 600u64;
    let mut max_pending = 0;
    for seq in 1..=ticks {
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 60);
        // A stalled peer also keeps asking for things (pings, commands): their answers queue.
        stalled.push_control(AxumMessage::Text("x".repeat(1000).into()));
        max_pending = max_pending.max(stalled.pending_frames());
        assert!(stalled.control_bytes() <= MAX_CONTROL_BYTES);
        tokio::task::yield_now().await;
    }
    // The writer took the first batch and is stuck sending it; every frame since pushed the
    // oldest out of its slot (a keyframe and at most MAX_PENDING_DELTAS deltas).
    assert!(
        stalled.dropped_frames() >= ticks - 3 - MAX_PENDING_DELTAS as u64,
        "only {} of {ticks} frames dropped",
        stalled.dropped_frames()
    );
    assert!(
        max_pending <= 1 + MAX_PENDING_DELTAS,
        "the stalled outbox held {max_pending} frames"
    );
    // Those count as the link's backpressure (the adaptive rate's signal); the late writer's
    // as much lost, but not the link's doing.
    assert!(
        stalled.dropped_while_held() >= ticks - 3 - MAX_PENDING_DELTAS as u64,
        "only {} of {} dropped while the socket held the writer",
        stalled.dropped_while_held(),
        stalled.dropped_frames()
    );
    assert!(late.dropped_frames() >= ticks - 3 - MAX_PENDING_DELTAS as u64);
    assert_eq!(late.dropped_while_held(), 0);
    assert!(
        !stalled.overflowed(),
        "600 kB of answers is under the bound"
    );
    // Past the byte bound it is a client that does not read: closed.
    let mut pushed = 0;
    while stalled.push_control(AxumMessage::Text("x".repeat(64 << 10).into())) {
        pushed += 64 << 10;
        assert!(pushed <= MAX_CONTROL_BYTES + (64 << 10), "never overflowed");
    }
    assert!(stalled.overflowed());
    assert_eq!(
        stalled.pending_frames(),
        0,
        "an overflowed outbox frees its frames"
    );
    // The reading subscriber got every tick, in order, all decodable.
    for _ in 0..100 {
        if received.0.lock().unwrap().len() >= 2 + ticks as usize {
            break;
        }
        tokio::task::yield_now().await;
    }
    let messages = received.0.lock().unwrap().clone();
    let mut decoder = FrameDecoder::new();
    let seqs: Vec<u64> = messages
        .iter()
        .filter_map(|m| match m {
            AxumMessage::Binary(b) => Some(decoder.decode(b).unwrap().header.seq),
            _ => None,
        })
        .collect();
    assert_eq!(seqs, (1..=ticks).collect::<Vec<_>>());
    assert_eq!(reading.dropped_frames(), 0);
    stalled_writer.abort();
    reading_writer.abort();
}

#[tokio::test]
async fn malformed_input_gets_typed_errors_and_harms_no_one() {
    let server = server(60.0).await;
    let watcher = client(&server, Encoding::Binary).await;
    assert!(wait_for(3.0, || watcher.latest(&avatar()).is_some()).await);
    let mut ws = raw(&server, Encoding::Json).await;
    let send = |text: String| Message::Text(text.into());
    let expect = async |ws: &mut common::Ws, msg: Message, code: ErrorCode| {
        ws.send(msg).await.unwrap();
        loop {
            match next_text(ws).await {
                Some(ServerMsg::Error(e)) => {
                    assert_eq!(e.code, code, "{e:?}");
                    return;
                }
                Some(_) => {}
                None => panic!("connection closed instead of {code:?}"),
            }
        }
    };
    expect(
        &mut ws,
        Message::Binary(vec![0xde, 0xad, 0xbe, 0xef].into()),
        ErrorCode::UnexpectedBinary,
    )
    .await;
    expect(&mut ws, send("{not json".into()), ErrorCode::BadMessage).await;
    expect(
        &mut ws,
        send(r#"{"type":"teleport"}"#.into()),
        ErrorCode::BadMessage,
    )
    .await;
    expect(
        &mut ws,
        send(r#"{"type":"subscribe","scene":"nowhere"}"#.into()),
        ErrorCode::UnknownScene,
    )
    .await;
    let nan = r#"{"type":"command","id":7,"command":{"op":"set_joint_rotation","avatar":"avatar","joint":"l_elbow","rotation":[0,0,0,0]}}"#;
    expect(&mut ws, send(nan.into()), ErrorCode::InvalidValue).await;
    let huge = r#"{"type":"command","id":8,"command":{"op":"set_joint_rotation","avatar":"avatar","joint":"l_elbow","rotation":[1e999,0,0,1]}}"#;
    expect(&mut ws, send(huge.into()), ErrorCode::BadMessage).await;
    expect(
        &mut ws,
        send(r#"{"type":"hello","version":1,"encoding":"json"}"#.into()),
        ErrorCode::NotAllowedNow,
    )
    .await;
    // Still alive after all that: a ping is answered.
    ws.send(send(r#"{"type":"ping","id":1,"client_time_us":5}"#.into()))
        .await
        .unwrap();
    assert!(matches!(
        next_text(&mut ws).await,
        Some(ServerMsg::Pong {
            id: 1,
            client_time_us: 5,
            ..
        })
    ));

    // Wrong protocol version: typed error, then a close.
    let (mut v, _) = tokio_tungstenite::connect_async(server.ws_url())
        .await
        .unwrap();
    v.send(send(
        r#"{"type":"hello","version":99,"encoding":"binary"}"#.into(),
    ))
    .await
    .unwrap();
    match next_text(&mut v).await {
        Some(ServerMsg::Error(e)) => assert_eq!(e.code, ErrorCode::UnsupportedVersion),
        other => panic!("expected unsupported_version, got {other:?}"),
    }
    assert!(next_text(&mut v).await.is_none(), "connection should close");

    // Oversized message: typed error or clean close, never a crash.
    let mut big = raw(&server, Encoding::Json).await;
    let padding = "x".repeat(MAX_CLIENT_MESSAGE_BYTES + 10);
    big.send(send(format!(
        r#"{{"type":"ping","id":1,"client_time_us":0,"pad":"{padding}"}}"#
    )))
    .await
    .ok();
    match next_text(&mut big).await {
        Some(ServerMsg::Error(e)) => assert_eq!(e.code, ErrorCode::MessageTooLarge),
        None => {}
        other => panic!("unexpected {other:?}"),
    }

    // The other connection never noticed.
    let before = watcher.latest(&avatar()).unwrap().seq;
    assert!(
        wait_for(2.0, || watcher
            .latest(&avatar())
            .is_some_and(|p| p.seq > before + 5))
        .await
    );
    assert_eq!(watcher.stats().undecodable, 0);
    server.stop().await;
}

#[tokio::test]
async fn binary_and_json_subscribers_decode_the_same_poses() {
    let server = common::kit_server(60.0).await;
    let b = server.client().await.unwrap();
    let j = server
        .client_builder()
        .encoding(Encoding::Json)
        .connect()
        .await
        .unwrap();
    b.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    j.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    let q = Quat::from_rotation_z(0.7);
    let set = b
        .command(Command::SetJointRotation {
            avatar: avatar(),
            joint: "r_elbow".into(),
            rotation: q.to_array(),
        })
        .await
        .unwrap();
    // The typed answer: the rotation set (no limits on the elbow's z turn this far).
    let CommandResult::Rotation { rotation } = set else {
        panic!("set_joint_rotation answered {set:?}");
    };
    assert!(angle_between_degrees(Quat::from_array(rotation), q) <= 1e-3);
    pause_at(&b, &avatar(), 1.0).await;
    let target = b.pose(AVATAR).unwrap().seq();
    let json = j
        .wait_for_pose(AVATAR, DEFAULT_TIMEOUT, |p| p.seq() >= target)
        .await
        .unwrap();
    let binary = b.pose(AVATAR).unwrap();
    binary
        .assert_near(json.locals(), MAX_ERROR_DEGREES)
        .unwrap();
    let (_, trans) = pose_error(binary.locals(), json.locals());
    assert!(trans <= TRANSLATION, "translation {trans} off");
    let got = binary.rotation("r_elbow").unwrap();
    assert!(angle_between_degrees(got, q) <= MAX_ERROR_DEGREES);
    server.stop().await;
}

#[tokio::test]
async fn world_space_increment_moves_the_joint_by_exactly_u() {
    let server = server(60.0).await;
    let c = client(&server, Encoding::Binary).await;
    assert!(wait_for(3.0, || c.latest(&avatar()).is_some()).await);
    pause_at(&c, &avatar(), 0.5).await;
    let view = c.avatar(&avatar()).unwrap();
    let elbow = view.skeleton.find("l_elbow").unwrap();
    let world = |locals: &[Transform]| {
        let mut w = vec![glam::Mat4::IDENTITY; locals.len()];
        posecast_proto::fk::forward_kinematics(&view.skeleton, locals, &mut w);
        w
    };
    let before = world(&c.latest(&avatar()).unwrap().locals)[elbow];
    let u = Quat::from_rotation_x(0.4);
    c.command(Command::RotateJointWorld {
        avatar: avatar(),
        joint: "l_elbow".into(),
        rotation: u.to_array(),
    })
    .await
    .unwrap();
    let seq = c.latest(&avatar()).unwrap().seq;
    assert!(wait_for(2.0, || c.latest(&avatar()).is_some_and(|p| p.seq > seq + 1)).await);
    let after = world(&c.latest(&avatar()).unwrap().locals)[elbow];
    // W' = U W about the joint's own position: same position, rotation U·R.
    let (_, r_before, p_before) = before.to_scale_rotation_translation();
    let (_, r_after, p_after) = after.to_scale_rotation_translation();
    assert!(
        p_before.distance(p_after) < 1e-4,
        "the elbow moved by {}",
        p_before.distance(p_after)
    );
    let err = angle_between_degrees(r_after, u * r_before);
    // Quantisation of the chain's rotations compounds a little.
    assert!(err < 0.05, "world rotation off by {err}°");
    server.stop().await;
}
