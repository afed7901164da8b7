//! Wire v2 over datagrams (protocol version 8, frame kind 4: deltas naming the frames they
//! refer to) in the JavaScript client's `server/sdk/frames2.js` against posecast-proto's
//! `Frame2Decoder::for_datagrams`, on shared vectors run by node:
//! - `main`, through one decoder for datagrams: a sender of five avatars (numbers up to
//!   2³² − 1; a precision's tiered grid, scales, morph weights, one still) naming only frames
//!   acknowledged for every avatar, of its last 48 ticks, to a receiver whose datagrams are
//!   lost, late (out of order), doubled and cut by avatar (`split_by_avatar`), whose
//!   acknowledgements are lost and late; keyframes sent again while unacknowledged; one
//!   avatar's rig changed midway. Then hand-made frames: two keyframes of one tick (a delta
//!   naming it finds the newer), the 64-frame retention's edge, a late keyframe of the same rig
//!   (the frames after it kept), a keyframe of a new rig (its avatar's frames dropped, the
//!   other's kept), malformed kind 4 frames (chunk lengths off by one, reference counts and
//!   distances out of range, a chunk deeper than the references, frames not held) and an
//!   avatar forgotten. Each frame decodes to exactly the Rust decoder's levels and header, or
//!   is refused where it refuses it, changing nothing.
//! - `plain`: the same frames through a decoder of frames that do not come as datagrams
//!   (`Frame2Decoder::new`: 8 frames kept, every keyframe drops them), alike on both sides.
//! - `odd`: a kind 4 delta with a bit or two flipped, and kind 4 deltas of random chunks,
//!   each through a fresh decoder for datagrams that took a short stream first; then random
//!   bytes after a kind 4 header (decoded or `bad_message`, never another exception).

use crate::root;
use crate::stream::{
    Lcg, frame_json, levels_json, near_steps, packed_move, packed_pose, put_varint,
};
use posecast_proto::frame::{AvatarPose, FrameHeader, FrameKind};
use posecast_proto::frame2::{
    self, DATAGRAM_REFERENCE_TICKS, Frame2Decoder, Frame2Error, MAX_DEPTH, QuantPose,
};
use posecast_proto::precision::Steps;
use posecast_proto::testing::skip;
use serde_json::{Value, json};
use std::cmp::Reverse;
use std::collections::{BTreeMap, HashMap};
use std::process::Command as Process;
use std::sync::Arc;

/// The server time of tick `seq`.
fn time(seq: u64) -> u64 {
    1_763_000_000_000_000 + seq * 16_667
}

/// Levels of an avatar (number, description hash, levels).
type Levels = (u32, u64, Arc<QuantPose>);

/// A frame of tick `seq`: a keyframe when `refs` is empty, else a delta naming `refs` (kind 5
/// at even ticks, 4 at odd ones),
/// each avatar's chunk coded against its levels of those ticks (`held`).
fn frame(
    scene_num: u32,
    seq: u64,
    avatars: &[Levels],
    refs: &[u64],
    held: &dyn Fn(u32, u64) -> Arc<QuantPose>,
) -> Vec<u8> {
    let mut header = FrameHeader {
        kind: FrameKind::Key,
        scene_num,
        seq,
        server_time_us: time(seq),
        base_seq: seq,
    };
    let mut out = Vec::new();
    if refs.is_empty() {
        frame2::write_header(&header, avatars.len(), &mut out);
        for (num, hash, q) in avatars {
            frame2::encode_key(*num, *hash, q, &mut out);
        }
    } else {
        header.kind = FrameKind::Delta;
        header.base_seq = refs[0];
        // Kind 5 (protocol version 9) at even ticks, kind 4 (version 8) at odd ones: the client
        // decodes both.
        let kind = if seq.is_multiple_of(2) {
            frame2::ReferencedKind::Ticks
        } else {
            frame2::ReferencedKind::Frames
        };
        frame2::write_referenced_header(&header, kind, refs, avatars.len(), &mut out);
        for (num, _, q) in avatars {
            let history: Vec<Arc<QuantPose>> = refs.iter().map(|&r| held(*num, r)).collect();
            let h: Vec<&QuantPose> = history.iter().map(|h| &**h).collect();
            let spacing = kind.spacing(seq, refs);
            assert!(frame2::encode_referenced_delta(
                *num, q, &h, spacing, &mut out
            ));
        }
    }
    out
}

