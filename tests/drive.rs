//! Live driving (issue 16): a driver's poses reach every subscriber in the next tick, through
//! world-space retargeting when a source rig is given; access, conflicts, bad poses, the
//! driver's disconnect and silence.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use glam::{Mat4, Quat, Vec3};
use posecast_client::net::{ClientError, Driver};
use posecast_proto::Transform;
use posecast_proto::command::{Command, OnRelease};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::live::BinaryPose;
use posecast_proto::msg::{AvatarId, Encoding, ErrorCode};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_server::auth::{Role, Secret, TokenRule};
use posecast_testkit::{TestClient, TestServer};
use std::time::Duration;

const ALICE: &str = "alice-drives-avatar";
const TICK_HZ: f32 = 30.0;

const AVATAR: &str = "avatar";

fn avatar() -> AvatarId {
    AvatarId(AVATAR.into())
}

/// A server whose token `alice` may command only avatar `avatar`, with `timeout` of silence.
async fn server(timeout: Duration) -> TestServer {
    let mut access = common::test_access();
    let mut alice = TokenRule::new("alice", Secret::new(ALICE), Role::Control);
    alice.avatars = Some(vec![avatar()]);
    access.add(alice).unwrap();
    common::kit_builder(TICK_HZ)
        .access(access)
        .configure(|c| c.drive_timeout = timeout)
        .start()
        .await
        .unwrap()
}

async fn driver(server: &TestServer, token: &str) -> Driver {
    server.driver_as(Some(token)).await.unwrap()
}

/// A client subscribed to the avatar's scene, holding the unlimited control token.
async fn subscriber(server: &TestServer, encoding: Encoding) -> TestClient {
    server
        .client_builder()
        .encoding(encoding)
        .connect()
        .await
        .unwrap()
}

fn joint(server: &TestServer, name: &str) -> usize {
    server.joint(AVATAR, name).unwrap()
}

/// Waits until `client`'s newest pose of `avatar` satisfies `f`; returns that sample's seq.
async fn until(client: &TestClient, secs: f32, f: impl Fn(&[Transform]) -> bool) -> Option<u64> {
    client
        .wait_for_pose(AVATAR, Duration::from_secs_f32(secs), |p| f(p.locals()))
        .await
        .ok()
        .map(|p| p.seq())
}

fn close(a: Quat, b: Quat) -> bool {
    angle_between_degrees(a, b) <= MAX_ERROR_DEGREES
}

async fn error_code(d: &Driver) -> ErrorCode {
    d.next_error(Duration::from_secs(3))
        .await
        .expect("an error")
        .code
}

fn server_error(r: Result<impl std::fmt::Debug, ClientError>) -> ErrorCode {
    match r {
        Err(ClientError::Server(e)) => e.code,
        other => panic!("expected a server error, got {other:?}"),
    }
}

#[tokio::test]
async fn a_driven_pose_reaches_every_subscriber_in_the_next_tick() {
    let server = server(Duration::from_secs(5)).await;
    let mut subscribers = Vec::new();
    for encoding in [Encoding::Binary, Encoding::Binary, Encoding::Json] {
        subscribers.push(subscriber(&server, encoding).await);
    }
    let d = driver(&server, ALICE).await;
    let info = d.drive(&avatar(), None, None).await.unwrap();
    assert_eq!(info.source, "avatar");
    let (elbow, knee) = (joint(&server, "l_elbow"), joint(&server, "r_knee"));
    let q = Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.3, 1.1);
    let seq_before = subscribers[0].latest(&avatar()).map_or(0, |s| s.seq);
    d.send_pose(&avatar(), [("l_elbow".into(), q.to_array())], None, Some(1))
        .await
        .unwrap();
    for s in &subscribers {
        let seq = until(s, 2.0, |l| close(l[elbow].rotation, q)).await;
        let seq = seq.expect("every subscriber sees the driven rotation");
        // The next tick carries it (two: the pose may land just after a tick's evaluation).
        assert!(
            seq <= seq_before + 2,
            "seen at tick {seq}, sent after {seq_before}"
        );
    }
    // The binary form, by joint index.
    let r = Quat::from_rotation_x(-0.8);
    d.send_binary_pose(&BinaryPose {
        avatar_num: info.avatar_num,
        time_us: Some(2),
        root_position: None,
        rotations: vec![(u16::try_from(knee).unwrap(), r)],
        weights: Vec::new(),
        trackers: Vec::new(),
    })
    .await
    .unwrap();
    for s in &subscribers {
        // Quantised twice (driver → server, server → subscriber).
        let seen = until(s, 2.0, |l| {
            angle_between_degrees(l[knee].rotation, r) <= 2.0 * MAX_ERROR_DEGREES
                && close(l[elbow].rotation, q)
        });
        assert!(
            seen.await.is_some(),
            "a partial binary pose keeps the others"
        );
    }
    assert!(d.next_error(Duration::from_millis(100)).await.is_none());
}

