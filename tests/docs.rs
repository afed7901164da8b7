//! What the documentation promises, run: the README's five-minute tour, as written, against
//! the real binaries, and the guide's server-flags page against what `posecast --help` prints.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use std::path::{Path, PathBuf};
use std::process::Command;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The bodies of the ```` ```sh ```` blocks of README's section `heading`.
fn sh_blocks(readme: &str, heading: &str) -> Vec<String> {
    let start = readme
        .find(&format!("\n{heading}\n"))
        .unwrap_or_else(|| panic!("README has a section {heading:?}"));
    let section = &readme[start + heading.len() + 2..];
    let section = &section[..section.find("\n## ").unwrap_or(section.len())];
    section
        .split("```sh\n")
        .skip(1)
        .map(|block| block[..block.find("\n```").expect("a closed block")].to_owned())
        .collect()
}

/// The `posecast-client` binary cargo built beside `posecast` (`cargo test --workspace`
/// builds every binary of the workspace before it runs a test).
fn client_binary() -> Option<PathBuf> {
    let path = Path::new(env!("CARGO_BIN_EXE_posecast")).with_file_name("posecast-client");
    path.exists().then_some(path)
}

/// README's tour: the server started with the first block's flags, the second block run by
/// bash with `cargo run --release -p posecast-client-cli --` standing for the client binary
/// and the server's address for `127.0.0.1:8080`. Every command must succeed and leave what
/// the tour says it makes.
#[test]
fn the_readmes_tour_runs_as_written() {
    let readme = std::fs::read_to_string(Path::new(ROOT).join("README.md")).unwrap();
    let blocks = sh_blocks(&readme, "## A five-minute tour");
    assert_eq!(
        blocks.len(),
        2,
        "the tour is a server command and a script: {blocks:?}"
    );
    let server_args: Vec<&str> = blocks[0]
        .trim()
        .strip_prefix("cargo run --release --")
        .expect("the tour starts the server with `cargo run --release -- FLAGS`")
        .split_whitespace()
        .collect();
    let Some(client) = client_binary() else {
        posecast_proto::testing::skip(
            "tests/docs.rs: target/…/posecast-client is not built (run `cargo test --workspace`)",
        );
        return;
    };

    let dir = tempfile::tempdir().unwrap();
    let server = Posecast::start_in(dir.path(), &server_args, &[]);
    let addr = server.addr.to_string();
    let script = blocks[1]
        .replace(
            "cargo run --release -p posecast-client-cli --",
            &client.to_string_lossy(),
        )
        .replace("127.0.0.1:8080", &addr);
    assert!(
        !script.contains("cargo ") && !script.contains(":8080"),
        "every command of the tour is one this test knows how to run: {script}"
    );
    let out = Command::new("bash")
        .args(["-euo", "pipefail", "-c", &script])
        .current_dir(dir.path())
        .env("POSECAST_URL", format!("ws://{addr}/ws"))
        .env_remove("RUST_BACKTRACE")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() && stderr.contains("no GPU adapter available") {
        posecast_proto::testing::skip(
            "tests/docs.rs: the tour renders, and no GPU adapter is here",
        );
        return;
    }
    assert!(
        out.status.success(),
        "the tour failed: {}\nstdout:\n{stdout}\nstderr:\n{stderr}\nserver:\n{:?}",
        out.status,
        server.output()
    );

    let file = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    assert!(
        file("walk.bvh").starts_with(b"HIERARCHY"),
        "walk.bvh is a BVH file"
    );
    assert!(
        file("take.glb").starts_with(b"glTF"),
        "take.glb is a binary glTF file"
    );
    assert!(
        file("scene.png").starts_with(b"\x89PNG\r\n\x1a\n"),
        "scene.png is a PNG"
    );
    // The upload, the new avatar and the take, in the order the tour makes them.
    let answers: Vec<serde_json::Value> = stdout
        .lines()
        .filter(|l| l.starts_with('{'))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let kinds: Vec<&str> = answers
        .iter()
        .map(|a| {
            a["kind"]
                .as_str()
                .or(a["code"].as_str())
                .unwrap_or("upload")
        })
        .collect();
    assert_eq!(
        kinds,
        ["upload", "avatar_added", "done", "recorded"],
        "{stdout}"
    );
    assert_eq!(answers[0]["result"][0]["name"], "walker", "{stdout}");
    assert_eq!(answers[1]["result"]["avatar"], "walker", "{stdout}");
    let frames = answers[3]["result"]["frames"].as_u64().unwrap();
    assert!(
        frames > 0,
        "the take has the ticks of two seconds: {stdout}"
    );
    assert!(
        stderr.contains("2 avatars") || stdout.contains("2 avatars"),
        "the render drew both avatars: {stdout}{stderr}"
    );
}

