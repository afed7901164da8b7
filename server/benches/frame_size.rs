//! Bytes per avatar-frame on the wire, and the angular error after decoding.
//!
//! Plays every clip of the built-in avatar and CMU 01_01 at 60 Hz the way a scene does: a
//! keyframe every 60 ticks and deltas against it in between (so a delta's keyframe is 1 to 59
//! ticks old). Each frame goes through the real `ChunkEncoder` and `FrameDecoder`; sizes are of
//! one avatar chunk (the 32-byte frame header is shared by all avatars of a frame and listed
//! apart). Compared with the same pose as raw f32 quaternions (16 bytes per joint, plus the same
//! f32 translations and scales) and with the avatar's object in a JSON frame.
//!
//! Run: `cargo bench -p posecast-server --bench frame_size` (CMU 01_01 needs ../shared/testdata;
//! it is skipped when absent). Prints a table; asserts nothing but the decoder's own errors.

use anyhow::{Context, Result, bail};
use glam::{Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{
    AvatarPose, ChunkEncoder, FrameDecoder, FrameHeader, FrameKind, HEADER_BYTES, write_header,
};
use posecast_proto::frame2;
use posecast_proto::msg::{AvatarId, AvatarPoseJson, FrameJson, SceneId, ServerMsg};
use posecast_proto::quant;
use posecast_proto::testing::testdata;
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::clip::Clip;
use posecast_server::import;
use posecast_server::rig::Rig;
use std::time::Instant;

/// Server tick rate the figures are for.
const RATE: f32 = 60.0;
/// Ticks between keyframes at [`RATE`] (the server's `key_interval`: one second).
const KEY_INTERVAL: usize = 60;
/// Bytes of a chunk before its rotations: avatar number, hash, three counts.
const CHUNK_HEAD: usize = 4 + 8 + 3 * 2;

/// One clip's figures.
#[derive(Debug, Default)]
struct Row {
    name: String,
    joints: usize,
    translations: usize,
    frames: usize,
    key_bytes: Vec<usize>,
    delta_bytes: Vec<usize>,
    /// Delta sizes one tick after the keyframe and in the last 10 ticks before the next.
    delta_young: Vec<usize>,
    delta_old: Vec<usize>,
    raw_bytes: usize,
    json_object: Vec<usize>,
    json_frame: Vec<usize>,
    /// Joints of all deltas by tag: unchanged, 3-byte difference, full 6 bytes.
    tags: [usize; 3],
    max_err_key: f64,
    max_err_delta: f64,
    /// The v2 estimate ([`estimate_v2`]).
    v2: V2Estimate,
    /// Wire v2 as shipped ([`measure_v2`]): keyframe every second, and first only.
    v2_keyed: V2Measured,
    v2_unkeyed: V2Measured,
}

/// Wire v2 measured through the real encoder and decoder ([`posecast_proto::frame2`]).
#[derive(Debug, Default, Clone, Copy)]
struct V2Measured {
    /// Mean bytes per joint per frame, whole frames (header included), one avatar a frame.
    per_joint: f64,
    /// Mean encode time of one avatar-frame (quantise + code), ns.
    encode_ns: f64,
    /// Largest rotation error after decoding, degrees; largest translation error, m.
    max_err: f64,
    max_terr: f64,
}

/// Plays `clip` looping for 60 s at 60 Hz through `frame2::StreamEncoder` and
/// `Frame2Decoder` (a receiver that gets every frame): a keyframe every `key_every` ticks
/// (`None`: the first only). Checks every decoded level against the encoder's.
fn measure_v2(
    rig: &Rig,
    streamed: &AvatarDescription,
    clip: &Clip,
    key_every: Option<usize>,
) -> Result<V2Measured> {
    let skeleton = rig.skeleton();
    let rest = skeleton.rest();
    let mut locals: Vec<Transform> = rest.to_vec();
    let frames = (60.0 * RATE) as usize;
    let duration = clip.duration().max(1e-3);
    let mut encoder = frame2::StreamEncoder::new();
    let mut decoder = frame2::Frame2Decoder::new();
    let (mut bytes, mut encode_ns) = (0usize, 0u128);
    let mut m = V2Measured::default();
    for i in 0..frames {
        let t = clip.start() + (i as f32 / RATE) % duration;
        clip.sample(t.min(clip.end()), rest, &mut locals);
        let pose = AvatarPose {
            avatar_num: 0,
            hash: 0x5eed,
            rotations: locals.iter().map(|l| l.rotation).collect(),
            translations: streamed
                .translated_joints
                .iter()
                .map(|&j| locals[usize::from(j)].translation)
                .collect(),
            scales: streamed
                .scaled_joints
                .iter()
                .map(|&j| locals[usize::from(j)].scale)
                .collect(),
            placement: Default::default(),
            weights: Vec::new(),
        };
        let key = key_every.map_or(i == 0, |k| i % k == 0);
        let seq = i as u64 + 1;
        let started = Instant::now();
        let (out, _) = encoder.encode(
            1,
            seq,
            1_750_000_000_000_000 + seq * 16_667,
            std::slice::from_ref(&pose),
            key,
        );
        encode_ns += started.elapsed().as_nanos();
        bytes += out.len();
        let got = decoder
            .decode_levels(&out)
            .with_context(|| format!("v2 frame {seq} does not decode"))?;
        let [a] = got.avatars.as_slice() else {
            bail!("v2 frame {seq}: {} avatars", got.avatars.len());
        };
        if *a.levels != frame2::QuantPose::from_pose(&pose) {
            bail!("v2 frame {seq}: decoded levels differ from the encoder's");
        }
        let back = a.levels.to_pose(0, 0x5eed);
        for (x, y) in pose.rotations.iter().zip(&back.rotations) {
            m.max_err = m.max_err.max(quant::angle_between_degrees(*x, *y));
        }
        for (x, y) in pose.translations.iter().zip(&back.translations) {
            m.max_terr = m.max_terr.max(f64::from((*x - *y).abs().max_element()));
        }
    }
    m.per_joint = bytes as f64 / frames as f64 / skeleton.len() as f64;
    m.encode_ns = encode_ns as f64 / frames as f64;
    Ok(m)
}

fn mean(v: &[usize]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<usize>() as f64 / v.len() as f64
    }
}

