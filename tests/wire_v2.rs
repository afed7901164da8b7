//! Wire v2 (protocol version 2) end to end: the scene's feed serving v1 and v2 subscribers
//! side by side, a slow v2 reader and a half-rate one, and v2 readers of joint subsets
//! (protocol version 3) slow and at half rate; and the native client over a real websocket
//! asking for version 2.

#![allow(clippy::unwrap_used)]

mod common;

use common::{CONTROL, server, wait_for};
use posecast_client::net::Client;
use posecast_proto::frame::{Frame, FrameDecoder, FrameKind};
use posecast_proto::frame2::{self, Frame2Decoder, MAX_TRANSLATION_ERROR};
use posecast_proto::msg::{AvatarId, Encoding, SceneId};
use posecast_proto::subset::{JointSet, Selection};
use posecast_server::avatar::Avatar;
use posecast_server::metrics::Metrics;
use posecast_server::scene::Scene;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::Outbox;
use posecast_testkit::ClientBuilder;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

fn assert_same_pose(v1: &Frame, v2: &Frame) {
    assert_eq!(v1.header.seq, v2.header.seq);
    // The server time too (a packed delta's is read from its base frame's).
    assert_eq!(v1.header.server_time_us, v2.header.server_time_us);
    assert_eq!(v1.avatars.len(), v2.avatars.len());
    for (a, b) in v1.avatars.iter().zip(&v2.avatars) {
        assert_eq!(a.avatar_num, b.avatar_num);
        assert_eq!(a.hash, b.hash);
        // The same 48-bit levels decode to bit-identical quaternions.
        assert_eq!(a.rotations, b.rotations, "seq {}", v1.header.seq);
        assert_eq!(a.scales, b.scales);
        assert_eq!(a.placement, b.placement);
        for (x, y) in a.translations.iter().zip(&b.translations) {
            let err = (*x - *y).abs().max_element();
            assert!(f64::from(err) <= MAX_TRANSLATION_ERROR + 1e-6, "{x} vs {y}");
        }
    }
}

/// `frame` with of every avatar only the joints of `selection` (the rig of both avatars).
fn cut(frame: &Frame, selection: &Selection) -> Frame {
    let mut frame = frame.clone();
    for a in &mut frame.avatars {
        a.rotations = Selection::pick(&a.rotations, selection.joint_indices());
        a.translations = Selection::pick(&a.translations, selection.translations.iter().copied());
        a.scales = Selection::pick(&a.scales, selection.scales.iter().copied());
    }
    frame
}

