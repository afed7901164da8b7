//! Precision per subscription (protocol versions 5 and 6): subscribers of one scene at different
//! precisions, rates and joint sets, each decoding every rotation within its joint's bound of
//! the pose the server streamed, with fewer bytes the coarser it asked; a world-space bound
//! held at the virtual vertices it names; and the refusals (out of range, JSON, an earlier
//! version) over a real websocket.

#![allow(clippy::unwrap_used)]

mod common;

use common::{CONTROL, Ws, server};
use futures_util::{SinkExt, StreamExt};
use glam::{Mat4, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::frame::{AvatarPose, Frame};
use posecast_proto::frame2::{Frame2Decoder, MAX_TRANSLATION_ERROR};
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, ErrorCode, SceneId, ServerMsg};
use posecast_proto::precision::{Precision, rotation_bound_degrees, translation_bound};
use posecast_proto::quant;
use posecast_proto::subset::JointSet;
use posecast_server::metrics::Metrics;
use posecast_server::scene::Scene;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::Outbox;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

fn degrees(d: f32) -> Precision {
    Precision {
        degrees: Some(d),
        ..Precision::FINEST
    }
}

/// Every joint of `got` (of the joints `joints`, in order) within its step's bound of
/// `source`; every translation within the translation step's.
fn assert_within(
    source: &AvatarPose,
    got: &AvatarPose,
    steps: &[u8],
    t_step: u16,
    joints: &[usize],
) {
    for (k, &j) in joints.iter().enumerate() {
        let angle = quant::angle_between_degrees(source.rotations[j], got.rotations[k]);
        let bound = rotation_bound_degrees(steps[j]);
        assert!(
            angle <= bound,
            "joint {j}: {angle}° > {bound}° (step {})",
            steps[j]
        );
    }
    if joints.len() == source.rotations.len() {
        for (x, y) in source.translations.iter().zip(&got.translations) {
            let err = f64::from((*x - *y).abs().max_element());
            assert!(
                err <= translation_bound(t_step) + 1e-6,
                "translation off by {err}"
            );
        }
    }
}