/// What `decoder` makes of `bytes` (decoded: the frame and its levels; refused: `null`) as a
/// vector, and the avatars it decoded.
fn step(decoder: &mut Frame2Decoder, bytes: &[u8], part: bool) -> (Value, Option<Vec<u32>>) {
    let got = decoder.decode_levels(bytes).ok();
    let expect = got.as_ref().map(|f| {
        let mut v = frame_json(&f.to_frame());
        v["levels"] = f.avatars.iter().map(|a| levels_json(&a.levels)).collect();
        v
    });
    let nums = got.map(|f| f.avatars.iter().map(|a| a.avatar_num).collect());
    (
        json!({"bytes": bytes, "expect": expect, "part": part}),
        nums,
    )
}

/// The two receivers of the same datagrams, and their vectors.
struct Receivers {
    /// `Frame2Decoder::for_datagrams`.
    datagrams: Frame2Decoder,
    /// `Frame2Decoder::new`.
    plain: Frame2Decoder,
    main: Vec<Value>,
    plain_steps: Vec<Value>,
}

impl Receivers {
    /// Gives `bytes` to both; returns the avatars the decoder for datagrams decoded, if it did.
    fn deliver(&mut self, bytes: &[u8], part: bool) -> Option<Vec<u32>> {
        let (v, nums) = step(&mut self.datagrams, bytes, part);
        self.main.push(v);
        self.plain_steps.push(step(&mut self.plain, bytes, part).0);
        nums
    }

    /// Gives `bytes`, which the decoder for datagrams must refuse (`why`: "base" a frame it
    /// does not hold, "flags" a chunk deeper than the frames named, else "malformed").
    fn refused(&mut self, bytes: &[u8], why: &str) {
        let e = self.datagrams.decode_levels(bytes).unwrap_err();
        let ok = match e {
            Frame2Error::MissingBase { .. } => why == "base",
            Frame2Error::Flags { .. } => why == "flags",
            _ => why == "malformed",
        };
        assert!(ok, "{why}: {e}");
        // Refused again (a refusal changes nothing), now as a vector.
        assert!(self.deliver(bytes, false).is_none());
    }

    fn forget_avatar(&mut self, scene_num: u32, num: u32) {
        self.datagrams.forget_avatar(scene_num, num);
        self.plain.forget_avatar(scene_num, num);
        let forget = json!({"forget_avatar": [scene_num, num]});
        self.main.push(forget.clone());
        self.plain_steps.push(forget);
    }
}

