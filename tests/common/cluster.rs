//! Helpers of the cluster tests that assert what an acknowledgement means
//! (`tests/cluster_acks.rs`, `tests/cluster_fuzz.rs`): servers of one cluster, a REST client
//! that never panics on a dead server, and where scene `stage` stands on each server and in
//! the bucket.

use super::CONTROL;
use super::child::Posecast;
use super::nats::Nats;
use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// The lease of every server of these tests, in seconds: short, so takeovers come quickly.
pub const LEASE: &str = "1.5";

/// A server of the cluster at `url`, named `name`, with no data folder (a killed one comes
/// back knowing only what is in NATS).
pub fn node_at(url: &str, name: &str) -> Posecast {
    Posecast::start(
        &[
            "--nats",
            url,
            "--node",
            name,
            "--lease",
            LEASE,
            "--no-persist",
            "--tick-rate",
            "20",
            "--control-token",
            CONTROL,
        ],
        &[],
    )
}

/// `POST /api/commands` with an optional `Idempotency-Key`: status and JSON body.
pub async fn post(addr: SocketAddr, json: &str, key: Option<&str>) -> (u16, serde_json::Value) {
    try_post(addr, json, key)
        .await
        .unwrap_or_else(|e| panic!("POST to {addr}: {e}"))
}

/// [`post`] that reports a connection refused or reset (a killed server) as an error.
pub async fn try_post(
    addr: SocketAddr,
    json: &str,
    key: Option<&str>,
) -> std::io::Result<(u16, serde_json::Value)> {
    let auth = format!("Bearer {CONTROL}");
    let mut headers = vec![
        ("Authorization", auth.as_str()),
        ("Content-Type", "application/json"),
    ];
    if let Some(key) = key {
        headers.push(("Idempotency-Key", key));
    }
    let response = super::http::request(addr, "POST", "/api/commands", &headers, json.into())
        .await
        .map_err(std::io::Error::other)?;
    let value = serde_json::from_slice(&response.body).unwrap_or(serde_json::Value::Null);
    Ok((response.status, value))
}

/// `posecast_cluster_takeovers_total` of `addr`.
pub async fn takeovers(addr: SocketAddr) -> f64 {
    let (status, text) =
        super::http_request(addr, Some(CONTROL), "GET", "/metrics", "text/plain", b"").await;
    assert_eq!(status, 200);
    text.lines()
        .find_map(|l| {
            l.strip_prefix("posecast_cluster_takeovers_total ")?
                .trim()
                .parse()
                .ok()
        })
        .unwrap_or(0.0)
}

/// The owner of scene `stage` and its avatars as `addr` lists them (`None` before it is
/// listed with an owner).
pub async fn listing(addr: SocketAddr) -> Option<(String, BTreeSet<String>)> {
    let (status, body) = post(addr, r#"{"op":"list_scenes"}"#, None).await;
    if status != 200 {
        return None;
    }
    let scene = body["result"]
        .as_array()?
        .iter()
        .find(|s| s["scene"] == "stage")?
        .clone();
    let owner = scene["owner"].as_str()?.to_owned();
    let avatars = scene["avatars"]
        .as_array()?
        .iter()
        .filter_map(|a| a["avatar"].as_str().map(str::to_owned))
        .collect();
    Some((owner, avatars))
}

/// The avatars of scene `stage` in its stored snapshot (bucket `posecast_scenes`, key: the id
/// in hex), read with a NATS client of the test's own.
pub async fn stored_avatars(nats: &Nats) -> BTreeSet<String> {
    let client = async_nats::connect(nats.url()).await.unwrap();
    let js = async_nats::jetstream::new(client);
    let kv = js.get_key_value("posecast_scenes").await.unwrap();
    let key: String = "stage".bytes().map(|b| format!("{b:02x}")).collect();
    let entry = kv.get(key).await.unwrap().expect("no snapshot of stage");
    let file: serde_json::Value = serde_json::from_slice(&entry).unwrap();
    file["avatars"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["id"].as_str().unwrap().to_owned())
        .collect()
}

/// Waits (at most 120 s: an event, on a busy machine too) until every server names the same
/// owner of `stage` and that owner lists it; returns the owner's index in `nodes` and its
/// avatars.
pub async fn settled(nodes: &[&Posecast], names: &[&str]) -> (usize, BTreeSet<String>) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let mut seen = Vec::new();
        for n in nodes {
            seen.push(listing(n.addr).await.map(|(o, _)| o));
        }
        if let Some(Some(owner)) = seen.first()
            && seen.iter().all(|s| s.as_ref() == Some(owner))
            && let Some(i) = names.iter().position(|n| n == owner)
            && let Some((own, avatars)) = listing(nodes[i].addr).await
            && &own == owner
        {
            return (i, avatars);
        }
        if Instant::now() >= deadline {
            // What each server said last, for the one that would not settle.
            for (n, name) in nodes.iter().zip(names) {
                let output = n.output();
                let tail = &output[output.len().saturating_sub(25)..];
                eprintln!("--- {name}'s last lines:\n{}", tail.join("\n"));
            }
            panic!("no settled owner: {seen:?}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// `/healthz` of `addr` until it says `needle` (at most 120 s).
pub async fn health_says(addr: SocketAddr, needle: &str) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let said = tokio::task::spawn_blocking(move || super::child::health(addr))
            .await
            .unwrap();
        if said.as_ref().is_some_and(|(_, b)| b.contains(needle)) {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{addr} never said {needle}: {said:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
