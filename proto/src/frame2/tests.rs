use super::*;
use crate::testing::{arb_quat, f32s};
use proptest::prelude::*;

fn pose(num: u32, rotations: Vec<Quat>, translations: Vec<Vec3>, scales: Vec<Vec3>) -> AvatarPose {
    AvatarPose {
        avatar_num: num,
        hash: 0x1234_5678_9abc_def0 ^ u64::from(num),
        rotations,
        translations,
        scales,
        placement: Placement::IDENTITY,
        weights: Vec::new(),
    }
}

fn frame_bytes(kind: FrameKind, seq: u64, base: u64, chunks: &[u8], count: usize) -> Vec<u8> {
    let mut out = Vec::new();
    write_header(
        &FrameHeader {
            kind,
            scene_num: 4,
            seq,
            server_time_us: 1_750_000_000_000_000 + seq,
            base_seq: base,
        },
        count,
        &mut out,
    );
    out.extend_from_slice(chunks);
    out
}

#[test]
fn constant_velocity_costs_one_bit_a_component() {
    // Levels 10, 8, 6 of every component (newest first): still residuals zigzag 4, 4, the
    // velocity residual 0, so the prediction is 12 with k = 0 and a level of 12 costs the
    // single bit "0". One joint: avatar varint, flags, 3 bits padded to a byte.
    let bits = |l: u64| 3 << 45 | l << 30 | l << 15 | l;
    let history: Vec<QuantPose> = [10, 8, 6]
        .map(|l| QuantPose {
            rotations: vec![bits(l)],
            ..QuantPose::default()
        })
        .into();
    let refs: Vec<&QuantPose> = history.iter().collect();
    let now = QuantPose {
        rotations: vec![bits(12)],
        ..QuantPose::default()
    };
    let mut out = Vec::new();
    assert!(encode_delta(3, &now, &refs, &mut out));
    assert_eq!(out, vec![3, 2 << 4, 0]);
    // One level off the prediction: zigzag 1 or 2 with k = 0 is "10" or "110".
    let off = QuantPose {
        rotations: vec![bits(13)],
        ..QuantPose::default()
    };
    out.clear();
    assert!(encode_delta(3, &off, &refs, &mut out));
    // 3 × "110" (zigzag(+1) = 2) = 9 bits: two bytes of stream.
    assert_eq!(out.len(), 4);
}

/// The block rotation predictor gives what the reference one (`predict`, in i64) gives for
/// each joint of each block, on random histories of every depth whose dropped components
/// change at random frames (cutting a joint's history short), at the ends of the level range,
/// and in a last block only partly filled with joints.
#[test]
fn the_rotation_predictor_matches_the_reference() {
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    let joints = 2 * LANES + 3;
    for case in 0..20_000 {
        let depth = (case % MAX_DEPTH) + 1;
        let spread = [1u64, 4, 64, 4096, 32768][case % 5];
        let mut frames = vec![vec![0u64; joints]; depth];
        for j in 0..joints {
            // The tag: dropped component and (protocol version 6) the grid tier.
            let index = next() % 8;
            let centre = (next() % 32768) as i64;
            for frame in &mut frames {
                let index = if next() % 6 == 0 { next() % 8 } else { index };
                let mut bits = index;
                for _ in 0..3 {
                    let level = match next() % 9 {
                        0 => 0,
                        1 => LEVEL_MASK as i64,
                        _ => (centre + (next() % spread) as i64 - spread as i64 / 2)
                            .clamp(0, LEVEL_MASK as i64),
                    };
                    bits = bits << 15 | level as u64;
                }
                frame[j] = bits;
            }
        }
        let slices: Vec<&[u64]> = frames.iter().map(|f| &f[..]).collect();
        // Two cases in three a kind 5 delta's spacing, of up to 300 ticks (past the clamp).
        let spacing = if case % 3 == 0 {
            None
        } else {
            let ahead = next() % 300;
            Some(Spacing::of(
                1000,
                &[1000 - ahead, 1000 - ahead - next() % 300],
            ))
        };
        for j0 in (0..joints).step_by(LANES) {
            let p = predict_rotations(&slices, j0, spacing);
            for l in 0..LANES.min(joints - j0) {
                let same: Vec<u64> = frames
                    .iter()
                    .map(|f| f[j0 + l])
                    .take_while(|&b| tag(b) == tag(frames[0][j0 + l]))
                    .collect();
                for c in 0..3 {
                    let h: Vec<i64> = same.iter().map(|&b| level(b, c)).collect();
                    assert_eq!(
                        (i64::from(p.pred[c][l]), p.k[c][l]),
                        predict(&h, true, spacing),
                        "{h:?} {spacing:?}"
                    );
                }
            }
        }
    }
}

/// The f32 Rice parameter is exact for every sum a rotation component can reach (below 2²¹)
/// and every divisor the predictor uses.
#[test]
fn the_rice_parameter_is_exact() {
    for d in 1..MAX_DEPTH as i32 {
        for x in 0..1i32 << 21 {
            assert_eq!(rice_parameter(x, d), (x / d + 1).ilog2(), "{x} / {d}");
        }
    }
}

#[test]
fn predict_picks_still_for_noise_and_velocity_for_motion() {
    let unit = None;
    assert_eq!(predict(&[7], true, unit), (7, K_WITHOUT_HISTORY));
    // Alternating noise: still residuals ±1 beat velocity residuals ±2.
    assert_eq!(predict(&[5, 4, 5, 4], false, unit).0, 5);
    assert_eq!(predict(&[100, 90, 80, 70], false, unit), (110, 0));
    // Prediction clamped to the level range for rotations, not for translations.
    assert_eq!(predict(&[32766, 32700, 32634], true, unit).0, 32766);
    assert_eq!(predict(&[32766, 32700, 32634], false, unit).0, 32832);
}

/// A kind 5 delta's prediction over the ticks to its frame, by hand. Frames at ticks 20, 19,
/// 18, 17, frame at 24 (`g = 4`; growths 4, 10 and 20):
/// - constant velocity 10: still `20 · 4 = 80`, velocity `0 · 10`, acceleration `0 · 20`; the
///   tie goes to velocity: `100 + ⌊(2·10·4 + 1) / 2⌋ = 140`, `k = 0`;
/// - steps 8, 10, 12 (accelerating): velocity `4 · 10 = 40`, acceleration 0 wins:
///   `100 + ⌊(2·12·4 + 2·4·5 + 1) / 2⌋ = 168` (= 100 + 14 + 16 + 18 + 20), `k = 0`;
/// - noise 5, 4, 5, 4: still `(5 / 3) · 4 = 6.67` beats velocity `3.5 · 10` and acceleration
///   `8 · 20`: `5`, `k = ⌊log₂ 7⌋ = 2`.
#[test]
fn a_referenced_delta_predicts_over_the_ticks_between_its_frames() {
    let four_ahead = Spacing::of(24, &[20, 19, 18, 17]);
    assert_eq!(four_ahead, Spacing { ahead: 4, apart: 1 });
    let on = Some(four_ahead);
    assert_eq!(predict(&[100, 90, 80, 70], false, on), (140, 0));
    assert_eq!(predict(&[100, 90, 80, 70], true, on), (140, 0));
    assert_eq!(predict(&[100, 88, 78, 70], false, on), (168, 0));
    assert_eq!(predict(&[5, 4, 5, 4], false, on), (5, 2));
    // Kind 4 predicts a tick on, whatever the ticks between.
    assert_eq!(predict(&[100, 88, 78, 70], false, None).0, 112);
    // Two ticks apart, three ahead: 10 · 3 / 2 = 15; 9 · 3 / 2 = 13.5 rounds up to 14,
    // −9 · 3 / 2 = −13.5 up to −13.
    let apart = Some(Spacing::of(13, &[10, 8]));
    assert_eq!(predict(&[100, 90, 80], false, apart).0, 115);
    assert_eq!(predict(&[100, 91, 82], false, apart).0, 114);
    assert_eq!(predict(&[100, 109, 118], false, apart).0, 87);
    // One frame named: `ahead` both ways; gaps beyond the clamp count as 255.
    assert_eq!(Spacing::of(9, &[5]), Spacing { ahead: 4, apart: 4 });
    assert_eq!(
        Spacing::of(10_000, &[9_000, 1]),
        Spacing {
            ahead: 255,
            apart: 255
        }
    );
    assert_eq!(Spacing::of(3, &[2, 1]), Spacing { ahead: 1, apart: 1 });
    // 255 ticks on: 1999 · 255 = 509,745 gives 18 bits; 3,999,999,999 · 255 stops at 32.
    let far = Some(Spacing::of(300, &[45, 44]));
    assert_eq!(predict(&[0, 1000], false, far), (0, 18));
    assert_eq!(predict(&[0, 2_000_000_000], false, far), (0, 32));
    // Clamped rotations stay in range; one value predicts itself.
    assert_eq!(predict(&[32000, 31000, 30000], true, on).0, 32766);
    assert_eq!(predict(&[7], true, on), (7, K_WITHOUT_HISTORY));
}

