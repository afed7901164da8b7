//! Start-up with the real binary: it listens at once and loads in the background, and stored
//! uploads are not kept in memory as bytes.
//!
//! The data folders are written here the way the store writes them (`assets/<name>/` with the
//! files and a `meta.json`, `scenes/<scene>.json`, `posecast.json`), from generated CSE169
//! files, so the tests need nothing from `../shared/testdata`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::{Ws, http_to, next_text};
use futures_util::SinkExt;
use posecast_proto::msg::{ClientMsg, Encoding, SceneId, ServerMsg};
use serde_json::{Value, json};
use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

/// A chain of `joints` ball joints, 0.1 apart along Y.
fn skel(joints: usize) -> String {
    let mut s = String::from("balljoint root {\n offset 0 1 0\n");
    for i in 1..joints {
        writeln!(s, "balljoint j{i} {{\n offset 0 0.1 0").unwrap();
    }
    s.push_str(&"}\n".repeat(joints));
    s
}

/// A `.skin` of `vertices` vertices over a `joints`-joint chain, each bound half to two joints:
/// enough per-vertex work (import, normalisation) that loading 200 of them takes a while.
fn skin(joints: usize, vertices: usize) -> String {
    let mut s = format!("positions {vertices} {{\n");
    for i in 0..vertices {
        let (x, y, z) = ((i % 7) as f32 * 0.01, 1.0 + (i % joints) as f32 * 0.1, 0.0);
        writeln!(s, "{x} {y} {z}").unwrap();
    }
    writeln!(s, "}}\nnormals {vertices} {{").unwrap();
    s.push_str(&"0 0 1\n".repeat(vertices));
    writeln!(s, "}}\nskinweights {vertices} {{").unwrap();
    for i in 0..vertices {
        writeln!(s, "2 {} 0.5 {} 0.5", i % joints, (i + 1) % joints).unwrap();
    }
    let triangles = vertices / 3;
    writeln!(s, "}}\ntriangles {triangles} {{").unwrap();
    for t in 0..triangles {
        writeln!(s, "{} {} {}", 3 * t, 3 * t + 1, 3 * t + 2).unwrap();
    }
    writeln!(s, "}}\nbindings {joints} {{").unwrap();
    for j in 0..joints {
        let y = 1.0 + j as f32 * 0.1;
        writeln!(s, "matrix {{\n1 0 0\n0 1 0\n0 0 1\n0 {y} 0\n}}").unwrap();
    }
    s.push_str("}\n");
    s
}

/// Writes `count` stored uploads `a000`, `a001`, … into the data folder `data` as the store
/// does, each made of `files` (name, content). Equal contents are hard-linked to the first
/// asset's copy, so a large set costs little disk. Marks the folder initialised (a restart).
fn write_uploads(data: &Path, count: usize, files: &[(&str, &str)]) -> Vec<String> {
    std::fs::create_dir_all(data.join("scenes")).unwrap();
    std::fs::write(data.join("posecast.json"), "{\"format\": 1}\n").unwrap();
    let names: Vec<String> = (0..count).map(|k| format!("a{k:03}")).collect();
    for (k, name) in names.iter().enumerate() {
        let dir = data.join("assets").join(name);
        std::fs::create_dir_all(&dir).unwrap();
        for (file, content) in files {
            if k == 0 {
                std::fs::write(dir.join(file), content).unwrap();
            } else {
                std::fs::hard_link(
                    data.join("assets").join(&names[0]).join(file),
                    dir.join(file),
                )
                .unwrap();
            }
        }
        let meta = json!({
            "format": 1, "name": name, "rigs": [name], "saved_us": 0,
            "files": files.iter().map(|(f, _)| *f).collect::<Vec<_>>(),
        });
        std::fs::write(dir.join("meta.json"), meta.to_string()).unwrap();
    }
    names
}

async fn hello(addr: std::net::SocketAddr) -> Ws {
    common::raw_at(addr, Encoding::Json, None).await
}

/// 200 stored uploads of a 20-joint `.skel` with a 3,000-vertex `.skin` (a few seconds of
/// loading in a debug build); returns their names.
fn write_200_uploads(data: &Path) -> Vec<String> {
    const JOINTS: usize = 20;
    write_uploads(
        data,
        200,
        &[
            ("rig.skel", &skel(JOINTS)),
            ("rig.skin", &skin(JOINTS, 3000)),
        ],
    )
}