fn max(v: &[usize]) -> usize {
    v.iter().copied().max().unwrap_or(0)
}

/// Counts the 2-bit joint tags of a delta chunk (layout in `posecast_proto::frame`).
fn count_tags(chunk: &[u8], joints: usize, tags: &mut [usize; 3]) -> Result<()> {
    let bytes = chunk
        .get(CHUNK_HEAD..CHUNK_HEAD + joints.div_ceil(4))
        .context("delta chunk shorter than its tags")?;
    for j in 0..joints {
        let tag = usize::from((bytes[j / 4] >> (2 * (j % 4))) & 3);
        *tags.get_mut(tag).context("tag 3 in a delta")? += 1;
    }
    Ok(())
}

/// Plays `clip` on `rig` at 60 Hz from its start to its end through encoder and decoder.
fn measure(name: &str, rig: &Rig, clip: &Clip) -> Result<Row> {
    let skeleton = rig.skeleton();
    let description = AvatarDescription::new(
        AvatarId("a".into()),
        0,
        rig.name.clone(),
        skeleton,
        &rig.translated,
        &rig.scaled,
        None,
    );
    let rest = skeleton.rest();
    let mut locals: Vec<Transform> = rest.to_vec();
    let mut encoder = ChunkEncoder::new();
    let mut decoder = FrameDecoder::new();
    let frames = (clip.duration() * RATE).floor() as usize + 1;
    let mut row = Row {
        name: name.to_owned(),
        joints: skeleton.len(),
        translations: description.translated_joints.len() + description.scaled_joints.len(),
        frames,
        ..Row::default()
    };
    row.raw_bytes = 16 * row.joints + 12 * row.translations;
    let mut last_key = 0u64;
    let mut out = Vec::new();
    for i in 0..frames {
        let t = clip.start() + i as f32 / RATE;
        clip.sample(t.min(clip.end()), rest, &mut locals);
        let pick = |list: &[u16], f: fn(&Transform) -> Vec3| -> Vec<Vec3> {
            list.iter().map(|&j| f(&locals[usize::from(j)])).collect()
        };
        let pose = AvatarPose {
            avatar_num: 0,
            hash: description.hash_u64(),
            rotations: locals.iter().map(|l| l.rotation).collect(),
            translations: pick(&description.translated_joints, |l| l.translation),
            scales: pick(&description.scaled_joints, |l| l.scale),
            placement: Default::default(),
            weights: Vec::new(),
        };
        let seq = i as u64 + 1;
        let age = i % KEY_INTERVAL;
        let kind = if age == 0 {
            last_key = seq;
            FrameKind::Key
        } else {
            FrameKind::Delta
        };
        let header = FrameHeader {
            kind,
            scene_num: 1,
            seq,
            server_time_us: 1_750_000_000_000_000 + seq * 16_667,
            base_seq: last_key,
        };
        out.clear();
        write_header(&header, 1, &mut out);
        encoder.encode(&pose, kind, &mut out);
        let chunk = &out[HEADER_BYTES..];
        let decoded = decoder
            .decode(&out)
            .with_context(|| format!("{name}: frame {seq} does not decode"))?;
        let [got] = decoded.avatars.as_slice() else {
            bail!(
                "{name}: frame {seq} decoded to {} avatars",
                decoded.avatars.len()
            );
        };
        if got.translations != pose.translations || got.scales != pose.scales {
            bail!("{name}: frame {seq}: translations or scales changed on the wire");
        }
        let err = pose
            .rotations
            .iter()
            .zip(&got.rotations)
            .map(|(&a, &b)| quant::angle_between_degrees(a, b))
            .fold(0.0f64, f64::max);
        match kind {
            FrameKind::Key => {
                row.key_bytes.push(chunk.len());
                row.max_err_key = row.max_err_key.max(err);
            }
            FrameKind::Delta => {
                row.delta_bytes.push(chunk.len());
                if age == 1 {
                    row.delta_young.push(chunk.len());
                } else if age >= KEY_INTERVAL - 10 {
                    row.delta_old.push(chunk.len());
                }
                count_tags(chunk, row.joints, &mut row.tags)?;
                row.max_err_delta = row.max_err_delta.max(err);
            }
        }
        let quat = |q: &Quat| q.to_array();
        let object = AvatarPoseJson {
            avatar: AvatarId("avatar-0".into()),
            hash: description.hash.clone(),
            rotations: pose.rotations.iter().map(quat).collect(),
            translations: pose.translations.iter().map(|v| v.to_array()).collect(),
            scales: pose.scales.iter().map(|v| v.to_array()).collect(),
            placement: pose.placement,
            joints: None,
            weights: Default::default(),
        };
        row.json_object.push(serde_json::to_string(&object)?.len());
        let message = ServerMsg::Frame(FrameJson {
            scene: SceneId("default".into()),
            seq,
            server_time_us: header.server_time_us,
            avatars: vec![object],
        });
        row.json_frame.push(serde_json::to_string(&message)?.len());
    }
    row.v2 = estimate_v2(rig, &description, clip);
    row.v2_keyed = measure_v2(rig, &description, clip, Some(KEY_INTERVAL))?;
    row.v2_unkeyed = measure_v2(rig, &description, clip, None)?;
    Ok(row)
}