/// The sender and the lossy path of `main` (scene 4), delivering to `rx`; returns how many
/// datagrams that came were refused (late ones of the changed rig's old frames).
fn lossy_stream(rng: &mut Lcg, rx: &mut Receivers) -> usize {
    let nums = [1u32, 9, 300, 70_000, u32::MAX];
    let joints = [5usize, 7, 4, 6, 3];
    let still = 4;
    let mut poses: Vec<AvatarPose> = nums
        .iter()
        .zip(joints)
        .enumerate()
        .map(|(i, (&num, j))| {
            let scales = if i == 2 { 2 } else { 0 };
            let weights = if i == 3 { 4 } else { 0 };
            packed_pose(rng, num, j, scales, weights)
        })
        .collect();
    // Avatars 9 and 2³² − 1 on a precision's grid, with near-axis steps (version 6 and on).
    let mut steps: HashMap<u32, Arc<Steps>> = HashMap::new();
    for i in [1usize, 4] {
        let m: Vec<u8> = (0..joints[i])
            .map(|_| (rng.next() * 40.0) as u8 + 1)
            .collect();
        steps.insert(
            nums[i],
            Arc::new(Steps {
                near: near_steps(&m),
                rotations: m,
                translation: 11,
            }),
        );
    }
    // The levels sent of each tick, by avatar; the ticks acknowledged for every avatar, newest
    // first; the avatars of each tick not acknowledged yet.
    let mut sent: BTreeMap<u64, HashMap<u32, Arc<QuantPose>>> = BTreeMap::new();
    let mut acked: Vec<u64> = Vec::new();
    let mut missing: HashMap<u64, Vec<u32>> = HashMap::new();
    // (arrival tick, seq, bytes, a part of a frame cut by avatar); (arrival tick, seq, avatars).
    let mut in_flight: Vec<(u64, u64, Vec<u8>, bool)> = Vec::new();
    let mut acks: Vec<(u64, u64, Vec<u32>)> = Vec::new();
    // Frames of ticks before the rig change are not named after it.
    let mut rig_since = 0u64;
    let mut last_key: Option<u64> = None;
    let mut refused = 0;
    for tick in 1..=250u64 {
        for (_, s, avatars) in acks.iter().filter(|a| a.0 <= tick) {
            if *s < rig_since {
                continue;
            }
            if let Some(m) = missing.get_mut(s) {
                m.retain(|n| !avatars.contains(n));
                if m.is_empty() {
                    missing.remove(s);
                    acked.push(*s);
                }
            }
        }
        acks.retain(|a| a.0 > tick);
        acked.sort_unstable_by_key(|&s| Reverse(s));
        acked.dedup();
        // The datagrams that come this tick, in the order they come (a later tick first).
        let mut arrived: Vec<(u64, u64, Vec<u8>, bool)> = Vec::new();
        in_flight.retain(|f| {
            if f.0 <= tick {
                arrived.push(f.clone());
            }
            f.0 > tick
        });
        arrived.sort_by_key(|f| (f.0, Reverse(f.1)));
        for (_, s, bytes, part) in arrived {
            let Some(avatars) = rx.deliver(&bytes, part) else {
                refused += 1;
                continue;
            };
            if rng.next() < 0.85 {
                acks.push((tick + 1 + (rng.next() * 5.0) as u64, s, avatars));
            }
            if rng.next() < 0.04 {
                // The path doubles it.
                let again = tick + 2 + (rng.next() * 4.0) as u64;
                in_flight.push((again, s, bytes, part));
            }
        }
        if tick > 240 {
            continue;
        }
        if tick == 130 {
            // Avatar 1's rig changes: the frames before are of no use to name.
            poses[0].hash ^= 0x5a5a;
            rig_since = tick;
            acked.clear();
            missing.clear();
        }
        for (i, p) in poses.iter_mut().enumerate() {
            if i != still {
                packed_move(p, rng);
            }
        }
        let levels: Vec<Levels> = poses
            .iter()
            .map(|p| {
                let q = QuantPose::from_pose(p);
                let q = match steps.get(&p.avatar_num) {
                    Some(s) => q.coarsen(s),
                    None => q,
                };
                (p.avatar_num, p.hash, Arc::new(q))
            })
            .collect();
        let refs: Vec<u64> = acked
            .iter()
            .copied()
            .filter(|&r| tick - r < DATAGRAM_REFERENCE_TICKS && r >= rig_since)
            .take(MAX_DEPTH)
            .collect();
        if refs.is_empty() {
            // A keyframe on its way unacknowledged: nothing else goes, and it goes again
            // after a while.
            if last_key.is_some_and(|k| k >= rig_since && tick - k < 3) {
                continue;
            }
            last_key = Some(tick);
        }
        let bytes = frame(4, tick, &levels, &refs, &|num, r| sent[&r][&num].clone());
        sent.insert(
            tick,
            levels.iter().map(|(n, _, q)| (*n, q.clone())).collect(),
        );
        missing.insert(tick, nums.to_vec());
        let cut = rng.next();
        let max = if cut < 0.3 {
            1
        } else if cut < 0.5 {
            bytes.len() / 2
        } else {
            bytes.len()
        };
        let parts = frame2::split_by_avatar(&bytes, max).unwrap();
        let split = parts.len() > 1;
        for (part, _) in parts {
            let r = rng.next();
            if r < 0.12 {
                continue;
            }
            let late = if r < 0.7 {
                0
            } else {
                1 + (rng.next() * 4.0) as u64
            };
            in_flight.push((tick + late, tick, part, split));
        }
    }
    refused
}