/// Six subscribers of one scene of two walking avatars: the finest (v5 without a precision),
/// 0.1° at full rate and reading at random ticks, 0.25° at half rate cut to a joint subset, a
/// world-space 5 mm, and 0.01° (no coarser than the finest: served the finest frames). Every
/// decoded rotation is within its joint's bound of the pose the scene streamed that tick, the
/// 5 mm one within 5 mm at every virtual vertex 3 cm from a joint (and coarser than the
/// finest there), and the bytes fall with the precision.
#[tokio::test]
async fn subscribers_at_different_precisions_each_decode_within_their_bound() {
    let scene = Scene::new(SceneId("s".into()), 1, Arc::new(Metrics::new()), 60.0);
    let rig = Arc::new(posecast_server::builtin::rig().unwrap());
    let ids = [AvatarId("a".into()), AvatarId("b".into())];
    let mut description = None;
    for (i, id) in ids.iter().enumerate() {
        let avatar = common::feed::walking(&rig, &id.0, i as u32 + 1, i as f32 * 0.37);
        description = Some(avatar.description.clone());
        scene.add_avatar(avatar).unwrap();
    }
    let description = description.unwrap();
    let world = Precision {
        millimetres: Some(5.0),
        ..Precision::FINEST
    };
    let subset = JointSet::Depth(4);
    let selection = subset.select(&description);
    // (precision, every, joints, protocol version): the last two are version 6 readers of
    // the same precisions as two version 5 ones, coded with near-axis steps.
    let cases: [(Precision, u32, Option<JointSet>, u32); 8] = [
        (Precision::FINEST, 1, None, 5),
        (degrees(0.1), 1, None, 5),
        (degrees(0.1), 1, None, 5),
        (degrees(0.25), 2, Some(subset.clone()), 5),
        (world, 1, None, 5),
        (degrees(0.01), 1, None, 5),
        (degrees(0.1), 1, None, 6),
        (world, 1, None, 6),
    ];
    const N: usize = 8;
    let outboxes: Vec<Arc<Outbox>> = cases.iter().map(|_| Arc::new(Outbox::new())).collect();
    for (conn, ((precision, every, joints, version), outbox)) in
        cases.iter().zip(&outboxes).enumerate()
    {
        scene
            .subscribe(
                Subscriber::new(
                    conn as u64 + 1,
                    outbox.clone(),
                    Encoding::Binary,
                    None,
                    *every,
                )
                .with_version(*version)
                .with_joints(joints.clone())
                .with_precision(Some(*precision)),
            )
            .unwrap();
    }
    let steps: Vec<_> = cases
        .iter()
        .map(|(p, _, _, version)| p.resolve_with(&description, *version >= 6))
        .collect();
    assert!(steps[6].tiered() && steps[7].tiered() && !steps[1].tiered());
    assert!(steps[0].is_finest() && steps[5].is_finest());
    assert!(
        steps[1].rotations.iter().all(|&m| m == 11),
        "{:?}",
        steps[1]
    );
    // The world-space bound codes the wrists' and ankles' children more coarsely than the
    // hips (joint 0).
    assert!(
        steps[4].rotations.iter().max() > steps[4].rotations.first(),
        "{:?}",
        steps[4].rotations
    );
    let mut decoders: Vec<Frame2Decoder> = cases.iter().map(|_| Frame2Decoder::new()).collect();
    let mut bytes = [0usize; N];
    let mut frames = [0usize; N];
    // Rotations the version 6 readers got on a near grid, and on the joint's own.
    let mut tiers = [0usize; 2];
    let mut source: HashMap<u64, Vec<AvatarPose>> = HashMap::new();
    let skeleton = rig.skeleton();
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let (mut worst_mm, mut finest_mm) = (0f32, 0f32);
    let per_frame = |bytes: &[usize; N], frames: &[usize; N]| -> Vec<f64> {
        (0..N)
            .map(|k| bytes[k] as f64 / frames[k].max(1) as f64)
            .collect()
    };
    for seq in 1..=300u64 {
        scene.tick(seq, seq as f64 / 60.0, seq * 16_667, 60);
        {
            let mut state = scene.lock();
            let poses = ids
                .iter()
                .map(|id| state.avatar_mut(id).unwrap().pose().clone())
                .collect();
            source.insert(seq, poses);
        }
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        let reads = [
            true,
            true,
            rng.is_multiple_of(4),
            seq.is_multiple_of(2),
            true,
            true,
            true,
            true,
        ];
        for (k, outbox) in outboxes.iter().enumerate() {
            if !reads[k] {
                continue;
            }
            for b in common::feed::binary_frames(outbox).await {
                let levels = decoders[k]
                    .decode_levels(&b)
                    .unwrap_or_else(|e| panic!("reader {k}, tick {seq}: {e}"));
                for a in &levels.avatars {
                    let tiered = a.levels.steps.as_ref().is_some_and(|s| s.tiered());
                    assert_eq!(tiered, k >= 6, "reader {k}: {:?}", a.levels.steps);
                    if tiered {
                        for &bits in &a.levels.rotations {
                            tiers[usize::from(bits >> 47 & 1 == 0)] += 1;
                        }
                    }
                }
                let f: Frame = levels.to_frame();
                bytes[k] += b.len();
                frames[k] += 1;
                let src = &source[&f.header.seq];
                for (s, got) in src.iter().zip(&f.avatars) {
                    let joints: Vec<usize> = if k == 3 {
                        selection.joint_indices().collect()
                    } else {
                        (0..s.rotations.len()).collect()
                    };
                    assert_within(s, got, &steps[k].rotations, steps[k].translation, &joints);
                    if k == 5 {
                        // The finest frames: exactly the v1 levels.
                        for (x, y) in s.rotations.iter().zip(&got.rotations) {
                            assert_eq!(quant::decode(quant::encode(*x)), *y);
                        }
                    }
                    if k == 4 {
                        worst_mm = worst_mm.max(world_error_mm(skeleton, s, got, &joints));
                    }
                    if k == 0 {
                        // The finest frames' error at the same vertices, for comparison.
                        finest_mm = finest_mm.max(world_error_mm(skeleton, s, got, &joints));
                    }
                }
            }
        }
    }
    let per_frame = per_frame(&bytes, &frames);
    println!(
        "bytes a frame by subscriber: {per_frame:?}; worst error at 3 cm: 5 mm subscriber \
         {worst_mm} mm, finest {finest_mm} mm"
    );
    assert!(worst_mm <= 5.0, "world-space error {worst_mm} mm");
    assert!(
        worst_mm > 2.0 * finest_mm,
        "the 5 mm subscriber was coded as finely as the finest ({worst_mm} vs {finest_mm} mm)"
    );
    assert!(per_frame[1] < 0.8 * per_frame[0], "{per_frame:?}");
    assert!(per_frame[4] < 0.85 * per_frame[0], "{per_frame:?}");
    assert!((per_frame[5] - per_frame[0]).abs() < 1e-9, "{per_frame:?}");
    // Version 6: within the same bounds (checked above), most of a walk's rotations on the
    // near grids, and no more bytes than version 5 (motion capture's savings are measured by
    // `cargo bench --bench subscriber_bytes`; this walk's residuals are small either way).
    assert!(tiers[0] > 2 * tiers[1], "near / own grid: {tiers:?}");
    assert!(per_frame[6] <= per_frame[1], "{per_frame:?}");
    assert!(per_frame[7] <= per_frame[4], "{per_frame:?}");
    assert!(frames[2] > 20 && frames[3] >= 150, "{frames:?}");
}

