//! VMC test helpers: servers with VMC inputs and outputs, a sender built from `rosc`, and the
//! pose a VMC performer means on the built-in avatar, derived by hand (not by the server's
//! code): Unity-frame forward kinematics, the X mirror, and the T-pose → H-Anim turn of the
//! arms.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use glam::{EulerRot, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::msg::AvatarId;
use posecast_server::config::Config;
use posecast_server::startup::Server;
use posecast_server::vmc::{VmcIn, VmcOut};
use rosc::{OscBundle, OscMessage, OscPacket, OscTime, OscType};
use std::f32::consts::FRAC_PI_2;
use std::net::SocketAddr;
use std::time::Duration;

/// The Unity bones the built-in avatar's joints take, with their Unity parents, in parent
/// order (the hierarchy is Unity's `HumanBodyBones`, written out here independently).
pub const BUILTIN_PAIRS: [(&str, Option<&str>, &str); 22] = [
    ("Hips", None, "humanoid_root"),
    ("Spine", Some("Hips"), "vl5"),
    ("Chest", Some("Spine"), "vt10"),
    ("UpperChest", Some("Chest"), "vt1"),
    ("Neck", Some("UpperChest"), "vc4"),
    ("Head", Some("Neck"), "skullbase"),
    ("LeftUpperLeg", Some("Hips"), "l_hip"),
    ("LeftLowerLeg", Some("LeftUpperLeg"), "l_knee"),
    ("LeftFoot", Some("LeftLowerLeg"), "l_ankle"),
    ("LeftToes", Some("LeftFoot"), "l_midtarsal"),
    ("RightUpperLeg", Some("Hips"), "r_hip"),
    ("RightLowerLeg", Some("RightUpperLeg"), "r_knee"),
    ("RightFoot", Some("RightLowerLeg"), "r_ankle"),
    ("RightToes", Some("RightFoot"), "r_midtarsal"),
    ("LeftShoulder", Some("UpperChest"), "l_sternoclavicular"),
    ("LeftUpperArm", Some("LeftShoulder"), "l_shoulder"),
    ("LeftLowerArm", Some("LeftUpperArm"), "l_elbow"),
    ("LeftHand", Some("LeftLowerArm"), "l_wrist"),
    ("RightShoulder", Some("UpperChest"), "r_sternoclavicular"),
    ("RightUpperArm", Some("RightShoulder"), "r_shoulder"),
    ("RightLowerArm", Some("RightUpperArm"), "r_elbow"),
    ("RightHand", Some("RightLowerArm"), "r_wrist"),
];

/// A server at `tick_rate` Hz with the built-in avatar and these VMC inputs and outputs.
pub async fn server(tick_rate: f32, vmc_in: &[&str], vmc_out: Vec<VmcOut>) -> Server {
    server_with(tick_rate, vmc_in, vmc_out, Duration::from_secs(2)).await
}

/// [`server`] with a drive timeout.
pub async fn server_with(
    tick_rate: f32,
    vmc_in: &[&str],
    vmc_out: Vec<VmcOut>,
    drive_timeout: Duration,
) -> Server {
    let config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate,
        access: super::test_access(),
        drive_timeout,
        vmc_in: vmc_in
            .iter()
            .map(|a| format!("127.0.0.1:0={a}").parse::<VmcIn>().unwrap())
            .collect(),
        vmc_out,
        ..Config::default()
    };
    let server = Server::start(config).await.unwrap();
    server.ready().await.unwrap();
    server
}

/// A UDP socket to send VMC from.
pub async fn sender() -> tokio::net::UdpSocket {
    tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap()
}

pub fn message(addr: &str, args: Vec<OscType>) -> OscPacket {
    OscPacket::Message(OscMessage {
        addr: addr.into(),
        args,
    })
}

pub fn bundle(content: Vec<OscPacket>) -> OscPacket {
    OscPacket::Bundle(OscBundle {
        timetag: OscTime {
            seconds: 0,
            fractional: 1,
        },
        content,
    })
}

/// `/VMC/Ext/Bone/Pos` or `/VMC/Ext/Root/Pos`.
pub fn pose_message(addr: &str, name: &str, p: Vec3, q: Quat) -> OscPacket {
    let mut args = vec![OscType::String(name.into())];
    args.extend(p.to_array().map(OscType::Float));
    args.extend(q.to_array().map(OscType::Float));
    message(addr, args)
}

