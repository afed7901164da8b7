//! Takes in a cluster (issue 32): two `posecast` processes and a `nats-server` on loopback. A
//! take of a scene ticked by one server, asked for through the other, lands in the cluster's
//! object store; the other server lists, describes, exports and replays it; the replay scene
//! is served by both, stored with its replay, and resumed where it was by the server that
//! takes it over when its owner is killed; deleting a take removes it everywhere.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::nats::Nats;
use common::watch::{PATIENCE, Watcher, find, unprefixed};
use common::{CONTROL, command_to};
use serde_json::Value;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// Ticks per second of both servers.
const RATE: &str = "30";

/// Server `name` of the cluster, keeping its data in `data` (else in memory).
fn node(nats: &Nats, name: &str, data: Option<&std::path::Path>) -> Posecast {
    let url = nats.url();
    let mut args = vec![
        "--nats",
        &url,
        "--node",
        name,
        "--lease",
        "1.5",
        "--tick-rate",
        RATE,
        "--control-token",
        CONTROL,
    ];
    match data {
        Some(dir) => args.extend(["--data", dir.to_str().unwrap()]),
        None => args.push("--no-persist"),
    }
    Posecast::start(&args, &[])
}

async fn ok(addr: SocketAddr, json: &str) -> Value {
    let (status, body) = command_to(addr, json).await;
    assert_eq!(status, 200, "{addr}: {json} → {body}");
    body["result"].clone()
}

