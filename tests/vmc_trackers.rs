//! VMC tracked devices (issue 29, goal 3): a VR tool that sends only `/VMC/Ext/Hmd/Pos`,
//! `/VMC/Ext/Con/Pos` and `/VMC/Ext/Tra/Pos` drives a whole avatar through the tracker solve.
//!
//! The devices sent are the built-in avatar's own joints in a known pose (its skullbase,
//! wrists, humanoid_root and ankles, model space), written in Unity's left-handed frame as a VR
//! tool writes them; a subscriber rebuilds world positions from the streamed local rotations
//! and the head, wrists (and hips and ankles) must be where their devices are, within 1 mm and
//! 0.5°.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::vmc::*;
use glam::{Quat, Vec3};
use posecast_client::net::Client;
use posecast_proto::Transform;
use posecast_proto::command::Command;
use posecast_proto::msg::Encoding;
use posecast_server::metrics::vmc::{MessageReject, PoseRefusal};
use posecast_server::rig::Rig;
use rosc::OscType;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// How long any wait may take on this loaded machine before the test fails.
const BOUND: Duration = Duration::from_secs(120);
/// How far a joint may be from its device, metres.
const MM: f32 = 1e-3;
/// How far a joint's rotation may be from its device's, degrees.
const DEGREES: f64 = 0.5;