/// A VMC frame as performers send it: OK, time, root, the bones.
pub fn frame(time: f32, root: Quat, bones: &[(&str, Quat)]) -> Vec<u8> {
    let mut content = vec![
        message("/VMC/Ext/OK", vec![OscType::Int(1)]),
        message("/VMC/Ext/T", vec![OscType::Float(time)]),
        pose_message("/VMC/Ext/Root/Pos", "root", Vec3::ZERO, root),
    ];
    for (name, q) in bones {
        content.push(pose_message("/VMC/Ext/Bone/Pos", name, Vec3::ZERO, *q));
    }
    rosc::encoder::encode(&bundle(content)).unwrap()
}

/// A test pose of every bone of [`BUILTIN_PAIRS`], Unity frame: up to ±40° about each axis.
pub fn test_pose(k: u32) -> Vec<(&'static str, Quat)> {
    BUILTIN_PAIRS
        .iter()
        .enumerate()
        .map(|(i, (name, _, _))| {
            let (i, k) = (i as f32, k as f32);
            let q = Quat::from_euler(
                EulerRot::XYZ,
                0.7 * (1.3 * i + k).sin(),
                0.6 * (0.7 * i + 2.0 * k).cos(),
                0.5 * (i + 0.5 * k).sin(),
            );
            (*name, q)
        })
        .collect()
}

/// Unity → glTF: mirror X, `(x, y, z, w) → (x, −y, −z, w)`.
pub fn mirror(q: Quat) -> Quat {
    Quat::from_xyzw(q.x, -q.y, -q.z, q.w)
}

/// The world rotation (relative to the H-Anim neutral pose, glTF frame) the performer gives
/// each Unity bone: Unity-frame world rotations (`root · Hips · …`), mirrored, then turned by
/// the T-pose's arm rotation: a T-pose arm points along +X (left) or −X (right), the neutral
/// arm along −Y, so `G = M(W) · Rz(±90°)` on the arms and hands and `M(W)` elsewhere.
pub fn expected_worlds(root: Quat, bones: &[(&str, Quat)]) -> Vec<(&'static str, Quat)> {
    let mut unity: Vec<(&str, Quat)> = Vec::new();
    for (name, parent, _) in BUILTIN_PAIRS {
        let local = bones
            .iter()
            .find(|(n, _)| *n == name)
            .map_or(Quat::IDENTITY, |b| b.1);
        let parent = match parent {
            Some(p) => unity.iter().find(|(n, _)| *n == p).unwrap().1,
            None => root,
        };
        unity.push((name, parent * local));
    }
    unity
        .into_iter()
        .map(|(name, w)| {
            let turn = match name {
                "LeftUpperArm" | "LeftLowerArm" | "LeftHand" => Quat::from_rotation_z(FRAC_PI_2),
                "RightUpperArm" | "RightLowerArm" | "RightHand" => {
                    Quat::from_rotation_z(-FRAC_PI_2)
                }
                _ => Quat::IDENTITY,
            };
            (name, mirror(w) * turn)
        })
        .collect()
}

/// The avatar's expected local rotations given the world rotations of its paired joints
/// (`pairs`: Unity bone → avatar joint name): unpaired joints keep their parent's world
/// rotation (`L = I`), and `L_j = G_parent⁻¹ G_j`.
pub fn expected_locals(
    rig: &posecast_server::rig::Rig,
    worlds: &[(&str, Quat)],
    pairs: &[(&str, &str)],
) -> Vec<Quat> {
    let sk = rig.skeleton();
    let mut world = vec![Quat::IDENTITY; sk.len()];
    let mut local = vec![Quat::IDENTITY; sk.len()];
    for j in 0..sk.len() {
        let parent = sk.parents()[j].map_or(Quat::IDENTITY, |p| world[p]);
        let name = sk.names()[j].as_str();
        let hanim = rig.hanim[j].as_deref();
        let bone = pairs
            .iter()
            .find(|(_, joint)| Some(*joint) == hanim || *joint == name)
            .map(|(b, _)| *b);
        world[j] = match bone.and_then(|b| worlds.iter().find(|(n, _)| *n == b)) {
            Some((_, g)) => *g,
            None => parent,
        };
        local[j] = parent.inverse() * world[j];
    }
    local
}

