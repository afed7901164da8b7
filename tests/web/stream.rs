//! The JavaScript client's stream parts against their Rust twins, on shared vectors run by
//! node through `server/web/check/stream.mjs`:
//! - `server/sdk/frames.js` decodes binary frames (keyframes, deltas with every tag, placements
//!   in keyframes and deltas, translations and scales; truncated, trailing, bad-magic and
//!   orphan-delta frames refused without changing its keyframes) as `posecast_proto::frame`'s
//!   `FrameDecoder` does;
//! - `server/sdk/frames2.js` decodes wire v2 frames made by `posecast_proto::frame2` (a reader
//!   of every frame, deltas up to depth 8; a slow reader with gaps, keyframes or deltas against
//!   its last decoded frame; escapes, Rice escapes, placements, scales) to the same rotations
//!   (float rounding), translations, scales and placements as `Frame2Decoder`, refuses what it
//!   refuses (cut short, trailing, magic, kind, bases not held, reserved flags, zero gaps,
//!   duplicates, counts, long varints) without changing its state, and agrees with it on random
//!   delta bit streams;
//! - `server/sdk/jitter.js` gives the playout delay and sampled poses (and how each was made)
//!   of posecast-client's `JitterBuffer` on an irregular stream with late and lost frames;
//! - `server/sdk/clock.js` gives `ClockEstimator`'s offset and round trip;
//! - `server/sdk/subset.js` selects the joints `posecast_proto::subset` does (by depth, by
//!   name with ancestors, on random trees) and makes a subset pose whole at rest.

use crate::root;
use glam::{Quat, Vec3};
use posecast_client::net::clock::ClockEstimator;
use posecast_client::net::jitter::{JitterBuffer, Sampled};
use posecast_proto::Transform;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{
    AvatarPose, ChunkEncoder, Frame, FrameDecoder, FrameHeader, FrameKind, write_header,
};
use posecast_proto::frame2::{self, Frame2Decoder, QuantPose, StreamEncoder};
use posecast_proto::msg::AvatarId;
use posecast_proto::placement::Placement;
use posecast_proto::subset::JointSet;
use posecast_proto::testing::skip;
use serde_json::{Value, json};
use std::process::Command as Process;

/// A small deterministic generator (the vectors must not change from run to run).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }

    fn vec3(&mut self) -> Vec3 {
        Vec3::new(
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
        )
    }

    fn quat(&mut self) -> Quat {
        loop {
            let q = Quat::from_xyzw(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            if q.length() > 0.1 {
                return q.normalize();
            }
        }
    }
}

fn pose_json(p: &AvatarPose) -> Value {
    json!({
        "num": p.avatar_num,
        "hash": format!("{:016x}", p.hash),
        "rotations": p.rotations.iter().map(|q| q.to_array()).collect::<Vec<_>>(),
        "translations": p.translations.iter().map(|t| t.to_array()).collect::<Vec<_>>(),
        "scales": p.scales.iter().map(|s| s.to_array()).collect::<Vec<_>>(),
        "placement": {
            "position": p.placement.position.to_array(),
            "rotation": p.placement.rotation.to_array(),
        },
        "weights": p.weights,
    })
}

