//! End to end: the server in-process on port 0 streams the built-in avatar; the library client
//! connects, pauses and seeks it (`walk` at 0.25 s), waits for a pose from after the seek and
//! renders it offscreen. The picture must show the avatar where the CPU says it is: the
//! non-background pixels are compared with a CPU rasterisation of the CPU-skinned mesh, posed by
//! sampling the clip directly (not from the stream), through the renderer's camera.
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod render_support;

use glam::{Mat4, Vec2, Vec3};
use posecast_client::net::{Client, ClientOptions};
use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::{Offscreen, Renderer, RendererOptions, RgbaImage};
use posecast_client::view_source::{fresh_pose, wait_for_avatars};
use posecast_proto::command::Command;
use posecast_proto::fk::PoseBuffers;
use posecast_proto::msg::AvatarId;
use posecast_proto::skinning::skin_cpu;
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::config::Config;
use posecast_server::startup::{DEFAULT_AVATAR, DEFAULT_SCENE, Server};

const TOKEN: &str = "render-e2e-control";
use render_support::gpu;
use std::time::{Duration, Instant};

const WAIT: Duration = Duration::from_secs(10);
const SEEK: f32 = 0.25;

/// Pixel mask of a mesh drawn through `view_proj`: pixel centres inside some triangle (either
/// winding), the rule GPUs rasterise by, minus their tie-breaking on shared edges.
fn cpu_mask(positions: &[Vec3], indices: &[u32], view_proj: Mat4, w: u32, h: u32) -> Vec<bool> {
    let screen: Vec<Option<Vec2>> = positions
        .iter()
        .map(|&p| {
            let c = view_proj * p.extend(1.0);
            (c.w > 1e-6).then(|| {
                let n = c.truncate() / c.w;
                Vec2::new((n.x + 1.0) * 0.5 * w as f32, (1.0 - n.y) * 0.5 * h as f32)
            })
        })
        .collect();
    let mut mask = vec![false; (w * h) as usize];
    for t in indices.chunks_exact(3) {
        let (Some(a), Some(b), Some(c)) = (
            screen[t[0] as usize],
            screen[t[1] as usize],
            screen[t[2] as usize],
        ) else {
            continue;
        };
        let area = (b - a).perp_dot(c - a);
        if area.abs() < 1e-12 {
            continue;
        }
        let lo = a.min(b).min(c).max(Vec2::ZERO);
        let hi = a
            .max(b)
            .max(c)
            .min(Vec2::new(w as f32 - 1.0, h as f32 - 1.0));
        for y in lo.y.floor() as u32..=hi.y.ceil().max(0.0) as u32 {
            for x in lo.x.floor() as u32..=hi.x.ceil().max(0.0) as u32 {
                if x >= w || y >= h {
                    continue;
                }
                let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                let e0 = (b - a).perp_dot(p - a) / area;
                let e1 = (c - b).perp_dot(p - b) / area;
                let e2 = (a - c).perp_dot(p - c) / area;
                if e0 >= 0.0 && e1 >= 0.0 && e2 >= 0.0 {
                    mask[(y * w + x) as usize] = true;
                }
            }
        }
    }
    mask
}

/// Pixels that differ from the background (the top-left pixel; the grid is off).
fn image_mask(image: &RgbaImage) -> Vec<bool> {
    let bg = image.pixel(0, 0).unwrap();
    image
        .pixels()
        .chunks_exact(4)
        .map(|p| (0..3).any(|c| p[c].abs_diff(bg[c]) > 4))
        .collect()
}

