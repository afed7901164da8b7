//! `posecast-client drive` end to end: the built binary streams CMU 01_01 to the built-in
//! avatar of an in-process server while a subscriber watches. Every driven pose the subscriber
//! sees must put the avatar's arms and legs where the BVH file's own forward kinematics puts
//! them at some time of the clip, those times must advance with the server's clock at the
//! requested speed, and once the command exits the avatar must be back on its clip.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::{Mat4, Quat, Vec3};
use posecast_client::net::{Client, ClientOptions, Driver};
use posecast_proto::Transform;
use posecast_proto::command::Command;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::import::bvh;
use posecast_server::startup::Server;
use std::io::Read;
use std::time::Duration;

const TOKEN: &str = "drive-cli-test-token";
const TICK_HZ: f32 = 30.0;
/// Clip seconds per second: the 22.9 s clip plays in under 4 s.
const SPEED: f32 = 6.0;
/// Limb direction error allowed between a streamed pose and the file (quantised twice, and the
/// clip is searched on a 1/480 s grid).
const MAX_LIMB_DEGREES: f32 = 2.0;

const LIMBS: [(&str, &str); 8] = [
    ("l_shoulder", "l_elbow"),
    ("l_elbow", "l_wrist"),
    ("r_shoulder", "r_elbow"),
    ("r_elbow", "r_wrist"),
    ("l_hip", "l_knee"),
    ("l_knee", "l_ankle"),
    ("r_hip", "r_knee"),
    ("r_knee", "r_ankle"),
];

fn avatar() -> AvatarId {
    AvatarId("avatar".into())
}

/// A server with the built-in avatar whose driver is never released by silence (30 s), so only
/// the command's own release returns the avatar to its clip.
async fn server() -> Server {
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new("test", Secret::new(TOKEN), Role::Control))
        .unwrap();
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: TICK_HZ,
        access,
        drive_timeout: Duration::from_secs(30),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    server
}