#[test]
fn translations_within_the_stated_bound() {
    for x in [
        0.0f32,
        1e-5,
        -0.3,
        1.0 / 16384.0,
        12.345_678,
        -999.999,
        5000.123,
    ] {
        let back = translation_value(translation_level(x));
        assert!(
            (f64::from(back) - f64::from(x)).abs() <= MAX_TRANSLATION_ERROR,
            "{x} -> {back}"
        );
    }
    assert_eq!(translation_level(f32::NAN), 0);
    assert_eq!(translation_level(1e30), i32::MAX);
}

/// Random smooth-ish motion of one rig: per joint a start rotation, an angular velocity and
/// per-tick noise; every so often a joint jumps to an arbitrary rotation.
#[derive(Debug, Clone)]
struct Motion {
    start: Vec<Quat>,
    spin: Vec<Vec3>,
    noise: f32,
    jumps: Vec<(usize, usize, Quat)>,
    translations: usize,
    scales: usize,
}

fn arb_motion() -> impl Strategy<Value = Motion> {
    (1usize..40).prop_flat_map(|joints| {
        (
            prop::collection::vec(arb_quat(), joints),
            prop::collection::vec(prop::array::uniform3(f32s(-3.0..3.0)), joints),
            prop_oneof![Just(0.0f32), f32s(0.0..0.01)],
            prop::collection::vec((0usize..60, 0..joints, arb_quat()), 0..4),
            0usize..3,
            0usize..2,
        )
            .prop_map(|(start, spin, noise, jumps, translations, scales)| Motion {
                start: start
                    .into_iter()
                    .map(|q| {
                        if q.length() < 1e-3 {
                            Quat::IDENTITY
                        } else {
                            q.normalize()
                        }
                    })
                    .collect(),
                spin: spin.into_iter().map(Vec3::from_array).collect(),
                noise,
                jumps,
                translations,
                scales,
            })
    })
}

