//! Joint subsets (`subscribe … joints`): a subscriber asking for the joints to depth 2, or for
//! a named joint (the built-in H-Anim rig's `l_wrist`), gets frames of those joints only — fewer bytes — and poses whose selected
//! joints are exactly what a full subscriber decodes at the same tick (binary: the same
//! quantised bits; JSON: within the quantisation bound of them), every other joint at rest —
//! on wire v1 and, cut alike and delta-coded against the subset's own frames, on wire v2.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_client::net::client::{Event, PoseSample};
use posecast_proto::frame::HEADER_BYTES;
use posecast_proto::frame2;
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, ErrorCode, SceneId};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_proto::subset::JointSet;
use posecast_testkit::{TestClient, TestServer};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

/// Every pose of `avatar` each client sees during `span`, by tick.
async fn collect(
    clients: &[&TestClient],
    avatar: &AvatarId,
    span: Duration,
) -> Vec<BTreeMap<u64, PoseSample>> {
    let mut seen = vec![BTreeMap::new(); clients.len()];
    let end = Instant::now() + span;
    while Instant::now() < end {
        for (client, seen) in clients.iter().zip(&mut seen) {
            if let Some(p) = client.latest(avatar) {
                seen.insert(p.seq, p);
            }
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn subsets_carry_exactly_the_selected_joints_for_fewer_bytes() {
    let server = TestServer::builder().tick_rate(30.0).start().await.unwrap();
    let avatar = AvatarId("avatar".into());
    // The reference: every joint, wire v1, f32 translations.
    let full = server
        .client_builder()
        .options(|o| o.version = 1)
        .connect()
        .await
        .unwrap();
    let depth = server
        .client_builder()
        .options(|o| {
            o.joints = Some(JointSet::Depth(2));
            o.version = 1;
        })
        .connect()
        .await
        .unwrap();
    // A connection of protocol version 3 (the client's default) gets a subset as v2 frames cut
    // to it: fewer bytes than every joint on v2 (the reference below), and than the same
    // subset on v1.
    let full_v2 = server.client_builder().connect().await.unwrap();
    let depth_v2 = server
        .client_builder()
        .options(|o| o.joints = Some(JointSet::Depth(2)))
        .connect()
        .await
        .unwrap();
    // Version 2 still gets it as v1 frames cut to it (told apart by the first byte).
    let depth_version_2 = server
        .client_builder()
        .options(|o| {
            o.joints = Some(JointSet::Depth(2));
            o.version = 2;
        })
        .connect()
        .await
        .unwrap();
    let hand = server
        .client_builder()
        .encoding(Encoding::Json)
        .options(|o| o.joints = Some(JointSet::Names(vec!["l_wrist".into()])))
        .connect()
        .await
        .unwrap();
    for c in [&full, &depth, &hand, &depth_v2, &full_v2, &depth_version_2] {
        c.first_pose("avatar", Duration::from_secs(10))
            .await
            .unwrap();
    }
    let view = full.avatar(&avatar).unwrap();
    let skeleton = view.skeleton.clone();
    let description = view.description.clone();
    let depth_joints = JointSet::Depth(2).select(&description);
    let hand_joints = JointSet::Names(vec!["l_wrist".into()]).select(&description);
    // What each selects of the built-in rig, by hand: the hand and its chain to the root.
    let name = |j: &u16| description.joint_names[usize::from(*j)].as_str();
    let chain: Vec<&str> = hand_joints.joints.iter().map(name).collect();
    assert_eq!(
        chain,
        [
            "humanoid_root",
            "vl5",
            "vt10",
            "vt1",
            "l_sternoclavicular",
            "l_shoulder",
            "l_elbow",
            "l_wrist"
        ],
        "{chain:?}"
    );
    assert!(depth_joints.joints.len() < description.len());
    assert_eq!(
        depth.avatar(&avatar).unwrap().selection,
        Some(depth_joints.clone())
    );

    let clients = [&full, &depth, &hand, &depth_v2, &full_v2, &depth_version_2];
    let before: Vec<_> = clients.iter().map(|c| c.stats()).collect();
    let seen = collect(&clients, &avatar, Duration::from_secs(3)).await;
    let after: Vec<_> = clients.iter().map(|c| c.stats()).collect();

    let rest = skeleton.rest();
    let mut compared = [0usize; 3];
    for (k, (poses, selection)) in [
        (&seen[1], &depth_joints),
        (&seen[2], &hand_joints),
        (&seen[3], &depth_joints),
    ]
    .into_iter()
    .enumerate()
    {
        let bound = if k == 1 { MAX_ERROR_DEGREES } else { 0.0 };
        // v2 quantises translations (v1 sends f32).
        let reach = if k == 2 {
            frame2::MAX_TRANSLATION_ERROR as f32 * 1.01
        } else {
            1e-6
        };
        for (seq, pose) in poses {
            let Some(reference) = seen[0].get(seq) else {
                continue;
            };
            compared[k] += 1;
            assert_eq!(pose.placement, reference.placement);
            for (j, (&got, &at_rest)) in pose.locals.iter().zip(rest).enumerate() {
                if selection.joints.contains(&(j as u16)) {
                    let err = angle_between_degrees(got.rotation, reference.locals[j].rotation);
                    assert!(
                        err <= bound,
                        "tick {seq}, joint {}: {err}° from the full stream",
                        name(&(j as u16))
                    );
                    assert!(
                        (got.translation - reference.locals[j].translation)
                            .abs()
                            .max_element()
                            <= reach,
                        "client {k}, tick {seq}, joint {j}: translation {} against {}",
                        got.translation,
                        reference.locals[j].translation
                    );
                } else {
                    assert_eq!(got, at_rest, "tick {seq}: joint {j} not sent is at rest");
                }
            }
        }
    }
    assert!(
        compared[0] >= 30 && compared[1] >= 30 && compared[2] >= 30,
        "ticks compared: {compared:?}"
    );
    // Deltas as well as keyframes reached the subset subscriber, and it decoded them all.
    let frames = |i: usize| after[i].frames - before[i].frames;
    let bytes = |i: usize| (after[i].frame_bytes - before[i].frame_bytes) as f64 / frames(i) as f64;
    assert!(after[1].keyframes - before[1].keyframes < frames(1));
    assert_eq!(after[1].undecodable, 0);
    assert_eq!(after[2].undecodable, 0);
    assert_eq!(after[3].undecodable, 0);
    assert_eq!(after[4].undecodable, 0);
    assert_eq!(after[5].undecodable, 0);
    assert!(after[3].keyframes - before[3].keyframes < frames(3));
    // Fewer bytes: the frame header, chunk head and root translation stay (one avatar, no
    // placement), the rotations shrink with the joints.
    let fixed = (HEADER_BYTES + 18 + 12 * description.translated_joints.len()) as f64;
    let payload = |i: usize| bytes(i) - fixed;
    let joint_share = depth_joints.joints.len() as f64 / description.len() as f64;
    println!(
        "v1 frame: all {} joints {:.1} B (rotations {:.1} B), depth ≤ 2 ({} joints) {:.1} B (rotations {:.1} B = {:.2}× for {:.2}× the joints); JSON hand chain ({} joints) {:.0} B; v2 frame: all joints {:.1} B, depth ≤ 2 {:.1} B",
        description.len(),
        bytes(0),
        payload(0),
        depth_joints.joints.len(),
        bytes(1),
        payload(1),
        payload(1) / payload(0),
        joint_share,
        hand_joints.joints.len(),
        bytes(2),
        bytes(4),
        bytes(3),
    );
    assert!(
        payload(1) < 0.6 * payload(0),
        "rotations {:.1} B of {:.1} B",
        payload(1),
        payload(0)
    );
    // Wire v2 cut to the subset: smaller than v2 of every joint (a subset served as v1, as it
    // once was, is larger than that) and than the subset on v1.
    assert!(
        bytes(3) < bytes(4) && bytes(3) < bytes(1),
        "v2 depth ≤ 2 {:.1} B, v2 all {:.1} B, v1 depth ≤ 2 {:.1} B",
        bytes(3),
        bytes(4),
        bytes(1)
    );
    // Version 2's subset frames are v1 ones: larger than v2 frames of every joint.
    assert!(
        bytes(5) > bytes(4),
        "version 2, depth ≤ 2: {:.1} B; v2 all joints {:.1} B",
        bytes(5),
        bytes(4)
    );
    server.stop().await;
}

#[tokio::test]
async fn a_malformed_joint_set_is_refused_and_subscribes_nothing() {
    let server = TestServer::builder().start().await.unwrap();
    let client = server
        .client_builder()
        .options(|o| o.subscriptions.clear())
        .connect()
        .await
        .unwrap();
    let mut events = client.events();
    client
        .send(ClientMsg::Subscribe {
            scene: SceneId("default".into()),
            avatars: None,
            rate: None,
            joints: Some(JointSet::Names(vec![])),
            morph_weights: None,
            precision: None,
        })
        .await
        .unwrap();
    let error = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            if let Ok(Event::Error(e)) = events.recv().await {
                return e;
            }
        }
    })
    .await
    .unwrap();
    assert_eq!(error.code, ErrorCode::InvalidValue, "{error:?}");
    assert!(error.message.contains("at least one"), "{error:?}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(
        client.avatars().is_empty(),
        "no description after a refusal"
    );
    assert_eq!(client.stats().frames, 0);
    server.stop().await;
}