/// World position of every joint of `skeleton` with local rotations `rotations` and rest
/// translations: `W_j = W_parent(j) · D_j`.
fn world_positions(skeleton: &posecast_proto::Skeleton, rotations: &[Quat]) -> Vec<Vec3> {
    let locals: Vec<Transform> = skeleton
        .rest()
        .iter()
        .zip(rotations)
        .map(|(t, q)| Transform { rotation: *q, ..*t })
        .collect();
    let mut world = vec![Mat4::IDENTITY; skeleton.len()];
    forward_kinematics(skeleton, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

/// Unit direction of each of [`LIMBS`] (H-Anim names looked up through `hanim`).
fn limb_directions(positions: &[Vec3], hanim: &[Option<String>]) -> [Vec3; 8] {
    let at = |name: &str| {
        let j = hanim
            .iter()
            .position(|h| h.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("no joint maps to {name}"));
        positions[j]
    };
    LIMBS.map(|(a, b)| (at(b) - at(a)).normalize())
}

fn worst_angle(a: &[Vec3; 8], b: &[Vec3; 8]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| x.dot(*y).clamp(-1.0, 1.0).acos().to_degrees())
        .fold(0.0, f32::max)
}

/// The file's limb directions every 1/480 s of its clip, from the file as parsed (authored
/// rotations and offsets, before any normalisation): normalising keeps every joint where it
/// was, so these are what any correct retargeting must reproduce.
struct Reference {
    step: f32,
    directions: Vec<[Vec3; 8]>,
}

impl Reference {
    fn new(bvh_text: &str, hanim: &[Option<String>]) -> Self {
        let asset = bvh::parse("01_01.bvh", bvh_text).unwrap();
        let clip = &asset.clips[0];
        let skeleton = &asset.skeleton;
        let step = 1.0 / 480.0;
        let count = (clip.duration() / step).floor() as usize + 1;
        let mut locals = skeleton.rest().to_vec();
        let directions = (0..count)
            .map(|i| {
                clip.sample(clip.start() + i as f32 * step, skeleton.rest(), &mut locals);
                let rotations: Vec<Quat> = locals.iter().map(|l| l.rotation).collect();
                limb_directions(&world_positions(skeleton, &rotations), hanim)
            })
            .collect();
        Self { step, directions }
    }

    /// The clip time whose pose is nearest `observed`, and its worst limb error in degrees.
    fn nearest(&self, observed: &[Vec3; 8]) -> (f32, f32) {
        self.directions
            .iter()
            .enumerate()
            .map(|(i, d)| (i as f32 * self.step, worst_angle(d, observed)))
            .fold(
                (0.0, f32::INFINITY),
                |best, c| if c.1 < best.1 { c } else { best },
            )
    }
}

/// The command as a child process, killed if the test ends first.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        // Already exited when the test got that far; nothing else to do about a failure.
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// A streamed pose: the server's tick time and the avatar's local rotations.
struct Seen {
    server_time_us: u64,
    rotations: Vec<Quat>,
}

fn same_pose(a: &[Quat], b: &[Quat]) -> bool {
    a.iter()
        .zip(b)
        .all(|(x, y)| angle_between_degrees(*x, *y) <= 2.0 * MAX_ERROR_DEGREES)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bvh_clip_drives_the_built_in_avatar_and_is_released_at_its_end() {
    let Some(path) = posecast_proto::testing::require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let text = std::fs::read_to_string(&path).unwrap();
    let server = server().await;
    let target = server.state.world.library.get("avatar").unwrap();

    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.encoding = Encoding::Binary;
    options.reconnect = false;
    let sub = Client::connect(options).await.unwrap();
    // A still clip pose to come back to.
    let director = Driver::connect(&server.ws_url(), Some(TOKEN.into()))
        .await
        .unwrap();
    director
        .command(Command::Pause { avatar: avatar() })
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let clip_pose: Vec<Quat> = sub
        .latest(&avatar())
        .unwrap()
        .locals
        .iter()
        .map(|t| t.rotation)
        .collect();

    let mut cli = Child(
        std::process::Command::new(env!("CARGO_BIN_EXE_posecast-client"))
            .args(["drive", "--bvh"])
            .arg(&path)
            .args([
                "--avatar",
                "avatar",
                "--url",
                &server.ws_url(),
                "--token",
                TOKEN,
            ])
            .args(["--once", "--speed", &SPEED.to_string(), "--rate", "60"])
            .env_remove("RUST_BACKTRACE")
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap(),
    );

    // Every new tick's pose until the command exits (it has 20 s).
    let mut seen: Vec<Seen> = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = cli.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the command never ended"
        );
        if let Some(s) = sub.latest(&avatar())
            && seen
                .last()
                .is_none_or(|l| l.server_time_us != s.server_time_us)
        {
            seen.push(Seen {
                server_time_us: s.server_time_us,
                rotations: s.locals.iter().map(|t| t.rotation).collect(),
            });
        }
        tokio::time::sleep(Duration::from_millis(3)).await;
    };
    // It has exited: reading its pipes to the end cannot block.
    let (mut stdout, mut stderr) = (String::new(), String::new());
    cli.0
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut stdout)
        .unwrap();
    cli.0
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    assert!(status.success(), "drive failed:\n{stdout}\n{stderr}");
    assert!(
        stdout.contains("uploaded the source rig as asset 01_01")
            && stdout.contains("end of the clip"),
        "{stdout}"
    );
    assert!(
        !stderr.contains("server error"),
        "the server refused poses:\n{stderr}"
    );

    // The source rig the server made of the upload names the H-Anim joints.
    let source = server.state.world.library.get("01_01").unwrap();
    let reference = Reference::new(&text, &source.hanim);
    let driven: Vec<&Seen> = seen
        .iter()
        .skip_while(|s| same_pose(&s.rotations, &clip_pose))
        .collect();
    let matches: Vec<(u64, f32, f32)> = driven
        .iter()
        .map(|s| {
            let positions = world_positions(target.skeleton(), &s.rotations);
            let (time, error) = reference.nearest(&limb_directions(&positions, &target.hanim));
            (s.server_time_us, time, error)
        })
        .collect();
    // Between `drive` and the first pose applied the avatar shows the source's neutral pose:
    // a tick, or a few on a loaded machine. From the first pose of the clip to the last, every
    // tick must show the clip.
    let first_match = matches
        .iter()
        .position(|m| m.2 <= MAX_LIMB_DEGREES)
        .expect("no streamed pose matches the clip");
    assert!(
        first_match <= 3,
        "{first_match} ticks between drive and the first pose"
    );
    let last = matches
        .iter()
        .rposition(|m| m.2 <= MAX_LIMB_DEGREES)
        .unwrap_or(first_match);
    let run = &matches[first_match..=last];
    let off: Vec<_> = run.iter().filter(|m| m.2 > MAX_LIMB_DEGREES).collect();
    assert!(
        off.is_empty(),
        "{} of {} driven poses are not the clip's (worst {:.2}°)",
        off.len(),
        run.len(),
        off.iter().map(|m| m.2).fold(0.0, f32::max)
    );
    let worst = run.iter().map(|m| m.2).fold(0.0, f32::max);
    let clip_seconds = reference.step * (reference.directions.len() - 1) as f32;
    let expected_ticks = clip_seconds / SPEED * TICK_HZ;
    assert!(
        run.len() as f32 >= 0.8 * expected_ticks,
        "only {} driven ticks of ~{expected_ticks:.0}",
        run.len()
    );
    // The clip advances with the server's clock at SPEED, from the start to the end.
    let (first, end) = (run[0], run[run.len() - 1]);
    let wall = (end.0 - first.0) as f32 / 1e6;
    let rate = (end.1 - first.1) / wall;
    println!(
        "{} driven ticks, worst limb error {worst:.3}°; clip {:.2} s → {:.2} s in {wall:.2} s \
         of ticks: {rate:.2} clip s/s",
        run.len(),
        first.1,
        end.1
    );
    assert!(
        (rate - SPEED).abs() <= 0.15 * SPEED,
        "the clip advanced at {rate:.2}×, not {SPEED}×"
    );
    assert!(first.1 <= 0.1 * clip_seconds, "started at {:.2} s", first.1);
    assert!(end.1 >= 0.9 * clip_seconds, "ended at {:.2} s", end.1);

    // Released at the end: back on the (paused) clip well within the 30 s drive timeout.
    let back = async {
        loop {
            let now = sub.latest(&avatar()).unwrap();
            let rotations: Vec<Quat> = now.locals.iter().map(|t| t.rotation).collect();
            if same_pose(&rotations, &clip_pose) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(2), back)
        .await
        .expect("the avatar is back on its clip after the command exits");
    // And free for another driver.
    director.drive(&avatar(), None, None).await.unwrap();
}