/// What a wire v2 as issue 14 sketches would cost: each frame against the *previous* one, every
/// 15-bit level predicted from the frames before (the previous level, or constant velocity
/// `2·l₋₁ − l₋₂`, whichever has done better: [`Adaptive`]), the zigzagged residual Rice-coded
/// with a parameter adapted per joint and component from its past residuals (so the decoder can
/// follow without side information); a joint whose dropped
/// component changed goes in full (6 bytes). Translations quantised to 1/8192 m (error ≤ 0.061
/// mm) and coded the same way. Headers as v2 would need them: 8 bytes a frame (magic and kind,
/// scene, seq and time as varints), 2 a delta chunk, 13 + 6·J + 12·T a keyframe chunk.
/// Nothing is encoded: this counts bits, to size the work, not to ship it.
#[derive(Debug, Default, Clone, Copy)]
struct V2Estimate {
    /// Mean bytes per joint per frame, one avatar per frame (its header not shared), over 60 s:
    /// keyframes once a second, and only the first.
    per_joint_keyed: f64,
    per_joint_unkeyed: f64,
    /// Share of joint-frames whose dropped component changed (sent in full).
    escapes: f64,
}

/// Bits of `u` in a Rice code of parameter `k`, escaping long quotients to 15 raw bits.
fn rice_bits(u: u64, k: u32) -> u64 {
    let q = u >> k;
    if q > 16 {
        17 + 16
    } else {
        q + 1 + u64::from(k)
    }
}

