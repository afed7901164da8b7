//! One VMC datagram, decoded (OSC by `rosc`) and checked: the messages VMC input uses, typed,
//! in Unity's frame as sent.
//!
//! A datagram that is not OSC (truncated, a bad type tag, bytes left over) or nests bundles
//! deeper than [`MAX_BUNDLE_DEPTH`] is dropped whole. Otherwise each message stands alone: one
//! with an unknown address, missing or mistyped arguments, a non-finite value or an unknown
//! bone name is counted and skipped, and the others apply. Extra arguments are ignored (later
//! protocol versions append some, e.g. `/VMC/Ext/OK`'s calibration state).

use glam::{Quat, Vec3};
use rosc::{OscMessage, OscPacket, OscType};

use super::unity::{bone_index, is_human_body_bone};
use crate::metrics::vmc::{MessageReject, PacketDrop};
use posecast_proto::live::MAX_ROOT_METRES;

/// Deepest bundle nesting accepted. VMC senders send one bundle of messages; `rosc` decodes
/// nested bundles recursively, so a datagram of 3,000 nested bundles (20 bytes each) must not
/// reach it.
pub const MAX_BUNDLE_DEPTH: usize = 8;

/// Longest blend shape name accepted, bytes.
pub const MAX_BLEND_NAME: usize = 64;

/// Longest device serial accepted, bytes (SteamVR serials are about a dozen characters).
pub const MAX_SERIAL: usize = 64;

/// What kind of tracked device a `/VMC/Ext/{Hmd,Con,Tra}/Pos` message is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum DeviceKind {
    /// `/VMC/Ext/Hmd/Pos`: a headset.
    Hmd,
    /// `/VMC/Ext/Con/Pos`: a hand controller.
    Controller,
    /// `/VMC/Ext/Tra/Pos`: a generic tracker (waist, feet, …).
    Tracker,
}

/// A message VMC input uses, with Unity-frame values.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    /// `/VMC/Ext/OK (int){loaded} …`.
    Available {
        /// Whether the sender has a model loaded (`1`).
        loaded: bool,
    },
    /// `/VMC/Ext/T (float){time}`: the sender's clock, seconds.
    Time(f32),
    /// `/VMC/Ext/Root/Pos (string)"root" p.xyz q.xyzw [s.xyz o.xyz]`: the model root's pose.
    Root {
        /// The root's position, metres, Unity frame.
        position: Vec3,
        /// The root's rotation, Unity frame.
        rotation: Quat,
        /// The mixed-reality scale (v2.1), when sent.
        scale: Option<Vec3>,
    },
    /// `/VMC/Ext/Bone/Pos (string){name} p.xyz q.xyzw`: a bone's local pose. `bone` indexes
    /// [`super::unity::BONES`]; `None` for a `HumanBodyBones` name posecast does not map (eyes,
    /// jaw).
    Bone {
        /// The bone's index in [`super::unity::BONES`], if posecast maps it.
        bone: Option<usize>,
        /// Its local position (relative to its parent), metres, Unity frame.
        position: Vec3,
        /// Its local rotation relative to the T-pose, Unity frame.
        rotation: Quat,
    },
    /// `/VMC/Ext/Blend/Val (string){name} (float){value}`.
    BlendValue {
        /// The blend shape's name (case-sensitive, as the protocol says).
        name: String,
        /// Its weight, 0 to 1.
        value: f32,
    },
    /// `/VMC/Ext/Blend/Apply`.
    BlendApply,
    /// `/VMC/Ext/Hmd/Pos`, `/VMC/Ext/Con/Pos` or `/VMC/Ext/Tra/Pos`
    /// `(string){serial} p.xyz q.xyzw`: a tracked device's pose in the sender's world
    /// (tracking) space. The `/Local` variants (VMC 2.3, relative to the avatar) are not used.
    Device {
        /// Headset, controller or generic tracker.
        kind: DeviceKind,
        /// The device's serial (at most [`MAX_SERIAL`] bytes), as the sender names it.
        serial: String,
        /// Its position, metres, Unity frame.
        position: Vec3,
        /// Its rotation, Unity frame.
        rotation: Quat,
    },
}

/// Decodes `bytes`, calling `each` for every usable message in order and `reject` for every
/// skipped one.
///
/// # Errors
/// The datagram is unusable as a whole.
pub fn decode(
    bytes: &[u8],
    mut each: impl FnMut(Message),
    mut reject: impl FnMut(MessageReject),
) -> Result<(), PacketDrop> {
    if !nesting_within(bytes, 0) {
        return Err(PacketDrop::TooDeep);
    }
    let (rest, packet) = rosc::decoder::decode_udp(bytes).map_err(|_| PacketDrop::Malformed)?;
    if !rest.is_empty() {
        return Err(PacketDrop::Malformed);
    }
    let mut stack = vec![packet];
    // Bundle contents are visited in order: push them reversed.
    while let Some(p) = stack.pop() {
        match p {
            OscPacket::Message(m) => match message(&m) {
                Ok(Some(msg)) => each(msg),
                Ok(None) => {}
                Err(why) => reject(why),
            },
            OscPacket::Bundle(b) => stack.extend(b.content.into_iter().rev()),
        }
    }
    Ok(())
}