impl Motion {
    fn at(&self, tick: usize, num: u32) -> AvatarPose {
        let t = tick as f32 / 60.0;
        let mut rng = (tick as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let mut noise = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            ((rng >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * self.noise
        };
        let mut rotations: Vec<Quat> = self
            .start
            .iter()
            .zip(&self.spin)
            .map(|(&q, &w)| {
                let n = Vec3::new(noise(), noise(), noise());
                (Quat::from_scaled_axis(w * t + n) * q).normalize()
            })
            .collect();
        for &(when, joint, q) in &self.jumps {
            if tick >= when && q.length() > 1e-3 {
                rotations[joint] = q.normalize();
            }
        }
        let translations = (0..self.translations)
            .map(|k| Vec3::new(t * (k as f32 + 0.5), 0.9 + 0.05 * (t * 7.0).sin(), -t) + noise())
            .collect();
        let scales = (0..self.scales)
            .map(|_| Vec3::splat(if tick > 30 { 1.5 } else { 1.0 }))
            .collect();
        let mut p = pose(num, rotations, translations, scales);
        if tick % 17 == 5 {
            p.placement.position = Vec3::new(t, 0.0, 1.0);
        }
        p
    }
}

fn assert_decoded(expected: &AvatarPose, q: &QuantPose, got: &DecodedAvatar) {
    assert_eq!(got.avatar_num, expected.avatar_num);
    assert_eq!(got.hash, expected.hash);
    // Exactly the encoder's levels; within the bounds of the source.
    assert_eq!(&*got.levels, q);
    let decoded = got.levels.to_pose(got.avatar_num, got.hash);
    for (a, b) in expected.rotations.iter().zip(&decoded.rotations) {
        assert!(quant::angle_between_degrees(*a, *b) <= quant::MAX_ERROR_DEGREES);
    }
    for (a, b) in expected.translations.iter().zip(&decoded.translations) {
        for c in 0..3 {
            assert!(f64::from((a[c] - b[c]).abs()) <= MAX_TRANSLATION_ERROR + 1e-7);
        }
    }
    assert_eq!(decoded.scales, expected.scales);
    assert_eq!(decoded.placement, expected.placement);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Two avatars streamed for 60 ticks to a reader that gets every frame (deltas against
    /// the previous one) and to a slow reader that misses random frames and, after a gap,
    /// gets a keyframe or a delta against the last frame it decoded (whichever the sender
    /// chooses): both decode exactly the encoder's levels every time.
    #[test]
    fn every_reader_decodes_the_encoders_levels(
        a in arb_motion(),
        b in arb_motion(),
        drops in prop::collection::vec(any::<bool>(), 60),
        key_after_gap in prop::collection::vec(any::<bool>(), 60),
        packed in any::<bool>(),
    ) {
        let mut fast = Frame2Decoder::new();
        let mut slow = Frame2Decoder::new();
        // The fast reader's deltas packed (protocol version 7) or not.
        let mut stream = StreamEncoder::new().with_packing(packed);
        // The sender's ring of quantised poses by tick, and the slow reader's decoded seqs.
        let mut ring: Vec<Vec<Arc<QuantPose>>> = Vec::new();
        let mut slow_seqs: Vec<u64> = Vec::new();
        for tick in 0..60usize {
            let seq = tick as u64 + 1;
            let poses = [a.at(tick, 1), b.at(tick, 9)];
            let q: Vec<Arc<QuantPose>> = poses.iter().map(|p| Arc::new(QuantPose::from_pose(p))).collect();
            let time = 1_750_000_000_000_000 + seq * 16_667 - (seq % 3) * 5_000;
            let (bytes, _) = stream.encode(4, seq, time, &poses, tick == 0);
            prop_assert_eq!(bytes[1] == 3, packed && tick > 0);
            let got = fast.decode_levels(&bytes).unwrap();
            prop_assert_eq!(got.header.seq, seq);
            prop_assert_eq!(got.header.server_time_us, time);
            for ((p, q), g) in poses.iter().zip(&q).zip(&got.avatars) {
                assert_decoded(p, q, g);
            }
            ring.push(q.clone());
            if drops[tick] && tick > 0 {
                continue;
            }
            let gap = slow_seqs.first().is_some_and(|&s| s + 1 != seq);
            let delta = !(slow_seqs.is_empty() || gap && key_after_gap[tick]);
            let bytes = if delta {
                let base = slow_seqs[0];
                let mut body = Vec::new();
                for (k, (p, now)) in poses.iter().zip(&q).enumerate() {
                    let h: Vec<&QuantPose> = slow_seqs.iter().map(|&s| &*ring[s as usize - 1][k]).collect();
                    prop_assert!(encode_delta(p.avatar_num, now, &h, &mut body));
                }
                frame_bytes(FrameKind::Delta, seq, base, &body, 2)
            } else {
                let mut body = Vec::new();
                for (p, now) in poses.iter().zip(&q) {
                    encode_key(p.avatar_num, p.hash, now, &mut body);
                }
                slow_seqs.clear();
                frame_bytes(FrameKind::Key, seq, seq, &body, 2)
            };
            let got = slow.decode_levels(&bytes).unwrap();
            for ((p, q), g) in poses.iter().zip(&q).zip(&got.avatars) {
                assert_decoded(p, q, g);
            }
            slow_seqs.insert(0, seq);
            slow_seqs.truncate(MAX_DEPTH);
        }
    }

    /// Frames as datagrams (protocol versions 8 and 9): each tick's frame is a keyframe until
    /// the reader acknowledged one, then a delta of kind 4 or 5 (at random) naming the newest
    /// frames it acknowledged,
    /// whole or cut into one part per avatar. Datagrams are lost, come up to 3 ticks late (out
    /// of order); acknowledgements name the part's avatars, take 1 to 6 ticks and are lost
    /// too; a frame counts as acknowledged once every part is. The reader decodes every part
    /// that comes, to exactly the encoder's levels, a late keyframe included.
    #[test]
    fn a_datagram_reader_decodes_every_frame_that_comes(
        a in arb_motion(),
        b in arb_motion(),
        lost in prop::collection::vec(0u8..10, 240),
        late in prop::collection::vec(0u64..4, 240),
        ack_after in prop::collection::vec(1u64..7, 240),
        cut in prop::collection::vec(any::<bool>(), 120),
        spaced in prop::collection::vec(any::<bool>(), 120),
    ) {
        let mut reader = Frame2Decoder::for_datagrams();
        let mut ring: Vec<Vec<Arc<QuantPose>>> = Vec::new();
        let mut poses_of: Vec<[AvatarPose; 2]> = Vec::new();
        // (arrival tick, seq, bytes) in flight; (arrival tick, seq, avatars) acknowledgements
        // in flight; the avatars of each frame not acknowledged yet.
        let mut in_flight: Vec<(u64, u64, Vec<u8>)> = Vec::new();
        let mut acks: Vec<(u64, u64, Vec<u32>)> = Vec::new();
        let mut missing: HashMap<u64, Vec<u32>> = HashMap::new();
        let mut acked: Vec<u64> = Vec::new();
        let (mut decoded, mut deltas, mut parts_sent) = (0, 0, 0);
        let mut dice = 0usize;
        for tick in 0..140u64 {
            let seq = tick + 1;
            // What reaches each side this tick.
            acks.retain(|(at, s, avatars)| {
                if *at <= tick
                    && let Some(m) = missing.get_mut(s)
                {
                    m.retain(|n| !avatars.contains(n));
                    if m.is_empty() {
                        acked.push(*s);
                    }
                }
                *at > tick
            });
            acked.sort_unstable_by(|x, y| y.cmp(x));
            acked.dedup();
            let mut arrived: Vec<(u64, u64, Vec<u8>)> = Vec::new();
            in_flight.retain(|f| {
                if f.0 <= tick {
                    arrived.push(f.clone());
                }
                f.0 > tick
            });
            // Late ones in the order they come (a later tick first when it came first).
            arrived.sort_by_key(|f| (f.0, std::cmp::Reverse(f.1)));
            for (_, s, bytes) in arrived {
                let got = reader.decode_levels(&bytes).unwrap();
                prop_assert_eq!(got.header.seq, s);
                let nums: Vec<u32> = got.avatars.iter().map(|g| g.avatar_num).collect();
                for g in &got.avatars {
                    let k = usize::from(g.avatar_num != 1);
                    assert_decoded(&poses_of[s as usize - 1][k], &ring[s as usize - 1][k], g);
                }
                decoded += 1;
                dice += 1;
                if lost[dice % 240] != 0 {
                    acks.push((tick + ack_after[dice % 240], s, nums));
                }
            }
            if tick >= 120 {
                continue;
            }
            let poses = [a.at(tick as usize, 1), b.at(tick as usize, 9)];
            let q: Vec<Arc<QuantPose>> = poses.iter().map(|p| Arc::new(QuantPose::from_pose(p))).collect();
            let refs: Vec<u64> = acked
                .iter()
                .copied()
                .filter(|&r| seq - r < DATAGRAM_REFERENCE_TICKS)
                .take(MAX_DEPTH)
                .collect();
            let header = FrameHeader {
                kind: if refs.is_empty() { FrameKind::Key } else { FrameKind::Delta },
                scene_num: 4,
                seq,
                server_time_us: 1_750_000_000_000_000 + seq * 16_667,
                base_seq: refs.first().copied().unwrap_or(seq),
            };
            let mut bytes = Vec::new();
            if refs.is_empty() {
                write_header(&header, 2, &mut bytes);
                for (p, now) in poses.iter().zip(&q) {
                    encode_key(p.avatar_num, p.hash, now, &mut bytes);
                }
            } else {
                deltas += 1;
                let kind = if spaced[tick as usize] { ReferencedKind::Ticks } else { ReferencedKind::Frames };
                write_referenced_header(&header, kind, &refs, 2, &mut bytes);
                for (k, (p, now)) in poses.iter().zip(&q).enumerate() {
                    let h: Vec<&QuantPose> = refs.iter().map(|&r| &*ring[r as usize - 1][k]).collect();
                    let spacing = kind.spacing(seq, &refs);
                    prop_assert!(encode_referenced_delta(p.avatar_num, now, &h, spacing, &mut bytes));
                }
            }
            ring.push(q);
            poses_of.push(poses);
            missing.insert(seq, vec![1, 9]);
            let parts = split_by_avatar(&bytes, if cut[tick as usize] { 1 } else { bytes.len() }).unwrap();
            if cut[tick as usize] {
                prop_assert_eq!(parts.iter().map(|p| p.1.clone()).collect::<Vec<_>>(), vec![vec![1], vec![9]]);
            } else {
                prop_assert_eq!(&parts[0].0, &bytes);
            }
            for (part, _) in parts {
                parts_sent += 1;
                if lost[(tick as usize * 2 + parts_sent) % 240] >= 2 {
                    in_flight.push((tick + late[(tick as usize + parts_sent) % 240], seq, part));
                }
            }
        }
        prop_assert!(decoded > 60 && deltas > 0, "{} decoded, {} deltas", decoded, deltas);
    }

    /// A stream coded on a coarser grid (random steps per joint and for translations, as a
    /// subscription's precision gives): the reader decodes exactly the encoder's grid values,
    /// and every rotation is within its joint's bound of the source, every translation within
    /// the translation step's.
    #[test]
    fn coarse_streams_decode_within_each_joints_bound(
        a in arb_motion(),
        rotation_steps in prop::collection::vec(1u8..=255, 40),
        translation_step in prop_oneof![Just(1u16), 1u16..=2000],
    ) {
        let joints = a.start.len();
        let steps = Arc::new(Steps {
            rotations: rotation_steps[..joints].to_vec(),
            translation: translation_step,
            near: Vec::new(),
        });
        let mut stream = StreamEncoder::new();
        stream.set_steps(3, steps.clone());
        let mut reader = Frame2Decoder::new();
        for tick in 0..60usize {
            let p = a.at(tick, 3);
            let (bytes, _) = stream.encode(4, tick as u64 + 1, 7, std::slice::from_ref(&p), tick == 0);
            let got = reader.decode_levels(&bytes).unwrap();
            let g = &got.avatars[0];
            prop_assert_eq!(&*g.levels, &QuantPose::from_pose(&p).coarsen(&steps));
            let decoded = g.levels.to_pose(3, p.hash);
            for (j, (x, y)) in p.rotations.iter().zip(&decoded.rotations).enumerate() {
                let angle = quant::angle_between_degrees(*x, *y);
                prop_assert!(angle <= precision::rotation_bound_degrees(steps.rotations[j]),
                    "joint {} step {}: {}°", j, steps.rotations[j], angle);
            }
            for (x, y) in p.translations.iter().zip(&decoded.translations) {
                for c in 0..3 {
                    prop_assert!(f64::from((x[c] - y[c]).abs())
                        <= precision::translation_bound(translation_step) + 1e-6);
                }
            }
        }
    }

    /// Protocol version 6: the same with each joint's near-axis step for its bound. Rotations
    /// near an axis go on the near grid (tier bit set), the others on the joint's grid; a
    /// joint crossing between them goes escaped in 48 bits. Every rotation stays within its
    /// joint's bound, and the reader decodes exactly the encoder's grid values.
    #[test]
    fn tiered_streams_decode_within_each_joints_bound(
        a in arb_motion(),
        rotation_steps in prop::collection::vec(1u8..=101, 40),
    ) {
        let joints = a.start.len();
        let rotations = rotation_steps[..joints].to_vec();
        let near: Vec<u8> = rotations
            .iter()
            .map(|&m| precision::near_rotation_step_for(precision::rotation_bound_degrees(m)).max(m))
            .collect();
        let steps = Arc::new(Steps { rotations, translation: 1, near });
        prop_assume!(steps.tiered());
        let mut stream = StreamEncoder::new();
        stream.set_steps(3, steps.clone());
        let mut reader = Frame2Decoder::new();
        for tick in 0..60usize {
            let p = a.at(tick, 3);
            let (bytes, _) = stream.encode(4, tick as u64 + 1, 7, std::slice::from_ref(&p), tick == 0);
            let got = reader.decode_levels(&bytes).unwrap();
            let g = &got.avatars[0];
            prop_assert_eq!(&*g.levels, &QuantPose::from_pose(&p).coarsen(&steps));
            let decoded = g.levels.to_pose(3, p.hash);
            for (j, (x, y)) in p.rotations.iter().zip(&decoded.rotations).enumerate() {
                let angle = quant::angle_between_degrees(*x, *y);
                prop_assert!(angle <= precision::rotation_bound_degrees(steps.rotations[j]),
                    "joint {} steps {}/{}: {}°", j, steps.rotations[j], steps.near[j], angle);
            }
        }
    }

    #[test]
    fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        let mut dec = Frame2Decoder::new();
        let _ = dec.decode(&bytes);
        for kind in [1u8, 2, 3, 4] {
            let mut framed = vec![MAGIC, kind];
            framed.extend_from_slice(&bytes);
            let _ = dec.decode(&framed);
        }
    }

    /// Random bytes as the body of a delta against a held frame: exercises the bit reader
    /// and the Rice escapes on arbitrary input.
    #[test]
    fn garbage_deltas_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200), depth in 0u8..16) {
        let p = pose(1, vec![Quat::from_rotation_x(0.4); 5], vec![Vec3::ONE], vec![Vec3::ONE]);
        let mut stream = StreamEncoder::new();
        let mut dec = Frame2Decoder::new();
        for seq in 1..4 {
            dec.decode(&stream.encode(4, seq, 0, std::slice::from_ref(&p), false).0).unwrap();
        }
        let mut body = vec![1, depth << 4 | (bytes.first().copied().unwrap_or(0) & 7)];
        body.extend_from_slice(&bytes);
        let _ = dec.decode(&frame_bytes(FrameKind::Delta, 4, 3, &body, 1));
    }