fn read_varint(bytes: &[u8], at: &mut usize) -> u64 {
    let (mut v, mut shift) = (0u64, 0);
    loop {
        let b = bytes[*at];
        *at += 1;
        v |= u64::from(b & 0x7f) << shift;
        shift += 7;
        if b & 0x80 == 0 {
            return v;
        }
    }
}

/// A kind 4 frame's header fields (count, scene, seq, time), its distances and its chunks
/// (without their lengths).
fn parse_referenced(bytes: &[u8]) -> ([u64; 4], Vec<u64>, Vec<Vec<u8>>) {
    assert_eq!(bytes[..2], [frame2::MAGIC, 4]);
    let mut at = 2;
    let fields = [(); 4].map(|()| read_varint(bytes, &mut at));
    let d = read_varint(bytes, &mut at);
    let gaps = (0..d).map(|_| read_varint(bytes, &mut at)).collect();
    let chunks = (0..fields[0])
        .map(|_| {
            let len = read_varint(bytes, &mut at) as usize;
            at += len;
            bytes[at - len..at].to_vec()
        })
        .collect();
    assert_eq!(at, bytes.len());
    (fields, gaps, chunks)
}

/// A frame of kind 4 (or `SPACED_KIND`, 5) of these fields, `d` said (whatever the distances'
/// count), each chunk after the length given.
fn build_referenced(fields: [u64; 4], d: u64, gaps: &[u64], chunks: &[(u64, &[u8])]) -> Vec<u8> {
    build_kind(4, fields, d, gaps, chunks)
}

/// The kind byte of a delta predicted over the ticks between (protocol version 9).
const SPACED_KIND: u8 = 5;

/// [`build_referenced`] of frame kind `kind`.
fn build_kind(
    kind: u8,
    fields: [u64; 4],
    d: u64,
    gaps: &[u64],
    chunks: &[(u64, &[u8])],
) -> Vec<u8> {
    let mut out = vec![frame2::MAGIC, kind];
    for f in fields.into_iter().chain([d]).chain(gaps.iter().copied()) {
        put_varint(f, &mut out);
    }
    for (len, chunk) in chunks {
        put_varint(*len, &mut out);
        out.extend_from_slice(chunk);
    }
    out
}

/// Malformed variants of `good`, a kind 4 frame of two chunks naming two frames, for
/// `rx`, which refuses each (and the reason); then `good` itself.
fn malformed_variants(rx: &mut Receivers, good: &[u8]) {
    let (fields, gaps, chunks) = parse_referenced(good);
    assert_eq!((gaps.len(), chunks.len()), (2, 2));
    let seq = fields[2];
    let len = |c: &[u8]| c.len() as u64;
    let (a, b) = (&chunks[0][..], &chunks[1][..]);
    let whole = |c0: (u64, &[u8]), c1: (u64, &[u8])| build_referenced(fields, 2, &gaps, &[c0, c1]);
    assert_eq!(whole((len(a), a), (len(b), b)), good);
    let longer = [a, &[0]].concat();
    let flags_deeper = {
        // The chunk's flags follow its avatar number (one byte here): depth 3 of 2 named.
        let mut c = a.to_vec();
        c[1] = (c[1] & 0x0f) | (2 << 4);
        c
    };
    let cases: Vec<(Vec<u8>, &str)> = vec![
        // A chunk with a byte more than the chunk holds, or one short.
        (whole((len(a) + 1, &longer), (len(b), b)), "malformed"),
        (
            whole((len(a) - 1, &a[..a.len() - 1]), (len(b), b)),
            "malformed",
        ),
        // A length beyond the frame.
        (whole((len(a), a), (len(b) + 5, b)), "malformed"),
        // No frame named, nine, distances not increasing, a distance beyond the seq.
        (
            build_referenced(fields, 0, &[], &[(len(a), a), (len(b), b)]),
            "malformed",
        ),
        (
            build_referenced(
                fields,
                9,
                &[1, 2, 3, 4, 5, 6, 7, 8, 9],
                &[(len(a), a), (len(b), b)],
            ),
            "malformed",
        ),
        (
            build_referenced(fields, 2, &[gaps[0], gaps[0]], &[(len(a), a), (len(b), b)]),
            "malformed",
        ),
        (
            build_referenced(fields, 1, &[seq + 1], &[(len(a), a), (len(b), b)]),
            "malformed",
        ),
        // A chunk deeper than the frames named.
        (whole((len(a), &flags_deeper), (len(b), b)), "flags"),
        // Frames the first avatar does not hold.
        (
            build_referenced(
                fields,
                2,
                &[gaps[1] + 3, gaps[1] + 4],
                &[(len(a), a), (len(b), b)],
            ),
            "base",
        ),
        // A chunk count beyond the chunks, a byte too many, cut short.
        (
            build_referenced(
                [3, fields[1], fields[2], fields[3]],
                2,
                &gaps,
                &[(len(a), a), (len(b), b)],
            ),
            "malformed",
        ),
        ([good, &[0]].concat(), "malformed"),
        (good[..good.len() - 1].to_vec(), "malformed"),
    ];
    for (bytes, why) in cases {
        rx.refused(&bytes, why);
    }
    assert!(rx.deliver(good, false).is_some());
}