/// A restart on 200 stored uploads listens within 1 s of the process starting (`/healthz`
/// answers 503 `starting` with the progress), welcomes a websocket and holds its subscribe
/// to a stored scene until that scene is restored (instead of `unknown_scene`), then becomes
/// ready with every upload listed. Before background loading, nothing listened until all 200
/// were imported, and `/healthz` never said `starting`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_with_200_stored_assets_listens_at_once_then_restores_them_all() {
    const ASSETS: usize = 200;
    let data = tempfile::tempdir().unwrap();
    let names = write_200_uploads(data.path());
    // A stored scene with an avatar of the last upload: scenes restore after every asset.
    let last = names.last().unwrap();
    let scene = json!({
        "format": 1, "scene": "stage", "saved_us": 0,
        "avatars": [{"id": "z", "asset": last, "playback": null, "overrides": {}}],
    });
    std::fs::write(data.path().join("scenes/stage.json"), scene.to_string()).unwrap();

    let began = Instant::now();
    let server = Posecast::launch(
        &["--data", data.path().to_str().unwrap()],
        &[("POSECAST_CONTROL_TOKEN", common::CONTROL)],
    );
    let first = server.health();
    let listening = began.elapsed();
    let (status, body) = first.expect("/healthz did not answer");
    assert!(
        listening < Duration::from_secs(1),
        "first /healthz answer {listening:?} after the process started ({status} {body})"
    );
    assert_eq!(status, 503, "{body}");
    let progress: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(progress["status"], "starting", "{body}");
    // The built-in avatar and the 200 uploads.
    assert_eq!(progress["assets_total"], ASSETS + 1, "{body}");
    assert!(progress["assets_loaded"].as_u64().unwrap() <= ASSETS as u64 + 1);

    // A websocket is welcomed at once; its subscribe waits for the scene's restore.
    let mut ws = hello(server.addr).await;
    let still_starting = server.health().is_some_and(|(s, _)| s == 503);
    let subscribe = ClientMsg::Subscribe {
        scene: SceneId("stage".into()),
        avatars: None,
        rate: None,
        joints: None,
        morph_weights: None,
        precision: None,
    };
    ws.send(Message::Text(
        serde_json::to_string(&subscribe).unwrap().into(),
    ))
    .await
    .unwrap();
    // The REST API waits too: this list is complete although it was asked for while starting.
    let addr = server.addr;
    let listing = tokio::spawn(async move { http_to(addr, "GET", "/api/assets", "", b"").await });

    let deadline = Instant::now() + Duration::from_secs(120);
    let answer = loop {
        match tokio::time::timeout(Duration::from_secs(5), next_text(&mut ws)).await {
            Ok(Some(msg)) => break msg,
            _ if Instant::now() < deadline => {}
            _ => panic!("no answer to subscribe; /healthz {:?}", server.health()),
        }
    };
    assert!(
        matches!(&answer, ServerMsg::Subscribed { scene, .. } if scene.0 == "stage"),
        "subscribe during start-up: {answer:?}"
    );
    server.wait_ready(Duration::from_secs(120));
    let ready = began.elapsed();
    assert!(
        still_starting,
        "ready before the subscribe was sent: the load was too quick to show the wait"
    );

    let (status, body) = listing.await.unwrap();
    assert_eq!(status, 200, "{body}");
    let all: Value = serde_json::from_str(&body).unwrap();
    let mut listed: Vec<String> = all
        .as_array()
        .unwrap_or_else(|| panic!("not a list: {body}"))
        .iter()
        .map(|a| a["name"].as_str().unwrap().to_owned())
        .collect();
    listed.sort();
    let mut expected = names.clone();
    expected.push("avatar".into());
    expected.sort();
    assert_eq!(listed, expected);
    eprintln!(
        "{ASSETS} stored assets: listening after {:.0} ms, ready after {:.2} s",
        listening.as_secs_f64() * 1000.0,
        ready.as_secs_f64()
    );
}

/// SIGTERM while loading: the loader gives up at its next step and the process exits
/// gracefully within the drain time, without finishing the load first.
#[test]
fn a_sigterm_during_start_up_exits_without_finishing_the_load() {
    let data = tempfile::tempdir().unwrap();
    write_200_uploads(data.path());
    let data = data.path().to_str().unwrap();
    let mut server = Posecast::launch(&["--data", data, "--shutdown-drain", "0.5"], &[]);
    let (status, body) = server.health().expect("/healthz did not answer");
    assert_eq!(status, 503, "the load was too quick to interrupt: {body}");
    let asked = Instant::now();
    server.terminate();
    let exit = server
        .wait_exit(Duration::from_secs(5))
        .unwrap_or_else(|| panic!("still running 5 s after SIGTERM: {:?}", server.output()));
    let took = asked.elapsed();
    assert!(exit.success(), "{exit:?}: {:?}", server.output());
    let output = server.output();
    assert!(
        !output.iter().any(|l| l.contains(": ready rigs=")),
        "finished loading before exiting ({took:?}): {output:?}"
    );
}