/// The worst distance, mm, between a virtual vertex 3 cm along each axis of every joint in
/// `joints` posed by `source` and by `got` (whose rotations are those joints'; every other
/// joint keeps `source`'s rotation, as a client holding that subset poses it from the rest).
fn world_error_mm(
    skeleton: &posecast_proto::Skeleton,
    source: &AvatarPose,
    got: &AvatarPose,
    joints: &[usize],
) -> f32 {
    let rest = skeleton.rest();
    let locals = |rotations: &dyn Fn(usize) -> glam::Quat| -> Vec<Transform> {
        rest.iter()
            .enumerate()
            .map(|(j, r)| Transform {
                rotation: rotations(j),
                ..*r
            })
            .collect()
    };
    let a = locals(&|j| source.rotations[j]);
    let b = locals(&|j| {
        joints
            .iter()
            .position(|&k| k == j)
            .map_or(source.rotations[j], |k| got.rotations[k])
    });
    let n = rest.len();
    let (mut wa, mut wb) = (vec![Mat4::IDENTITY; n], vec![Mat4::IDENTITY; n]);
    forward_kinematics(skeleton, &a, &mut wa);
    forward_kinematics(skeleton, &b, &mut wb);
    let mut worst = 0f32;
    for &j in joints {
        for axis in [Vec3::X, Vec3::Y, Vec3::Z] {
            let v = axis * 0.03;
            worst = worst.max(
                wa[j]
                    .transform_point3(v)
                    .distance(wb[j].transform_point3(v)),
            );
        }
    }
    worst * 1000.0
}

/// The first `error` or `subscribed` on `ws` (other messages skipped; 120 s at most).
async fn answer(ws: &mut Ws) -> ServerMsg {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        match tokio::time::timeout_at(deadline, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                let msg: ServerMsg = serde_json::from_str(&t).unwrap();
                if matches!(msg, ServerMsg::Error(_) | ServerMsg::Subscribed { .. }) {
                    return msg;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("no answer: {other:?}"),
        }
    }
}