/// Binary frames of two avatars and what `FrameDecoder` makes of each, in order (a frame it
/// refuses: `null`, and it must change nothing).
fn frame_vectors(rng: &mut Lcg) -> Vec<Value> {
    let joints = [9usize, 23];
    let mut poses: Vec<AvatarPose> = joints
        .iter()
        .enumerate()
        .map(|(i, &n)| AvatarPose {
            avatar_num: i as u32 + 1,
            hash: 0x9f0c_1234_abcd_0000 + i as u64,
            rotations: (0..n).map(|_| rng.quat()).collect(),
            translations: vec![rng.vec3()],
            scales: if i == 1 {
                vec![rng.vec3(), rng.vec3()]
            } else {
                vec![]
            },
            placement: Placement::IDENTITY,
            weights: Vec::new(),
        })
        .collect();
    let mut encoders = vec![ChunkEncoder::new(); poses.len()];
    let mut decoder = FrameDecoder::new();
    let mut out = Vec::new();
    let mut key_seq = 0;
    for seq in 100u64..160 {
        let kind = if seq % 20 == 0 {
            FrameKind::Key
        } else {
            FrameKind::Delta
        };
        if kind == FrameKind::Key {
            key_seq = seq;
        }
        for pose in &mut poses {
            for q in &mut pose.rotations {
                let r = rng.next();
                // Unchanged (tag 0), a small turn (tag 1) or a new rotation (tag 2).
                if r < 0.3 {
                } else if r < 0.8 {
                    *q = (Quat::from_scaled_axis(rng.vec3() * 0.004) * *q).normalize();
                } else {
                    *q = rng.quat();
                }
            }
            pose.translations[0] += rng.vec3() * 0.01;
            if rng.next() < 0.3 {
                pose.placement =
                    Placement::try_new((rng.vec3() * 5.0).to_array(), rng.quat().to_array())
                        .unwrap();
            }
        }
        let header = FrameHeader {
            kind,
            scene_num: 3,
            seq,
            server_time_us: 1_763_891_000_000_000 + seq * 16_667,
            base_seq: key_seq,
        };
        let mut bytes = Vec::new();
        write_header(&header, poses.len() as u16, &mut bytes);
        for (pose, encoder) in poses.iter().zip(&mut encoders) {
            encoder.encode(pose, kind, &mut bytes);
        }
        // Refused frames between the good ones: cut short, one byte too many, not a frame,
        // and a delta against a keyframe never sent.
        if seq % 7 == 3 {
            let mut bad = vec![bytes[..bytes.len() - 1].to_vec(), bytes.clone()];
            bad[1].push(0);
            let mut magic = bytes.clone();
            magic[0] = b'Q';
            bad.push(magic);
            if kind == FrameKind::Delta {
                let mut orphan = bytes.clone();
                orphan[24..32].copy_from_slice(&(key_seq - 1).to_le_bytes());
                bad.push(orphan);
            }
            for b in bad {
                assert!(decoder.decode(&b).is_err());
                out.push(json!({"bytes": b, "expect": null}));
            }
        }
        let frame = decoder.decode(&bytes).unwrap();
        out.push(json!({
            "bytes": bytes,
            "expect": {
                "key": kind == FrameKind::Key,
                "scene_num": frame.header.scene_num,
                "seq": frame.header.seq,
                "server_time_us": frame.header.server_time_us,
                "base_seq": frame.header.base_seq,
                "avatars": frame.avatars.iter().map(pose_json).collect::<Vec<_>>(),
            },
        }));
        if kind == FrameKind::Key {
            // A later keyframe cut short in its last chunk: refused whole, so the first
            // avatar's keyframe stays this one and the next deltas still decode.
            let mut cut = bytes.clone();
            cut[8..16].copy_from_slice(&(seq + 500).to_le_bytes());
            cut[24..32].copy_from_slice(&(seq + 500).to_le_bytes());
            cut.pop();
            assert!(decoder.decode(&cut).is_err());
            out.push(json!({"bytes": cut, "expect": null}));
        }
    }
    out
}

/// The expected decoding of a frame (as both decoders report it).
fn frame_json(frame: &Frame) -> Value {
    json!({
        "key": frame.header.kind == FrameKind::Key,
        "scene_num": frame.header.scene_num,
        "seq": frame.header.seq,
        "server_time_us": frame.header.server_time_us,
        "base_seq": frame.header.base_seq,
        "avatars": frame.avatars.iter().map(pose_json).collect::<Vec<_>>(),
    })
}

/// A v2 frame's bytes with its header rewritten (`seq`, `base_seq`), its chunks kept.
fn v2_rehead(bytes: &[u8], seq: u64, base_seq: u64) -> Vec<u8> {
    let (header, count) = frame2::read_header(bytes).unwrap();
    let mut old = Vec::new();
    frame2::write_header(&header, count, &mut old);
    let mut out = Vec::new();
    frame2::write_header(
        &FrameHeader {
            seq,
            base_seq,
            ..header
        },
        count,
        &mut out,
    );
    out.extend_from_slice(&bytes[old.len()..]);
    out
}