/// The `text` block of `docs/src/reference/server-flags.md` is `posecast --help`, character
/// for character (`POSECAST_UPDATE_DOCS=1` writes it).
#[test]
fn the_server_flags_page_is_what_the_binary_prints() {
    let mut command = Command::new(env!("CARGO_BIN_EXE_posecast"));
    command.arg("--help");
    // clap shows a set variable's value beside its flag: the page shows none.
    for (key, _) in std::env::vars_os() {
        if key.to_string_lossy().starts_with("POSECAST_") {
            command.env_remove(key);
        }
    }
    let out = command.output().unwrap();
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();

    let path = Path::new(ROOT).join("docs/src/reference/server-flags.md");
    let page = std::fs::read_to_string(&path).unwrap();
    let start = page
        .find("```text\n")
        .expect("the page has a ```text block")
        + 8;
    let end = start + page[start..].find("```\n").expect("a closed block");
    if std::env::var_os("POSECAST_UPDATE_DOCS").is_some() {
        std::fs::write(&path, format!("{}{help}{}", &page[..start], &page[end..])).unwrap();
        return;
    }
    let shown = &page[start..end];
    if shown != help {
        let line = shown
            .lines()
            .zip(help.lines())
            .position(|(a, b)| a != b)
            .map_or_else(|| "the end".to_owned(), |i| format!("line {}", i + 1));
        panic!(
            "docs/src/reference/server-flags.md differs from `posecast --help` at {line} of the \
             block: run `POSECAST_UPDATE_DOCS=1 cargo test --test docs`"
        );
    }
}

/// An example program as `cargo build --examples` leaves it (`target/…/examples/NAME`;
/// scripts/test builds them first: `cargo test` builds examples only as test harnesses), or a
/// skip.
fn example(name: &str) -> Option<PathBuf> {
    let path = Path::new(env!("CARGO_BIN_EXE_posecast"))
        .with_file_name("examples")
        .join(name);
    if !path.exists() {
        posecast_proto::testing::skip(&format!(
            "tests/docs.rs: examples/{name}.rs is not built (run `cargo build -p posecast --examples`)"
        ));
        return None;
    }
    Some(path)
}

/// `examples/watch.rs` prints the built-in avatar's head where an upright avatar's head is,
/// and `examples/wave.rs` drives the avatar: while it runs, a viewer sees the right upper arm
/// at the rotation the example sends, within the wire's bound; afterwards it exits cleanly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_examples_watch_and_drive() {
    let (Some(watch), Some(wave)) = (example("watch"), example("wave")) else {
        return;
    };
    let server = Posecast::start(&["--no-persist", "--control-token", "examples-secret"], &[]);
    let url = format!("ws://{}/ws", server.addr);

    let out = Command::new(&watch)
        .env("POSECAST_URL", &url)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let heights: Vec<f32> = stdout
        .lines()
        .filter_map(|l| l.strip_prefix("avatar tick "))
        .map(|l| {
            let inner = &l[l.find('(').unwrap() + 1..l.find(')').unwrap()];
            inner.split(", ").nth(1).unwrap().parse().unwrap()
        })
        .collect();
    assert!(
        heights.len() >= 20,
        "a line about ten times a second: {stdout}"
    );
    // The built-in avatar is 1.75 m tall; its skull base stands about 1.6 m up.
    assert!(
        heights.iter().all(|y| (1.45..1.7).contains(y)),
        "{heights:?}"
    );

    let mut child = Command::new(&wave)
        .env("POSECAST_URL", &url)
        .env("POSECAST_TOKEN", "examples-secret")
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let seen = viewer_sees_the_arm(&url, &mut child, glam::Quat::from_rotation_z(-1.5)).await;
    let out = tokio::task::spawn_blocking(move || child.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "wave failed: {stdout}");
    assert!(
        stdout.contains("sent 180 poses; released avatar"),
        "{stdout}"
    );
    assert!(seen <= posecast_proto::quant::MAX_ERROR_DEGREES);
}

/// Waits until a viewer of `url` sees the built-in avatar's right upper arm at `sent` (within
/// the wire's bound) while `child` runs; panics if it exits first. Returns the angle seen.
async fn viewer_sees_the_arm(url: &str, child: &mut std::process::Child, sent: glam::Quat) -> f64 {
    let viewer = posecast_client::net::Client::connect(posecast_client::net::ClientOptions::new(
        url.to_owned(),
        "default",
    ))
    .await
    .unwrap();
    let avatar = posecast_proto::msg::AvatarId("avatar".into());
    let mut events = viewer.events();
    loop {
        if let Some(view) = viewer.avatar(&avatar)
            && let Some(pose) = &view.latest
        {
            let shoulder = view.skeleton.find("r_shoulder").unwrap();
            let angle =
                posecast_proto::quant::angle_between_degrees(pose.locals[shoulder].rotation, sent);
            if angle <= posecast_proto::quant::MAX_ERROR_DEGREES {
                return angle;
            }
        }
        if let Ok(Some(status)) = child.try_wait() {
            panic!("the driver exited ({status}) before a viewer saw its pose");
        }
        // Wait for the next frame, however long a busy machine takes.
        let _ = events.recv().await;
    }
}

