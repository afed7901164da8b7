//! Bytes per joint per frame as subscribers receive them: an in-process server at 60 Hz, the
//! clip played by avatars of a scene, and library clients (`posecast_client::net::Client`)
//! subscribed to it — one per protocol version and joint set — whose received frame bytes
//! (headers and every avatar chunk, whole frames, keyframes included) are divided by the
//! frames and the joints they carried. Nothing is modelled: these are the bytes the websocket
//! delivered.
//!
//! Clients of protocol versions 5 to 7 ask for a precision each (`subscribe … precision`): a
//! worst angle, or a world-space bound at 3 cm from every joint; version 6's frames use
//! near-axis steps (`posecast_proto::precision::Steps::near`), as the second table's do, and
//! version 7's deltas are packed (`posecast_proto::frame2::PackedDeltas`). A
//! second table gives, for each precision and the same served rig and clip, what the coding
//! costs in accuracy and time:
//! the clip sampled at 60 Hz for a minute as the server samples it, coded and decoded with the
//! wire's own `StreamEncoder` / `Frame2Decoder` at that precision's steps, against the source
//! poses — the worst angle of any joint, the world-space error of ACL's metric (virtual
//! vertices 3 cm from every joint along its three axes; worst and 99th percentile), and the
//! encode time per avatar-frame.
//!
//! `cargo bench -p posecast --bench subscriber_bytes` — rows: the built-in avatar walking
//! (one avatar; ten at staggered times), and CMU 01_01 loaded as the server loads an asset
//! folder's BVH (`../shared/testdata`; absent, the row says so, and under `CI=true` the bench
//! fails).

use glam::{Mat4, Vec3};
use posecast_proto::Transform;
use posecast_proto::command::Command;
use posecast_proto::description::AvatarDescription;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::frame::AvatarPose;
use posecast_proto::frame2::{Frame2Decoder, StreamEncoder};
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_proto::precision::Precision;
use posecast_proto::quant;
use posecast_proto::subset::JointSet;
use posecast_server::rig::Rig;
use posecast_server::stream::feed::V2_KEY_SECONDS;
use posecast_testkit::{TestClient, TestServer};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Seconds measured per row, after the clients' first frames and a second of settling (as
/// long as a wire v2 subscriber's keyframe interval, so a row holds its share of them).
const SECONDS: f64 = 10.0;

/// One scene to measure: `avatars` avatars of rig `asset` playing `clip`, the i-th started
/// `i × stagger` seconds into it.
struct Case<'a> {
    name: &'a str,
    asset: &'a str,
    clip: &'a str,
    avatars: usize,
    stagger: f32,
}

/// The clients of one row: (label, protocol version, joint set, precision).
fn subscriptions() -> Vec<(String, u32, Option<u16>, Option<Precision>)> {
    let mut out = vec![
        ("v1".to_owned(), 1, None, None),
        ("v2".to_owned(), 3, None, None),
        ("v2, v7".to_owned(), 7, None, None),
        ("v2, depth ≤ 3".to_owned(), 3, Some(3), None),
    ];
    for (label, p) in precisions().into_iter().skip(1) {
        out.push((format!("v2 at {label}, v5"), 5, None, Some(p)));
        out.push((format!("v2 at {label}, v6"), 6, None, Some(p)));
        out.push((format!("v2 at {label}, v7"), 7, None, Some(p)));
    }
    out
}

/// The precisions measured: (label, precision), the finest first.
fn precisions() -> Vec<(&'static str, Precision)> {
    let deg = |d: f32| Precision {
        degrees: Some(d),
        ..Precision::FINEST
    };
    let mm = |m: f32| Precision {
        millimetres: Some(m),
        ..Precision::FINEST
    };
    vec![
        ("finest (0.0087°)", Precision::FINEST),
        ("0.05°", deg(0.05)),
        ("0.1°", deg(0.1)),
        ("0.25°", deg(0.25)),
        ("1 mm at 3 cm", mm(1.0)),
        ("5 mm at 3 cm", mm(5.0)),
    ]
}