/// Malformed variants of a v2 frame the decoder holding `decoder`'s state refuses (checked
/// here): cut short (by one byte and at a random point), one byte too many, v1's magic, an
/// unknown kind, and for a delta a base it does not hold, a reserved flag bit and a zero gap.
fn v2_refused(bytes: &[u8], decoder: &mut Frame2Decoder, rng: &mut Lcg) -> Vec<Value> {
    let (header, _) = frame2::read_header(bytes).unwrap();
    let mut bad = vec![
        bytes[..bytes.len() - 1].to_vec(),
        bytes[..(rng.next() * bytes.len() as f32) as usize].to_vec(),
        [bytes, &[0]].concat(),
    ];
    let mut magic = bytes.to_vec();
    magic[0] = posecast_proto::frame::MAGIC;
    bad.push(magic);
    let mut kind = bytes.to_vec();
    kind[1] = 3;
    bad.push(kind);
    if header.kind == FrameKind::Delta {
        bad.push(v2_rehead(bytes, header.seq, header.base_seq - 1));
        bad.push(v2_rehead(bytes, header.seq + 3, header.base_seq + 3));
        let mut head = Vec::new();
        frame2::write_header(&header, 2, &mut head);
        // The first chunk's flags follow its avatar number (one byte: avatars 1 and 2).
        let mut reserved = bytes.to_vec();
        reserved[head.len() + 1] |= 8;
        bad.push(reserved);
        let mut gap = bytes.to_vec();
        gap[head.len() - 1] = 0;
        bad.push(gap);
    }
    bad.into_iter()
        .map(|b| {
            assert!(decoder.decode(&b).is_err(), "{b:?}");
            json!({"bytes": b, "expect": null})
        })
        .collect()
}