/// `(min x, min y, max x, max y)` of the set pixels.
fn bbox(mask: &[bool], w: u32) -> Option<(u32, u32, u32, u32)> {
    mask.iter()
        .enumerate()
        .filter(|(_, m)| **m)
        .map(|(i, _)| (i as u32 % w, i as u32 / w))
        .fold(None, |b, (x, y)| {
            Some(match b {
                None => (x, y, x, y),
                Some((x0, y0, x1, y1)) => (x0.min(x), y0.min(y), x1.max(x), y1.max(y)),
            })
        })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn offscreen_render_of_the_live_stream_shows_the_seeked_avatar() {
    let Some(gpu) = gpu() else { return };
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new("test", Secret::new(TOKEN), Role::Control))
        .unwrap();
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        access,
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    let mut options = ClientOptions::new(server.ws_url(), DEFAULT_SCENE);
    options.token = Some(TOKEN.into());
    let client = Client::connect(options).await.unwrap();
    let avatar = AvatarId(DEFAULT_AVATAR.into());
    wait_for_avatars(&client, Some(&avatar), WAIT)
        .await
        .unwrap();
    client
        .command(Command::Play {
            avatar: avatar.clone(),
            clip: "walk".into(),
            from_asset: None,
            speed: None,
            looping: None,
            start: None,
            fade: Some(0.0),
            // The reference below samples the clip as authored, root motion included.
            root_motion: Some(posecast_proto::command::RootMotion::Accumulate),
        })
        .await
        .unwrap();
    client
        .command(Command::Pause {
            avatar: avatar.clone(),
        })
        .await
        .unwrap();
    client
        .command(Command::Seek {
            avatar: avatar.clone(),
            time: SEEK,
        })
        .await
        .unwrap();
    let seen = client.latest(&avatar).unwrap().seq;
    let pose = fresh_pose(&client, &avatar, seen, WAIT).await.unwrap();
    let view = client.avatar(&avatar).unwrap();
    let mesh = GlbMesh::from_slice(AVATAR_GLB)
        .unwrap()
        .for_joints(&view.description.joint_names)
        .unwrap();

    let (width, height) = (320, 240);
    let mut renderer = Renderer::new(
        gpu,
        Offscreen::FORMAT,
        width,
        height,
        RendererOptions {
            grid: false,
            skeleton_overlay: false,
            ..RendererOptions::default()
        },
    )
    .unwrap();
    let target = Offscreen::new(gpu, width, height).unwrap();
    let handle = renderer.add_avatar(&view.skeleton, &mesh).unwrap();
    renderer.set_pose(handle, &pose.locals).unwrap();
    let start = Instant::now();
    let image = target.render(&mut renderer).unwrap();
    eprintln!(
        "tick {} rendered in {:.1} ms",
        pose.seq,
        start.elapsed().as_secs_f64() * 1e3
    );
    let view_proj = renderer.camera().view_proj(width as f32 / height as f32);

    // The reference: the importer's rig and clip, sampled here, skinned on the CPU.
    let rig = posecast_server::builtin::rig().unwrap();
    let skeleton = rig.skeleton();
    assert_eq!(skeleton.names(), &view.description.joint_names[..]);
    let walk = rig.clip("walk").unwrap();
    let mut locals = skeleton.rest().to_vec();
    walk.sample(walk.start() + SEEK, skeleton.rest(), &mut locals);
    let mut buffers = PoseBuffers::new(skeleton);
    buffers.update(skeleton, &locals);
    let mut positions = vec![Vec3::ZERO; mesh.vertex_count()];
    let mut normals = positions.clone();
    skin_cpu(&mesh, &buffers.skinning, &mut positions, &mut normals);
    let expected = cpu_mask(&positions, mesh.indices(), view_proj, width, height);
    let actual = image_mask(&image);

    let count = |m: &[bool]| m.iter().filter(|x| **x).count();
    let both = expected
        .iter()
        .zip(&actual)
        .filter(|(a, b)| **a && **b)
        .count();
    let either = expected
        .iter()
        .zip(&actual)
        .filter(|(a, b)| **a || **b)
        .count();
    let iou = both as f64 / either.max(1) as f64;
    let (e, a) = (
        bbox(&expected, width).unwrap(),
        bbox(&actual, width).unwrap(),
    );
    eprintln!(
        "coverage CPU {} px, GPU {} px, IoU {iou:.4}; bbox CPU {e:?}, GPU {a:?}",
        count(&expected),
        count(&actual)
    );
    let failed = || {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
        image.write_png(&dir.join("e2e-actual.png")).ok();
        format!(
            "picture written to {}",
            dir.join("e2e-actual.png").display()
        )
    };
    // The avatar fills a good part of the frame (auto-framed), so it is no speck.
    assert!(
        count(&expected) > 2000,
        "CPU silhouette too small: {}",
        count(&expected)
    );
    // Quantised rotations (streamed) move silhouette edges by well under a pixel at this size;
    // anti-aliasing is off; so the sets differ only along edges: 1 px of 2 px-wide limbs is
    // the worst case, ~5 % of the area.
    let ratio = count(&actual) as f64 / count(&expected) as f64;
    assert!(
        (0.95..=1.05).contains(&ratio),
        "coverage ratio {ratio}; {}",
        failed()
    );
    assert!(iou > 0.93, "IoU {iou}; {}", failed());
    let near = |p: u32, q: u32| p.abs_diff(q) <= 2;
    assert!(
        near(e.0, a.0) && near(e.1, a.1) && near(e.2, a.2) && near(e.3, a.3),
        "bbox CPU {e:?} vs GPU {a:?}; {}",
        failed()
    );
    drop(client);
    server.stop().await;
}