/// Whether bundles in `bytes` nest at most [`MAX_BUNDLE_DEPTH`] deep (below `depth`). Walks
/// the bundle headers only; anything else is left to the decoder to judge.
fn nesting_within(bytes: &[u8], depth: usize) -> bool {
    let Some(mut rest) = bytes.strip_prefix(b"#bundle\0") else {
        return true;
    };
    if depth >= MAX_BUNDLE_DEPTH {
        return false;
    }
    // The time tag.
    rest = rest.get(8..).unwrap_or_default();
    while let Some((size, after)) = rest.split_first_chunk::<4>() {
        let size = u32::from_be_bytes(*size) as usize;
        let Some(element) = after.get(..size) else {
            return true;
        };
        if !nesting_within(element, depth + 1) {
            return false;
        }
        rest = after.get(size..).unwrap_or_default();
    }
    true
}

/// The message VMC input uses, `Ok(None)` for one it recognises and has no use for.
fn message(m: &OscMessage) -> Result<Option<Message>, MessageReject> {
    let args = Args(&m.args);
    Ok(Some(match m.addr.as_str() {
        "/VMC/Ext/OK" => Message::Available {
            loaded: args.int(0)? != 0,
        },
        "/VMC/Ext/T" => Message::Time(finite(args.float(0)?)?),
        "/VMC/Ext/Root/Pos" => {
            args.string(0)?;
            let scale = if m.args.len() >= 11 {
                let s = args.vec3(8)?;
                if !s.is_finite() || s.min_element() < 1e-3 || s.max_element() > 1e3 {
                    return Err(MessageReject::InvalidValue);
                }
                Some(s)
            } else {
                None
            };
            Message::Root {
                position: position(args.vec3(1)?)?,
                rotation: rotation(args.quat(4)?)?,
                scale,
            }
        }
        "/VMC/Ext/Bone/Pos" => {
            let name = args.string(0)?;
            if !is_human_body_bone(name) {
                return Err(MessageReject::UnknownBone);
            }
            Message::Bone {
                bone: bone_index(name),
                position: position(args.vec3(1)?)?,
                rotation: rotation(args.quat(4)?)?,
            }
        }
        "/VMC/Ext/Blend/Val" => {
            let name = args.string(0)?;
            if name.len() > MAX_BLEND_NAME {
                return Err(MessageReject::BlendShapeLimit);
            }
            Message::BlendValue {
                name: name.to_owned(),
                value: finite(args.float(1)?)?,
            }
        }
        "/VMC/Ext/Blend/Apply" => Message::BlendApply,
        "/VMC/Ext/Hmd/Pos" => device(DeviceKind::Hmd, &args)?,
        "/VMC/Ext/Con/Pos" => device(DeviceKind::Controller, &args)?,
        "/VMC/Ext/Tra/Pos" => device(DeviceKind::Tracker, &args)?,
        // The rest of the protocol (cameras, devices' `/Local` poses, MIDI, settings) is not
        // used.
        a if a.starts_with("/VMC/") => return Ok(None),
        _ => return Err(MessageReject::UnknownAddress),
    }))
}

/// A device pose message's arguments: `(string){serial} p.xyz q.xyzw`.
fn device(kind: DeviceKind, args: &Args<'_>) -> Result<Message, MessageReject> {
    let serial = args.string(0)?;
    let (position, rotation) = (args.vec3(1)?, args.quat(4)?);
    if serial.len() > MAX_SERIAL {
        return Err(MessageReject::DeviceLimit);
    }
    Ok(Message::Device {
        kind,
        serial: serial.to_owned(),
        position: self::position(position)?,
        rotation: self::rotation(rotation)?,
    })
}

fn finite(v: f32) -> Result<f32, MessageReject> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(MessageReject::InvalidValue)
    }
}

fn position(p: Vec3) -> Result<Vec3, MessageReject> {
    if p.is_finite() && p.length() <= MAX_ROOT_METRES {
        Ok(p)
    } else {
        Err(MessageReject::InvalidValue)
    }
}

fn rotation(q: [f32; 4]) -> Result<Quat, MessageReject> {
    posecast_proto::unit_quat(q).ok_or(MessageReject::InvalidValue)
}

/// A message's arguments, read by position.
struct Args<'a>(&'a [OscType]);