/// Two avatars moving for 120 ticks, coded in wire v2 by `posecast_proto::frame2`: what
/// `Frame2Decoder` makes of each frame, in order, (`fast`) for a reader of every frame (the
/// `StreamEncoder`'s deltas against the previous frame, up to depth 8, a keyframe every 40
/// ticks) and (`slow`) for one that misses frames and, after a gap, gets a keyframe or a delta
/// against the last frame it decoded — and the fast stream's deltas whose base it lacks.
/// Joints mostly turn a little (predicted, Rice-coded), some jump (escapes), the first avatar
/// now and then teleports (Rice escapes); placements and scales change; the fast stream codes
/// the second avatar on a precision's grid (version 5). Malformed frames
/// between the good ones: `null`, and they change nothing.
fn frame2_vectors(rng: &mut Lcg) -> Value {
    let joints = [9usize, 23];
    let mut poses: Vec<AvatarPose> = joints
        .iter()
        .enumerate()
        .map(|(i, &n)| AvatarPose {
            avatar_num: i as u32 + 1,
            hash: 0xf00d_0000_0000_0000 + i as u64,
            rotations: (0..n).map(|_| rng.quat()).collect(),
            translations: vec![rng.vec3(); i + 1],
            scales: if i == 1 {
                vec![rng.vec3(), rng.vec3()]
            } else {
                vec![]
            },
            placement: Placement::IDENTITY,
            // The second avatar has a face: seven morph channels (protocol version 4).
            weights: if i == 1 {
                (0..7).map(|_| rng.next()).collect()
            } else {
                Vec::new()
            },
        })
        .collect();
    let spin: Vec<Vec<Vec3>> = poses
        .iter()
        .map(|p| p.rotations.iter().map(|_| rng.vec3() * 0.02).collect())
        .collect();
    let velocity = rng.vec3() * 0.02;
    let mut stream = StreamEncoder::new();
    // The fast stream codes the second avatar at a subscription's precision (protocol version
    // 6): grid steps from the finest to the coarsest per joint, each joint's coarser step near
    // an axis for the same bound, and a coarse translation step.
    let steps: Vec<u8> = (0..joints[1])
        .map(|j| {
            if j % 4 == 0 {
                1
            } else {
                (rng.next() * 254.0) as u8 + 1
            }
        })
        .collect();
    stream.set_steps(
        2,
        std::sync::Arc::new(posecast_proto::precision::Steps {
            near: near_steps(&steps),
            rotations: steps,
            translation: 37,
        }),
    );
    let (mut fast, mut slow) = (Frame2Decoder::new(), Frame2Decoder::new());
    let (mut fast_out, mut slow_out) = (Vec::new(), Vec::new());
    let mut ring: Vec<Vec<QuantPose>> = Vec::new();
    let mut slow_seqs: Vec<u64> = Vec::new();
    let (first, ticks) = (1000u64, 120u64);
    for seq in first..first + ticks {
        for (pose, spin) in poses.iter_mut().zip(&spin) {
            for (q, w) in pose.rotations.iter_mut().zip(spin) {
                let r = rng.next();
                if r < 0.05 {
                    *q = rng.quat();
                } else if r < 0.9 {
                    *q = (Quat::from_scaled_axis(*w + rng.vec3() * 0.001) * *q).normalize();
                }
            }
            for t in &mut pose.translations {
                *t += velocity + rng.vec3() * 0.0005;
            }
            if rng.next() < 0.1 {
                pose.placement =
                    Placement::try_new((rng.vec3() * 5.0).to_array(), rng.quat().to_array())
                        .unwrap();
            }
            if rng.next() < 0.1 {
                for s in &mut pose.scales {
                    *s = rng.vec3();
                }
            }
            // Speech: a channel or two moves most ticks; now and then all rest at 0 or 1.
            for w in &mut pose.weights {
                let r = rng.next();
                if r < 0.25 {
                    *w = rng.next();
                } else if r < 0.28 {
                    *w = if r < 0.265 { 0.0 } else { 1.0 };
                }
            }
        }
        if seq % 13 == 0 {
            poses[0].translations[0] += Vec3::new(100.0, -40.0, 7.5);
        }
        let time = 1_763_891_000_000_000 + seq * 16_667;
        let (bytes, kind) = stream.encode(5, seq, time, &poses, seq % 40 == 0);
        if seq % 5 == 2 {
            fast_out.extend(v2_refused(&bytes, &mut fast, rng));
        }
        let frame = fast.decode(&bytes).unwrap();
        fast_out.push(json!({"bytes": bytes, "expect": frame_json(&frame)}));
        let q: Vec<QuantPose> = poses.iter().map(QuantPose::from_pose).collect();
        ring.push(q.clone());

        // The slow reader: misses about one frame in three.
        if rng.next() < 0.35 && seq > first {
            continue;
        }
        if kind == FrameKind::Delta && slow_seqs.first() != Some(&(seq - 1)) {
            // The fast stream's delta refers to a frame this reader missed.
            assert!(slow.decode(&bytes).is_err());
            slow_out.push(json!({"bytes": bytes, "expect": null}));
        }
        let gap = slow_seqs.first().is_some_and(|&s| s + 1 != seq);
        let mut body = Vec::new();
        let bytes = if slow_seqs.is_empty() || gap && rng.next() < 0.3 {
            for (p, now) in poses.iter().zip(&q) {
                frame2::encode_key(p.avatar_num, p.hash, now, &mut body);
            }
            slow_seqs.clear();
            v2_frame(FrameKind::Key, seq, seq, time, &body)
        } else {
            for (k, (p, now)) in poses.iter().zip(&q).enumerate() {
                let h: Vec<&QuantPose> = slow_seqs
                    .iter()
                    .map(|&s| &ring[(s - first) as usize][k])
                    .collect();
                assert!(frame2::encode_delta(p.avatar_num, now, &h, &mut body));
            }
            v2_frame(FrameKind::Delta, seq, slow_seqs[0], time, &body)
        };
        if seq % 4 == 1 {
            slow_out.extend(v2_refused(&bytes, &mut slow, rng));
        }
        let frame = slow.decode(&bytes).unwrap();
        slow_out.push(json!({"bytes": bytes, "expect": frame_json(&frame)}));
        slow_seqs.insert(0, seq);
        slow_seqs.truncate(frame2::MAX_DEPTH);
    }
    json!({"fast": fast_out, "slow": slow_out, "odd": frame2_odd_vectors(rng)})
}

