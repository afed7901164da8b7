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
use posecast_proto::msg::{AvatarId, AvatarPoseJson, FrameJson, SceneId, ServerMsg};
use posecast_proto::quant;
use posecast_proto::testing::testdata;
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::clip::Clip;
use posecast_server::import;
use posecast_server::rig::Rig;

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
    Ok(row)
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
