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
//! - the same decoder reads packed deltas (protocol version 7, frame kind 3: a packing
//!   `StreamEncoder`'s and hand-made `PackedDeltas`) to exactly the levels and server times
//!   `Frame2Decoder` reads (avatar numbers consecutive or not, up to 2³² − 1; precision grids
//!   with tiers; placements, scales and morph weights; times jittering, going back, up to
//!   2⁵³ − 1 and past it, which it refuses), and refuses what it refuses: a packed delta whose
//!   base is not the scene's last decoded frame (its time cannot be read), one whose avatar's
//!   base is not held, one after the scene was forgotten, a lagging reader's after a miss,
//!   malformed ones; random packed bit streams decoded or refused alike;
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
pub(crate) struct Lcg(pub(crate) u64);

impl Lcg {
    pub(crate) fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }

    pub(crate) fn vec3(&mut self) -> Vec3 {
        Vec3::new(
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
        )
    }

    pub(crate) fn quat(&mut self) -> Quat {
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
pub(crate) fn frame_json(frame: &Frame) -> Value {
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
    // (3 is a packed delta, protocol version 7.)
    kind[1] = 4;
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
pub(crate) fn near_steps(steps: &[u8]) -> Vec<u8> {
    use posecast_proto::precision::{near_rotation_step_for, rotation_bound_degrees};
    steps
        .iter()
        .map(|&m| near_rotation_step_for(rotation_bound_degrees(m)).max(m))
        .collect()
}

// Packed deltas (protocol version 7, frame kind 3).

/// A LEB128 varint.
pub(crate) fn put_varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(r: i64) -> u64 {
    ((r << 1) ^ (r >> 63)) as u64
}

/// Bits written least significant first, as a v2 bit stream (padded with 0 by `bytes`).
#[derive(Default)]
struct Bits(Vec<bool>);

impl Bits {
    fn put(&mut self, v: u64, n: u32) {
        self.0.extend((0..n).map(|i| v >> i & 1 == 1));
    }

    fn bytes(&self) -> Vec<u8> {
        self.0
            .chunks(8)
            .map(|c| c.iter().rev().fold(0u8, |b, &bit| b << 1 | u8::from(bit)))
            .collect()
    }
}

/// A packed delta's header fields: (count, scene, seq, gap, zigzagged time difference), and
/// where its bit stream starts.
fn packed_header(bytes: &[u8]) -> ([u64; 5], usize) {
    assert_eq!(bytes[..2], [frame2::MAGIC, 3]);
    let mut at = 2;
    let mut fields = [0u64; 5];
    for f in &mut fields {
        let mut shift = 0;
        loop {
            let b = bytes[at];
            at += 1;
            *f |= u64::from(b & 0x7f) << shift;
            shift += 7;
            if b & 0x80 == 0 {
                break;
            }
        }
    }
    (fields, at)
}

/// A packed delta with its header fields replaced, its bit stream kept.
fn packed_rehead(bytes: &[u8], fields: [u64; 5]) -> Vec<u8> {
    let (_, at) = packed_header(bytes);
    let mut out = vec![frame2::MAGIC, 3];
    for f in fields {
        put_varint(f, &mut out);
    }
    out.extend_from_slice(&bytes[at..]);
    out
}

/// A decoded frame's levels (what `QuantPose` holds: exactly what the JavaScript decoder must
/// hold too), beside its poses.
pub(crate) fn levels_json(q: &QuantPose) -> Value {
    json!({
        "rotations": q.rotations,
        "translations": q.translations,
        "scales": q.scales.iter().map(|s| s.to_array()).collect::<Vec<_>>(),
        "placement": {
            "position": q.placement.position.to_array(),
            "rotation": q.placement.rotation.to_array(),
        },
        "weights": q.weights,
        "steps": q.steps.as_deref().map(|s| json!({
            "rotations": s.rotations, "translation": s.translation, "near": s.near,
        })),
    })
}

/// What `decoder` makes of `bytes` (decoded: the frame, its levels; refused: `null`), as a
/// vector; `beyond_js` when it decodes a server time or seq beyond 2⁵³, which the JavaScript
/// decoder refuses.
fn packed_step(decoder: &mut Frame2Decoder, bytes: Vec<u8>) -> Value {
    let expect = decoder.decode_levels(&bytes).ok().map(|f| {
        let mut v = frame_json(&f.to_frame());
        v["levels"] = f.avatars.iter().map(|a| levels_json(&a.levels)).collect();
        v
    });
    let beyond_js = expect.as_ref().is_some_and(|f| {
        f["server_time_us"].as_u64() > Some((1 << 53) - 1)
            || f["seq"].as_u64() > Some((1 << 53) - 1)
    });
    json!({"bytes": bytes, "expect": expect, "beyond_js": beyond_js})
}

/// A still avatar, or one whose joints turn (now and then jump), whose root walks, whose
/// placement, scales and morph weights change now and then.
pub(crate) fn packed_move(pose: &mut AvatarPose, rng: &mut Lcg) {
    for q in &mut pose.rotations {
        let r = rng.next();
        if r < 0.03 {
            *q = rng.quat();
        } else if r < 0.9 {
            *q = (Quat::from_scaled_axis(rng.vec3() * 0.01) * *q).normalize();
        }
    }
    for t in &mut pose.translations {
        *t += rng.vec3() * 0.01;
    }
    if rng.next() < 0.1 {
        pose.placement =
            Placement::try_new((rng.vec3() * 5.0).to_array(), rng.quat().to_array()).unwrap();
    }
    if rng.next() < 0.1 {
        for s in &mut pose.scales {
            *s = rng.vec3();
        }
    }
    for w in &mut pose.weights {
        if rng.next() < 0.2 {
            *w = rng.next();
        }
    }
}

pub(crate) fn packed_pose(
    rng: &mut Lcg,
    num: u32,
    joints: usize,
    scales: usize,
    weights: usize,
) -> AvatarPose {
    AvatarPose {
        avatar_num: num,
        hash: 0x7ac0_0000_0000_0000 + u64::from(num),
        rotations: (0..joints).map(|_| rng.quat()).collect(),
        translations: vec![rng.vec3()],
        scales: (0..scales).map(|_| rng.vec3()).collect(),
        placement: Placement::IDENTITY,
        weights: (0..weights).map(|_| rng.next()).collect(),
    }
}

/// Packed delta streams and what `Frame2Decoder` makes of each frame, in order:
/// - `main`, through one decoder: scene 6, nine avatars (numbers 0, 1, 2, 9, 5, 6, 70,000,
///   2³² − 2, 2³² − 1: runs of consecutive numbers, jumps up and down, the largest) coded by a
///   packing `StreamEncoder` — three on a precision's tiered grid, two with morph weights, two
///   with scales, two still (the usual chunk head) — for 160 ticks with a keyframe every 40,
///   server times jittering by some hundred µs and once going back 250 µs; interleaved with
///   scene 7, whose times run up to 2⁵³ − 1 (exact in JavaScript) and then past it (the Rust
///   decoder takes that frame, the JavaScript one refuses it), and scene 8, hand-made frames
///   checking the scene clock (a packed delta whose avatar's base is held but which is not the
///   scene's last frame; one after a kind 2 delta, going back in time; one with an avatar
///   whose base is not held; one without avatars; one after the scene was forgotten). Refused variants of scene
///   6's packed deltas (cut short, a byte too many, a base other than the last frame, v1's
///   magic, an unknown kind) between the good ones: `null`, and they change nothing.
/// - `lagging`: scene 6's frames to a reader that starts late and misses some (a keyframe
///   too): the packed deltas after a miss refused until the next keyframe.
/// - `odd`: after a short packed stream of two avatars, each through a fresh decoder: its next
///   packed delta with a bit or two flipped, and packed deltas whose first chunk is an avatar
///   held, a random head and random bits — decoded or refused, as the Rust decoder does.
fn packed_vectors(rng: &mut Lcg) -> Value {
    let mut main = Vec::new();
    let mut decoder = Frame2Decoder::new();
    let mut lag = Frame2Decoder::new();
    let mut lagging = Vec::new();
    let nums = [0u32, 1, 2, 9, 5, 6, 70_000, u32::MAX - 1, u32::MAX];
    let joints = [4usize, 7, 5, 6, 3, 8, 5, 4, 6];
    let mut poses: Vec<AvatarPose> = nums
        .iter()
        .zip(joints)
        .enumerate()
        .map(|(i, (&num, j))| {
            let scales = if i == 2 || i == 6 { 2 } else { 0 };
            let weights = if i == 3 || i == 7 { 6 } else { 0 };
            packed_pose(rng, num, j, scales, weights)
        })
        .collect();
    let still = [5usize, 8];
    let mut stream = StreamEncoder::new().with_packing(true);
    for i in [1usize, 4, 7] {
        let steps: Vec<u8> = (0..joints[i])
            .map(|_| (rng.next() * 40.0) as u8 + 1)
            .collect();
        stream.set_steps(
            nums[i],
            std::sync::Arc::new(posecast_proto::precision::Steps {
                near: near_steps(&steps),
                rotations: steps,
                translation: 11,
            }),
        );
    }
    // Scene 7: two avatars, times up to 2⁵³ − 1, then one beyond.
    let mut near_end = StreamEncoder::new().with_packing(true);
    let mut pair = vec![packed_pose(rng, 3, 5, 0, 0), packed_pose(rng, 4, 5, 1, 0)];
    let mut near_seq = 0u64;
    let (first, ticks) = (1000u64, 160u64);
    let mut time = 1_763_891_000_000_000u64;
    let mut backwards = 0;
    for seq in first..first + ticks {
        for (i, p) in poses.iter_mut().enumerate() {
            if !still.contains(&i) {
                packed_move(p, rng);
            }
        }
        let before = time;
        time += 16_667;
        time = time + (rng.next() * 800.0) as u64 - 400;
        if seq == first + 77 {
            time = before - 250;
        }
        let (bytes, kind) = stream.encode(6, seq, time, &poses, seq % 40 == 0);
        if kind == FrameKind::Delta {
            assert_eq!(bytes[1], 3, "a packing stream's deltas are packed");
            backwards += usize::from(time < before);
        }
        if kind == FrameKind::Delta && seq % 7 == 3 {
            let (fields, _) = packed_header(&bytes);
            let [count, scene, s, gap, since] = fields;
            let mut bad = vec![
                bytes[..bytes.len() - 1].to_vec(),
                bytes[..(rng.next() * bytes.len() as f32) as usize].to_vec(),
                [&bytes[..], &[0]].concat(),
                packed_rehead(&bytes, [count, scene, s, gap + 1, since]),
                packed_rehead(&bytes, [count, scene, s + 1, gap, since]),
            ];
            let mut magic = bytes.clone();
            magic[0] = posecast_proto::frame::MAGIC;
            bad.push(magic);
            let mut kind = bytes.clone();
            kind[1] = 4;
            bad.push(kind);
            for b in bad {
                assert!(decoder.decode(&b).is_err(), "{b:?}");
                main.push(json!({"bytes": b, "expect": null, "beyond_js": false}));
            }
        }
        main.push(packed_step(&mut decoder, bytes.clone()));
        // The lagging reader starts late, misses a frame after each keyframe and misses a
        // keyframe.
        if seq >= first + 5 && seq % 40 != 25 && seq != first + 80 {
            lagging.push(packed_step(&mut lag, bytes));
        }
        if seq % 5 == 1 && near_seq <= 30 {
            near_seq += 1;
            for p in &mut pair {
                packed_move(p, rng);
            }
            let t = if near_seq <= 30 {
                (1u64 << 53) - 1 - (30 - near_seq) * 16_667
            } else {
                (1 << 53) + 2
            };
            let (bytes, _) = near_end.encode(7, near_seq, t, &pair, near_seq == 1);
            main.push(packed_step(&mut decoder, bytes));
        }
        if seq == first + 50 {
            main.extend(clock_vectors_packed(rng, &mut decoder));
        }
    }
    assert!(backwards >= 1);
    json!({"main": main, "lagging": lagging, "odd": packed_odd_vectors(rng)})
}

/// Scene 8, hand-made: the scene clock a packed delta's time is read from (see
/// [`packed_vectors`]), through `decoder`; `{"forget": 8}` forgets the scene.
fn clock_vectors_packed(rng: &mut Lcg, decoder: &mut Frame2Decoder) -> Vec<Value> {
    use posecast_proto::frame2::{Frame2Error, PackedDeltas};
    let mut a = packed_pose(rng, 3, 5, 0, 0);
    let mut b = packed_pose(rng, 4, 6, 1, 2);
    // Levels of A and B at seqs 10 to 17.
    let mut qa = std::collections::BTreeMap::new();
    let mut qb = std::collections::BTreeMap::new();
    for seq in 10u64..19 {
        packed_move(&mut a, rng);
        packed_move(&mut b, rng);
        qa.insert(seq, QuantPose::from_pose(&a));
        qb.insert(seq, QuantPose::from_pose(&b));
    }
    let t = |seq: u64| {
        let t = 1_700_000_000_000_000 + seq * 20_000;
        if seq == 12 { t - 20_300 } else { t }
    };
    let header = |kind, seq, base_seq| FrameHeader {
        kind,
        scene_num: 8,
        seq,
        server_time_us: t(seq),
        base_seq,
    };
    let key = |seq| {
        let mut out = Vec::new();
        frame2::write_header(&header(FrameKind::Key, seq, seq), 2, &mut out);
        frame2::encode_key(3, a.hash, &qa[&seq], &mut out);
        frame2::encode_key(4, b.hash, &qb[&seq], &mut out);
        out
    };
    // Chunks (avatar, seq, history seqs newest first) of a packed delta of `seq` on `base`.
    let packed = |seq, base, chunks: &[(u32, &[u64])]| {
        let mut out = Vec::new();
        let mut p = PackedDeltas::new(
            &header(FrameKind::Delta, seq, base),
            t(base),
            chunks.len(),
            &mut out,
        );
        for &(num, held) in chunks {
            let q = if num == 3 { &qa } else { &qb };
            let h: Vec<&QuantPose> = held.iter().map(|s| &q[s]).collect();
            assert!(p.push(num, &q[&seq], &h));
        }
        p.finish();
        out
    };
    // A kind 2 delta of A alone.
    let mut d11 = Vec::new();
    frame2::write_header(&header(FrameKind::Delta, 11, 10), 1, &mut d11);
    assert!(frame2::encode_delta(3, &qa[&11], &[&qa[&10]], &mut d11));
    // Each frame and why the decoder refuses it, if it does; `None`: the scene forgotten.
    let plan = [
        Some((key(10), None)),
        Some((d11, None)),
        // B's base (10) is held, but the scene's last frame is 11: its time cannot be read.
        Some((packed(12, 10, &[(4, &[10])]), Some("clock"))),
        // A against 11, its time 300 µs before 11's.
        Some((packed(12, 11, &[(3, &[11, 10])]), None)),
        // B's last frame is 10, not 12: refused whole, A's chunk too.
        Some((
            packed(13, 12, &[(3, &[12, 11, 10]), (4, &[10])]),
            Some("base"),
        )),
        Some((packed(13, 12, &[(3, &[12, 11, 10])]), None)),
        // No avatar: only the time, from 13's.
        Some((packed(14, 13, &[]), None)),
        None,
        // The scene forgotten, its clock too: the time of an empty packed delta cannot be
        // read, nor A's levels.
        Some((packed(15, 14, &[]), Some("clock"))),
        Some((packed(15, 14, &[(3, &[13, 12])]), Some("clock"))),
        Some((key(16), None)),
        Some((packed(17, 16, &[(3, &[16]), (4, &[16])]), None)),
        // B before A: both numbers in full.
        Some((packed(18, 17, &[(4, &[17, 16]), (3, &[17, 16])]), None)),
    ];
    let mut out = Vec::new();
    for step in plan {
        match step {
            None => {
                decoder.forget_scene(8);
                out.push(json!({"forget": 8}));
            }
            Some((bytes, Some(why))) => {
                let e = decoder.decode(&bytes).unwrap_err();
                let ok = match e {
                    Frame2Error::BaseTime { .. } => why == "clock",
                    Frame2Error::MissingBase { .. } => why == "base",
                    _ => false,
                };
                assert!(ok, "{why}: {e}");
                out.push(json!({"bytes": bytes, "expect": null, "beyond_js": false}));
            }
            Some((bytes, None)) => out.push(packed_step(decoder, bytes)),
        }
    }
    out
}

/// See [`packed_vectors`]: odd packed deltas after a short packed stream, each for a fresh
/// decoder.
fn packed_odd_vectors(rng: &mut Lcg) -> Vec<Value> {
    let mut poses = vec![packed_pose(rng, 1, 5, 1, 3), packed_pose(rng, 2, 4, 0, 0)];
    let time = |seq: u64| 5_000_000 + seq * 16_667;
    let mut stream = StreamEncoder::new().with_packing(true);
    let mut prefix = Vec::new();
    for seq in 1..5 {
        for p in &mut poses {
            packed_move(p, rng);
        }
        prefix.push(stream.encode(4, seq, time(seq), &poses, false).0);
    }
    let primed = || {
        let mut dec = Frame2Decoder::new();
        for p in &prefix {
            dec.decode(p).unwrap();
        }
        dec
    };
    for p in &mut poses {
        packed_move(p, rng);
    }
    poses[0].placement = Placement::try_new([1.0, 2.0, 3.0], rng.quat().to_array()).unwrap();
    poses[0].weights[1] = 0.5;
    let next = stream.encode(4, 5, time(5) - 40, &poses, false).0;
    assert_eq!(next[1], 3);
    let mut odd: Vec<Vec<u8>> = Vec::new();
    for case in 0..80 {
        let mut b = next.clone();
        for _ in 0..1 + case % 2 {
            let at = (rng.next() * b.len() as f32) as usize;
            b[at] ^= 1 << (rng.next() * 8.0) as u32;
        }
        odd.push(b);
    }
    odd.push(next);
    for case in 0..150 {
        let mut bytes = vec![frame2::MAGIC, 3];
        for f in [
            1 + case % 2,
            4,
            5,
            1,
            zigzag((rng.next() * 2000.0) as i64 - 1000),
        ] {
            put_varint(f, &mut bytes);
        }
        let mut bits = Bits::default();
        // Avatar 1 or 2 (n = 1 or 2), then a random head and random bits.
        let num = 1 + u64::from(rng.next() < 0.5);
        let n = if num == 1 { 1 } else { 2 };
        bits.put(n - 1, 5);
        bits.put(num, n as u32);
        if rng.next() < 0.2 {
            bits.put(1, 1);
        } else {
            bits.put(0, 1);
            bits.put((rng.next() * 4.0) as u64, 3);
            bits.put((rng.next() * 16.0) as u64, 4);
        }
        let ones = case % 3 == 0;
        for _ in 0..(rng.next() * 400.0) as usize {
            bits.put(u64::from(rng.next() < if ones { 0.8 } else { 0.5 }), 1);
        }
        bytes.extend(bits.bytes());
        let start = bytes.len() - bits.bytes().len();
        // Every other case cut where the Rust decoder takes it whole, if anywhere.
        let fits = (start..=bytes.len()).find(|&n| primed().decode(&bytes[..n]).is_ok());
        match fits {
            Some(n) if case % 2 == 0 => odd.push(bytes[..n].to_vec()),
            _ => odd.push(bytes),
        }
    }
    odd.into_iter()
        .map(|b| {
            let mut v = packed_step(&mut primed(), b);
            v["prefix"] = json!(prefix);
            v
        })
        .collect()
}

/// Runs by node: decodes the packed vectors with `server/sdk/frames2.js` and compares, frame
/// by frame, the header (server time exactly), each avatar's number and hash, the levels it
/// keeps (exactly) and the poses; then random bytes after a packed delta's kind byte, which
/// must decode or throw `bad_message`. Prints a report; exits 1 on a mismatch.
const PACKED_CHECK: &str = r#"
import { readFileSync } from "node:fs";
import { pathToFileURL } from "node:url";
const sdk = process.env.POSECAST_SDK;
const { Frame2Decoder } = await import(pathToFileURL(`${sdk}/frames2.js`).href);
const { quatAngleDegrees } = await import(pathToFileURL(`${sdk}/math.js`).href);
const vectors = JSON.parse(readFileSync(process.env.POSECAST_VECTORS, "utf8"));
const failures = [];
const fail = (m) => failures.push(m);
const levels = (l) => JSON.stringify({
  rotations: l.rotations, translations: l.translations, scales: l.scales,
  placement: { position: l.placement.position, rotation: l.placement.rotation }, weights: l.weights,
  steps: l.steps && { rotations: l.steps.rotations, translation: l.steps.translation, near: l.steps.near },
});
const last = new Map();
function check(d, f, label, counts) {
  if (f.forget !== undefined) { d.forgetScene(f.forget); last.delete(f.forget); return; }
  const packed = f.bytes[1] === 3;
  let got;
  try {
    got = d.decode(new Uint8Array(f.bytes));
  } catch (e) {
    if (e?.code !== "bad_message") return fail(`${label}: threw ${e}`);
    if (f.beyond_js) counts.beyond++;
    else if (f.expect === null) counts.refused++;
    else fail(`${label}: refused (${e.message}), the Rust decoder decodes it`);
    return;
  }
  if (f.expect === null || f.beyond_js) return fail(`${label}: decoded (seq ${got.seq}), the Rust decoder refuses it`);
  const w = f.expect;
  const before = failures.length;
  for (const k of ["key", "scene_num", "seq", "server_time_us", "base_seq"]) {
    if (got[k] !== w[k]) fail(`${label} ${k}: ${got[k]} vs ${w[k]}`);
  }
  if (got.avatars.length !== w.avatars.length) return fail(`${label}: ${got.avatars.length} avatars, expected ${w.avatars.length}`);
  got.avatars.forEach((a, i) => {
    const want = w.avatars[i];
    const what = `${label} (scene ${w.scene_num} seq ${w.seq}) avatar ${want.num}`;
    if (a.num !== want.num || a.hash !== want.hash) fail(`${what}: num/hash ${a.num} ${a.hash} vs ${want.num} ${want.hash}`);
    const held = d.history.get(`${got.scene_num}:${a.num}`);
    const mine = held && held.frames[0].seq === got.seq ? levels(held.frames[0].levels) : "nothing";
    const theirs = levels(w.levels[i]);
    if (mine !== theirs) fail(`${what}: levels ${mine} vs ${theirs}`);
    a.rotations.forEach((q, j) => {
      const x = quatAngleDegrees(q, want.rotations[j]);
      if (!(x <= 5e-4)) fail(`${what} joint ${j}: ${q} vs ${want.rotations[j]} (${x}°)`);
    });
    for (const k of ["translations", "scales", "placement", "weights"]) {
      if (JSON.stringify(a[k]) !== JSON.stringify(want[k])) fail(`${what} ${k}: ${JSON.stringify(a[k])} vs ${JSON.stringify(want[k])}`);
    }
  });
  if (failures.length !== before) return;
  counts.frames++;
  if (packed) counts.packed++;
  if (packed && got.server_time_us < last.get(got.scene_num)) counts.backwards++;
  last.set(got.scene_num, got.server_time_us);
}
const main = { frames: 0, packed: 0, refused: 0, beyond: 0, backwards: 0 };
const d = new Frame2Decoder();
vectors.main.forEach((f, i) => check(d, f, `main ${i}`, main));
const lagging = { frames: 0, packed: 0, refused: 0, beyond: 0, backwards: 0 };
last.clear();
const slow = new Frame2Decoder();
vectors.lagging.forEach((f, i) => check(slow, f, `lagging ${i}`, lagging));
// A fresh decoder that took `prefix` (good frames: each must decode).
const primed = (prefix, label) => {
  const dec = new Frame2Decoder();
  prefix.forEach((p, k) => {
    try {
      dec.decode(new Uint8Array(p));
    } catch (e) {
      fail(`${label}: prefix frame ${k} refused: ${e}`);
    }
  });
  return dec;
};
const odd = { frames: 0, packed: 0, refused: 0, beyond: 0, backwards: 0 };
vectors.odd.forEach((c, i) => {
  const fresh = primed(c.prefix, `odd ${i}`);
  last.clear();
  check(fresh, c, `odd ${i}`, odd);
});
// Random bytes after a packed delta's kind: decoded or bad_message, never another exception.
let seed = 0x51a3;
const random = () => { seed ^= seed << 13; seed ^= seed >>> 17; seed ^= seed << 5; return (seed >>> 0) / 2 ** 32; };
const fuzzed = primed(vectors.odd[0].prefix, "random bytes");
let fuzz = 0;
for (let i = 0; i < 3000; i++) {
  const bytes = new Uint8Array(2 + Math.floor(random() * 200));
  for (let k = 2; k < bytes.length; k++) bytes[k] = random() * 256;
  [bytes[0], bytes[1]] = [0x51, 3];
  // Mostly a header naming scene 4 and its next seq, so the chunks are read too.
  if (i % 4 !== 0 && bytes.length > 6) bytes.set([1 + (i % 3), 4, 5, 1], 2);
  try {
    fuzzed.decode(bytes);
  } catch (e) {
    if (e?.code !== "bad_message") fail(`random bytes ${i}: threw ${e}`);
  }
  fuzz++;
}
console.log(JSON.stringify({ main, lagging, odd, fuzz, failures: failures.slice(0, 20) }));
process.exit(failures.length ? 1 : 0);
"#;

/// Packed deltas (protocol version 7) made by `posecast_proto::frame2` (`StreamEncoder` with
/// packing, `PackedDeltas`) decode in the JavaScript client's `server/sdk/frames2.js` to the
/// levels and server times `Frame2Decoder` decodes, and are refused where it refuses them
/// (a base other than the scene's last frame, not held, forgotten; malformed) without a change.
#[test]
fn the_clients_decoder_reads_packed_deltas_as_the_rust_one() {
    let mut rng = Lcg(0x7_9ac3);
    let vectors = packed_vectors(&mut rng);
    let file = std::env::temp_dir().join(format!("posecast-packed-{}.json", std::process::id()));
    std::fs::write(&file, serde_json::to_vec(&vectors).unwrap()).unwrap();
    let out = match Process::new("node")
        .args(["--input-type=module", "-e", PACKED_CHECK])
        .env("POSECAST_SDK", root().join("server/sdk"))
        .env("POSECAST_VECTORS", &file)
        .output()
    {
        Ok(out) => out,
        Err(e) => {
            skip(&format!(
                "node is not installed ({e}): the JavaScript decoder's packed deltas are not checked"
            ));
            return;
        }
    };
    std::fs::remove_file(&file).ok();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "packed deltas in JavaScript: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_str(stdout.trim()).unwrap();
    let n = |path: &[&str]| {
        path.iter()
            .fold(&report, |v, k| &v[*k])
            .as_u64()
            .unwrap_or_else(|| panic!("{path:?}: {report}"))
    };
    // Scene 6's 160 frames, scene 7's 30 (the 31st is beyond 2⁵³), scene 8's 8.
    assert_eq!(n(&["main", "frames"]), 160 + 30 + 8, "{report}");
    assert!(n(&["main", "packed"]) >= 150 + 25 + 4, "{report}");
    assert_eq!(n(&["main", "beyond"]), 1, "{report}");
    assert!(n(&["main", "backwards"]) >= 2, "{report}");
    assert!(n(&["main", "refused"]) >= 100, "{report}");
    assert!(n(&["lagging", "packed"]) >= 40, "{report}");
    assert!(n(&["lagging", "refused"]) >= 40, "{report}");
    assert!(n(&["odd", "frames"]) >= 10, "{report}");
    assert!(n(&["odd", "refused"]) >= 80, "{report}");
    assert_eq!(n(&["fuzz"]), 3000, "{report}");
    println!("JavaScript packed deltas vs Rust: {report}");
}