fn v2_frame(kind: FrameKind, seq: u64, base_seq: u64, time: u64, body: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let header = FrameHeader {
        kind,
        scene_num: 5,
        seq,
        server_time_us: time,
        base_seq,
    };
    frame2::write_header(&header, 2, &mut out);
    out.extend_from_slice(body);
    out
}

/// Short sequences, each for a fresh decoder: three good frames of a 5-joint avatar, then one
/// odd one — a delta with a bit or two flipped, a delta chunk of random bytes (any depth, flags and bit stream: whatever
/// `Frame2Decoder` makes of it, decoded or refused), a keyframe with the avatar twice, a count
/// over the limit, an 11-byte varint, a scene number over u32 — and what it makes of that.
fn frame2_odd_vectors(rng: &mut Lcg) -> Vec<Value> {
    let pose = AvatarPose {
        avatar_num: 1,
        hash: 0xabad_cafe_0000_0001,
        rotations: (0..5).map(|_| rng.quat()).collect(),
        translations: vec![rng.vec3()],
        scales: vec![Vec3::ONE],
        placement: Placement::IDENTITY,
        weights: Vec::new(),
    };
    let header = |kind, count: usize, seq: u64, base_seq: u64| {
        let mut out = Vec::new();
        frame2::write_header(
            &FrameHeader {
                kind,
                scene_num: 4,
                seq,
                server_time_us: 77,
                base_seq,
            },
            count,
            &mut out,
        );
        out
    };
    let prefix: Vec<Vec<u8>> = {
        let mut stream = StreamEncoder::new();
        (1..4)
            .map(|seq| {
                stream
                    .encode(4, seq, 0, std::slice::from_ref(&pose), false)
                    .0
            })
            .collect()
    };
    let primed = || {
        let mut dec = Frame2Decoder::new();
        for p in &prefix {
            dec.decode(p).unwrap();
        }
        dec
    };
    let mut odd: Vec<Vec<u8>> = Vec::new();
    for case in 0..120 {
        let mut bytes = header(FrameKind::Delta, 1, 4, 3);
        let depth = (rng.next() * 4.0) as u8;
        bytes.extend([1, depth << 4 | (rng.next() * 8.0) as u8]);
        // Mostly ones (long unary runs, Rice escapes) in some cases, uniform in others.
        let ones = case % 3 == 0;
        let start = bytes.len();
        for _ in 0..(rng.next() * 80.0) as usize {
            let b = (rng.next() * 256.0) as u8;
            bytes.push(if ones { b | 0xf7 } else { b });
        }
        // Every other case cut where the Rust decoder takes it whole, if anywhere: random bit
        // streams decoded, not only refused.
        let fits = (start..=bytes.len()).find(|&n| primed().decode(&bytes[..n]).is_ok());
        match fits {
            Some(n) if case % 2 == 0 => odd.push(bytes[..n].to_vec()),
            _ => odd.push(bytes),
        }
    }
    // The next good delta (the avatar turned and moved) with one or two bytes changed.
    let mut moved = pose.clone();
    for q in &mut moved.rotations {
        *q = (Quat::from_scaled_axis(rng.vec3() * 0.01) * *q).normalize();
    }
    moved.translations[0] += rng.vec3() * 0.01;
    let next = {
        let mut stream = StreamEncoder::new();
        for seq in 1..4 {
            stream.encode(4, seq, 0, std::slice::from_ref(&pose), false);
        }
        stream
            .encode(4, 4, 0, std::slice::from_ref(&moved), false)
            .0
    };
    for case in 0..60 {
        let mut b = next.clone();
        for _ in 0..1 + case % 2 {
            let at = (rng.next() * b.len() as f32) as usize;
            b[at] ^= 1 << (rng.next() * 8.0) as u32;
        }
        odd.push(b);
    }
    odd.push(next);
    let mut chunk = Vec::new();
    frame2::encode_key(1, 9, &QuantPose::from_pose(&pose), &mut chunk);
    odd.push(
        [
            header(FrameKind::Key, 2, 9, 9),
            chunk.clone(),
            chunk.clone(),
        ]
        .concat(),
    );
    let mut count = header(FrameKind::Key, 1, 9, 9);
    count.extend([1, 0, 0, 0, 0, 0, 0, 0, 0, 0x80, 0x80, 0x08, 0, 0, 0]);
    odd.push(count);
    let mut long = vec![frame2::MAGIC, 1];
    long.extend([0x81; 10]);
    long.push(1);
    odd.push(long);
    let mut scene = vec![frame2::MAGIC, 1, 0];
    scene.extend([0x80, 0x80, 0x80, 0x80, 0x10, 1, 1]);
    odd.push(scene);
    // A keyframe of seq 2⁶⁰: the Rust decoder takes it; the JavaScript one refuses it (beyond
    // 2⁵³, it cannot hold the seq exactly).
    odd.push([header(FrameKind::Key, 1, 1 << 60, 1 << 60), chunk].concat());
    odd.into_iter()
        .map(|b| {
            let expect = primed().decode(&b).ok().map(|f| frame_json(&f));
            let beyond_js = expect
                .as_ref()
                .is_some_and(|f| f["seq"].as_u64() > Some(1 << 53));
            json!({"prefix": prefix, "bytes": b, "expect": expect, "beyond_js": beyond_js})
        })
        .collect()
}