    /// Random bytes as the chunks of a kind 4 delta naming held frames (protocol version 8),
    /// with a length that may disagree with them: refused or decoded, never a panic; the
    /// splitter takes the same bytes without panicking either.
    #[test]
    fn garbage_referenced_deltas_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200), depth in 0u8..16, len in 0u8..255) {
        let p = pose(1, vec![Quat::from_rotation_x(0.4); 5], vec![Vec3::ONE], vec![Vec3::ONE]);
        let mut stream = StreamEncoder::new();
        let mut dec = Frame2Decoder::for_datagrams();
        for seq in 1..4 {
            dec.decode(&stream.encode(4, seq, 0, std::slice::from_ref(&p), false).0).unwrap();
        }
        let header = FrameHeader { kind: FrameKind::Delta, scene_num: 4, seq: 5, server_time_us: 0, base_seq: 3 };
        let mut frame = Vec::new();
        let kind = if len % 2 == 0 { ReferencedKind::Ticks } else { ReferencedKind::Frames };
        write_referenced_header(&header, kind, &[3, 1], 1, &mut frame);
        frame.push(len);
        frame.extend_from_slice(&[1, depth << 4 | (bytes.first().copied().unwrap_or(0) & 7)]);
        frame.extend_from_slice(&bytes);
        let _ = dec.decode(&frame);
        let _ = split_by_avatar(&frame, 40);
    }

    /// Random bits as the chunks of a packed delta (protocol version 7) against held frames
    /// of three avatars: the avatar numbers, heads, residuals and floats all from garbage.
    #[test]
    fn garbage_packed_deltas_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200), count in 0u8..5) {
        let poses: Vec<AvatarPose> = (1..4)
            .map(|num| {
                let mut p = pose(num, vec![Quat::from_rotation_x(0.4); 5], vec![Vec3::ONE], vec![Vec3::ONE]);
                p.weights = vec![0.5; 3];
                p
            })
            .collect();
        let mut stream = StreamEncoder::new();
        let mut dec = Frame2Decoder::new();
        for seq in 1..4 {
            dec.decode(&stream.encode(4, seq, 100, &poses, false).0).unwrap();
        }
        let mut framed = vec![MAGIC, 3, count, 4, 4, 1, 2];
        framed.extend_from_slice(&bytes);
        if let Ok(frame) = dec.decode(&framed) {
            prop_assert_eq!(frame.header.server_time_us, 101);
        }
    }

    /// The same against frames on a grid with near-axis steps (protocol version 6), whose
    /// escapes carry a tier flag and a tier change is predicted from a converted history.
    #[test]
    fn garbage_deltas_against_a_tiered_frame_never_panic(
        bytes in prop::collection::vec(any::<u8>(), 0..200),
        depth in 0u8..16,
    ) {
        let rotations = vec![
            Quat::from_rotation_x(0.4),
            Quat::from_rotation_y(1.9),
            Quat::from_xyzw(0.5, 0.5, 0.5, 0.5),
            Quat::IDENTITY,
            Quat::from_rotation_z(-0.8),
        ];
        let p = pose(1, rotations, vec![Vec3::ONE], vec![Vec3::ONE]);
        let steps = Arc::new(Steps { rotations: vec![5; 5], translation: 3, near: vec![9, 9, 1, 255, 9] });
        let mut stream = StreamEncoder::new();
        stream.set_steps(1, steps);
        let mut dec = Frame2Decoder::new();
        for seq in 1..4 {
            dec.decode(&stream.encode(4, seq, 0, std::slice::from_ref(&p), false).0).unwrap();
        }
        let mut body = vec![1, depth << 4 | (bytes.first().copied().unwrap_or(0) & 7)];
        body.extend_from_slice(&bytes);
        let _ = dec.decode(&frame_bytes(FrameKind::Delta, 4, 3, &body, 1));
    }
}

