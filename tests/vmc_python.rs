//! VMC interoperability with `python-osc`, an OSC implementation that is not ours
//! (`scripts/vmc_python.py`; `scripts/test` installs it into `target/venv`): bundles and single
//! messages it sends drive the avatar, and the bundles posecast sends decode there with the
//! expected bone names and values.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::vmc::*;
use glam::Quat;
use posecast_proto::msg::Encoding;
use posecast_server::vmc::VmcOut;
use std::io::BufRead;
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::mpsc;
use std::time::Duration;

/// Kills the receiver when the test ends, however it ends.
struct KillOnDrop(std::process::Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// The next line from `rx` within `secs`, polled without blocking the runtime.
async fn next_line(rx: &mpsc::Receiver<String>, secs: f32) -> Option<String> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f32(secs);
    loop {
        match rx.try_recv() {
            Ok(line) => return Some(line),
            Err(mpsc::TryRecvError::Disconnected) => return None,
            Err(mpsc::TryRecvError::Empty) if tokio::time::Instant::now() > deadline => {
                return None;
            }
            Err(mpsc::TryRecvError::Empty) => tokio::time::sleep(Duration::from_millis(5)).await,
        }
    }
}

/// `target/venv/bin/python3` with python-osc, or `None` (a failure under `CI=true`).
fn python() -> Option<PathBuf> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let python = root.join("target/venv/bin/python3");
    let ok = python.exists()
        && std::process::Command::new(&python)
            .args(["-c", "import pythonosc"])
            .status()
            .is_ok_and(|s| s.success());
    if ok {
        Some(python)
    } else {
        posecast_proto::testing::skip(
            "target/venv with python-osc is missing (scripts/test installs it: \
             python3 -m venv target/venv && target/venv/bin/pip install python-osc)",
        );
        None
    }
}

fn script() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scripts/vmc_python.py")
}