fn kind_name(k: Sampled) -> &'static str {
    match k {
        Sampled::Interpolated => "interpolated",
        Sampled::Extrapolated => "extrapolated",
        Sampled::Held => "held",
    }
}

/// A 60 Hz stream with jittery arrivals, a late burst and a gap pushed into a
/// `JitterBuffer`, queried around the playout point after every few pushes.
fn jitter_vectors(rng: &mut Lcg) -> Value {
    let tick = 16_667u64;
    let mut buffer = JitterBuffer::new(60.0);
    let mut steps = Vec::new();
    let mut pose: Vec<Transform> = (0..3)
        .map(|_| Transform {
            translation: rng.vec3(),
            rotation: rng.quat(),
            scale: Vec3::ONE,
        })
        .collect();
    let start = 5_000_000u64;
    for i in 0..400u64 {
        if (200..215).contains(&i) {
            continue; // a quarter-second gap: extrapolated, then held
        }
        for t in &mut pose {
            t.rotation = (Quat::from_scaled_axis(rng.vec3() * 0.05) * t.rotation).normalize();
            t.translation += rng.vec3() * 0.01;
        }
        let stamp = start + i * tick;
        // 20 ms base delay (and clock offset), up to 8 ms jitter, now and then 60 ms late.
        let late = if i % 53 == 0 { 60_000.0 } else { 0.0 };
        let arrival = stamp + 20_000 + (rng.range(0.0, 8_000.0) + late) as u64;
        buffer.push(stamp, arrival, pose.clone());
        let mut queries = Vec::new();
        if i % 5 == 0 {
            for offset in [-40_000.0, -8_000.0, 0.0, 9_000.0, 50_000.0, 150_000.0] {
                let now = arrival as f64 + offset;
                let time = buffer.playout_time(now as u64);
                let (sampled, kind) = buffer.sample_with_kind(time).unwrap();
                queries.push(json!({
                    "now": now as u64,
                    "time": time,
                    "kind": kind_name(kind),
                    "rotations": sampled.iter().map(|t| t.rotation.to_array()).collect::<Vec<_>>(),
                    "translations": sampled.iter().map(|t| t.translation.to_array()).collect::<Vec<_>>(),
                }));
            }
        }
        steps.push(json!({
            "stamp": stamp,
            "arrival": arrival,
            "rotations": pose.iter().map(|t| t.rotation.to_array()).collect::<Vec<_>>(),
            "translations": pose.iter().map(|t| t.translation.to_array()).collect::<Vec<_>>(),
            "delay": buffer.delay_us(),
            "queries": queries,
        }));
    }
    json!(steps)
}