/// A joint and where its device puts it (model space).
type Target = (&'static str, Vec3, Quat);

/// A VR tool: sends its devices to one VMC input with its own clock (`/VMC/Ext/T`).
struct Tool {
    udp: tokio::net::UdpSocket,
    to: SocketAddr,
    start: Instant,
}

impl Tool {
    async fn new(to: SocketAddr) -> Self {
        Self {
            udp: sender().await,
            to,
            start: Instant::now(),
        }
    }

    async fn send(&self, devices: &[DeviceSent<'_>]) {
        let t = self.elapsed();
        self.udp
            .send_to(&devices_frame(Some(t), devices), self.to)
            .await
            .unwrap();
    }

    /// The tool's clock, seconds.
    fn elapsed(&self) -> f32 {
        self.start.elapsed().as_secs_f32()
    }

    async fn send_raw(&self, bytes: &[u8]) {
        self.udp.send_to(bytes, self.to).await.unwrap();
    }

    /// Sends `devices` every 10 ms (as a tool streams them) until `sub`'s newest pose of the
    /// avatar puts every target's joint on it, or [`BOUND`] passes; returns the worst errors
    /// seen last (mm, degrees).
    async fn until_reached(
        &self,
        sub: &Client,
        rig: &Rig,
        devices: &[DeviceSent<'_>],
        targets: &[Target],
    ) -> (f32, f64) {
        let deadline = Instant::now() + BOUND;
        let mut worst = (f32::MAX, f64::MAX);
        while Instant::now() < deadline {
            self.send(devices).await;
            tokio::time::sleep(Duration::from_millis(10)).await;
            if let Some(s) = sub.latest(&avatar("avatar")) {
                worst = errors(rig, &s.locals, targets);
                if worst.0 <= MM && worst.1 <= DEGREES {
                    return worst;
                }
            }
        }
        worst
    }
}

/// The worst position (metres) and rotation (degrees) error of `targets` in the pose
/// `locals` (model space: the streamed locals, without the placement).
fn errors(rig: &Rig, locals: &[Transform], targets: &[Target]) -> (f32, f64) {
    let world = model_worlds(rig, locals);
    targets
        .iter()
        .fold((0.0f32, 0.0f64), |(p, a), (joint, tp, tq)| {
            let (jp, jq) = joint_at(rig, &world, joint);
            (
                p.max(jp.distance(*tp)),
                a.max(posecast_proto::quant::angle_between_degrees(jq, *tq)),
            )
        })
}

/// The model-space transforms of `joints` in `locals`.
fn targets(rig: &Rig, locals: &[Transform], joints: &[&'static str]) -> Vec<Target> {
    let world = model_worlds(rig, locals);
    joints
        .iter()
        .map(|j| {
            let (p, q) = joint_at(rig, &world, j);
            (*j, p, q)
        })
        .collect()
}

/// A reaching pose: the body turned by `yaw` and moved by `offset`, the head looking down, the
/// left arm reaching forward, the right out and bent, the left wrist turned.
fn reaching(rig: &Rig, yaw: f32, offset: Vec3, k: f32) -> Vec<Transform> {
    model_pose(
        rig,
        offset,
        Quat::from_rotation_y(yaw),
        &[
            ("skullbase", Quat::from_rotation_x(0.25)),
            ("l_shoulder", Quat::from_rotation_x(-1.1 - 0.2 * k)),
            ("l_elbow", Quat::from_rotation_x(-0.5)),
            ("l_wrist", Quat::from_rotation_y(0.6)),
            (
                "r_shoulder",
                Quat::from_rotation_z(-0.7) * Quat::from_rotation_x(-0.3 * k),
            ),
            ("r_elbow", Quat::from_rotation_x(-1.0)),
            ("r_wrist", Quat::from_rotation_z(0.3)),
        ],
    )
}

/// The three devices of `pose` (model space), the right controller first (a tool's order is
/// its own).
fn three_points(rig: &Rig, pose: &[Transform]) -> (Vec<DeviceSent<'static>>, Vec<Target>) {
    let t = targets(rig, pose, &["skullbase", "l_wrist", "r_wrist"]);
    let devices = vec![
        (CONTROLLER, "LHR-RIGHT", t[2].1, t[2].2),
        (CONTROLLER, "LHR-LEFT", t[1].1, t[1].2),
        (HMD, "HMD-1", t[0].1, t[0].2),
    ];
    (devices, t)
}

async fn avatar_state(client: &Client) -> serde_json::Value {
    client
        .command(Command::GetAvatar {
            avatar: avatar("avatar"),
        })
        .await
        .unwrap()
        .to_value()
}

/// A headset and two controllers drive the built-in avatar: the head and both wrists reach
/// their devices within 1 mm and 0.5°, the controllers on the right hands though the right one
/// is sent first and both before the headset; a second pose follows; the avatar reports a VMC
/// driver.
#[tokio::test]
async fn a_headset_and_two_controllers_drive_the_head_and_hands() {
    let server = server(60.0, &["avatar"], Vec::new()).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let pose = reaching(&rig, 0.5, Vec3::new(0.15, 0.0, -0.1), 0.0);
    let (devices, targets) = three_points(&rig, &pose);
    // The controllers alone first: nothing to place them by yet, nothing driven.
    tool.send(&devices[..2]).await;
    let (mm, deg) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    println!(
        "VMC headset + controllers → built-in avatar: head and wrists within {:.4} mm, {deg:.3}°",
        mm * 1000.0
    );
    assert!(mm <= MM && deg <= DEGREES, "off by {mm} m, {deg}°");
    let state = avatar_state(&sub).await;
    assert_eq!(state["driven"], true, "{state}");
    assert_eq!(state["driver"]["via"], "vmc", "{state}");
    // Another pose, the devices in another order.
    let pose = reaching(&rig, 0.5, Vec3::new(0.15, 0.0, -0.1), 1.0);
    let (mut devices, targets) = three_points(&rig, &pose);
    devices.reverse();
    let (mm, deg) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    assert!(
        mm <= MM && deg <= DEGREES,
        "second pose off by {mm} m, {deg}°"
    );
    let m = &server.state.metrics.vmc;
    assert!(m.poses() > 0);
    assert_eq!(m.rejected_total(MessageReject::InvalidValue), 0);
}

/// Six points, the avatar placed away from the scene's origin and turned: a headset, two
/// controllers and three trackers (waist and feet, sent feet first and right before left)
/// put the head, wrists, humanoid_root and ankles of a crouching, turned body on their devices,
/// the devices' space being the avatar's (its placement the tool's origin).
#[tokio::test]
async fn six_points_drive_the_hips_and_feet_too() {
    let server = server(60.0, &["avatar"], Vec::new()).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    sub.command(Command::PlaceAvatar {
        avatar: avatar("avatar"),
        position: [1.5, 0.0, -2.0],
        rotation: Quat::from_rotation_y(1.2).to_array(),
        duration: None,
    })
    .await
    .unwrap();
    let pose = model_pose(
        &rig,
        Vec3::new(-0.1, -0.12, 0.2),
        Quat::from_rotation_y(-0.7),
        &[
            ("l_hip", Quat::from_rotation_x(-0.6)),
            ("l_knee", Quat::from_rotation_x(0.9)),
            ("l_ankle", Quat::from_rotation_x(-0.2)),
            (
                "r_hip",
                Quat::from_rotation_x(-0.3) * Quat::from_rotation_z(-0.1),
            ),
            ("r_knee", Quat::from_rotation_x(0.5)),
            ("r_ankle", Quat::from_rotation_y(-0.3)),
            ("l_shoulder", Quat::from_rotation_x(-0.8)),
            ("l_elbow", Quat::from_rotation_x(-1.2)),
            ("r_shoulder", Quat::from_rotation_z(-0.4)),
            ("r_elbow", Quat::from_rotation_x(-0.3)),
        ],
    );
    let joints = [
        "skullbase",
        "l_wrist",
        "r_wrist",
        "humanoid_root",
        "l_ankle",
        "r_ankle",
    ];
    let t = targets(&rig, &pose, &joints);
    let devices: Vec<DeviceSent<'_>> = vec![
        (TRACKER, "TRK-C", t[5].1, t[5].2),
        (TRACKER, "TRK-A", t[4].1, t[4].2),
        (CONTROLLER, "CON-2", t[2].1, t[2].2),
        (TRACKER, "TRK-B", t[3].1, t[3].2),
        (HMD, "HMD", t[0].1, t[0].2),
        (CONTROLLER, "CON-1", t[1].1, t[1].2),
    ];
    let (mm, deg) = tool.until_reached(&sub, &rig, &devices, &t).await;
    println!(
        "VMC 6 points → built-in avatar (placed away, turned): head, wrists, hips and ankles \
         within {:.4} mm, {deg:.3}°",
        mm * 1000.0
    );
    assert!(mm <= MM && deg <= DEGREES, "off by {mm} m, {deg}°");
}

/// Malformed device messages — NaN, a position beyond 10 km, a zero quaternion, too few
/// arguments, a string where a float goes, a serial too long — are counted by kind and change
/// nothing: the avatar keeps the pose its good devices gave, and the next good frame still
/// drives. (The user faces the tool's −Z here: the hands go by the head's frame, not the
/// tool's X.)
#[tokio::test]
async fn malformed_device_messages_are_counted_and_change_nothing() {
    // A long drive timeout: the avatar holds the tool's pose while only bad messages come.
    let server = server_with(60.0, &["avatar"], Vec::new(), Duration::from_secs(600)).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let pose = reaching(&rig, 2.8, Vec3::ZERO, 0.0);
    let (devices, targets) = three_points(&rig, &pose);
    let (mm, _) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    assert!(mm <= MM, "off by {mm} m");
    let m = &server.state.metrics.vmc;
    let before = [
        MessageReject::InvalidValue,
        MessageReject::BadArguments,
        MessageReject::DeviceLimit,
    ]
    .map(|r| m.rejected_total(r));
    // Each bad message moves a device elsewhere if it got through.
    let away = Vec3::new(0.3, -0.4, 0.2);
    let bad_pose = |serial: &str, p: Vec3, q: [f32; 4]| {
        let mut args = vec![OscType::String(serial.into())];
        args.extend(p.to_array().map(OscType::Float));
        args.extend(q.map(OscType::Float));
        args
    };
    let (head, left, right) = (targets[0].1, targets[1].1, targets[2].1);
    let long = "S".repeat(65);
    let bad = bundle(vec![
        message(
            HMD,
            bad_pose("HMD-1", Vec3::new(f32::NAN, 1.0, 0.0), [0.0, 0.0, 0.0, 1.0]),
        ),
        message(
            HMD,
            bad_pose("HMD-1", Vec3::new(2e4, 1.0, 0.0), [0.0, 0.0, 0.0, 1.0]),
        ),
        message(CONTROLLER, bad_pose("LHR-LEFT", left + away, [0.0; 4])),
        message(
            CONTROLLER,
            bad_pose("LHR-RIGHT", right + away, [0.0, 0.0, f32::INFINITY, 1.0]),
        ),
        // q.w missing.
        message(CONTROLLER, {
            let mut a = bad_pose("LHR-LEFT", left + away, [0.0, 0.0, 0.0, 1.0]);
            a.pop();
            a
        }),
        // A string for p.y.
        message(CONTROLLER, {
            let mut a = bad_pose("LHR-RIGHT", right + away, [0.0, 0.0, 0.0, 1.0]);
            a[2] = OscType::String("1.0".into());
            a
        }),
        message(TRACKER, bad_pose(&long, head + away, [0.0, 0.0, 0.0, 1.0])),
    ]);
    let bad = rosc::encoder::encode(&bad).unwrap();
    let shown = sub.latest(&avatar("avatar")).unwrap();
    let expected = [4, 2, 1];
    let counted = || {
        [
            MessageReject::InvalidValue,
            MessageReject::BadArguments,
            MessageReject::DeviceLimit,
        ]
        .map(|r| m.rejected_total(r))
    };
    // Five datagrams that arrived (UDP may drop one: sent again when not counted in 2 s).
    let mut delivered = 0u64;
    let deadline = Instant::now() + BOUND;
    while delivered < 5 {
        assert!(
            Instant::now() < deadline,
            "bad messages not counted: {:?}",
            counted()
        );
        tool.send_raw(&bad).await;
        let want = before[2] + delivered + 1;
        if common::wait_for(2.0, || counted()[2] >= want).await {
            delivered += 1;
        }
    }
    let after = counted();
    for (k, n) in expected.into_iter().enumerate() {
        assert_eq!(
            after[k] - before[k],
            n * delivered,
            "reason {k}: {after:?} {before:?}"
        );
    }
    // Ticks went on and the pose stayed the good devices'.
    let seq = shown.seq;
    assert!(
        common::wait_for(BOUND.as_secs_f32(), || {
            sub.latest(&avatar("avatar"))
                .is_some_and(|s| s.seq > seq + 10)
        })
        .await
    );
    let latest = sub.latest(&avatar("avatar")).unwrap();
    let (mm, deg) = errors(&rig, &latest.locals, &targets);
    assert!(
        mm <= MM && deg <= DEGREES,
        "bad messages moved the avatar: {mm} m, {deg}°"
    );
    // Good devices still drive.
    let pose = reaching(&rig, 2.8, Vec3::ZERO, 1.0);
    let (devices, targets) = three_points(&rig, &pose);
    let (mm, _) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    assert!(mm <= MM, "off by {mm} m");
}

/// Serials past the input's limit (16) are refused and counted: a tool whose trackers fill the
/// limit before its headset and controllers never drives the avatar.
#[tokio::test]
async fn devices_past_the_limit_are_counted_and_change_nothing() {
    let server = server(60.0, &["avatar"], Vec::new()).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let m = &server.state.metrics.vmc;
    let serials: Vec<String> = (0..16).map(|i| format!("TRK-{i}")).collect();
    // Above the head: no tracker of a body.
    let fill: Vec<DeviceSent<'_>> = serials
        .iter()
        .map(|s| {
            (
                TRACKER,
                s.as_str(),
                Vec3::new(0.0, 2.5, 0.0),
                Quat::IDENTITY,
            )
        })
        .collect();
    let (devices, _) = three_points(&rig, &reaching(&rig, 0.0, Vec3::ZERO, 0.0));
    let deadline = Instant::now() + BOUND;
    while m.rejected_total(MessageReject::DeviceLimit) < 30 {
        assert!(
            Instant::now() < deadline,
            "serials past the limit not counted"
        );
        tool.send(&fill).await;
        tool.send(&devices).await;
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // 3 refused per frame of the headset and controllers.
    assert_eq!(m.rejected_total(MessageReject::DeviceLimit) % 3, 0);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let state = avatar_state(&sub).await;
    assert_ne!(state["driven"], true, "{state}");
    assert_eq!(m.poses(), 0);
}

/// A tool sending bones and devices drives by its bones (within 0.05°, as `tests/vmc.rs`);
/// once its bones stop for the drive timeout, its devices drive.
#[tokio::test]
async fn bones_win_over_devices_until_they_stop() {
    let server = server_with(60.0, &["avatar"], Vec::new(), Duration::from_millis(500)).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let pose = reaching(&rig, 0.2, Vec3::ZERO, 0.5);
    let (devices, targets) = three_points(&rig, &pose);
    let bones = test_pose(3);
    let pairs: Vec<_> = BUILTIN_PAIRS.iter().map(|(b, _, j)| (*b, *j)).collect();
    let expected = expected_locals(&rig, &expected_worlds(Quat::IDENTITY, &bones), &pairs);
    let deadline = Instant::now() + BOUND;
    let mut worst = f64::MAX;
    // The devices first in each frame, as their own datagram, then the bones.
    let mut frames = 0;
    while frames < 30 || worst > 0.05 {
        assert!(
            Instant::now() < deadline,
            "the bones did not drive: off by {worst}°"
        );
        tool.send(&devices).await;
        tool.send_raw(&frame(tool.elapsed(), Quat::IDENTITY, &bones))
            .await;
        frames += 1;
        tokio::time::sleep(Duration::from_millis(10)).await;
        if let Some(s) = sub.latest(&avatar("avatar")) {
            worst = worst_degrees(&s.locals, &expected);
        }
    }
    // Devices only now: after the timeout they drive.
    let (mm, deg) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    assert!(
        mm <= MM && deg <= DEGREES,
        "the devices did not take over: {mm} m, {deg}°"
    );
    let state = avatar_state(&sub).await;
    assert_eq!(state["driven"], true, "{state}");
    assert_eq!(state["driver"]["via"], "vmc", "{state}");
}

/// `calibrate_trackers` works on a VMC device drive: a user 10 % taller than the avatar
/// stands in the neutral pose; calibrated, the avatar stands in its own neutral pose (head and
/// wrists within 1 mm), the scale measured 1/1.1.
#[tokio::test]
async fn a_device_drive_calibrates() {
    // A drive that ends forgets its calibration (the next frame starts a new one): a long
    // drive timeout, so a loaded machine's scheduling pauses cannot end it.
    let server = server_with(60.0, &["avatar"], Vec::new(), Duration::from_secs(600)).await;
    let tool = Tool::new(server.vmc.inputs[0]).await;
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let neutral = model_pose(&rig, Vec3::ZERO, Quat::IDENTITY, &[]);
    let (_, targets) = three_points(&rig, &neutral);
    // The user: the avatar scaled by 1.1 about the floor under its head.
    let skull = targets[0].1;
    let anchor = Vec3::new(skull.x, 0.0, skull.z);
    let user: Vec<Target> = targets
        .iter()
        .map(|(j, p, q)| (*j, anchor + 1.1 * (*p - anchor), *q))
        .collect();
    let devices = vec![
        (HMD, "HMD-1", user[0].1, user[0].2),
        (CONTROLLER, "LHR-LEFT", user[1].1, user[1].2),
        (CONTROLLER, "LHR-RIGHT", user[2].1, user[2].2),
    ];
    // Driven: the tracker drive has samples to calibrate from.
    let m = &server.state.metrics.vmc;
    let deadline = Instant::now() + BOUND;
    while m.poses() < 5 {
        assert!(Instant::now() < deadline, "the devices did not drive");
        tool.send(&devices).await;
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // The tool streams on while the command runs (a silent tool would let go of the avatar
    // after the drive timeout, and its next frame would start an uncalibrated drive).
    let calibrate = sub.command(Command::CalibrateTrackers {
        avatar: avatar("avatar"),
        pose: None,
    });
    let streaming = async {
        loop {
            tool.send(&devices).await;
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    };
    let result = tokio::select! {
        r = calibrate => r.unwrap().to_value(),
        () = streaming => unreachable!("streams until the command returns"),
    };
    let scale = result["scale"].as_f64().unwrap();
    assert!((scale - 1.0 / 1.1).abs() < 1e-3, "{result}");
    assert_eq!(
        result["trackers"],
        serde_json::json!(["head", "l_hand", "r_hand"]),
        "{result}"
    );
    let (mm, deg) = tool.until_reached(&sub, &rig, &devices, &targets).await;
    println!(
        "VMC devices calibrated: a user 1.1× the avatar's size puts it in its neutral pose within \
         {:.4} mm, {deg:.3}°",
        mm * 1000.0
    );
    assert!(mm <= MM && deg <= DEGREES, "off by {mm} m, {deg}°");
}

/// `target/venv/bin/python3` with python-osc, or `None` (a failure under `CI=true`).
fn python() -> Option<std::path::PathBuf> {
    let python =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/venv/bin/python3");
    let ok = python.exists()
        && std::process::Command::new(&python)
            .args(["-c", "import pythonosc"])
            .status()
            .is_ok_and(|s| s.success());
    if ok {
        Some(python)
    } else {
        posecast_proto::testing::skip(
            "target/venv with python-osc is missing (scripts/test installs it: \
             python3 -m venv target/venv && target/venv/bin/pip install python-osc)",
        );
        None
    }
}

/// A VR tool written with python-osc (not posecast's OSC code): a bundle per frame of
/// `/VMC/Ext/OK`, `/VMC/Ext/T` and one device pose each, Unity frame, at 60 Hz.
const PYTHON_TOOL: &str = r#"
import json, sys, time
from pythonosc import osc_bundle_builder, osc_message_builder
from pythonosc.udp_client import SimpleUDPClient

host, port, devices, seconds = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3]), float(sys.argv[4])
client = SimpleUDPClient(host, port)

def message(address, *args):
    m = osc_message_builder.OscMessageBuilder(address=address)
    for a in args:
        m.add_arg(a, arg_type="f" if isinstance(a, float) else None)
    return m.build()

start = time.monotonic()
while time.monotonic() - start < seconds:
    b = osc_bundle_builder.OscBundleBuilder(osc_bundle_builder.IMMEDIATELY)
    b.add_content(message("/VMC/Ext/OK", 1))
    b.add_content(message("/VMC/Ext/T", float(time.monotonic() - start)))
    for address, serial, values in devices:
        b.add_content(message(address, serial, *[float(v) for v in values]))
    client.send(b.build())
    time.sleep(1 / 60)
"#;

/// python-osc sends a headset and two controllers (Unity frame, written out here from the
/// avatar's pose): the head and wrists reach them within 1 mm.
#[tokio::test]
async fn python_osc_devices_drive_the_avatar() {
    let Some(python) = python() else { return };
    let server = server(60.0, &["avatar"], Vec::new()).await;
    let to = server.vmc.inputs[0];
    let sub = common::client(&server, Encoding::Json).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let pose = reaching(&rig, 0.8, Vec3::new(-0.2, 0.0, 0.3), 0.5);
    let (devices, targets) = three_points(&rig, &pose);
    let json: Vec<serde_json::Value> = devices
        .iter()
        .map(|(addr, serial, p, q)| {
            let (p, q) = (mirror_position(*p), mirror(*q));
            serde_json::json!([addr, serial, [p.x, p.y, p.z, q.x, q.y, q.z, q.w]])
        })
        .collect();
    let mut child = std::process::Command::new(&python)
        .args(["-c", PYTHON_TOOL, "127.0.0.1", &to.port().to_string()])
        .arg(serde_json::Value::from(json).to_string())
        .arg(BOUND.as_secs().to_string())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + BOUND;
    let mut worst = (f32::MAX, f64::MAX);
    while Instant::now() < deadline {
        if let Some(s) = sub.latest(&avatar("avatar")) {
            worst = errors(&rig, &s.locals, &targets);
            if worst.0 <= MM && worst.1 <= DEGREES {
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    child.kill().ok();
    child.wait().ok();
    println!(
        "python-osc devices → built-in avatar: head and wrists within {:.4} mm, {:.3}°",
        worst.0 * 1000.0,
        worst.1
    );
    assert!(worst.0 <= MM && worst.1 <= DEGREES, "off by {worst:?}");
    assert_eq!(
        server
            .state
            .metrics
            .vmc
            .refused_total(PoseRefusal::NotHumanoid),
        0
    );
}