/// Polls `f` (every 50 ms, at most [`PATIENCE`]) until it gives a value.
async fn until<T, F: std::future::Future<Output = Option<T>>>(
    what: &str,
    mut f: impl FnMut() -> F,
) -> T {
    let start = Instant::now();
    loop {
        if let Some(v) = f().await {
            return v;
        }
        assert!(start.elapsed() < PATIENCE, "waited {PATIENCE:?} for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The owner `addr` lists for scene `scene`, once it lists one.
async fn owner(addr: SocketAddr, scene: &str) -> String {
    until(&format!("{addr} to list {scene} with an owner"), || async {
        let scenes = ok(addr, r#"{"op":"list_scenes"}"#).await;
        scenes.as_array()?.iter().find(|s| s["scene"] == scene)?["owner"]
            .as_str()
            .map(str::to_owned)
    })
    .await
}

/// Take `take` as `addr` lists it, once it does.
async fn listed(addr: SocketAddr, take: &str) -> Value {
    until(&format!("{addr} to list take {take}"), || async {
        let takes = ok(addr, r#"{"op":"list_takes"}"#).await;
        takes
            .as_array()?
            .iter()
            .find(|t| t["take"] == take && t["recording"] == false)
            .cloned()
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn any_server_lists_exports_and_replays_a_take_and_a_replay_survives_its_owner() {
    let Some(nats) = Nats::start() else { return };
    // A records into its data folder (the take is put from its file); B keeps its copies in
    // memory.
    let data = tempfile::tempdir().unwrap();
    let a = node(&nats, "a", Some(data.path()));
    let b = node(&nats, "b", None);
    ok(a.addr, r#"{"op":"create_scene","scene":"stage"}"#).await;
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"dancer","clip":"walk"}"#,
    )
    .await;
    ok(
        a.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"waver","clip":"wave"}"#,
    )
    .await;
    assert_eq!(owner(b.addr, "stage").await, "a");

    // What live subscribers of the scene receive, through the server that does not tick it.
    let live = Watcher::start(b.addr, "stage").await;
    live.until("the live stream", |f| !f.is_empty()).await;

    // Recording asked for through B runs where the scene is ticked (A).
    let started = ok(
        b.addr,
        r#"{"op":"record_scene","scene":"stage","take":"t1"}"#,
    )
    .await;
    assert_eq!(started["recording"], true, "{started}");
    let from = live.frames().len();
    live.until("60 frames while recording", |f| f.len() >= from + 60)
        .await;
    let stopped = ok(b.addr, r#"{"op":"stop_recording_scene","scene":"stage"}"#).await;
    let frames = stopped["frames"].as_u64().unwrap();
    assert!(frames >= 30, "{stopped}");

    // The take is the cluster's: both servers list and describe it as it was stopped.
    for addr in [a.addr, b.addr] {
        let t = listed(addr, "t1").await;
        assert_eq!(t["frames"], frames, "{addr}: {t}");
        assert_eq!(t["scene"], "stage");
        let got = ok(addr, r#"{"op":"get_take","take":"t1"}"#).await;
        assert_eq!(got["frames"], frames, "{addr}: {got}");
        assert_eq!(got["bytes"], stopped["bytes"], "{addr}: {got}");
    }
    // Its name is taken cluster-wide.
    let (status, body) = command_to(
        a.addr,
        r#"{"op":"record_scene","scene":"stage","take":"t1"}"#,
    )
    .await;
    assert_eq!(status, 409, "{body}");
    let kept = data.path().join("takes");
    assert!(kept.join("t1.take").is_file());
    assert!(
        kept.join("t1.shared").is_file(),
        "{:?}",
        common::list_tree(data.path())
    );
    // B exports it (it reads the cluster's copy).
    let (status, glb) = common::get_bytes(b.addr, "/api/takes/t1.glb").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&glb));
    assert_eq!(&glb[..4], b"glTF");

    // A take that ends by itself (its limit) reaches the cluster without a stop.
    ok(
        b.addr,
        r#"{"op":"record_scene","scene":"stage","take":"short","max_seconds":0.5}"#,
    )
    .await;
    let short = listed(b.addr, "short").await;
    assert!(short["frames"].as_u64().unwrap() >= 10, "{short}");

    // B replays it: the replay scene is B's, served by A too, frame for frame what the live
    // subscribers received.
    let replay = ok(
        b.addr,
        r#"{"op":"replay","take":"t1","scene":"again","loop":true}"#,
    )
    .await;
    assert_eq!(replay["take"], "t1", "{replay}");
    assert_eq!(common::metric(b.addr, "posecast_replays").await, 1.0);
    // A put both takes into the cluster's store; B read t1 from it (once: it was not changed).
    assert_eq!(
        common::metric(a.addr, "posecast_cluster_takes_shared_total").await,
        2.0
    );
    assert_eq!(
        common::metric(b.addr, "posecast_cluster_takes_fetched_total").await,
        1.0
    );
    assert_eq!(owner(a.addr, "again").await, "b");
    let replayed = Watcher::start(a.addr, "again").await;
    replayed
        .until("20 replayed frames on A", |f| {
            f.iter().filter(|s| s.poses.len() == 2).count() >= 20
        })
        .await;
    let seen = live.frames();
    for frame in replayed.frames().iter().filter(|s| s.poses.len() == 2) {
        let poses = unprefixed(&frame.poses, "again");
        assert!(
            find(&seen, 0, &poses).is_some(),
            "replayed frame {} is no frame the live subscriber received",
            frame.seq
        );
    }

    // Paused at 0.5 s through A (forwarded to B, stored with the scene).
    let paused = ok(
        a.addr,
        r#"{"op":"control_replay","scene":"again","time":0.5,"paused":true}"#,
    )
    .await;
    assert_eq!(paused["paused"], true, "{paused}");
    let at = paused["time"].as_f64().unwrap();
    assert!((at - 0.5).abs() < 1e-3, "{paused}");

    // B dies: A takes the replay scene over and resumes it where it was.
    b.kill();
    until("A to take the replay over", || async {
        (owner(a.addr, "again").await == "a").then_some(())
    })
    .await;
    let resumed = until("the resumed replay to answer", || async {
        let (status, body) = command_to(a.addr, r#"{"op":"control_replay","scene":"again"}"#).await;
        (status == 200).then(|| body["result"].clone())
    })
    .await;
    assert_eq!(resumed["take"], "t1", "{resumed}");
    assert_eq!(resumed["paused"], true, "{resumed}");
    assert_eq!(resumed["loop"], true, "{resumed}");
    let now = resumed["time"].as_f64().unwrap();
    assert!((now - at).abs() < 1e-3, "paused at {at}, resumed at {now}");
    // Its avatars are back on stage, still in the take's poses.
    let before = replayed.frames().len();
    replayed
        .until("replayed frames from the new owner", |f| {
            f.len() >= before + 10 && f.last().is_some_and(|s| s.poses.len() == 2)
        })
        .await;
    let last = replayed.frames().last().cloned().unwrap();
    assert!(find(&seen, 0, &unprefixed(&last.poses, "again")).is_some());

    // Deleted through A: gone from the cluster.
    ok(a.addr, r#"{"op":"delete_scene","scene":"again"}"#).await;
    ok(a.addr, r#"{"op":"delete_take","take":"t1"}"#).await;
    let takes = ok(a.addr, r#"{"op":"list_takes"}"#).await;
    assert!(
        !takes.as_array().unwrap().iter().any(|t| t["take"] == "t1"),
        "{takes}"
    );
    let (status, body) = command_to(a.addr, r#"{"op":"get_take","take":"t1"}"#).await;
    assert_eq!(status, 404, "{body}");
}