/// Ping/pong exchanges, the slow ones asymmetric, and the estimate after each.
fn clock_vectors(rng: &mut Lcg) -> Value {
    let mut clock = ClockEstimator::new();
    let offset = 7_340_000.0f32;
    let mut out = Vec::new();
    let mut t0 = 1_000_000u64;
    for _ in 0..40 {
        let up = rng.range(200.0, 30_000.0);
        let down = rng.range(200.0, 30_000.0);
        let server = (t0 as f32 + up + offset) as u64;
        let t1 = t0 + (up + down) as u64;
        clock.add(t0, server, t1);
        out.push(json!({
            "t0": t0, "server": server, "t1": t1,
            "offset": clock.offset_us(), "rtt": clock.rtt_us(),
        }));
        t0 = t1 + 100_000;
    }
    json!(out)
}

/// Random trees and joint sets: the joints `posecast_proto::subset` selects, and a pose of
/// those joints made whole by hand (every other joint at rest) — what `subset.js` must give.
fn subset_vectors(rng: &mut Lcg) -> Value {
    let mut out = Vec::new();
    for case in 0..40 {
        let n = 1 + (rng.next() * 40.0) as usize;
        // Parents before children; about one tree in four has a second root.
        let parents: Vec<i32> = (0..n)
            .map(|j| {
                if j == 0 || rng.next() < 0.05 {
                    -1
                } else {
                    (rng.next() * j as f32) as i32
                }
            })
            .collect();
        let names: Vec<String> = (0..n).map(|j| format!("j{j}")).collect();
        let rest_rotations: Vec<[f32; 4]> = (0..n).map(|_| rng.quat().to_array()).collect();
        let rest_translations: Vec<[f32; 3]> = (0..n).map(|_| rng.vec3().to_array()).collect();
        let rest_scales: Vec<[f32; 3]> = (0..n).map(|_| rng.vec3().to_array()).collect();
        let translated: Vec<u16> = (0..n as u16).filter(|_| rng.next() < 0.3).collect();
        let scaled: Vec<u16> = (0..n as u16).filter(|_| rng.next() < 0.2).collect();
        let d = AvatarDescription {
            id: AvatarId(format!("a{case}")),
            num: case,
            name: "tree".into(),
            joint_names: names.clone(),
            parents: parents.clone(),
            rest_translations,
            rest_rotations,
            rest_scales,
            inverse_binds: vec![glam::Mat4::IDENTITY.to_cols_array(); n],
            translated_joints: translated,
            scaled_joints: scaled,
            mesh_url: None,
            morph_targets: vec![],
            expressions: std::collections::BTreeMap::new(),
            expression_binds: Vec::new(),
            clip: None,
            hash: String::new(),
        };
        let set = if case % 2 == 0 {
            JointSet::Depth((rng.next() * 6.0) as u16)
        } else {
            let k = 1 + (rng.next() * 4.0) as usize;
            let mut picked: Vec<String> = (0..k)
                .map(|_| names[(rng.next() * n as f32) as usize].clone())
                .collect();
            picked.push("no such joint".into());
            JointSet::Names(picked)
        };
        let sel = set.select(&d);
        // The part sent, and the whole pose by hand.
        let sent_rotations: Vec<[f32; 4]> =
            sel.joints.iter().map(|_| rng.quat().to_array()).collect();
        let sent_t: Vec<[f32; 3]> = sel
            .translations
            .iter()
            .map(|_| rng.vec3().to_array())
            .collect();
        let sent_s: Vec<[f32; 3]> = sel.scales.iter().map(|_| rng.vec3().to_array()).collect();
        let mut rotations = d.rest_rotations.clone();
        for (k, &j) in sel.joints.iter().enumerate() {
            rotations[usize::from(j)] = sent_rotations[k];
        }
        let whole = |list: &[u16], which: &[usize], sent: &[[f32; 3]], rest: &[[f32; 3]]| {
            list.iter()
                .enumerate()
                .map(|(i, &j)| match which.iter().position(|&w| w == i) {
                    Some(k) => sent[k],
                    None => rest[usize::from(j)],
                })
                .collect::<Vec<_>>()
        };
        out.push(json!({
            "description": d,
            "set": set,
            "joints": sel.joints,
            "sent": {"rotations": sent_rotations, "translations": sent_t, "scales": sent_s},
            "whole": {
                "rotations": rotations,
                "translations": whole(&d.translated_joints, &sel.translations, &sent_t, &d.rest_translations),
                "scales": whole(&d.scaled_joints, &sel.scales, &sent_s, &d.rest_scales),
            },
        }));
    }
    json!(out)
}