/// One level's coder: of two predictions — the previous frame (`still`) and constant velocity
/// (`moving`) — it codes the residual of the one whose running mean has been smaller (noisy
/// motion-capture joints do better without the velocity term, which doubles their noise), with
/// the Rice parameter `k = ⌊log₂(mean |residual| + 1)⌋` of that running mean. The decoder can
/// keep the same state from the levels it decodes, so nothing is sent about either choice.
#[derive(Debug, Default, Clone, Copy)]
struct Adaptive {
    /// Running means of the zigzagged residuals, in 1/16 units: still, moving.
    mean16: [u64; 2],
}

impl Adaptive {
    fn code(&mut self, still: i64, moving: i64) -> u64 {
        let zigzag = |r: i64| ((r << 1) ^ (r >> 63)) as u64;
        let u = [zigzag(still), zigzag(moving)];
        let pick = usize::from(self.mean16[1] <= self.mean16[0]);
        let k = 63 - ((self.mean16[pick] >> 4) + 1).leading_zeros();
        let bits = rice_bits(u[pick], k.min(15));
        for (mean, u) in self.mean16.iter_mut().zip(u) {
            // mean ← 7/8 mean + 1/8 u.
            *mean = *mean - (*mean >> 3) + ((u.min(1 << 20) << 4) >> 3);
        }
        bits
    }
}