/// Prints the row's byte figures; returns its rows of the accuracy table.
async fn measure(server: &TestServer, case: &Case<'_>) -> anyhow::Result<Vec<String>> {
    let scene = format!("bytes-{}-{}", case.asset, case.avatars);
    let id = |i: usize| AvatarId(format!("{}-{}-{i}", case.asset, case.avatars));
    server
        .command(Command::CreateScene {
            scene: SceneId(scene.clone()),
        })
        .await?;
    for i in 0..case.avatars {
        let avatar = id(i);
        server
            .command(Command::AddAvatar {
                scene: SceneId(scene.clone()),
                asset: case.asset.to_owned(),
                avatar: Some(avatar.clone()),
                clip: None,
                position: None,
                rotation: None,
            })
            .await?;
        server
            .command(Command::Play {
                avatar,
                clip: case.clip.to_owned(),
                from_asset: None,
                speed: None,
                looping: Some(true),
                start: Some(i as f32 * case.stagger),
                fade: None,
                root_motion: None,
            })
            .await?;
    }
    let rig = server.rig(case.asset)?;
    let joints = rig.skeleton().len();
    let mut clients: Vec<(String, TestClient, usize)> = Vec::new();
    let mut description = None;
    for (label, version, depth, precision) in subscriptions() {
        let client = server
            .client_builder()
            .subscribe(&scene)
            .options(|o| {
                o.version = version;
                o.joints = depth.map(JointSet::Depth);
                o.precision = precision;
            })
            .connect()
            .await?;
        client.first_pose(&id(0).0, Duration::from_secs(30)).await?;
        // The joints its frames carry (the subset the server and the client derive alike).
        let view = client.avatar(&id(0));
        description = description.or_else(|| view.as_ref().map(|v| v.description.clone()));
        let carried = view
            .and_then(|v| v.selection)
            .map_or(joints, |s| s.joints.len());
        clients.push((label, client, carried));
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let before: Vec<_> = clients.iter().map(|(_, c, _)| c.stats()).collect();
    tokio::time::sleep(Duration::from_secs_f64(SECONDS)).await;
    for ((label, client, carried), before) in clients.iter().zip(before) {
        let after = client.stats();
        let frames = after.frames - before.frames;
        let bytes = after.frame_bytes - before.frame_bytes;
        let per_frame = bytes as f64 / frames.max(1) as f64;
        let per_joint = per_frame / (case.avatars * carried) as f64;
        println!(
            "| {} | {} | {label} | {carried} of {joints} | {frames} | {per_frame:.1} | {per_joint:.2} | {} |",
            case.name,
            case.avatars,
            after.undecodable - before.undecodable,
        );
    }
    if case.avatars > 1 {
        return Ok(Vec::new());
    }
    let description = description.ok_or_else(|| anyhow::anyhow!("no description"))?;
    errors(case, &rig, &description)
}

/// The second table's rows for one rig and clip: every precision's accuracy and encode time
/// on a minute of the clip as the server samples it (see the module docs).
fn errors(
    case: &Case<'_>,
    rig: &Rig,
    description: &Arc<AvatarDescription>,
) -> anyhow::Result<Vec<String>> {
    let mut rows = Vec::new();
    const RATE: f32 = 60.0;
    const SHELL: f32 = 0.03;
    let clip = rig
        .clips
        .iter()
        .find(|c| c.name() == case.clip)
        .ok_or_else(|| anyhow::anyhow!("no clip {}", case.clip))?;
    let skeleton = rig.skeleton();
    let rest = skeleton.rest();
    let n = skeleton.len();
    let frames = (60.0 * RATE) as usize;
    // A keyframe as often as the server sends one to a wire v2 subscriber that keeps up.
    let key_every = (f64::from(RATE) * V2_KEY_SECONDS).ceil() as usize;
    let duration = clip.duration().max(1e-3);
    for (label, precision) in precisions() {
        // As a protocol version 7 subscriber gets them (near-axis steps, packed deltas).
        let steps = Arc::new(precision.resolve_with(description, true));
        let mut encoder = StreamEncoder::new().with_packing(true);
        encoder.set_steps(0, steps.clone());
        let mut decoder = Frame2Decoder::new();
        let mut locals: Vec<Transform> = rest.to_vec();
        let mut decoded_locals: Vec<Transform> = rest.to_vec();
        let (mut world, mut decoded_world) = (vec![Mat4::IDENTITY; n], vec![Mat4::IDENTITY; n]);
        let (mut worst_angle, mut bytes, mut encode_ns) = (0f64, 0usize, 0u128);
        let mut vertex_errors: Vec<f32> = Vec::with_capacity(frames * n * 3);
        for i in 0..frames {
            let t = clip.start() + (i as f32 / RATE) % duration;
            clip.sample(t.min(clip.end()), rest, &mut locals);
            let pose = AvatarPose {
                avatar_num: 0,
                hash: description.hash_u64(),
                rotations: locals.iter().map(|l| l.rotation).collect(),
                // The joints the server streams translations and scales of (the description's
                // lists, roots included).
                translations: description
                    .translated_joints
                    .iter()
                    .map(|&j| locals[usize::from(j)].translation)
                    .collect(),
                scales: description
                    .scaled_joints
                    .iter()
                    .map(|&j| locals[usize::from(j)].scale)
                    .collect(),
                placement: Default::default(),
                weights: Vec::new(),
            };
            let seq = i as u64 + 1;
            let started = Instant::now();
            let (out, _) = encoder.encode(
                1,
                seq,
                seq * 16_667,
                std::slice::from_ref(&pose),
                i % key_every == 0,
            );
            encode_ns += started.elapsed().as_nanos();
            bytes += out.len();
            let got = decoder.decode(&out)?;
            let back = &got.avatars[0];
            for (j, (x, y)) in pose.rotations.iter().zip(&back.rotations).enumerate() {
                worst_angle = worst_angle.max(quant::angle_between_degrees(*x, *y));
                decoded_locals[j] = Transform {
                    rotation: *y,
                    ..locals[j]
                };
            }
            for (&j, &t) in description.translated_joints.iter().zip(&back.translations) {
                decoded_locals[usize::from(j)].translation = t;
            }
            forward_kinematics(skeleton, &locals, &mut world);
            forward_kinematics(skeleton, &decoded_locals, &mut decoded_world);
            for (w, d) in world.iter().zip(&decoded_world) {
                for axis in [Vec3::X, Vec3::Y, Vec3::Z] {
                    let v = axis * SHELL;
                    vertex_errors.push(w.transform_point3(v).distance(d.transform_point3(v)));
                }
            }
        }
        vertex_errors.sort_by(f32::total_cmp);
        let worst_mm = vertex_errors.last().copied().unwrap_or(0.0) * 1000.0;
        let p99_mm = vertex_errors[vertex_errors.len() * 99 / 100] * 1000.0;
        let coarsest = steps.rotations.iter().max().copied().unwrap_or(1);
        rows.push(format!(
            "| {} | {label} | {}–{coarsest} | {:.2} | {worst_angle:.4}° | {worst_mm:.3} | {p99_mm:.3} | {:.2} |",
            case.name,
            steps.rotations.iter().min().copied().unwrap_or(1),
            bytes as f64 / frames as f64 / n as f64,
            encode_ns as f64 / frames as f64 / 1000.0,
        ));
    }
    Ok(rows)
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    // An asset folder holding only a link to the shared BVH (nothing copied).
    let folder = tempfile::tempdir()?;
    let bvh = posecast_proto::testing::testdata("bvh/cmu/01_01.bvh");
    let have_cmu = bvh.is_file();
    if have_cmu {
        std::os::unix::fs::symlink(&bvh, folder.path().join("01_01.bvh"))?;
    } else if std::env::var("CI").as_deref() == Ok("true") {
        anyhow::bail!("{} is missing", bvh.display());
    }
    let server = TestServer::builder()
        .tick_rate(60.0)
        .assets(folder.path())
        .start()
        .await?;
    let cmu_clip = if have_cmu {
        let rig = server.rig("01_01")?;
        Some(
            rig.clips
                .first()
                .map(|c| c.name().to_owned())
                .unwrap_or_default(),
        )
    } else {
        None
    };
    println!(
        "Bytes per joint per frame as subscribers receive them, 60 Hz, {SECONDS} s a row (whole frames: header, every avatar, keyframes: v1 once a second, v2 every {V2_KEY_SECONDS} s)\n"
    );
    println!(
        "| clip | avatars | wire | joints sent | frames | B/frame | B/joint/frame | undecodable |"
    );
    println!("|---|---:|---|---|---:|---:|---:|---:|");
    let mut cases = vec![
        Case {
            name: "built-in walk",
            asset: "avatar",
            clip: "walk",
            avatars: 1,
            stagger: 0.0,
        },
        Case {
            name: "built-in walk",
            asset: "avatar",
            clip: "walk",
            avatars: 10,
            stagger: 0.37,
        },
    ];
    if let Some(clip) = &cmu_clip {
        cases.push(Case {
            name: "CMU 01_01",
            asset: "01_01",
            clip,
            avatars: 1,
            stagger: 0.0,
        });
        cases.push(Case {
            name: "CMU 01_01",
            asset: "01_01",
            clip,
            avatars: 10,
            stagger: 0.37,
        });
    } else {
        println!("(CMU 01_01 absent: {} is missing)", bvh.display());
    }
    let mut accuracy = Vec::new();
    for case in &cases {
        // One scene per row: the built-in rig's two rows use distinct scenes too.
        accuracy.extend(measure(&server, case).await?);
    }
    println!(
        "\nAccuracy and encode time per precision: the served rig's clip, 60 s at 60 Hz, one avatar, a keyframe every {V2_KEY_SECONDS} s (as the server sends a v2 subscriber that keeps up), coded and decoded by the wire's StreamEncoder / Frame2Decoder\n"
    );
    println!(
        "| clip | precision | rotation steps | B/joint/frame (one stream) | worst angle | worst error at 3 cm, mm | p99, mm | encode µs/avatar-frame |"
    );
    println!("|---|---|---|---:|---:|---:|---:|---:|");
    for row in accuracy {
        println!("{row}");
    }
    server.stop().await;
    Ok(())
}