#[test]
fn every_truncation_is_an_error_and_leaves_the_decoder_unchanged() {
    let m = Motion {
        start: vec![Quat::from_rotation_y(0.3); 6],
        spin: vec![Vec3::new(0.5, 1.0, 0.0); 6],
        noise: 0.002,
        jumps: vec![(3, 2, Quat::from_rotation_x(3.0))],
        translations: 1,
        scales: 1,
    };
    let mut stream = StreamEncoder::new();
    let mut dec = Frame2Decoder::new();
    for tick in 0..6 {
        let p = m.at(tick, 2);
        let (bytes, kind) = stream.encode(4, tick as u64 + 1, 0, std::slice::from_ref(&p), false);
        assert_eq!(kind == FrameKind::Key, tick == 0);
        for len in 0..bytes.len() {
            assert!(
                dec.decode(&bytes[..len]).is_err(),
                "tick {tick}, length {len}"
            );
        }
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(dec.decode(&long), Err(Frame2Error::Trailing(1)));
        // The failed attempts changed nothing: the whole frame still decodes against its base.
        let got = dec.decode_levels(&bytes).unwrap();
        assert_eq!(*got.avatars[0].levels, QuantPose::from_pose(&p));
    }
}

#[test]
fn a_delta_against_a_frame_not_held_is_refused() {
    let p = pose(1, vec![Quat::IDENTITY; 3], vec![], vec![]);
    let mut stream = StreamEncoder::new();
    let key = stream.encode(4, 1, 0, std::slice::from_ref(&p), true).0;
    let delta = stream.encode(4, 2, 0, std::slice::from_ref(&p), false).0;
    let delta3 = stream.encode(4, 3, 0, std::slice::from_ref(&p), false).0;
    let mut dec = Frame2Decoder::new();
    assert_eq!(
        dec.decode(&delta),
        Err(Frame2Error::MissingBase {
            avatar: 1,
            base_seq: 1,
            depth: 1
        })
    );
    dec.decode(&key).unwrap();
    // Frame 3 refers to 2 (depth 2), which this decoder skipped.
    assert!(matches!(
        dec.decode(&delta3),
        Err(Frame2Error::MissingBase { base_seq: 2, .. })
    ));
    dec.decode(&delta).unwrap();
    dec.decode(&delta3).unwrap();
    // An unchanged pose of 3 joints: 2 chunk bytes and 9 one-bit residuals (2 bytes).
    let (_, count) = read_header(&delta3).unwrap();
    assert_eq!(count, 1);
    assert!(delta3.ends_with(&[1, 1 << 4, 0, 0]));
}

/// A packed delta (protocol version 7) of ten unchanged 3-joint avatars numbered in a run:
/// 24 bytes where kind 2 takes 49, the numbers and heads costing 2 bits an avatar; its time
/// reads only against its base frame (the reader's last of the scene), and a reader without
/// that frame refuses it and changes nothing.
#[test]
fn a_packed_delta_costs_two_bits_an_avatar_and_reads_its_time_from_its_base() {
    let poses: Vec<AvatarPose> = (5..15)
        .map(|n| pose(n, vec![Quat::from_rotation_y(0.2); 3], vec![], vec![]))
        .collect();
    let mut plain = StreamEncoder::new();
    let mut packed = StreamEncoder::new().with_packing(true);
    let mut frames = Vec::new();
    let mut last_plain = Vec::new();
    for seq in 1..=10u64 {
        let time = 1_000_000 + seq * 16_667;
        last_plain = plain.encode(4, seq, time, &poses, false).0;
        frames.push(packed.encode(4, seq, time, &poses, false).0);
    }
    assert_eq!(frames[0][1], 1, "a keyframe first");
    assert_eq!(frames[9][1], 3);
    // Header 9 bytes (the time since the base frame, 33,334 zigzagged, in 3); then 8 + 1 + 9
    // bits for the first avatar (its number in 5 + 3, the usual head, nine one-bit residuals)
    // and 1 + 1 + 9 for each next one: 117 bits, 15 bytes.
    assert_eq!(frames[9].len(), 24);
    assert_eq!(last_plain.len(), 49);
    // A reader that skipped frame 9 cannot read 10's time.
    let mut dec = Frame2Decoder::new();
    for f in &frames[..8] {
        dec.decode(f).unwrap();
    }
    let missing = Frame2Error::BaseTime {
        scene: 4,
        base_seq: 9,
    };
    assert_eq!(dec.decode(&frames[9]), Err(missing.clone()));
    assert_eq!(read_header(&frames[9]), Err(missing));
    dec.decode(&frames[8]).unwrap();
    let got = dec.decode(&frames[9]).unwrap();
    assert_eq!(got.header.server_time_us, 1_000_000 + 10 * 16_667);
    assert_eq!(got.avatars.len(), 10);
    // A reader of headers alone keeps a clock.
    let mut clock = FrameClock::default();
    for f in &frames {
        let (header, count) = clock.read(f).unwrap();
        assert_eq!(count, 10);
        assert_eq!(header.server_time_us, 1_000_000 + header.seq * 16_667);
        clock.record(&header);
    }
}

#[test]
fn a_forgotten_avatar_or_scene_needs_a_keyframe_again() {
    let a = pose(1, vec![Quat::IDENTITY; 2], vec![], vec![]);
    let b = pose(2, vec![Quat::from_rotation_x(0.5); 2], vec![], vec![]);
    let mut stream = StreamEncoder::new();
    let key = stream.encode(4, 1, 0, &[a.clone(), b], true).0;
    // Avatar 2 left: the next frame carries avatar 1 only, against the keyframe.
    let only_a = stream.encode(4, 2, 0, std::slice::from_ref(&a), false).0;
    let decoder = || {
        let mut dec = Frame2Decoder::new();
        dec.decode(&key).unwrap();
        dec
    };
    // Forgetting the avatar that left, or another scene's avatar 1, loses nothing needed.
    let mut kept = decoder();
    kept.forget_avatar(4, 2);
    kept.forget_avatar(5, 1);
    kept.decode(&only_a).unwrap();
    // Forgetting avatar 1 itself, or the scene: its delta is refused until a keyframe.
    let mut forgot = decoder();
    forgot.forget_avatar(4, 1);
    assert!(matches!(
        forgot.decode(&only_a),
        Err(Frame2Error::MissingBase { avatar: 1, .. })
    ));
    let mut left = decoder();
    left.forget_scene(4);
    assert!(left.decode(&only_a).is_err());
}