/// Hand-made frames of scene 6 to `rx` (see the module's documentation), avatars 2 and 3.
fn hand_made(rng: &mut Lcg, rx: &mut Receivers) {
    let mut a = packed_pose(rng, 2, 5, 0, 3);
    let mut b = packed_pose(rng, 3, 4, 1, 0);
    let mut qa: BTreeMap<u64, Arc<QuantPose>> = BTreeMap::new();
    let mut qb: BTreeMap<u64, Arc<QuantPose>> = BTreeMap::new();
    for seq in 10..=90 {
        packed_move(&mut a, rng);
        packed_move(&mut b, rng);
        qa.insert(seq, Arc::new(QuantPose::from_pose(&a)));
        qb.insert(seq, Arc::new(QuantPose::from_pose(&b)));
    }
    // Tick 10 again from another source (a restarted sender counting its ticks again).
    packed_move(&mut a, rng);
    packed_move(&mut b, rng);
    let (alt_a, alt_b) = (
        Arc::new(QuantPose::from_pose(&a)),
        Arc::new(QuantPose::from_pose(&b)),
    );
    let (ha, hb) = (a.hash, b.hash);
    let held = |num: u32, r: u64| {
        if num == 2 {
            qa[&r].clone()
        } else {
            qb[&r].clone()
        }
    };
    let both =
        |seq: u64| -> Vec<Levels> { vec![(2, ha, qa[&seq].clone()), (3, hb, qb[&seq].clone())] };
    let scene = 6;
    assert!(
        rx.deliver(&frame(scene, 10, &both(10), &[], &held), false)
            .is_some()
    );
    let alt = vec![(2, ha, alt_a.clone()), (3, hb, alt_b.clone())];
    assert!(
        rx.deliver(&frame(scene, 10, &alt, &[], &held), false)
            .is_some()
    );
    // Tick 11 against the newer frame of tick 10.
    let on_alt = |num: u32, _: u64| {
        if num == 2 {
            alt_a.clone()
        } else {
            alt_b.clone()
        }
    };
    assert!(
        rx.deliver(&frame(scene, 11, &both(11), &[10], &on_alt), false)
            .is_some()
    );
    // 64 more, each naming up to 8 frames before it: 12 is then the oldest held, 11 gone.
    for seq in 12..=75u64 {
        let refs: Vec<u64> = (1..=8).map(|k| seq - k).filter(|&r| r >= 11).collect();
        assert!(
            rx.deliver(&frame(scene, seq, &both(seq), &refs, &held), false)
                .is_some()
        );
    }
    rx.refused(&frame(scene, 76, &both(76), &[11], &held), "base");
    assert!(
        rx.deliver(&frame(scene, 76, &both(76), &[12], &held), false)
            .is_some()
    );
    // A keyframe of tick 40 comes late: of the same rigs, it drops nothing.
    assert!(
        rx.deliver(&frame(scene, 40, &both(40), &[], &held), false)
            .is_some()
    );
    assert!(
        rx.deliver(&frame(scene, 77, &both(77), &[76, 75, 74], &held), false)
            .is_some()
    );
    // Avatar 2's rig changes: its frames are dropped, avatar 3's kept.
    let new_rig = vec![(2, ha ^ 0x5a5a, qa[&78].clone()), (3, hb, qb[&78].clone())];
    assert!(
        rx.deliver(&frame(scene, 78, &new_rig, &[], &held), false)
            .is_some()
    );
    let a_only = |seq: u64| vec![(2, ha ^ 0x5a5a, qa[&seq].clone())];
    let b_only = |seq: u64| vec![(3, hb, qb[&seq].clone())];
    rx.refused(&frame(scene, 79, &a_only(79), &[77], &held), "base");
    assert!(
        rx.deliver(&frame(scene, 79, &b_only(79), &[77], &held), false)
            .is_some()
    );
    let both_new = |seq: u64| vec![a_only(seq)[0].clone(), b_only(seq)[0].clone()];
    assert!(
        rx.deliver(&frame(scene, 80, &both_new(80), &[78], &held), false)
            .is_some()
    );
    malformed_variants(rx, &frame(scene, 81, &both_new(81), &[80, 78], &held));
    // Avatar 3 forgotten (it left the scene).
    rx.forget_avatar(scene, 3);
    rx.refused(&frame(scene, 82, &b_only(82), &[81], &held), "base");
    assert!(
        rx.deliver(&frame(scene, 82, &a_only(82), &[81], &held), false)
            .is_some()
    );
}