#[test]
fn the_clients_decoder_jitter_buffer_and_clock_match_the_rust_ones() {
    let mut rng = Lcg(0x57_4ea4);
    let vectors = json!({
        "frames": frame_vectors(&mut rng),
        "frames2": frame2_vectors(&mut rng),
        "jitter": jitter_vectors(&mut rng),
        "clock": clock_vectors(&mut rng),
        "subsets": subset_vectors(&mut rng),
    });
    let file = std::env::temp_dir().join(format!("posecast-stream-{}.json", std::process::id()));
    std::fs::write(&file, serde_json::to_vec(&vectors).unwrap()).unwrap();
    let script = root().join("server/web/check/stream.mjs");
    let out = match Process::new("node").arg(&script).arg(&file).output() {
        Ok(out) => out,
        Err(e) => {
            skip(&format!(
                "node is not installed ({e}): the JavaScript decoder is not checked"
            ));
            return;
        }
    };
    std::fs::remove_file(&file).ok();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "stream.mjs: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_str(stdout.trim()).unwrap();
    assert!(report["frames"].as_u64().unwrap() >= 60, "{report}");
    assert!(report["refused"].as_u64().unwrap() >= 20, "{report}");
    assert_eq!(report["subsets"].as_u64(), Some(40), "{report}");
    let v2 = &report["v2"];
    assert_eq!(v2["fast"]["frames"].as_u64(), Some(120), "{report}");
    assert!(v2["fast"]["keys"].as_u64().unwrap() >= 3, "{report}");
    assert!(v2["fast"]["refused"].as_u64().unwrap() >= 100, "{report}");
    assert!(v2["slow"]["frames"].as_u64().unwrap() >= 60, "{report}");
    assert!(v2["slow"]["keys"].as_u64().unwrap() >= 3, "{report}");
    assert!(v2["slow"]["refused"].as_u64().unwrap() >= 60, "{report}");
    let odd = &report["odd"];
    assert_eq!(odd["beyond"].as_u64(), Some(1), "{report}");
    assert_eq!(report["fuzz"].as_u64(), Some(3000), "{report}");
    assert!(odd["decoded"].as_u64().unwrap() >= 10, "{report}");
    assert!(odd["refused"].as_u64().unwrap() >= 50, "{report}");
    for kind in ["interpolated", "extrapolated", "held"] {
        assert!(
            report["kinds"][kind].as_u64().unwrap_or(0) >= 5,
            "{kind}: {report}"
        );
    }
    println!("JavaScript stream parts vs Rust: {report}");
}

/// Each joint's near-axis step for the bound of its step `m` (as `Precision::resolve_with`
/// gives a protocol version 6 subscriber).
fn near_steps(steps: &[u8]) -> Vec<u8> {
    use posecast_proto::precision::{near_rotation_step_for, rotation_bound_degrees};
    steps
        .iter()
        .map(|&m| near_rotation_step_for(rotation_bound_degrees(m)).max(m))
        .collect()
}