fn estimate_v2(rig: &Rig, streamed: &AvatarDescription, clip: &Clip) -> V2Estimate {
    let skeleton = rig.skeleton();
    let rest = skeleton.rest();
    let joints = skeleton.len();
    // The joints whose translations frames carry (the description's, as the server streams).
    let translated: Vec<usize> = streamed
        .translated_joints
        .iter()
        .map(|&j| usize::from(j))
        .collect();
    let mut locals: Vec<Transform> = rest.to_vec();
    let frames = (60.0 * RATE) as usize;
    let levels = |bits: u64| {
        let l = |k: u32| ((bits >> (15 * (2 - k))) & 0x7fff) as i64;
        ((bits >> 45) & 3, [l(0), l(1), l(2)])
    };
    // The last two frames of every joint: (dropped component, the three levels).
    type Levels = Option<(u64, [i64; 3])>;
    let mut history: Vec<[Levels; 2]> = vec![[None, None]; joints];
    let mut thistory: Vec<[Option<[i64; 3]>; 2]> = vec![[None, None]; translated.len()];
    let mut coders = vec![Adaptive::default(); 3 * (joints + translated.len())];
    let (mut keyed_bits, mut unkeyed_bits, mut escapes) = (0u64, 0u64, 0u64);
    let key_chunk_bits = 8 * (13 + 6 * joints + 12 * translated.len()) as u64;
    let duration = clip.duration().max(1e-3);
    for i in 0..frames {
        let t = clip.start() + (i as f32 / RATE) % duration;
        clip.sample(t.min(clip.end()), rest, &mut locals);
        let mut delta_bits = 8 * 2u64 + 1; // chunk head, "any index changed" flag
        let mut changed_any = false;
        for (j, local) in locals.iter().enumerate() {
            let (index, now) = levels(quant::encode(local.rotation));
            let [prev, prev2] = history[j];
            match prev {
                Some((pi, pl)) if pi == index => {
                    let velocity = match prev2 {
                        Some((qi, ql)) if qi == index => [0, 1, 2].map(|c| pl[c] - ql[c]),
                        _ => [0; 3],
                    };
                    for c in 0..3 {
                        let still = now[c] - pl[c];
                        delta_bits += coders[3 * j + c].code(still, still - velocity[c]);
                    }
                }
                _ => {
                    changed_any = true;
                    escapes += 1;
                    delta_bits += 48;
                }
            }
            history[j] = [Some((index, now)), prev];
        }
        if changed_any {
            delta_bits += joints as u64; // which joints went in full
        }
        for (k, &j) in translated.iter().enumerate() {
            let now = locals[j]
                .translation
                .to_array()
                .map(|v| (f64::from(v) * 8192.0).round() as i64);
            let [prev, prev2] = thistory[k];
            let predicted = match (prev, prev2) {
                (Some(p), Some(q)) => [0, 1, 2].map(|c| 2 * p[c] - q[c]),
                (Some(p), None) => p,
                _ => [0; 3],
            };
            for c in 0..3 {
                let still = now[c] - prev.map_or(0, |p| p[c]);
                delta_bits += coders[3 * (joints + k) + c].code(still, now[c] - predicted[c]);
            }
            thistory[k] = [Some(now), prev];
        }
        let delta_bits = delta_bits.div_ceil(8) * 8;
        let header = 8 * 8;
        keyed_bits += header
            + if i % KEY_INTERVAL == 0 {
                key_chunk_bits
            } else {
                delta_bits
            };
        unkeyed_bits += header + if i == 0 { key_chunk_bits } else { delta_bits };
    }
    let per_joint = |bits: u64| bits as f64 / 8.0 / frames as f64 / joints as f64;
    V2Estimate {
        per_joint_keyed: per_joint(keyed_bits),
        per_joint_unkeyed: per_joint(unkeyed_bits),
        escapes: escapes as f64 / (frames * joints) as f64,
    }
}