#[tokio::test]
async fn v1_and_v2_subscribers_decode_the_same_poses_even_when_slow() {
    let metrics = Arc::new(Metrics::new());
    let scene = Scene::new(SceneId("s".into()), 1, metrics, 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    let mut description = None;
    for (i, id) in ["a", "b"].into_iter().enumerate() {
        let avatar = Avatar::new(AvatarId(id.into()), i as u32 + 1, rig.clone());
        description = Some(avatar.description.clone());
        scene.add_avatar(avatar).unwrap();
    }
    let description = description.unwrap();
    let sets = [
        JointSet::Depth(2),
        JointSet::Names(vec!["l_wrist".into(), "r_ankle".into()]),
    ];
    let selections = sets.clone().map(|set| set.select(&description));
    assert!(
        selections
            .iter()
            .all(|s| !s.is_all() && !s.joints.is_empty())
    );
    let v1 = Arc::new(Outbox::new());
    let v2 = Arc::new(Outbox::new());
    let slow = Arc::new(Outbox::new());
    let half = Arc::new(Outbox::new());
    let subset_slow = Arc::new(Outbox::new());
    let subset_half = Arc::new(Outbox::new());
    let packed = Arc::new(Outbox::new());
    // Readers of protocol version 7 (the slow one, the half-rate subset and `packed`) get
    // packed deltas (frame kind 3), the others kind 2.
    for (conn, outbox, every, version, joints) in [
        (1, &v1, 1, 1, None),
        (2, &v2, 1, 2, None),
        (3, &slow, 1, 7, None),
        (4, &half, 2, 2, None),
        (5, &subset_slow, 1, 3, Some(sets[0].clone())),
        (6, &subset_half, 2, 7, Some(sets[1].clone())),
        (7, &packed, 1, 7, None),
    ] {
        scene
            .subscribe(
                Subscriber::new(conn, outbox.clone(), Encoding::Binary, None, every)
                    .with_version(version)
                    .with_joints(joints),
            )
            .unwrap();
    }
    let mut d1 = FrameDecoder::new();
    let mut decoders = [
        Frame2Decoder::new(),
        Frame2Decoder::new(),
        Frame2Decoder::new(),
        Frame2Decoder::new(),
        Frame2Decoder::new(),
        Frame2Decoder::new(),
    ];
    let mut by_seq: HashMap<u64, Frame> = HashMap::new();
    let mut kinds = [[0usize; 2]; 6];
    let (mut v1_bytes, mut v2_bytes, mut packed_bytes) = (0usize, 0usize, 0usize);
    // The slow reader reads at irregular ticks: in between, the outbox replaces its frames.
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let ticks = 360u64;
    for seq in 1..=ticks {
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 60);
        for bytes in common::feed::binary_frames(&v1).await {
            let f = d1.decode(&bytes).unwrap();
            v1_bytes += bytes.len();
            by_seq.insert(f.header.seq, f);
        }
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        let slow_read = rng.is_multiple_of(5);
        let reads = [
            true,
            slow_read,
            seq.is_multiple_of(2),
            (rng >> 8).is_multiple_of(3),
            seq.is_multiple_of(2),
            true,
        ];
        let readers = [&v2, &slow, &half, &subset_slow, &subset_half, &packed];
        for (k, outbox) in readers.into_iter().enumerate() {
            if !reads[k] {
                continue;
            }
            for bytes in common::feed::binary_frames(outbox).await {
                assert_eq!(bytes[0], frame2::MAGIC);
                let f = decoders[k]
                    .decode(&bytes)
                    .unwrap_or_else(|e| panic!("reader {k}, tick {seq}: {e}"));
                kinds[k][usize::from(f.header.kind == FrameKind::Delta)] += 1;
                let packs = [1, 4, 5].contains(&k);
                let kind = match f.header.kind {
                    FrameKind::Key => 1,
                    FrameKind::Delta if packs => 3,
                    FrameKind::Delta => 2,
                };
                assert_eq!(bytes[1], kind, "reader {k}, tick {seq}");
                if k == 0 {
                    v2_bytes += bytes.len();
                }
                if k == 5 {
                    packed_bytes += bytes.len();
                }
                let reference = by_seq.get(&f.header.seq).unwrap();
                match k {
                    3 | 4 => assert_same_pose(&cut(reference, &selections[k - 3]), &f),
                    _ => assert_same_pose(reference, &f),
                }
            }
        }
    }
    // The full-rate reader got a keyframe a second (the scene's key interval) and deltas
    // otherwise; the half-rate one deltas too (against 2 ticks back); the slow one keyframes
    // after its gaps, and still some deltas (reads on consecutive ticks).
    assert_eq!(kinds[0][0] + kinds[0][1], ticks as usize);
    assert!(kinds[0][0] <= 2 + ticks as usize / 60, "{kinds:?}");
    assert!(kinds[2][1] >= kinds[2][0] * 5, "{kinds:?}");
    assert!(kinds[1][0] > 0, "{kinds:?}");
    // The subset readers too: deltas against their own frames, keyframes after the gaps.
    assert!(kinds[3][0] > 0 && kinds[3][1] > 0, "{kinds:?}");
    assert!(kinds[4][1] >= kinds[4][0] * 5, "{kinds:?}");
    assert!(
        (v2_bytes as f64) < 0.6 * v1_bytes as f64,
        "v2 {v2_bytes} B vs v1 {v1_bytes} B"
    );
    // The same frames packed: 2.6 bytes a frame less for two avatars (two numbers and flags
    // bytes and a padding, against a first number and two heads in bits; the times here are
    // small, so the header's is not shorter).
    assert_eq!(kinds[5], kinds[0]);
    assert!(
        (v2_bytes - packed_bytes) as f64 >= 2.4 * ticks as f64,
        "packed {packed_bytes} B vs kind 2 {v2_bytes} B"
    );
}