/// See the module's documentation: odd kind 4 deltas after a short stream (scene 7), each for
/// a fresh decoder for datagrams.
fn odd_vectors(rng: &mut Lcg) -> Vec<Value> {
    let mut poses = vec![packed_pose(rng, 1, 5, 1, 3), packed_pose(rng, 2, 4, 0, 0)];
    let mut sent: BTreeMap<u64, Vec<Levels>> = BTreeMap::new();
    let mut prefix = Vec::new();
    for seq in 1..=5u64 {
        for p in &mut poses {
            packed_move(p, rng);
        }
        if seq == 5 {
            poses[0].weights[1] = 0.5;
        }
        let levels: Vec<Levels> = poses
            .iter()
            .map(|p| (p.avatar_num, p.hash, Arc::new(QuantPose::from_pose(p))))
            .collect();
        let refs: Vec<u64> = (1..seq).rev().collect();
        let held = |num: u32, r: u64| sent[&r][num as usize - 1].2.clone();
        let bytes = frame(7, seq, &levels, &refs, &held);
        sent.insert(seq, levels);
        prefix.push(bytes);
    }
    let next = prefix.pop().unwrap();
    let primed = || {
        let mut dec = Frame2Decoder::for_datagrams();
        for p in &prefix {
            dec.decode(p).unwrap();
        }
        dec
    };
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
    for case in 0..150u64 {
        let d = 1 + (rng.next() * 3.0) as u64;
        let count = 1 + case % 2;
        let mut bodies: Vec<Vec<u8>> = Vec::new();
        for c in 0..count {
            // Avatar 1 or 2, flags of a depth up to d (now and then beyond), random bits.
            let depth = (rng.next() * (d as f32 + 0.3)) as u8;
            let mut body = vec![1 + c as u8, depth << 4 | (rng.next() * 16.0) as u8];
            let ones = case % 3 == 0;
            for _ in 0..(rng.next() * 40.0) as usize {
                let mut byte = 0u8;
                for bit in 0..8 {
                    byte |= u8::from(rng.next() < if ones { 0.8 } else { 0.5 }) << bit;
                }
                body.push(byte);
            }
            bodies.push(body);
        }
        let fields = [count, 7, 6, time(6)];
        let gaps: Vec<u64> = (1..=d).collect();
        let bytes = |bodies: &[Vec<u8>]| {
            let chunks: Vec<(u64, &[u8])> =
                bodies.iter().map(|b| (b.len() as u64, &b[..])).collect();
            // Half the cases kind 5: its residuals predicted over the ticks between.
            let kind = if case % 4 < 2 { SPACED_KIND } else { 4 };
            build_kind(kind, fields, d, &gaps, &chunks)
        };
        // Every other case with the last chunk cut where the Rust decoder takes it, if anywhere.
        let last = bodies.len() - 1;
        let fits = (2..=bodies[last].len()).find(|&n| {
            let mut cut = bodies.clone();
            cut[last].truncate(n);
            primed().decode(&bytes(&cut)).is_ok()
        });
        match fits {
            Some(n) if case % 2 == 0 => bodies[last].truncate(n),
            _ => {}
        }
        odd.push(bytes(&bodies));
    }
    odd.into_iter()
        .map(|b| {
            let mut v = step(&mut primed(), &b, false).0;
            v["prefix"] = json!(prefix);
            v
        })
        .collect()
}

