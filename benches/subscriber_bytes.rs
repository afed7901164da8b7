//! Bytes per joint per frame as subscribers receive them: an in-process server at 60 Hz, the
//! clip played by avatars of a scene, and library clients (`posecast_client::net::Client`)
//! subscribed to it — one per protocol version and joint set — whose received frame bytes
//! (headers and every avatar chunk, whole frames, keyframes included) are divided by the
//! frames and the joints they carried. Nothing is modelled: these are the bytes the websocket
//! delivered.
//!
//! `cargo bench -p posecast --bench subscriber_bytes` — rows: the built-in avatar walking
//! (one avatar; ten at staggered times), and CMU 01_01 loaded as the server loads an asset
//! folder's BVH (`../shared/testdata`; absent, the row says so, and under `CI=true` the bench
//! fails).

use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_proto::subset::JointSet;
use posecast_testkit::{TestClient, TestServer};
use std::time::Duration;

/// Seconds measured per row, after the clients' first frames and a second of settling.
const SECONDS: f64 = 6.0;

/// One scene to measure: `avatars` avatars of rig `asset` playing `clip`, the i-th started
/// `i × stagger` seconds into it.
struct Case<'a> {
    name: &'a str,
    asset: &'a str,
    clip: &'a str,
    avatars: usize,
    stagger: f32,
}

/// The clients of one row: (label, protocol version, joint set).
const CLIENTS: [(&str, u32, Option<u16>); 3] = [
    ("v1", 1, None),
    ("v2", 3, None),
    ("v2, depth ≤ 3", 3, Some(3)),
];

async fn measure(server: &TestServer, case: &Case<'_>) -> anyhow::Result<()> {
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
    let mut clients: Vec<(&str, TestClient, usize)> = Vec::new();
    for (label, version, depth) in CLIENTS {
        let client = server
            .client_builder()
            .subscribe(&scene)
            .options(|o| {
                o.version = version;
                o.joints = depth.map(JointSet::Depth);
            })
            .connect()
            .await?;
        client.first_pose(&id(0).0, Duration::from_secs(30)).await?;
        // The joints its frames carry (the subset the server and the client derive alike).
        let carried = client
            .avatar(&id(0))
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
    Ok(())
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
        "Bytes per joint per frame as subscribers receive them, 60 Hz, {SECONDS} s a row (whole frames: header, every avatar, keyframes once a second)\n"
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
    for case in &cases {
        // One scene per row: the built-in rig's two rows use distinct scenes too.
        measure(&server, case).await?;
    }
    server.stop().await;
    Ok(())
}