impl Args<'_> {
    fn get(&self, i: usize) -> Result<&OscType, MessageReject> {
        self.0.get(i).ok_or(MessageReject::BadArguments)
    }

    fn float(&self, i: usize) -> Result<f32, MessageReject> {
        match self.get(i)? {
            OscType::Float(v) => Ok(*v),
            // Some senders write doubles; f64 → f32 keeps the range checks meaningful (an
            // overflow becomes infinity and is refused).
            OscType::Double(v) => Ok(*v as f32),
            _ => Err(MessageReject::BadArguments),
        }
    }

    fn int(&self, i: usize) -> Result<i32, MessageReject> {
        match self.get(i)? {
            OscType::Int(v) => Ok(*v),
            _ => Err(MessageReject::BadArguments),
        }
    }

    fn string(&self, i: usize) -> Result<&str, MessageReject> {
        match self.get(i)? {
            OscType::String(s) => Ok(s),
            _ => Err(MessageReject::BadArguments),
        }
    }

    fn vec3(&self, i: usize) -> Result<Vec3, MessageReject> {
        Ok(Vec3::new(
            self.float(i)?,
            self.float(i + 1)?,
            self.float(i + 2)?,
        ))
    }

    fn quat(&self, i: usize) -> Result<[f32; 4], MessageReject> {
        Ok([
            self.float(i)?,
            self.float(i + 1)?,
            self.float(i + 2)?,
            self.float(i + 3)?,
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rosc::{OscBundle, OscTime};

    fn msg(addr: &str, args: Vec<OscType>) -> OscPacket {
        OscPacket::Message(OscMessage {
            addr: addr.into(),
            args,
        })
    }

    fn bundle(content: Vec<OscPacket>) -> OscPacket {
        OscPacket::Bundle(OscBundle {
            timetag: OscTime {
                seconds: 0,
                fractional: 1,
            },
            content,
        })
    }

    fn bone(name: &str, q: [f32; 4]) -> OscPacket {
        let mut args = vec![OscType::String(name.into())];
        args.extend([0.0, 0.1, 0.2].map(OscType::Float));
        args.extend(q.map(OscType::Float));
        msg("/VMC/Ext/Bone/Pos", args)
    }

    fn run(bytes: &[u8]) -> (Result<(), PacketDrop>, Vec<Message>, Vec<MessageReject>) {
        let (mut ok, mut bad) = (Vec::new(), Vec::new());
        let r = decode(bytes, |m| ok.push(m), |r| bad.push(r));
        (r, ok, bad)
    }

    #[test]
    fn a_bundle_decodes_in_order_and_bad_messages_stand_alone() {
        let p = bundle(vec![
            msg("/VMC/Ext/OK", vec![OscType::Int(1), OscType::Int(3)]),
            msg("/VMC/Ext/T", vec![OscType::Float(12.5)]),
            bone("LeftUpperArm", [0.0, 0.0, 0.38, 0.92]),
            bone("LeftEye", [0.0, 0.0, 0.0, 1.0]),
            bone("Tail", [0.0, 0.0, 0.0, 1.0]),
            bone("Head", [f32::NAN, 0.0, 0.0, 1.0]),
            bone("Neck", [0.0, 0.0, 0.0, 0.0]),
            msg(
                "/VMC/Ext/Bone/Pos",
                vec![OscType::String("Neck".into()), OscType::Int(1)],
            ),
            msg("/foo", vec![]),
            msg("/VMC/Ext/Cam", vec![]),
            msg(
                "/VMC/Ext/Blend/Val",
                vec![OscType::String("A".into()), OscType::Float(0.5)],
            ),
            msg("/VMC/Ext/Blend/Apply", vec![]),
        ]);
        let bytes = rosc::encoder::encode(&p).unwrap();
        let (r, ok, bad) = run(&bytes);
        assert_eq!(r, Ok(()));
        assert_eq!(ok.len(), 6, "{ok:?}");
        assert_eq!(ok[0], Message::Available { loaded: true });
        assert_eq!(ok[1], Message::Time(12.5));
        assert!(
            matches!(ok[2], Message::Bone { bone: Some(15), .. }),
            "{:?}",
            ok[2]
        );
        assert!(matches!(ok[3], Message::Bone { bone: None, .. }));
        assert_eq!(ok[5], Message::BlendApply);
        assert_eq!(
            bad,
            [
                MessageReject::UnknownBone,
                MessageReject::InvalidValue,
                MessageReject::InvalidValue,
                MessageReject::BadArguments,
                MessageReject::UnknownAddress,
            ]
        );
    }

    #[test]
    fn truncated_garbage_and_deep_nesting_drop_the_datagram() {
        let bytes =
            rosc::encoder::encode(&bundle(vec![bone("Hips", [0.0, 0.0, 0.0, 1.0])])).unwrap();
        for cut in [1, 8, 17, bytes.len() - 3] {
            assert_eq!(
                run(&bytes[..cut]).0,
                Err(PacketDrop::Malformed),
                "cut at {cut}"
            );
        }
        // A wrong type tag: 'f' overwritten with 'x'.
        let mut tagged = rosc::encoder::encode(&bone("Hips", [0.0, 0.0, 0.0, 1.0])).unwrap();
        let at = tagged.windows(3).position(|w| w == b",sf").unwrap();
        tagged[at + 2] = b'x';
        assert_eq!(run(&tagged).0, Err(PacketDrop::Malformed));
        let mut deep = bone("Hips", [0.0, 0.0, 0.0, 1.0]);
        for _ in 0..MAX_BUNDLE_DEPTH {
            deep = bundle(vec![deep]);
        }
        let ok = rosc::encoder::encode(&deep).unwrap();
        assert_eq!(run(&ok).0, Ok(()));
        // 3,000 levels: refused before the recursive decoder sees it.
        let mut deeper = bone("Hips", [0.0, 0.0, 0.0, 1.0]);
        for _ in 0..3000 {
            deeper = bundle(vec![deeper]);
        }
        let bytes = rosc::encoder::encode(&deeper).unwrap();
        assert_eq!(run(&bytes).0, Err(PacketDrop::TooDeep));
    }

    #[test]
    fn extreme_finite_values() {
        let p = bundle(vec![
            bone("Hips", [2e19, 0.0, 0.0, 0.0]),
            bone("Spine", [3e38, 3e38, 0.0, 0.0]),
            msg(
                "/VMC/Ext/Root/Pos",
                [OscType::String("root".into())]
                    .into_iter()
                    .chain([1e19, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0].map(OscType::Float))
                    .collect(),
            ),
        ]);
        let bytes = rosc::encoder::encode(&p).unwrap();
        let (r, ok, bad) = run(&bytes);
        assert_eq!(r, Ok(()));
        // Huge finite quaternions are rotations (normalised in f64); a root 1e19 m away is not.
        assert_eq!(ok.len(), 2);
        assert_eq!(bad, [MessageReject::InvalidValue]);
    }

    fn device(addr: &str, serial: &str, floats: &[f32]) -> OscPacket {
        let mut args = vec![OscType::String(serial.into())];
        args.extend(floats.iter().copied().map(OscType::Float));
        msg(addr, args)
    }

    #[test]
    fn device_poses_decode_and_bad_ones_stand_alone() {
        let pose = [0.1, 1.6, -0.2, 0.0, 0.0, 0.0, 1.0];
        let long = "S".repeat(MAX_SERIAL + 1);
        let p = bundle(vec![
            device("/VMC/Ext/Hmd/Pos", "LHR-1", &pose),
            device("/VMC/Ext/Con/Pos", "LHR-2", &pose),
            device("/VMC/Ext/Tra/Pos", "LHR-3", &pose),
            // VMC 2.3's local poses: not used, not counted.
            device("/VMC/Ext/Tra/Pos/Local", "LHR-3", &pose),
            device(
                "/VMC/Ext/Con/Pos",
                "nan",
                &[f32::NAN, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            ),
            device(
                "/VMC/Ext/Con/Pos",
                "zero",
                &[0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            ),
            device(
                "/VMC/Ext/Con/Pos",
                "far",
                &[2e4, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            ),
            device("/VMC/Ext/Con/Pos", "short", &pose[..6]),
            msg(
                "/VMC/Ext/Hmd/Pos",
                [OscType::Int(1)]
                    .into_iter()
                    .chain(pose.map(OscType::Float))
                    .collect(),
            ),
            device("/VMC/Ext/Tra/Pos", &long, &pose),
        ]);
        let bytes = rosc::encoder::encode(&p).unwrap();
        let (r, ok, bad) = run(&bytes);
        assert_eq!(r, Ok(()));
        assert_eq!(
            ok,
            [
                (DeviceKind::Hmd, "LHR-1"),
                (DeviceKind::Controller, "LHR-2"),
                (DeviceKind::Tracker, "LHR-3")
            ]
            .map(|(kind, serial)| Message::Device {
                kind,
                serial: serial.into(),
                position: Vec3::new(0.1, 1.6, -0.2),
                rotation: Quat::IDENTITY,
            })
        );
        assert_eq!(
            bad,
            [
                MessageReject::InvalidValue,
                MessageReject::InvalidValue,
                MessageReject::InvalidValue,
                MessageReject::BadArguments,
                MessageReject::BadArguments,
                MessageReject::DeviceLimit,
            ]
        );
    }
}