/// The binary imports the built-in avatar ahead, before it has read its flags
/// (`startup::prepare`): it is in the library, with its scene, when the flags ask for it, and
/// that import is dropped, not added, when they do not (`--no-builtin`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_avatar_imported_ahead_is_kept_only_when_the_flags_ask_for_it() {
    let env = [("POSECAST_CONTROL_TOKEN", common::CONTROL)];
    let names = |listing: &str| -> Vec<String> {
        let value: Value = serde_json::from_str(listing).unwrap();
        let list = value.as_array().expect("an asset list");
        list.iter()
            .map(|a| a["name"].as_str().unwrap().to_owned())
            .collect()
    };
    let with = Posecast::start(&["--no-persist"], &env);
    let (status, listing) = http_to(with.addr, "GET", "/api/assets", "", b"").await;
    assert_eq!(status, 200, "{listing}");
    assert_eq!(names(&listing), ["avatar"], "{listing}");
    let (_, scenes) = http_to(with.addr, "GET", "/api/scenes", "", b"").await;
    assert!(scenes.contains("\"scene\":\"default\""), "{scenes}");
    with.kill();

    let without = Posecast::start(&["--no-persist", "--no-builtin"], &env);
    let (status, listing) = http_to(without.addr, "GET", "/api/assets", "", b"").await;
    assert_eq!(status, 200, "{listing}");
    assert!(names(&listing).is_empty(), "{listing}");
    let (_, scenes) = http_to(without.addr, "GET", "/api/scenes", "", b"").await;
    assert!(!scenes.contains("\"scene\":\"default\""), "{scenes}");
    without.kill();
}