fn print(rows: &[Row]) {
    println!(
        "\nBytes per avatar-frame at {RATE} Hz (one avatar chunk; +{HEADER_BYTES} B frame header per frame, shared by all avatars)\n"
    );
    println!(
        "| clip | joints | T+S | frames | key B | delta mean B | delta max B | delta @1 tick | delta @50–59 ticks | raw f32 B | JSON B (avatar / 1-avatar frame) | key / raw | delta / raw | stream kB/s |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let key = mean(&r.key_bytes);
        let delta = mean(&r.delta_bytes);
        let per_frame = (r.key_bytes.iter().sum::<usize>() + r.delta_bytes.iter().sum::<usize>())
            as f64
            / r.frames as f64;
        println!(
            "| {} | {} | {} | {} | {key:.0} | {delta:.1} | {} | {:.1} | {:.1} | {} | {:.0} / {:.0} | {:.2} | {:.2} | {:.2} |",
            r.name,
            r.joints,
            r.translations,
            r.frames,
            max(&r.delta_bytes),
            mean(&r.delta_young),
            mean(&r.delta_old),
            r.raw_bytes,
            mean(&r.json_object),
            mean(&r.json_frame),
            key / r.raw_bytes as f64,
            delta / r.raw_bytes as f64,
            per_frame * f64::from(RATE) / 1000.0,
        );
    }
    println!("\nDelta joints by tag, and the largest angular error after decoding\n");
    println!(
        "| clip | unchanged | 3-byte difference | full 6 bytes | max error key ° | max error delta ° | bound ° |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let total = r.tags.iter().sum::<usize>().max(1) as f64;
        let pct = |n: usize| 100.0 * n as f64 / total;
        println!(
            "| {} | {:.1} % | {:.1} % | {:.1} % | {:.5} | {:.5} | {} |",
            r.name,
            pct(r.tags[0]),
            pct(r.tags[1]),
            pct(r.tags[2]),
            r.max_err_key,
            r.max_err_delta,
            quant::MAX_ERROR_DEGREES,
        );
    }
    println!(
        "\nA wire v2 estimate (`estimate_v2`: against the previous frame, constant-velocity prediction, adaptive Rice residuals; 60 s looping, one avatar per frame, headers included)\n"
    );
    println!(
        "| clip | v1 B/joint (today, +32 B header) | v2 B/joint, keyframe every 1 s | v2 B/joint, first keyframe only | joints sent in full (dropped component changed) |"
    );
    println!("|---|---:|---:|---:|---:|");
    for r in rows {
        let v1 = (r.key_bytes.iter().sum::<usize>()
            + r.delta_bytes.iter().sum::<usize>()
            + HEADER_BYTES * r.frames) as f64
            / r.frames as f64
            / r.joints as f64;
        println!(
            "| {} | {v1:.2} | {:.2} | {:.2} | {:.2} % |",
            r.name,
            r.v2.per_joint_keyed,
            r.v2.per_joint_unkeyed,
            100.0 * r.v2.escapes,
        );
    }
    println!(
        "\nWire v2 measured (`measure_v2`: real encoder and decoder, 60 s looping at {RATE} Hz, one avatar per frame, whole frames with their header; encode time per avatar-frame, quantisation included)\n"
    );
    println!(
        "| clip | joints | raw f32 (28 B/joint) | JSON B/joint | v1 B/joint | v2 B/joint, key every 1 s | v2 B/joint, first key only | v2 encode ns/avatar | v2 max rotation error ° | v2 max translation error m |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        let v1 = (r.key_bytes.iter().sum::<usize>()
            + r.delta_bytes.iter().sum::<usize>()
            + HEADER_BYTES * r.frames) as f64
            / r.frames as f64
            / r.joints as f64;
        println!(
            "| {} | {} | 28 | {:.1} | {v1:.2} | {:.2} | {:.2} | {:.0} | {:.5} | {:.6} |",
            r.name,
            r.joints,
            mean(&r.json_frame) / r.joints as f64,
            r.v2_keyed.per_joint,
            r.v2_unkeyed.per_joint,
            r.v2_keyed.encode_ns,
            r.v2_keyed.max_err.max(r.v2_unkeyed.max_err),
            r.v2_keyed.max_terr.max(r.v2_unkeyed.max_terr),
        );
    }
    println!(
        "\nkey B = {CHUNK_HEAD} (avatar, hash, counts) + 6·joints + 12·(T+S); raw f32 B = 16·joints + 12·(T+S);\n\
         stream kB/s = one avatar's chunks at {RATE} Hz (key + 59 deltas per second), without frame header or websocket framing."
    );
}

fn main() -> Result<()> {
    // `cargo bench` passes `--bench`; this harness takes no options.
    let mut rows = Vec::new();
    let mut assets = import::gltf::from_slice("avatar.glb", AVATAR_GLB)?;
    if assets.is_empty() {
        bail!("the built-in avatar holds no rig");
    }
    let builtin = posecast_server::rig::Rig::from_asset(assets.remove(0), &Default::default())?;
    for clip in &builtin.clips {
        rows.push(measure(
            &format!("built-in {}", clip.name()),
            &builtin,
            clip,
        )?);
    }
    let path = testdata("bvh/cmu/01_01.bvh");
    if path.exists() {
        let mut assets = import::load_path(&path)?;
        if assets.is_empty() {
            bail!("{} holds no rig", path.display());
        }
        let cmu = posecast_server::rig::Rig::from_asset(assets.remove(0), &Default::default())?;
        let clip = cmu
            .clips
            .first()
            .with_context(|| format!("{} has no clip", path.display()))?
            .clone();
        rows.push(measure("CMU 01_01", &cmu, &clip)?);
    } else {
        eprintln!("skipping CMU 01_01: {} is absent", path.display());
    }
    print(&rows);
    Ok(())
}