/// Runs by node: decodes the vectors with `server/sdk/frames2.js` (`Frame2Decoder.forDatagrams`
/// for `main` and `odd`, `new Frame2Decoder()` for `plain`) and compares, frame by frame, the
/// header, each avatar's number and hash, the levels it keeps (exactly) and the poses; then
/// random bytes after a kind 4 header, which must decode or throw `bad_message`. Prints a
/// report; exits 1 on a mismatch.
const DATAGRAM_CHECK: &str = r#"
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
const counts = () => ({ frames: 0, referenced: 0, spaced: 0, keys: 0, late: 0, late_keys: 0, parts: 0, refused: 0, held_most: 0, newest: new Map() });
function check(d, f, label, c) {
  if (f.forget_avatar !== undefined) return d.forgetAvatar(...f.forget_avatar);
  let got;
  try {
    got = d.decode(new Uint8Array(f.bytes));
  } catch (e) {
    if (e?.code !== "bad_message") return fail(`${label}: threw ${e}`);
    if (f.expect === null) c.refused++;
    else fail(`${label}: refused (${e.message}), the Rust decoder decodes it`);
    return;
  }
  if (f.expect === null) return fail(`${label}: decoded (seq ${got.seq}), the Rust decoder refuses it`);
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
  c.frames++;
  if (f.bytes[1] === 4 || f.bytes[1] === 5) c.referenced++;
  if (f.bytes[1] === 5) c.spaced++;
  if (got.key) c.keys++;
  if (f.part) c.parts++;
  const newest = c.newest.get(got.scene_num) ?? -1;
  if (got.seq < newest) {
    c.late++;
    if (got.key) c.late_keys++;
  }
  c.newest.set(got.scene_num, Math.max(newest, got.seq));
  for (const h of d.history.values()) c.held_most = Math.max(c.held_most, h.frames.length);
}
const report = (c) => { const { newest, ...rest } = c; return rest; };
const main = counts();
const datagrams = Frame2Decoder.forDatagrams();
vectors.main.forEach((f, i) => check(datagrams, f, `main ${i}`, main));
const plain = counts();
const plainDecoder = new Frame2Decoder();
vectors.plain.forEach((f, i) => check(plainDecoder, f, `plain ${i}`, plain));
// A fresh decoder for datagrams that took `prefix` (good frames: each must decode).
const primed = (prefix, label) => {
  const dec = Frame2Decoder.forDatagrams();
  prefix.forEach((p, k) => {
    try {
      dec.decode(new Uint8Array(p));
    } catch (e) {
      fail(`${label}: prefix frame ${k} refused: ${e}`);
    }
  });
  return dec;
};
const odd = counts();
vectors.odd.forEach((c, i) => check(primed(c.prefix, `odd ${i}`), c, `odd ${i}`, odd));
// Random bytes after a kind 4 frame's kind: decoded or bad_message, never another exception.
let seed = 0x4a4d;
const random = () => { seed ^= seed << 13; seed ^= seed >>> 17; seed ^= seed << 5; return (seed >>> 0) / 2 ** 32; };
const fuzzed = primed(vectors.odd[0].prefix, "random bytes");
let fuzz = 0;
for (let i = 0; i < 3000; i++) {
  const bytes = new Uint8Array(2 + Math.floor(random() * 200));
  for (let k = 2; k < bytes.length; k++) bytes[k] = random() * 256;
  [bytes[0], bytes[1]] = [0x51, 4];
  // Mostly a header naming scene 7, tick 6 and frames held, so the chunks are read too.
  if (i % 4 !== 0 && bytes.length > 12) bytes.set([1 + (i % 2), 7, 6, 0, 1 + (i % 3), 1, 2, 3], 2);
  try {
    fuzzed.decode(bytes);
  } catch (e) {
    if (e?.code !== "bad_message") fail(`random bytes ${i}: threw ${e}`);
  }
  fuzz++;
}
console.log(JSON.stringify({ main: report(main), plain: report(plain), odd: report(odd), fuzz, failures: failures.slice(0, 20) }));
process.exit(failures.length ? 1 : 0);
"#;