async fn connect(server: &posecast_server::startup::Server, version: u32) -> Client {
    ClientBuilder::new(server.ws_url())
        .encoding(Encoding::Binary)
        .token(Some(CONTROL))
        .options(|o| o.version = version)
        .connect()
        .await
        .unwrap()
        .into_inner()
}

#[tokio::test]
async fn the_native_client_speaks_v2_and_sees_what_a_v1_client_sees() {
    let server = server(60.0).await;
    let c1 = connect(&server, 1).await;
    let c2 = connect(&server, 2).await;
    let id = AvatarId("avatar".into());
    assert!(
        wait_for(10.0, || c1.latest(&id).is_some()
            && c2.latest(&id).is_some())
        .await,
        "no poses"
    );
    // Let a few seconds of v2 deltas through, then compare the newest pose of one tick.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut compared = 0;
    for _ in 0..200 {
        let (a, b) = (c1.latest(&id).unwrap(), c2.latest(&id).unwrap());
        if a.seq == b.seq {
            assert_eq!(a.locals.len(), b.locals.len());
            for (x, y) in a.locals.iter().zip(&b.locals) {
                assert_eq!(x.rotation, y.rotation, "tick {}", a.seq);
                assert!(
                    f64::from((x.translation - y.translation).abs().max_element())
                        <= MAX_TRANSLATION_ERROR + 1e-6
                );
            }
            compared += 1;
            if compared >= 5 {
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(7)).await;
    }
    assert!(compared >= 5, "only {compared} common ticks");
    let (s1, s2) = (c1.stats(), c2.stats());
    assert_eq!(s2.undecodable, 0);
    assert!(s2.frames > 30 && s1.frames > 30);
    let per = |s: &posecast_client::net::Stats| s.frame_bytes as f64 / s.frames as f64;
    assert!(
        per(&s2) < 0.6 * per(&s1),
        "v2 {} B vs v1 {} B a frame",
        per(&s2),
        per(&s1)
    );
}

/// A server of before protocol version 2 refuses `hello {version: 9}`, … `{version: 2}` with
/// `unsupported_version` and closes: the native client, asking for 9 by default, says hello
/// again with the version before until it is welcomed with 1 — it works with the old server
/// out of the box.
#[tokio::test]
async fn the_native_client_falls_back_to_version_1_for_an_older_server() {
    use posecast_proto::msg::SUPPORTED_VERSIONS;

    let (addr, hellos) = common::version_1_server().await;
    let client = ClientBuilder::new(format!("ws://{addr}/ws"))
        .connect()
        .await
        .expect("welcomed after falling back");
    assert!(client.is_connected());
    assert_eq!(*hellos.lock().unwrap(), vec![9, 8, 7, 6, 5, 4, 3, 2, 1]);
    assert_eq!(SUPPORTED_VERSIONS, [1, 2, 3, 4, 5, 6, 7, 8, 9]);
    // Any refused version above 1 falls back the same way.
    let mut options = posecast_client::net::ClientOptions::new(format!("ws://{addr}/ws"), "x");
    options.version = 2;
    options.reconnect = false;
    let refused = Client::connect(options).await;
    assert!(
        refused.is_ok(),
        "2 is refused, then 1 welcomed: {refused:?}"
    );
    assert_eq!(
        *hellos.lock().unwrap(),
        vec![9, 8, 7, 6, 5, 4, 3, 2, 1, 2, 1]
    );
}

/// A v2 reader that falls behind — its writer takes what is pending only every fifth tick, so
/// pending deltas pile up to the outbox's bound — keeps getting deltas: each new one takes the
/// place of the newest pending delta, coded against the frames below it, instead of breaking
/// the chain into a keyframe a tick. It decodes every frame to the poses a v1 reader of the same
/// ticks gets, and gets no more keyframes than the scene makes.
#[tokio::test]
async fn a_reader_that_falls_behind_gets_deltas_not_a_keyframe_a_tick() {
    let scene = Scene::new(SceneId("s".into()), 1, Arc::new(Metrics::new()), 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    scene
        .add_avatar(common::feed::walking(&rig, "a", 1, 0.0))
        .unwrap();
    let v1 = Arc::new(Outbox::new());
    let behind = Arc::new(Outbox::new());
    for (conn, outbox, version) in [(1, &v1, 1), (2, &behind, 3)] {
        scene
            .subscribe(
                Subscriber::new(conn, outbox.clone(), Encoding::Binary, None, 1)
                    .with_version(version),
            )
            .unwrap();
    }
    let (mut d1, mut d2) = (FrameDecoder::new(), Frame2Decoder::new());
    let mut by_seq: HashMap<u64, Frame> = HashMap::new();
    let (mut keys, mut deltas) = (0usize, 0usize);
    let ticks = 600u64;
    for seq in 1..=ticks {
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 60);
        for bytes in common::feed::binary_frames(&v1).await {
            let f = d1.decode(&bytes).unwrap();
            by_seq.insert(f.header.seq, f);
        }
        if !seq.is_multiple_of(5) {
            continue;
        }
        for bytes in common::feed::binary_frames(&behind).await {
            let f = d2
                .decode(&bytes)
                .unwrap_or_else(|e| panic!("tick {seq}: {e}"));
            assert_same_pose(&by_seq[&f.header.seq], &f);
            match f.header.kind {
                FrameKind::Key => keys += 1,
                FrameKind::Delta => deltas += 1,
            }
        }
    }
    // The scene's keyframes (one a second) and the first: no keyframe for falling behind.
    assert!(
        keys <= 2 + ticks as usize / 60,
        "{keys} keyframes, {deltas} deltas"
    );
    assert!(
        deltas >= 2 * (ticks as usize / 5) - keys,
        "{keys} keyframes, {deltas} deltas"
    );
}

/// A v2 reader that keeps up gets the scene's keyframes only every `V2_KEY_SECONDS`: between
/// them its chain of deltas continues through the scene's once-a-second keyframes (which a v1
/// reader of the same scene gets), and every frame decodes to the v1 reader's poses. A second
/// avatar added mid-way reaches it as a keyframe (its chain cannot continue without one). A
/// reader at half the rate, whose ticks never fall on the scene's keyframe ticks, gets its own
/// a second later. A reader joining mid-way starts its chain from its first keyframe (the
/// newest cached frame): its next frames are deltas.
#[tokio::test]
async fn a_v2_reader_that_keeps_up_gets_a_keyframe_every_ten_seconds_not_every_second() {
    let scene = Scene::new(SceneId("s".into()), 1, Arc::new(Metrics::new()), 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    scene
        .add_avatar(common::feed::walking(&rig, "a", 1, 0.0))
        .unwrap();
    let v1 = Arc::new(Outbox::new());
    let v2 = Arc::new(Outbox::new());
    let half = Arc::new(Outbox::new());
    for (conn, outbox, version, every) in [(1, &v1, 1, 1), (2, &v2, 5, 1), (3, &half, 6, 2)] {
        scene
            .subscribe(
                Subscriber::new(conn, outbox.clone(), Encoding::Binary, None, every)
                    .with_version(version),
            )
            .unwrap();
    }
    let (mut d1, mut d2, mut dh) = (
        FrameDecoder::new(),
        Frame2Decoder::new(),
        Frame2Decoder::new(),
    );
    let (mut v1_keys, mut v2_keys, mut half_keys) = (Vec::new(), Vec::new(), Vec::new());
    let mut by_seq: HashMap<u64, Frame> = HashMap::new();
    let late = Arc::new(Outbox::new());
    let mut dl = Frame2Decoder::new();
    let mut late_keys = Vec::new();
    let joins = 300u64;
    let ticks = 1500u64;
    let added = 900u64;
    for seq in 1..=ticks {
        if seq == added {
            scene
                .add_avatar(common::feed::walking(&rig, "b", 2, 0.3))
                .unwrap();
        }
        if seq == joins {
            scene
                .subscribe(
                    Subscriber::new(4, late.clone(), Encoding::Binary, None, 1).with_version(6),
                )
                .unwrap();
        }
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 60);
        for bytes in common::feed::binary_frames(&v1).await {
            let f = d1.decode(&bytes).unwrap();
            if f.header.kind == FrameKind::Key {
                v1_keys.push(f.header.seq);
            }
            by_seq.insert(f.header.seq, f);
        }
        for bytes in common::feed::binary_frames(&v2).await {
            let f = d2
                .decode(&bytes)
                .unwrap_or_else(|e| panic!("tick {seq}: {e}"));
            assert_same_pose(&by_seq[&f.header.seq], &f);
            if f.header.kind == FrameKind::Key {
                v2_keys.push(f.header.seq);
            }
        }
        if seq >= joins {
            for bytes in common::feed::binary_frames(&late).await {
                let f = dl
                    .decode(&bytes)
                    .unwrap_or_else(|e| panic!("tick {seq}: {e}"));
                assert_same_pose(&by_seq[&f.header.seq], &f);
                if f.header.kind == FrameKind::Key {
                    late_keys.push(f.header.seq);
                }
            }
        }
        // It holds frames on the ticks it is due (even ones), and its first at once.
        if seq != 1 && !seq.is_multiple_of(2) {
            continue;
        }
        for bytes in common::feed::binary_frames(&half).await {
            let f = dh
                .decode(&bytes)
                .unwrap_or_else(|e| panic!("tick {seq}: {e}"));
            // (Its first frame, made when it subscribed before the first tick, is of tick 0.)
            if f.header.seq == 0 {
                continue;
            }
            assert_same_pose(&by_seq[&f.header.seq], &f);
            if f.header.kind == FrameKind::Key {
                half_keys.push(f.header.seq);
            }
        }
    }
    // Until the added avatar the scene's keyframe ticks are odd (1, 61, …) and the half-rate
    // reader's ticks even: its second keyframe comes 11 s after its first. From the added
    // avatar's keyframe (900) on they are even, and its next one comes 10 s after.
    assert!(v1_keys[..15].iter().all(|k| k % 2 == 1), "{v1_keys:?}");
    assert_eq!(half_keys.len(), 4, "half-rate keyframes at {half_keys:?}");
    assert_eq!(half_keys[1] - half_keys[0], 660, "{half_keys:?}");
    assert_eq!(half_keys[2], added, "{half_keys:?}");
    assert_eq!(half_keys[3] - half_keys[2], 600, "{half_keys:?}");
    // The late joiner: the newest cached frame as its keyframe, then deltas until the added
    // avatar's keyframe, and one 10 s after that.
    assert_eq!(
        late_keys,
        vec![joins - 1, added, added + 600],
        "late joiner"
    );
    assert!(v1_keys.len() >= 25, "v1 keyframes at {v1_keys:?}");
    // The first, one ten seconds after it, the added avatar's, one ten seconds after that.
    assert_eq!(v2_keys.len(), 4, "v2 keyframes at {v2_keys:?}");
    assert_eq!(v2_keys[1] - v2_keys[0], 600, "v2 keyframes at {v2_keys:?}");
    assert_eq!(v2_keys[2], added, "v2 keyframes at {v2_keys:?}");
    assert_eq!(v2_keys[3] - v2_keys[2], 600, "v2 keyframes at {v2_keys:?}");
}