#[tokio::test]
async fn python_osc_drives_the_avatar() {
    let Some(python) = python() else { return };
    let server = server(60.0, &["avatar"], Vec::new()).await;
    let to = server.vmc.inputs[0];
    let sub = common::client(&server, Encoding::Binary).await;
    let rig = server.state.world.library.get("avatar").unwrap();
    let root = Quat::from_rotation_y(0.4);
    let bones = test_pose(7);
    let pose = serde_json::json!({
        "root": root.to_array(),
        "bones": bones.iter().map(|(n, q)| {
            serde_json::json!([n, q.x, q.y, q.z, q.w])
        }).collect::<Vec<_>>(),
        "blend": {"Joy": 0.5, "Blink": 1.0},
    });
    let (port, pose) = (to.port().to_string(), pose.to_string());
    let status = tokio::task::spawn_blocking(move || {
        std::process::Command::new(&python)
            .arg(script())
            .args(["send", "127.0.0.1", &port, &pose, "20"])
            .status()
    })
    .await
    .unwrap()
    .unwrap();
    assert!(status.success());
    let pairs: Vec<_> = BUILTIN_PAIRS.iter().map(|(b, _, j)| (*b, *j)).collect();
    let expected = expected_locals(&rig, &expected_worlds(root, &bones), &pairs);
    let mut worst = f64::MAX;
    for _ in 0..100 {
        let latest = sub.latest(&avatar("avatar")).unwrap().locals;
        worst = worst_degrees(&latest, &expected);
        if worst <= 0.05 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    println!("python-osc → built-in avatar: worst joint {worst:.4}°");
    assert!(worst <= 0.05, "off by {worst}°");
    let state = sub
        .command(posecast_proto::command::Command::GetAvatar {
            avatar: avatar("avatar"),
        })
        .await
        .unwrap()
        .to_value();
    assert_eq!(state["blend_shapes"]["Joy"], 0.5, "{state}");
    assert_eq!(state["blend_shapes"]["Blink"], 1.0, "{state}");
    let m = &server.state.metrics.vmc;
    assert_eq!(
        m.dropped_total(posecast_server::metrics::vmc::PacketDrop::Malformed),
        0
    );
}

#[tokio::test]
async fn python_osc_decodes_what_posecast_sends() {
    let Some(python) = python() else { return };
    let mut receiver = KillOnDrop(
        std::process::Command::new(&python)
            .arg(script())
            .arg("receive")
            .stdout(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let stdout = receiver.0.stdout.take().unwrap();
    let (tx, lines) = mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let first = next_line(&lines, 10.0).await.expect("the receiver's port");
    let port: u16 = first.strip_prefix("PORT ").unwrap().parse().unwrap();
    let server = server(
        60.0,
        &[],
        vec![VmcOut {
            avatar: avatar("avatar"),
            addr: format!("127.0.0.1:{port}").parse().unwrap(),
        }],
    )
    .await;
    // Put the avatar in the pose a performer's `bones` would give it (hand-derived), with its
    // humanoid_root where it stands at neutral: posecast must send `bones` back.
    let rig = server.state.world.library.get("avatar").unwrap();
    let bones = test_pose(5);
    let pairs: Vec<_> = BUILTIN_PAIRS.iter().map(|(b, _, j)| (*b, *j)).collect();
    let locals = expected_locals(&rig, &expected_worlds(Quat::IDENTITY, &bones), &pairs);
    let driver =
        posecast_client::net::Driver::connect(&server.ws_url(), Some(common::CONTROL.into()))
            .await
            .unwrap();
    driver.drive(&avatar("avatar"), None, None).await.unwrap();
    let names = rig.skeleton().names().to_vec();
    let root_rest =
        rig.skeleton().rest()[rig.skeleton().find("humanoid_root").unwrap()].translation;
    driver
        .send_pose(
            &avatar("avatar"),
            names
                .iter()
                .cloned()
                .zip(locals.iter().map(|q| q.to_array())),
            Some(root_rest.to_array()),
            Some(1),
        )
        .await
        .unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    let mut worst = f64::MAX;
    let mut last = String::new();
    while tokio::time::Instant::now() < deadline {
        let Some(line) = next_line(&lines, 2.0).await else {
            break;
        };
        let msgs: Vec<Vec<serde_json::Value>> = serde_json::from_str(&line).unwrap();
        let addresses: Vec<&str> = msgs.iter().map(|m| m[0].as_str().unwrap()).collect();
        assert!(addresses.contains(&"/VMC/Ext/OK"), "{line}");
        assert!(addresses.contains(&"/VMC/Ext/T"), "{line}");
        assert!(addresses.contains(&"/VMC/Ext/Root/Pos"), "{line}");
        let sent: Vec<(&str, [f32; 3], Quat)> = msgs
            .iter()
            .filter(|m| m[0] == "/VMC/Ext/Bone/Pos")
            .map(|m| {
                let f = |i: usize| m[i].as_f64().unwrap() as f32;
                (
                    m[1].as_str().unwrap(),
                    [f(2), f(3), f(4)],
                    Quat::from_xyzw(f(5), f(6), f(7), f(8)),
                )
            })
            .collect();
        let mut names: Vec<&str> = sent.iter().map(|s| s.0).collect();
        names.sort_unstable();
        let mut wanted: Vec<&str> = BUILTIN_PAIRS.iter().map(|p| p.0).collect();
        wanted.sort_unstable();
        assert_eq!(names, wanted, "one Bone/Pos per mapped bone");
        let hips = sent.iter().find(|s| s.0 == "Hips").unwrap().1;
        worst = bones
            .iter()
            .map(|(name, q)| {
                let got = sent.iter().find(|s| s.0 == *name).unwrap().2;
                posecast_proto::quant::angle_between_degrees(got, *q)
            })
            .fold(0.0, f64::max);
        last = line.clone();
        if worst <= 0.05 {
            // The hips where the T-pose rig has them (0, 0.95, 0), Unity frame.
            assert!(
                (hips[0].abs() + (hips[1] - 0.95).abs() + hips[2].abs()) < 1e-3,
                "hips at {hips:?}"
            );
            break;
        }
    }
    println!("posecast → python-osc: worst bone {worst:.4}°");
    assert!(worst <= 0.05, "bones off by {worst}°: {last}");
}