/// Over a real websocket: a precision out of range is refused naming the field, and so is one
/// asked on JSON frames or on protocol version 4; the native client at 0.1° gets frames
/// within the bound, and `subscribed` echoes the precision.
#[tokio::test]
async fn precisions_are_checked_and_served_over_a_websocket() {
    let server = server(60.0).await;
    let ask = |version: u32, encoding: Encoding, precision: Precision| {
        let url = server.ws_url();
        async move {
            let (mut ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
            let say = |m: &ClientMsg| Message::Text(serde_json::to_string(m).unwrap().into());
            let hello = ClientMsg::Hello {
                version,
                encoding,
                token: Some(CONTROL.into()),
                client: None,
            };
            ws.send(say(&hello)).await.unwrap();
            let subscribe = ClientMsg::Subscribe {
                scene: SceneId("default".into()),
                avatars: None,
                rate: None,
                joints: None,
                morph_weights: None,
                precision: Some(precision),
            };
            ws.send(say(&subscribe)).await.unwrap();
            answer(&mut ws).await
        }
    };
    let refused = [
        (5, Encoding::Binary, degrees(0.001), "degrees"),
        (5, Encoding::Binary, degrees(f32::MAX), "degrees"),
        (
            5,
            Encoding::Binary,
            Precision {
                millimetres: Some(0.0),
                ..Precision::FINEST
            },
            "millimetres",
        ),
        (5, Encoding::Json, degrees(0.1), "version 5"),
        (4, Encoding::Binary, degrees(0.1), "version 5"),
    ];
    for (version, encoding, precision, says) in refused {
        match ask(version, encoding, precision).await {
            ServerMsg::Error(e) => {
                assert_eq!(e.code, ErrorCode::InvalidValue, "{e:?}");
                assert!(e.message.contains(says), "{}", e.message);
            }
            other => panic!("{precision:?} on v{version} {encoding:?}: {other:?}"),
        }
    }
    match ask(5, Encoding::Binary, degrees(0.1)).await {
        ServerMsg::Subscribed { precision, .. } => assert_eq!(precision, Some(degrees(0.1))),
        other => panic!("{other:?}"),
    }
    // A precision a hair from a series value is rounded towards finer to it (subscriptions
    // that ask for nearly the same share their frames), and echoed so.
    let asked = Precision {
        degrees: Some(0.1234),
        millimetres: Some(2.2),
        shell: Some(0.028),
        translation: Some(0.0011),
    };
    match ask(5, Encoding::Binary, asked).await {
        ServerMsg::Subscribed { precision, .. } => assert_eq!(
            precision,
            Some(Precision {
                degrees: Some(0.1),
                millimetres: Some(2.0),
                shell: Some(0.0315),
                translation: Some(0.001),
            })
        ),
        other => panic!("{other:?}"),
    }
    // The native client at 0.1°, beside one at the finest: the same ticks within the bound.
    let connect = |precision: Option<Precision>| {
        posecast_testkit::ClientBuilder::new(server.ws_url())
            .token(Some(CONTROL))
            .options(move |o| o.precision = precision)
            .connect()
    };
    let fine = connect(None).await.unwrap().into_inner();
    let coarse = connect(Some(degrees(0.1))).await.unwrap().into_inner();
    let id = AvatarId("avatar".into());
    let bound = rotation_bound_degrees(11) + rotation_bound_degrees(1);
    let mut compared = 0;
    for _ in 0..20_000 {
        if let (Some(a), Some(b)) = (fine.latest(&id), coarse.latest(&id))
            && a.seq == b.seq
        {
            for (x, y) in a.locals.iter().zip(&b.locals) {
                let angle = quant::angle_between_degrees(x.rotation, y.rotation);
                assert!(angle <= bound, "tick {}: {angle}°", a.seq);
                let t = f64::from((x.translation - y.translation).abs().max_element());
                assert!(t <= 2.0 * MAX_TRANSLATION_ERROR + 1e-6);
            }
            compared += 1;
            if compared >= 5 {
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert!(compared >= 5, "only {compared} common ticks");
    assert_eq!(coarse.stats().undecodable, 0);
}