/// World position of each joint of `rig` with local rotations `rot` (rest translations).
fn world_positions(rig: &posecast_server::rig::Rig, rot: &[Quat]) -> Vec<Vec3> {
    let sk = rig.skeleton();
    let locals: Vec<Transform> = sk
        .rest()
        .iter()
        .zip(rot)
        .map(|(t, q)| Transform { rotation: *q, ..*t })
        .collect();
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

#[tokio::test]
async fn a_source_rig_is_retargeted_in_world_space() {
    let Some(bvh) = common::testdata_bytes("bvh/cmu/01_01.bvh") else {
        return;
    };
    let server = server(Duration::from_secs(5)).await;
    let (status, body) =
        common::upload_files(server.addr, "/api/assets/01_01", &[("01_01.bvh", &bvh)]).await;
    assert_eq!(status, 200, "{body}");
    let source = server.state.world.library.get("01_01").unwrap();
    let target = server.state.world.library.get("avatar").unwrap();
    let sub = subscriber(&server, Encoding::Binary).await;
    let d = driver(&server, ALICE).await;
    let info = d.drive(&avatar(), Some("01_01"), None).await.unwrap();
    assert_eq!(info.joints, source.skeleton().names());
    let hanim = |rig: &posecast_server::rig::Rig, name: &str| {
        rig.hanim
            .iter()
            .position(|h| h.as_deref() == Some(name))
            .unwrap()
    };
    let limbs = [
        ("l_shoulder", "l_elbow"),
        ("l_elbow", "l_wrist"),
        ("r_shoulder", "r_elbow"),
        ("r_elbow", "r_wrist"),
        ("l_hip", "l_knee"),
        ("l_knee", "l_ankle"),
        ("r_hip", "r_knee"),
        ("r_knee", "r_ankle"),
    ];
    let clip = source.clips[0].clone();
    let sk = source.skeleton();
    let mut worst = 0.0f32;
    for (i, t) in [0.5f32, 1.5, 2.5].into_iter().enumerate() {
        let mut locals = sk.rest().to_vec();
        clip.sample(clip.start() + t, sk.rest(), &mut locals);
        let rot: Vec<Quat> = locals.iter().map(|l| l.rotation).collect();
        d.send_pose(
            &avatar(),
            sk.names()
                .iter()
                .cloned()
                .zip(rot.iter().map(|q| q.to_array())),
            None,
            Some(i as u64),
        )
        .await
        .unwrap();
        let src = world_positions(&source, &rot);
        let dir = |p: &[Vec3], rig, (a, b): (&str, &str)| {
            (p[hanim(rig, b)] - p[hanim(rig, a)]).normalize()
        };
        // Every limb of the streamed pose within 1° of the source's.
        let error = |l: &[Transform]| {
            let rot: Vec<Quat> = l.iter().map(|t| t.rotation).collect();
            let tgt = world_positions(&target, &rot);
            limbs
                .iter()
                .map(|&limb| {
                    dir(&src, &source, limb)
                        .dot(dir(&tgt, &target, limb))
                        .clamp(-1.0, 1.0)
                        .acos()
                        .to_degrees()
                })
                .fold(0.0f32, f32::max)
        };
        let seen = until(&sub, 3.0, |l| error(l) < 1.0).await;
        assert!(
            seen.is_some(),
            "frame {t}: limbs off by {:?}°",
            sub.latest(&avatar()).map(|s| error(&s.locals))
        );
        worst = worst.max(error(&sub.latest(&avatar()).unwrap().locals));
    }
    println!("retargeted live pose: worst limb direction error {worst:.4}°");
}

#[tokio::test]
async fn a_limited_token_drives_only_its_avatar_and_a_second_driver_conflicts() {
    let server = server(Duration::from_secs(5)).await;
    let director = driver(&server, common::CONTROL).await;
    director
        .command(Command::AddAvatar {
            scene: posecast_proto::msg::SceneId("default".into()),
            asset: "avatar".into(),
            avatar: Some(AvatarId("bob".into())),
            clip: Some("idle".into()),
            position: None,
            rotation: None,
        })
        .await
        .unwrap();
    let alice = driver(&server, ALICE).await;
    let bob = AvatarId("bob".into());
    assert_eq!(
        server_error(alice.drive(&bob, None, None).await),
        ErrorCode::Forbidden
    );
    alice.drive(&avatar(), None, None).await.unwrap();
    assert_eq!(
        server_error(director.drive(&avatar(), None, None).await),
        ErrorCode::Conflict
    );
    // Once released, another may drive.
    alice.release(&avatar()).await.unwrap();
    director.drive(&avatar(), None, None).await.unwrap();
}

#[tokio::test]
async fn bad_poses_get_typed_errors_and_change_nothing() {
    let server = server(Duration::from_secs(5)).await;
    let sub = subscriber(&server, Encoding::Json).await;
    let d = driver(&server, ALICE).await;
    let info = d.drive(&avatar(), None, None).await.unwrap();
    let elbow = joint(&server, "l_elbow");
    let q = Quat::from_rotation_z(0.9);
    d.send_pose(&avatar(), [("l_elbow".into(), q.to_array())], None, None)
        .await
        .unwrap();
    assert!(
        until(&sub, 2.0, |l| close(l[elbow].rotation, q))
            .await
            .is_some()
    );
    let other = Quat::from_rotation_z(-0.5).to_array();
    type BadPose = (Vec<(String, [f32; 4])>, Option<[f32; 3]>, ErrorCode);
    let bad: [BadPose; 4] = [
        (
            vec![("l_elbow".into(), other), ("no_such_joint".into(), other)],
            None,
            ErrorCode::UnknownJoint,
        ),
        (
            vec![("l_elbow".into(), other), ("r_elbow".into(), [0.0; 4])],
            None,
            ErrorCode::InvalidValue,
        ),
        // JSON has no NaN: serde writes null, which is not a number.
        (
            vec![("l_elbow".into(), [f32::NAN, 0.0, 0.0, 1.0])],
            None,
            ErrorCode::BadMessage,
        ),
        (
            vec![("l_elbow".into(), other)],
            Some([1e9, 0.0, 0.0]),
            ErrorCode::InvalidValue,
        ),
    ];
    for (rotations, root, code) in bad {
        d.send_pose(&avatar(), rotations, root, None).await.unwrap();
        assert_eq!(error_code(&d).await, code);
    }
    // A binary pose naming a joint index past the rig.
    d.send_binary_pose(&BinaryPose {
        avatar_num: info.avatar_num,
        time_us: None,
        root_position: None,
        rotations: vec![(0, Quat::from_array(other)), (9999, Quat::IDENTITY)],
        weights: Vec::new(),
        trackers: Vec::new(),
    })
    .await
    .unwrap();
    assert_eq!(error_code(&d).await, ErrorCode::UnknownJoint);
    // Not the driver.
    let stranger = driver(&server, common::CONTROL).await;
    stranger
        .send_pose(&avatar(), [("l_elbow".into(), other)], None, None)
        .await
        .unwrap();
    assert_eq!(error_code(&stranger).await, ErrorCode::NotAllowedNow);
    // Too fast: a burst far past 120 Hz (the driver's pacing off, as a client without it).
    d.set_pacing(false);
    tokio::time::sleep(Duration::from_millis(200)).await;
    for _ in 0..40 {
        d.send_pose(&avatar(), [("l_elbow".into(), q.to_array())], None, None)
            .await
            .unwrap();
    }
    let limited = d
        .next_error(Duration::from_secs(3))
        .await
        .expect("rate_limited");
    assert_eq!(limited.code, ErrorCode::RateLimited);
    assert!(limited.retry_after_ms.is_some_and(|ms| ms >= 1));
    // Several ticks later the pose is still the good one.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let l = sub.latest(&avatar()).unwrap().locals;
    assert!(
        close(l[elbow].rotation, q),
        "a refused pose changed the avatar"
    );
    assert!(close(
        l[joint(&server, "r_elbow")].rotation,
        sub_rest(&server, "r_elbow", &l)
    ));
}

#[tokio::test]
async fn a_paced_driver_sending_as_fast_as_it_can_is_never_rate_limited() {
    let server = server(Duration::from_secs(5)).await;
    let d = driver(&server, ALICE).await;
    let info = d.drive(&avatar(), None, None).await.unwrap();
    assert!(info.max_rate_hz > 0.0);
    // Three times the server's burst, back to back, JSON and binary mixed (one budget).
    let poses = 40u32;
    let began = std::time::Instant::now();
    for i in 0..poses {
        let q = Quat::from_rotation_z(0.01 * i as f32);
        if i % 2 == 0 {
            d.send_pose(&avatar(), [("l_elbow".into(), q.to_array())], None, None)
                .await
                .unwrap();
        } else {
            d.send_binary_pose(&BinaryPose {
                avatar_num: info.avatar_num,
                time_us: None,
                root_position: None,
                rotations: vec![(0, q)],
                weights: Vec::new(),
                trackers: Vec::new(),
            })
            .await
            .unwrap();
        }
    }
    let spent = began.elapsed();
    // Spaced at the budget: the last pose left no sooner than (n − 1) intervals after the first.
    let floor = Duration::from_secs_f64(f64::from(poses - 1) / f64::from(info.max_rate_hz));
    assert!(
        spent >= floor,
        "{poses} poses in {spent:?}, below {floor:?}"
    );
    // A command answered after them: any refusal of a pose would have come before its ack.
    d.command(Command::GetAvatar { avatar: avatar() })
        .await
        .unwrap();
    let refused = d.next_error(Duration::ZERO).await;
    assert!(refused.is_none(), "a paced pose was refused: {refused:?}");
}

/// The rotation the avatar had before driving (the driven pose starts from it): whatever it
/// is, a refused pose must not have replaced it with identity-from-zero.
fn sub_rest(server: &TestServer, name: &str, l: &[Transform]) -> Quat {
    l[joint(server, name)].rotation
}

/// Pauses the avatar's clip and returns its (now still) pose of `l_elbow`.
async fn paused_clip_elbow(server: &TestServer, sub: &TestClient, d: &Driver) -> Quat {
    d.command(Command::Pause { avatar: avatar() })
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(150)).await;
    sub.latest(&avatar()).unwrap().locals[joint(server, "l_elbow")].rotation
}