/// Morph weights (protocol version 4): a keyframe carries every level, a delta only the
/// changed ones behind a change mask; both decode to the levels sent. 52 ARKit weights with 10
/// changed cost at most 26 bytes a frame (issue 30's budget): 52 mask bits and 10 × 10-bit
/// levels, 19 bytes.
#[test]
fn weights_ride_keyframes_and_deltas_within_the_budget() {
    let rotations = vec![quant::encode(Quat::IDENTITY); 3];
    let mut key = QuantPose {
        rotations,
        weights: (0..52).map(|i| (i * 19) % 1024).collect(),
        ..QuantPose::default()
    };
    key.weights[0] = crate::morph::WEIGHT_LEVELS;
    let mut bare = Vec::new();
    encode_key(9, 77, &key.without_weights(), &mut bare);
    let mut with = Vec::new();
    encode_key(9, 77, &key, &mut with);
    // 52 levels of 10 bits = 65 bytes, plus the count's varint.
    assert_eq!(with.len() - bare.len(), 1 + 65);
    let mut dec = Frame2Decoder::new();
    let got = dec
        .decode_levels(&frame_bytes(FrameKind::Key, 10, 10, &with, 1))
        .unwrap();
    assert_eq!(got.avatars[0].levels.weights, key.weights);
    let poses = got.to_frame();
    assert_eq!(poses.avatars[0].weights.len(), 52);
    assert!((poses.avatars[0].weights[0] - 1.0).abs() < 1e-6);

    let mut next = key.clone();
    for i in (0..52).step_by(5).take(10) {
        next.weights[i] = (next.weights[i] + 37) % 1024;
    }
    let mut still = Vec::new();
    assert!(encode_delta(9, &next, &[&next], &mut still));
    let mut delta = Vec::new();
    assert!(encode_delta(9, &next, &[&key], &mut delta));
    let cost = delta.len() - still.len();
    assert_eq!(cost, (52 + 10 * 10usize).div_ceil(8));
    assert!(cost <= 26, "{cost} bytes");
    let got = dec
        .decode_levels(&frame_bytes(FrameKind::Delta, 11, 10, &delta, 1))
        .unwrap();
    assert_eq!(got.avatars[0].levels.weights, next.weights);
    // Unchanged weights: no flag, no bytes.
    let got = dec
        .decode_levels(&frame_bytes(FrameKind::Delta, 12, 11, &still, 1))
        .unwrap();
    assert_eq!(got.avatars[0].levels.weights, next.weights);
}

/// A weights block shorter than its count, or a weights flag on a delta whose base has none,
/// is refused and
/// changes nothing.
#[test]
fn malformed_weights_are_refused() {
    let key = QuantPose {
        rotations: vec![quant::encode(Quat::IDENTITY)],
        weights: vec![5],
        ..QuantPose::default()
    };
    let mut bytes = Vec::new();
    encode_key(1, 2, &key, &mut bytes);
    // Count, then the 10-bit level in two bytes: a count of 2 reads past the data.
    let mut dec = Frame2Decoder::new();
    let n = bytes.len();
    bytes[n - 3] = 2;
    assert!(
        dec.decode_levels(&frame_bytes(FrameKind::Key, 1, 1, &bytes, 1))
            .is_err()
    );
    let plain = QuantPose {
        rotations: vec![quant::encode(Quat::IDENTITY)],
        ..QuantPose::default()
    };
    let mut k = Vec::new();
    encode_key(1, 2, &plain, &mut k);
    dec.decode_levels(&frame_bytes(FrameKind::Key, 1, 1, &k, 1))
        .unwrap();
    let mut d = Vec::new();
    assert!(encode_delta(1, &plain, &[&plain], &mut d));
    d[1] |= 8;
    d.extend_from_slice(&[1, 0]);
    assert!(matches!(
        dec.decode_levels(&frame_bytes(FrameKind::Delta, 2, 1, &d, 1)),
        Err(Frame2Error::Flags { .. })
    ));
}

/// A delta chunk as the module docs and PROTOCOL.md describe it, one bit at a time, with the
/// i64 reference predictor: its flags byte, its bit stream (escape mask, rotations,
/// translations), and the weights' bits (change mask and levels; empty when unchanged).
struct ReferenceChunk {
    flags: u8,
    bits: Vec<bool>,
    weights: Vec<bool>,
    scales: bool,
    placement: bool,
}

fn put_bits(bits: &mut Vec<bool>, v: u64, n: u32) {
    bits.extend((0..n).map(|b| v >> b & 1 == 1));
}

/// `bits` as bytes, least significant bit first, the last byte padded with zeros.
fn bytes_of(bits: &[bool]) -> Vec<u8> {
    bits.chunks(8)
        .map(|byte| {
            byte.iter()
                .rev()
                .fold(0u8, |b, &bit| b << 1 | u8::from(bit))
        })
        .collect()
}

/// A kind 2 delta chunk from [`reference_chunk`]: what [`encode_delta`] must write byte for
/// byte (decoders in Rust and JavaScript read these bytes; the encoder's shortcuts must not
/// change one of them).
fn reference_delta(avatar_num: u32, pose: &QuantPose, history: &[&QuantPose]) -> Option<Vec<u8>> {
    let c = reference_chunk(pose, history)?;
    let mut out = Vec::new();
    varint(u64::from(avatar_num), &mut out);
    out.push(c.flags);
    out.extend(bytes_of(&c.bits));
    write_scales_placement(pose, c.scales, c.placement, &mut out);
    if !c.weights.is_empty() {
        out.extend(bytes_of(&c.weights));
    }
    Some(out)
}

/// A packed delta frame (kind 3, protocol version 7) of `chunks` (avatar number, pose,
/// history), written from PROTOCOL.md: the header with the time since `base_time`, then one bit
/// stream of every chunk.
fn reference_packed(
    header: &FrameHeader,
    base_time: u64,
    chunks: &[(u32, &QuantPose, &[&QuantPose])],
) -> Option<Vec<u8>> {
    let mut out = vec![MAGIC, 3];
    varint(chunks.len() as u64, &mut out);
    varint(u64::from(header.scene_num), &mut out);
    varint(header.seq, &mut out);
    varint(header.seq - header.base_seq, &mut out);
    let since = header.server_time_us as i64 - base_time as i64;
    varint(
        if since >= 0 {
            2 * since as u64
        } else {
            (-2 * since - 1) as u64
        },
        &mut out,
    );
    let mut bits = Vec::new();
    let mut prev: Option<u32> = None;
    for &(num, pose, history) in chunks {
        let c = reference_chunk(pose, history)?;
        if prev.is_some() {
            let next = prev == num.checked_sub(1);
            put_bits(&mut bits, u64::from(next), 1);
        }
        if prev.is_none() || prev != num.checked_sub(1) {
            let n = if num == 0 {
                1
            } else {
                32 - num.leading_zeros()
            };
            put_bits(&mut bits, u64::from(n - 1), 5);
            put_bits(&mut bits, u64::from(num), n);
        }
        prev = Some(num);
        if c.flags == 7 << 4 {
            put_bits(&mut bits, 1, 1);
        } else {
            put_bits(&mut bits, 0, 1);
            put_bits(&mut bits, u64::from(c.flags >> 4), 3);
            put_bits(&mut bits, u64::from(c.flags & 15), 4);
        }
        bits.extend(&c.bits);
        let mut floats = Vec::new();
        write_scales_placement(pose, c.scales, c.placement, &mut floats);
        for f in floats.chunks(4) {
            put_bits(
                &mut bits,
                u64::from(u32::from_le_bytes(f.try_into().unwrap())),
                32,
            );
        }
        bits.extend(&c.weights);
    }
    out.extend(bytes_of(&bits));
    Some(out)
}