/// The largest angle between `locals`' rotations and `expected`, degrees.
pub fn worst_degrees(locals: &[Transform], expected: &[Quat]) -> f64 {
    locals
        .iter()
        .zip(expected)
        .map(|(l, e)| posecast_proto::quant::angle_between_degrees(l.rotation, *e))
        .fold(0.0, f64::max)
}

/// A free UDP port on 127.0.0.1 (bound, then let go).
pub fn free_udp_addr() -> SocketAddr {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

pub fn avatar(id: &str) -> AvatarId {
    AvatarId(id.into())
}

/// `/VMC/Ext/Hmd/Pos`: a headset's pose.
pub const HMD: &str = "/VMC/Ext/Hmd/Pos";
/// `/VMC/Ext/Con/Pos`: a controller's pose.
pub const CONTROLLER: &str = "/VMC/Ext/Con/Pos";
/// `/VMC/Ext/Tra/Pos`: a generic tracker's pose.
pub const TRACKER: &str = "/VMC/Ext/Tra/Pos";

/// glTF → Unity position: mirror X (its own inverse).
pub fn mirror_position(p: Vec3) -> Vec3 {
    Vec3::new(-p.x, p.y, p.z)
}

/// One tracked device as a VR tool sends it: `(address, serial, position, rotation)` with the
/// pose given in glTF's frame (posecast's) and written in Unity's by the helpers below.
pub type DeviceSent<'a> = (&'a str, &'a str, Vec3, Quat);

/// A datagram of devices as VR tools send them: OK, the sender's time (when given), then one
/// `/VMC/Ext/{Hmd,Con,Tra}/Pos` per device in the order given, each mirrored into Unity's
/// frame (position `(−x, y, z)`, rotation `(x, −y, −z, w)`).
pub fn devices_frame(time: Option<f32>, devices: &[DeviceSent<'_>]) -> Vec<u8> {
    let mut content = vec![message("/VMC/Ext/OK", vec![OscType::Int(1)])];
    if let Some(t) = time {
        content.push(message("/VMC/Ext/T", vec![OscType::Float(t)]));
    }
    for (addr, serial, p, q) in devices {
        content.push(pose_message(addr, serial, mirror_position(*p), mirror(*q)));
    }
    rosc::encoder::encode(&bundle(content)).unwrap()
}

/// A pose of `rig` in its model space: every joint at its rest translation with an identity
/// rotation (the H-Anim neutral pose), then `rotations` (by joint name) and the humanoid root
/// moved by `root_offset` and turned by `root_turn` (about its rest position).
pub fn model_pose(
    rig: &posecast_server::rig::Rig,
    root_offset: Vec3,
    root_turn: Quat,
    rotations: &[(&str, Quat)],
) -> Vec<Transform> {
    let sk = rig.skeleton();
    let mut locals: Vec<Transform> = sk.rest().to_vec();
    for l in &mut locals {
        l.rotation = Quat::IDENTITY;
    }
    for (name, q) in rotations {
        let j = sk.find(name).unwrap_or_else(|| panic!("no joint {name}"));
        locals[j].rotation = *q;
    }
    let root = sk.find("humanoid_root").unwrap();
    // The root's parent is at neutral (identity rotations), so a model-space turn and offset
    // are local ones too.
    locals[root].rotation = root_turn * locals[root].rotation;
    locals[root].translation += root_offset;
    locals
}

/// Model-space world matrices of `locals` on `rig`.
pub fn model_worlds(rig: &posecast_server::rig::Rig, locals: &[Transform]) -> Vec<glam::Mat4> {
    let mut world = vec![glam::Mat4::IDENTITY; locals.len()];
    posecast_proto::fk::forward_kinematics(rig.skeleton(), locals, &mut world);
    world
}

/// Joint `name`'s model-space position and rotation in `world`.
pub fn joint_at(rig: &posecast_server::rig::Rig, world: &[glam::Mat4], name: &str) -> (Vec3, Quat) {
    let j = rig
        .skeleton()
        .find(name)
        .unwrap_or_else(|| panic!("no joint {name}"));
    let (_, q, p) = world[j].to_scale_rotation_translation();
    (p, q.normalize())
}