/// The resident memory of process `pid`, bytes (`VmRSS` of `/proc/<pid>/status`).
#[cfg(target_os = "linux")]
fn resident_bytes(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().strip_suffix("kB"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no VmRSS in {status}"));
    kib * 1024
}

/// Stored uploads are read, imported and dropped: the server keeps their rigs, not their
/// files. 24 uploads of a `.skel` padded with 4 MiB of blanks (96 MiB of files, a 5-joint rig
/// each) against the same 24 unpadded: once ready, the padded server is resident by far less
/// than 96 MiB more (allocator slack of a few reads at most). When the store kept every
/// upload's files to add clips later, it was resident by all 96 MiB more.
#[cfg(target_os = "linux")]
#[test]
fn resident_memory_does_not_hold_stored_upload_bytes() {
    const UPLOADS: usize = 24;
    const PAD: usize = 4 << 20;
    let resident = |pad: usize| {
        let data = tempfile::tempdir().unwrap();
        let text = format!("{}{}", skel(5), " ".repeat(pad));
        write_uploads(data.path(), UPLOADS, &[("rig.skel", &text)]);
        let data = data.path().to_str().unwrap();
        let server = Posecast::start(&["--data", data, "--no-builtin"], &[]);
        let bytes = resident_bytes(server.pid());
        server.kill();
        bytes
    };
    let plain = resident(0);
    let padded = resident(PAD);
    let grown = padded.saturating_sub(plain);
    let files = (UPLOADS * PAD) as u64;
    eprintln!(
        "resident: {} MiB plain, {} MiB with {} MiB of stored upload files",
        plain >> 20,
        padded >> 20,
        files >> 20
    );
    assert!(
        grown < files / 4,
        "resident memory grew by {} MiB with {} MiB of stored uploads",
        grown >> 20,
        files >> 20
    );
}

/// Resident bytes of the binary's own mappings of process `pid` (its code and data pages,
/// from `/proc/<pid>/smaps`).
#[cfg(target_os = "linux")]
fn resident_binary_bytes(pid: u32, binary: &str) -> u64 {
    let smaps = std::fs::read_to_string(format!("/proc/{pid}/smaps")).unwrap();
    let mut ours = false;
    let mut kib = 0;
    for line in smaps.lines() {
        if let Some(rss) = line.strip_prefix("Rss:") {
            if ours {
                kib += rss
                    .trim()
                    .trim_end_matches("kB")
                    .trim()
                    .parse::<u64>()
                    .unwrap();
            }
        } else if line.split_whitespace().next().is_some_and(|f| {
            f.split_once('-').is_some_and(|(a, b)| {
                u64::from_str_radix(a, 16).is_ok() && u64::from_str_radix(b, 16).is_ok()
            })
        }) {
            // A mapping's header: `start-end perms offset dev inode [path]`.
            ours = line.ends_with(&format!(" {binary}"));
        }
    }
    kib * 1024
}

/// Once ready and idle, the binary gives back the pages of its code the start touched and an
/// idle server never runs again: the binary's resident pages shrink by more than a third (in
/// this debug build from ~20 MiB to 8.7 MiB on a quiet machine; 10.3 MiB in a CI run, where
/// the idle path had mapped back more of its code by the time they were counted; with the
/// advice a no-op they do not shrink at all), and the server goes on answering, its code
/// mapped back as it runs.
#[cfg(target_os = "linux")]
#[test]
fn the_start_up_code_is_given_back_once_ready() {
    let binary = env!("CARGO_BIN_EXE_posecast");
    let server = Posecast::start(&["--no-persist"], &[]);
    let before = resident_binary_bytes(server.pid(), binary);
    let deadline = Instant::now() + Duration::from_secs(120);
    while !server
        .output()
        .iter()
        .any(|l| l.contains("start-up code unmapped"))
    {
        assert!(
            Instant::now() < deadline,
            "never gave its start-up code back: {:?}",
            server.output()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let after = resident_binary_bytes(server.pid(), binary);
    eprintln!(
        "the binary's resident pages: {:.1} MiB once ready, {:.1} MiB after giving back",
        before as f64 / 1048576.0,
        after as f64 / 1048576.0
    );
    assert!(before > 0, "no resident pages of {binary} found");
    assert!(
        after * 3 < before * 2,
        "resident pages of the binary: {before} B once ready, {after} B after giving back"
    );
    assert_eq!(server.health(), Some((200, "ok".to_owned())));
    server.kill();
}

/// A missing `--assets` folder stops the start with its name; a `RUST_LOG` that does not
/// parse is reported (and the server runs at `info`).
#[test]
fn a_missing_assets_folder_is_an_error_and_a_bad_rust_log_is_reported() {
    let (status, output) =
        common::child::run_to_exit(&["--assets", "/no/such/folder", "--no-persist"], &[]);
    assert!(!status.success(), "{output}");
    assert!(output.contains("/no/such/folder"), "{output}");
    let server = Posecast::launch(&["--no-persist"], &[("RUST_LOG", "posecast=bogus_level")]);
    std::thread::sleep(Duration::from_millis(300));
    let printed = server.output().join("\n");
    assert!(printed.contains("RUST_LOG"), "{printed}");
    server.kill();
}

/// With `--log-format json` every line is a JSON object; connections, commands (refusals
/// included) and start/stop are logged with the token's name, never the token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operational_logs_name_connections_commands_and_refusals_as_json() {
    let mut server = Posecast::start(
        &["--no-persist", "--log-format", "json"],
        &[("POSECAST_CONTROL_TOKEN", common::CONTROL)],
    );
    let (status, _) = http_to(
        server.addr,
        "POST",
        "/api/commands",
        "application/json",
        br#"{"op":"create_scene","scene":"audited"}"#,
    )
    .await;
    assert_eq!(status, 200);
    let (status, _) = common::http_request(
        server.addr,
        Some("wrong-token"),
        "POST",
        "/api/commands",
        "application/json",
        br#"{"op":"delete_scene","scene":"audited"}"#,
    )
    .await;
    assert_eq!(status, 401);
    let ws = hello(server.addr).await;
    drop(ws);
    tokio::time::sleep(Duration::from_millis(300)).await;
    server.terminate();
    server.wait_exit(Duration::from_secs(10));
    let lines = server.output();
    let logs: Vec<Value> = lines
        .iter()
        .filter(|l| l.starts_with('{'))
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    let find = |f: &dyn Fn(&Value) -> bool| logs.iter().find(|l| f(l)).cloned();
    let field = |l: &Value, k: &str| l["fields"][k].as_str().unwrap_or_default().to_owned();
    let created = find(&|l| field(l, "op") == "create_scene").expect("an audit line");
    assert_eq!(created["target"], "posecast::audit");
    assert_eq!(field(&created, "outcome"), "ok");
    assert_eq!(field(&created, "target"), "scene audited");
    assert_ne!(field(&created, "caller"), "");
    let refused = find(&|l| field(l, "message") == "refused").expect("a refusal line");
    assert_eq!(field(&refused, "target"), "/api/commands");
    assert!(
        field(&refused, "outcome").contains("Unauthorized"),
        "{refused}"
    );
    assert!(find(&|l| field(l, "message") == "websocket opened").is_some());
    assert!(find(&|l| field(l, "message") == "websocket closed").is_some());
    assert!(find(&|l| field(l, "message") == "started").is_some());
    assert!(find(&|l| field(l, "message") == "stopped").is_some());
    let text = lines.join("\n");
    assert!(!text.contains(common::CONTROL), "a token was logged");
}

/// A control token under the minimum length stops the start with a message that names the
/// flag (not the rule's internal name) and the rule, and no backtrace.
#[test]
fn a_short_control_token_is_refused_naming_the_flag() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_posecast"))
        .args([
            "--no-persist",
            "--listen",
            "127.0.0.1:0",
            "--control-token",
            "secret",
        ])
        .env_remove("RUST_BACKTRACE")
        .env_remove("POSECAST_CONTROL_TOKEN")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("--control-token (number 1): shorter than 8 characters"),
        "{stderr}"
    );
    assert!(!stderr.contains("control-1"), "{stderr}");
}