fn reference_chunk(pose: &QuantPose, history: &[&QuantPose]) -> Option<ReferenceChunk> {
    let base = *history.first()?;
    if !pose.same_shape(base) {
        return None;
    }
    let history: Vec<&QuantPose> = history
        .iter()
        .take(MAX_DEPTH)
        .take_while(|h| h.same_shape(base))
        .copied()
        .collect();
    let escaped: Vec<bool> = (0..pose.rotations.len())
        .map(|j| pose.rotations[j] >> 45 & 7 != base.rotations[j] >> 45 & 7)
        .collect();
    // An escaped joint: tier, dropped component and levels on a grid with near-axis steps.
    let full = if pose.steps.as_ref().is_some_and(|s| !s.near.is_empty()) {
        48
    } else {
        47
    };
    let escapes = escaped.contains(&true);
    let scales = pose.scales != base.scales;
    let placement = pose.placement != base.placement;
    let weights = pose.weights != base.weights;
    let flags = ((history.len() - 1) as u8) << 4
        | u8::from(placement)
        | u8::from(scales) << 1
        | u8::from(escapes) << 2
        | u8::from(weights) << 3;
    // The bit stream, LSB first.
    let mut bits: Vec<bool> = Vec::new();
    let put = |bits: &mut Vec<bool>, v: u64, n: u32| bits.extend((0..n).map(|b| v >> b & 1 == 1));
    let rice = |bits: &mut Vec<bool>, u: u64, k: u32| {
        let q = u >> k;
        if q < RICE_ESCAPE {
            bits.extend((0..q).map(|_| true));
            bits.push(false);
            put(bits, u, k);
        } else {
            bits.extend((0..RICE_ESCAPE).map(|_| true));
            let n = (64 - u.leading_zeros()).max(1);
            put(bits, u64::from(n - 1), 6);
            put(bits, u, n);
        }
    };
    if escapes {
        for &e in &escaped {
            put(&mut bits, u64::from(e), 1);
        }
    }
    for (j, &now) in pose.rotations.iter().enumerate() {
        if escaped[j] {
            let steps = pose.steps.as_ref().filter(|s| !s.near.is_empty());
            if let Some(steps) = steps {
                let dropped = base.rotations[j] >> 45 & 3;
                if now >> 45 & 3 == dropped {
                    // Only the tier changed: residuals against the history on the new grid.
                    put(&mut bits, 1, 1);
                    let step = |b: u64| {
                        if b >> 47 & 1 == 1 {
                            steps.near[j]
                        } else {
                            steps.rotations[j]
                        }
                    };
                    let same: Vec<u64> = history
                        .iter()
                        .map(|f| f.rotations[j])
                        .take_while(|b| b >> 45 & 3 == dropped)
                        .collect();
                    for c in 0..3 {
                        let h: Vec<i64> = same
                            .iter()
                            .map(|&b| {
                                let fine = precision::fine_rotation_level(level(b, c), step(b));
                                precision::coarse_rotation_level(fine, step(now))
                            })
                            .collect();
                        let (pred, k) = predict(&h, true, None);
                        rice(&mut bits, zigzag(level(now, c) - pred), k);
                    }
                    continue;
                }
                put(&mut bits, 0, 1);
            }
            put(&mut bits, now, full);
            continue;
        }
        let same: Vec<u64> = history
            .iter()
            .map(|f| f.rotations[j])
            .take_while(|b| b >> 45 & 7 == now >> 45 & 7)
            .collect();
        for c in 0..3 {
            let h: Vec<i64> = same.iter().map(|&b| level(b, c)).collect();
            let (pred, k) = predict(&h, true, None);
            rice(&mut bits, zigzag(level(now, c) - pred), k);
        }
    }
    for (t, now) in pose.translations.iter().enumerate() {
        for (c, &value) in now.iter().enumerate() {
            let h: Vec<i64> = history
                .iter()
                .map(|f| i64::from(f.translations[t][c]))
                .collect();
            let (pred, k) = predict(&h, false, None);
            rice(&mut bits, zigzag(i64::from(value) - pred), k);
        }
    }
    let mut weight_bits = Vec::new();
    if weights {
        for (a, b) in pose.weights.iter().zip(&base.weights) {
            put(&mut weight_bits, u64::from(a != b), 1);
        }
        for (a, b) in pose.weights.iter().zip(&base.weights) {
            if a != b {
                put(&mut weight_bits, u64::from(*a), WEIGHT_BITS);
            }
        }
    }
    Some(ReferenceChunk {
        flags,
        bits,
        weights: weight_bits,
        scales,
        placement,
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    /// [`encode_delta`] writes exactly the reference's bytes: streams with noise, jumps that
    /// change a joint's dropped component (escapes, and histories cut short), on the finest
    /// grid and on coarse ones, against histories of every depth with frames skipped.
    #[test]
    fn deltas_are_the_reference_bytes(
        a in arb_motion(),
        skips in prop::collection::vec(0usize..3, 70),
        rotation_step in prop_oneof![Just(1u8), 1u8..=40],
        weights in 0usize..5,
        near in any::<bool>(),
    ) {
        let steps = Arc::new(Steps {
            rotations: vec![rotation_step; a.start.len()],
            translation: u16::from(rotation_step),
            // Protocol version 6: a coarser step near an axis (tier bit, 48-bit escapes).
            near: if near { vec![rotation_step.saturating_mul(2) | 1; a.start.len()] } else { Vec::new() },
        });
        let mut levels: Vec<QuantPose> = Vec::new();
        for tick in 0..70usize {
            let mut q = QuantPose::from_pose(&a.at(tick, 2)).coarsen(&steps);
            q.weights = (0..weights).map(|w| ((tick / (w + 1)) * 37 % 1024) as u16).collect();
            levels.push(q);
        }
        for (now, skip) in levels.iter().enumerate().skip(1).zip(&skips) {
            // Newest first, every `skip + 1`-th frame before `now`.
            let history: Vec<&QuantPose> = levels[..now.0]
                .iter()
                .rev()
                .step_by(skip + 1)
                .take(MAX_DEPTH + 1)
                .collect();
            let mut out = vec![0xAA];
            let written = encode_delta(2, now.1, &history, &mut out);
            let expected = reference_delta(2, now.1, &history);
            prop_assert_eq!(written, expected.is_some());
            let expected = expected.unwrap_or_default();
            prop_assert_eq!(&out[1..], expected.as_slice());
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// A packed delta frame (protocol version 7) is exactly the reference's bytes: three
    /// avatars (numbers in a run, apart, and 0 and `u32::MAX`) with noise, jumps, placements,
    /// scales and weights, against histories of every depth, with the time going forwards and
    /// backwards; and a decoder that took the base frame reads back the time and the levels.
    #[test]
    fn packed_deltas_are_the_reference_bytes(
        a in arb_motion(),
        b in arb_motion(),
        nums in prop_oneof![Just([4u32, 5, 6]), Just([9, 3, 4]), Just([0, 1, u32::MAX]), Just([u32::MAX, 0, 7])],
        skips in prop::collection::vec(0usize..3, 40),
        times in prop::collection::vec(-20_000i64..40_000, 40),
        weights in 0usize..4,
        rotation_step in prop_oneof![Just(1u8), 1u8..=40],
        near in any::<bool>(),
    ) {
        let motions = [&a, &b, &a];
        // On the finest grid or a coarse one, with near-axis steps (protocol version 6) or not.
        let grid = |joints: usize| {
            Arc::new(Steps {
                rotations: vec![rotation_step; joints],
                translation: u16::from(rotation_step),
                near: if near { vec![rotation_step.saturating_mul(2) | 1; joints] } else { Vec::new() },
            })
        };
        let mut levels: Vec<Vec<QuantPose>> = Vec::new();
        for tick in 0..40usize {
            levels.push(
                motions
                    .iter()
                    .zip(nums)
                    .map(|(m, num)| {
                        let mut q = QuantPose::from_pose(&m.at(tick + num as usize % 7, num))
                            .coarsen(&grid(m.start.len()));
                        q.weights = (0..weights).map(|w| ((tick / (w + 1)) * 37 % 1024) as u16).collect();
                        q
                    })
                    .collect(),
            );
        }
        let time = |tick: usize| (1_750_000_000_000_000i64 + tick as i64 * 16_667 + times[tick]) as u64;
        for (now, skip) in (1..40usize).zip(&skips) {
            let ticks: Vec<usize> = (0..now).rev().step_by(skip + 1).take(MAX_DEPTH + 1).collect();
            let histories: Vec<Vec<&QuantPose>> =
                (0..3).map(|k| ticks.iter().map(|&t| &levels[t][k]).collect()).collect();
            let header = FrameHeader {
                kind: FrameKind::Delta,
                scene_num: 4,
                seq: now as u64 + 1,
                server_time_us: time(now),
                base_seq: ticks[0] as u64 + 1,
            };
            let mut out = Vec::new();
            let mut packed = PackedDeltas::new(&header, time(ticks[0]), 3, &mut out);
            for k in 0..3 {
                prop_assert!(packed.push(nums[k], &levels[now][k], &histories[k]));
            }
            packed.finish();
            let chunks: Vec<(u32, &QuantPose, &[&QuantPose])> =
                (0..3).map(|k| (nums[k], &levels[now][k], &histories[k][..])).collect();
            let expected = reference_packed(&header, time(ticks[0]), &chunks).unwrap();
            prop_assert_eq!(&out, &expected);
            // A decoder holding the history (oldest first) reads it back.
            let mut dec = Frame2Decoder::new();
            let held: Vec<usize> = ticks.iter().take(MAX_DEPTH).rev().copied().collect();
            for (i, &t) in held.iter().enumerate() {
                let mut frame = Vec::new();
                let kind = if i == 0 { FrameKind::Key } else { FrameKind::Delta };
                let base_seq = if i == 0 { t } else { held[i - 1] } as u64 + 1;
                let h = FrameHeader { kind, scene_num: 4, seq: t as u64 + 1, server_time_us: time(t), base_seq };
                write_header(&h, 3, &mut frame);
                for k in 0..3 {
                    if i == 0 {
                        encode_key(nums[k], 77, &levels[t][k], &mut frame);
                    } else {
                        let history: Vec<&QuantPose> = held[..i].iter().rev().map(|&t| &levels[t][k]).collect();
                        prop_assert!(encode_delta(nums[k], &levels[t][k], &history, &mut frame));
                    }
                }
                dec.decode(&frame).unwrap();
            }
            let got = dec.decode_levels(&out).unwrap();
            prop_assert_eq!(got.header, header);
            for k in 0..3 {
                prop_assert_eq!(got.avatars[k].avatar_num, nums[k]);
                prop_assert_eq!(&*got.avatars[k].levels, &levels[now][k]);
            }
        }
    }
}

/// Near-axis grids (protocol version 6) are what makes a coarse precision cheaper: joints
/// swinging within 50° of their rest rotation with a capture's jitter (as a body's do), coded
/// at 0.1°, take at least 10 % fewer bytes with their near steps than without, every rotation
/// within 0.1°.
#[test]
fn near_axis_grids_code_joints_near_rest_in_fewer_bytes_within_the_bound() {
    let mut seed = 0x0123_4567_89ab_cdefu64;
    let mut rnd = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0
    };
    const JOINTS: usize = 31;
    let axes: Vec<Vec3> = (0..JOINTS)
        .map(|_| Vec3::new(rnd(), rnd(), rnd()).normalize_or(Vec3::Y))
        .collect();
    let phases: Vec<f32> = (0..JOINTS).map(|_| rnd() * 3.0).collect();
    let poses: Vec<AvatarPose> = (0..600)
        .map(|tick| {
            let t = tick as f32 / 60.0;
            AvatarPose {
                avatar_num: 1,
                hash: 9,
                rotations: (0..JOINTS)
                    .map(|j| {
                        // A swing, and a capture's jitter of about 0.1°.
                        let angle = 0.87 * (t * 1.3 + phases[j]).sin() + rnd() * 0.002;
                        Quat::from_axis_angle(axes[j], angle)
                    })
                    .collect(),
                translations: vec![Vec3::new(t, 1.0, 0.0)],
                scales: Vec::new(),
                placement: Placement::IDENTITY,
                weights: Vec::new(),
            }
        })
        .collect();
    let m = precision::rotation_step_for(0.1);
    let near = precision::near_rotation_step_for(0.1);
    let mut bytes = [0usize; 2];
    for (i, tiered) in [false, true].into_iter().enumerate() {
        let steps = Arc::new(Steps {
            rotations: vec![m; JOINTS],
            translation: 1,
            near: if tiered {
                vec![near; JOINTS]
            } else {
                Vec::new()
            },
        });
        let mut stream = StreamEncoder::new();
        stream.set_steps(1, steps);
        let mut reader = Frame2Decoder::new();
        for (tick, p) in poses.iter().enumerate() {
            let (out, _) = stream.encode(1, tick as u64 + 1, 7, std::slice::from_ref(p), tick == 0);
            bytes[i] += out.len();
            let got = reader.decode(&out).unwrap();
            for (x, y) in p.rotations.iter().zip(&got.avatars[0].rotations) {
                let angle = quant::angle_between_degrees(*x, *y);
                assert!(angle <= 0.1, "tiered {tiered} tick {tick}: {angle}°");
            }
        }
    }
    assert!(
        (bytes[1] as f64) < 0.9 * bytes[0] as f64,
        "near steps {near} against {m}: {} bytes against {}",
        bytes[1],
        bytes[0]
    );
}

/// Bytes of a kind 4 delta of 20 spinning joints and two translations at tick `seq` against
/// ticks `refs` (the motion's frames there), predicted with `spacing`.
fn referenced_bytes(seq: u64, refs: &[u64], spacing: Option<Spacing>) -> usize {
    let motion = Motion {
        start: (0..20)
            .map(|j| Quat::from_rotation_y(j as f32 * 0.3) * Quat::from_rotation_x(0.2))
            .collect(),
        spin: (0..20)
            .map(|j| Vec3::new(0.4 + 0.05 * j as f32, -0.3, 0.2 * (j % 3) as f32))
            .collect(),
        noise: 0.0,
        jumps: Vec::new(),
        translations: 2,
        scales: 0,
    };
    let q = |tick: u64| QuantPose::from_pose(&motion.at(tick as usize, 1));
    let history: Vec<QuantPose> = refs.iter().map(|&r| q(r)).collect();
    let h: Vec<&QuantPose> = history.iter().collect();
    let mut out = Vec::new();
    assert!(encode_referenced_delta(1, &q(seq), &h, spacing, &mut out));
    out.len()
}

/// Smooth motion four ticks past the newest frame named (a datagram's round trip at 60 Hz),
/// predicted over the ticks between (kind 5), costs at most 2.5 times a delta one tick on
/// (39 against 21 bytes here); predicted as one tick on (kind 4), over 6 times as much as that
/// (290 bytes; 514–574 bytes a frame of ten avatars in the link suite's 25 ms runs, against the
/// websocket's 169).
#[test]
fn a_referenced_delta_four_ticks_on_costs_near_a_one_tick_delta() {
    let refs: Vec<u64> = (23..=30).rev().collect();
    let one_tick = referenced_bytes(31, &refs, Some(Spacing::of(31, &refs)));
    let spaced = referenced_bytes(34, &refs, Some(Spacing::of(34, &refs)));
    let unspaced = referenced_bytes(34, &refs, None);
    eprintln!("one tick on {one_tick} B, four ticks on {spaced} B, as one tick {unspaced} B");
    assert!(
        spaced * 10 <= one_tick * 25,
        "{spaced} B against {one_tick} B"
    );
    assert!(spaced * 6 <= unspaced, "{spaced} B against {unspaced} B");
    // Frames named two ticks apart, three ahead.
    let apart: Vec<u64> = (0..8).map(|i| 30 - 2 * i).collect();
    let spaced = referenced_bytes(33, &apart, Some(Spacing::of(33, &apart)));
    let unspaced = referenced_bytes(33, &apart, None);
    eprintln!("two apart, three on: {spaced} B, as one tick {unspaced} B");
    assert!(spaced * 6 <= unspaced, "{spaced} B against {unspaced} B");
}