/// Frames as datagrams (protocol version 8: keyframes and kind 4 deltas made by
/// `posecast_proto::frame2`, cut by `split_by_avatar`, lost, late, doubled) decode in the
/// JavaScript client's `server/sdk/frames2.js` to the levels `Frame2Decoder::for_datagrams`
/// decodes, and are refused where it refuses them; `Frame2Decoder::new`'s twin agrees too.
#[test]
fn the_clients_decoder_reads_datagrams_as_the_rust_one() {
    let mut rng = Lcg(0x0d47_a6a8);
    let mut rx = Receivers {
        datagrams: Frame2Decoder::for_datagrams(),
        plain: Frame2Decoder::new(),
        main: Vec::new(),
        plain_steps: Vec::new(),
    };
    let lossy_refused = lossy_stream(&mut rng, &mut rx);
    hand_made(&mut rng, &mut rx);
    let vectors = json!({"main": rx.main, "plain": rx.plain_steps, "odd": odd_vectors(&mut rng)});
    let file = std::env::temp_dir().join(format!("posecast-datagrams-{}.json", std::process::id()));
    std::fs::write(&file, serde_json::to_vec(&vectors).unwrap()).unwrap();
    let out = match Process::new("node")
        .args(["--input-type=module", "-e", DATAGRAM_CHECK])
        .env("POSECAST_SDK", root().join("server/sdk"))
        .env("POSECAST_VECTORS", &file)
        .output()
    {
        Ok(out) => out,
        Err(e) => {
            skip(&format!(
                "node is not installed ({e}): the JavaScript decoder's datagrams are not checked"
            ));
            return;
        }
    };
    std::fs::remove_file(&file).ok();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "datagrams in JavaScript: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_str(stdout.trim()).unwrap();
    let n = |path: &[&str]| {
        path.iter()
            .fold(&report, |v, k| &v[*k])
            .as_u64()
            .unwrap_or_else(|| panic!("{path:?}: {report}"))
    };
    // Every datagram of the lossy stream that came decodes, but late ones of the changed
    // rig's old frames after its new keyframe.
    assert!(lossy_refused <= 10, "{lossy_refused} refused");
    assert!(n(&["main", "frames"]) >= 550, "{report}");
    assert!(n(&["main", "referenced"]) >= 500, "{report}");
    assert!(n(&["main", "spaced"]) >= 200, "{report}");
    assert!(n(&["main", "keys"]) >= 10, "{report}");
    assert!(n(&["main", "late"]) >= 100, "{report}");
    assert!(n(&["main", "late_keys"]) >= 2, "{report}");
    assert!(n(&["main", "parts"]) >= 300, "{report}");
    assert!(n(&["main", "refused"]) >= 15, "{report}");
    assert_eq!(n(&["main", "held_most"]), 64, "{report}");
    // Without datagrams' retention and keyframes that keep frames, most deltas are refused.
    assert_eq!(n(&["plain", "held_most"]), 8, "{report}");
    assert!(n(&["plain", "refused"]) >= 400, "{report}");
    assert!(n(&["odd", "frames"]) >= 20, "{report}");
    assert!(n(&["odd", "refused"]) >= 100, "{report}");
    assert_eq!(n(&["fuzz"]), 3000, "{report}");
    println!(
        "JavaScript datagrams vs Rust ({lossy_refused} of the lossy stream refused): {report}"
    );
}