/// `examples/node` with its dependencies installed (`npm install` links `posecast` to
/// server/sdk), or `None` after [`posecast_proto::testing::skip`] when npm is missing.
///
/// The install runs once per test process: the two Node tests run at once, and two
/// `npm install`s in one folder race each other (one of them fails renaming `node_modules`).
fn node_examples() -> Option<std::path::PathBuf> {
    static INSTALLED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    let dir = Path::new(ROOT).join("examples/node");
    let installed = INSTALLED.get_or_init(|| {
        let npm = Command::new("npm")
            .args([
                "install",
                "--no-audit",
                "--no-fund",
                "--no-package-lock",
                "--silent",
            ])
            .current_dir(&dir)
            .output();
        match npm {
            Err(_) => Err(String::new()),
            Ok(npm) if !npm.status.success() => Err(format!(
                "npm install in examples/node: {}{}",
                String::from_utf8_lossy(&npm.stdout),
                String::from_utf8_lossy(&npm.stderr)
            )),
            Ok(_) => Ok(()),
        }
    });
    match installed {
        Err(why) if why.is_empty() => {
            posecast_proto::testing::skip(
                "tests/docs.rs: npm is missing (scripts/test installs Node.js)",
            );
            return None;
        }
        Err(why) => panic!("{why}"),
        Ok(()) => {}
    }
    assert!(
        dir.join("node_modules/posecast/package.json").exists(),
        "the SDK is installed as the package `posecast`"
    );
    Some(dir)
}

/// `examples/node/drive.mjs` drives the avatar from Node.js with the SDK installed from the
/// repository as an npm package (`npm install` in examples/node links `posecast` to
/// server/sdk): a viewer sees the right upper arm at the rotation it sends, and it exits
/// cleanly having released the avatar.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_node_example_drives_through_the_npm_package() {
    let Some(dir) = node_examples() else {
        return;
    };
    let server = Posecast::start(&["--no-persist", "--control-token", "examples-secret"], &[]);
    let url = format!("ws://{}/ws", server.addr);
    // Node 20 has the WebSocket global behind a flag; 22 and later without it.
    let mut child = Command::new("node")
        .args(["--experimental-websocket", "drive.mjs"])
        .current_dir(&dir)
        .env("POSECAST_URL", &url)
        .env("POSECAST_TOKEN", "examples-secret")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let seen = viewer_sees_the_arm(&url, &mut child, glam::Quat::from_rotation_z(-1.5)).await;
    let out = tokio::task::spawn_blocking(move || child.wait_with_output())
        .await
        .unwrap()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "drive.mjs failed: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("released avatar"), "{stdout}");
    assert!(seen <= posecast_proto::quant::MAX_ERROR_DEGREES);
}

/// `examples/node/mint.mjs` is an app's back end: it mints a drive-only token for one avatar,
/// connects with it, is refused a pause, revokes the token and sees its connection closed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_node_example_mints_and_revokes_a_users_token() {
    let Some(dir) = node_examples() else {
        return;
    };
    let server = Posecast::start(&["--no-persist", "--control-token", "examples-secret"], &[]);
    let out = tokio::task::spawn_blocking(move || {
        Command::new("node")
            .args(["--experimental-websocket", "mint.mjs"])
            .current_dir(&dir)
            .env("POSECAST_URL", format!("ws://{}/ws", server.addr))
            .env("POSECAST_ADMIN_TOKEN", "examples-secret")
            .output()
    })
    .await
    .unwrap()
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "mint.mjs failed: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for line in [
        "for alice: view, drive until",
        "alice is online: may view, drive",
        "pause refused: forbidden",
        "alice's connection closed: token no longer valid",
    ] {
        assert!(stdout.contains(line), "{line:?} missing from:\n{stdout}");
    }
}

/// `client-cli/examples/drive_bvh.rs` drives the avatar from CMU 01_01: it uploads the file
/// as a rig named after its contents (CMU's 31 joints), drives for three seconds without a
/// refused pose and releases; a second run finds the same asset rather than uploading another.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bvh_example_drives_from_a_motion_capture_file() {
    let Some(bvh) = posecast_proto::testing::require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let Some(example) = example("drive_bvh") else {
        return;
    };
    let server = Posecast::start(&["--no-persist", "--control-token", "examples-secret"], &[]);
    let url = format!("ws://{}/ws", server.addr);
    for run in 0..2 {
        let out = Command::new(&example)
            .arg(&bvh)
            .env("POSECAST_URL", &url)
            .env("POSECAST_TOKEN", "examples-secret")
            .env_remove("RUST_BACKTRACE")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "run {run}: {stdout}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            stdout.contains("(31 joints)") && stdout.contains("sent 180 poses; released avatar"),
            "run {run}: {stdout}"
        );
    }
    let (status, _, body) = common::http_with_headers(
        server.addr,
        "GET",
        "/api/assets",
        &[("Authorization", "Bearer examples-secret")],
        &[],
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let assets: Vec<serde_json::Value> = serde_json::from_str(&body).unwrap();
    let motions = assets
        .iter()
        .filter(|a| a["name"].as_str().is_some_and(|n| n.starts_with("motion-")))
        .count();
    assert_eq!(
        motions, 1,
        "one asset for the file, found again the second time: {body}"
    );
}