async fn drive_away(
    server: &TestServer,
    sub: &TestClient,
    d: &Driver,
    on_release: Option<OnRelease>,
) -> Quat {
    d.drive(&avatar(), None, on_release).await.unwrap();
    let q = Quat::from_rotation_y(1.2);
    d.send_pose(&avatar(), [("l_elbow".into(), q.to_array())], None, None)
        .await
        .unwrap();
    let elbow = joint(server, "l_elbow");
    assert!(
        until(sub, 2.0, |l| close(l[elbow].rotation, q))
            .await
            .is_some()
    );
    q
}

#[tokio::test]
async fn the_drivers_disconnect_returns_the_avatar_to_its_clip() {
    let server = server(Duration::from_secs(30)).await;
    let sub = subscriber(&server, Encoding::Binary).await;
    let d = driver(&server, ALICE).await;
    let clip = paused_clip_elbow(&server, &sub, &d).await;
    drive_away(&server, &sub, &d, None).await;
    let driven = |server: &TestServer| {
        let scene = server.state.world.find_avatar(&avatar()).unwrap();
        scene.info().avatars[0].driven
    };
    assert!(driven(&server), "get_avatar reports the driver");
    d.close().await;
    let elbow = joint(&server, "l_elbow");
    assert!(
        until(&sub, 2.0, |l| close(l[elbow].rotation, clip))
            .await
            .is_some(),
        "back to the clip's pose after the driver left"
    );
    assert!(!driven(&server), "and no more once it left");
}

#[tokio::test]
async fn silence_past_the_timeout_returns_the_avatar_to_its_clip_or_holds() {
    let server = server(Duration::from_millis(400)).await;
    let sub = subscriber(&server, Encoding::Binary).await;
    let d = driver(&server, ALICE).await;
    let elbow = joint(&server, "l_elbow");
    let clip = paused_clip_elbow(&server, &sub, &d).await;
    let started = std::time::Instant::now();
    drive_away(&server, &sub, &d, None).await;
    assert!(
        until(&sub, 3.0, |l| close(l[elbow].rotation, clip))
            .await
            .is_some()
    );
    assert!(
        started.elapsed() >= Duration::from_millis(400),
        "released before the timeout"
    );
    // With `hold`, silence keeps the last pose.
    let q = drive_away(&server, &sub, &d, Some(OnRelease::Hold)).await;
    tokio::time::sleep(Duration::from_millis(900)).await;
    assert!(close(
        sub.latest(&avatar()).unwrap().locals[elbow].rotation,
        q
    ));
    // The silent driver was released: another may drive now.
    let other = driver(&server, common::CONTROL).await;
    other.drive(&avatar(), None, None).await.unwrap();
}
