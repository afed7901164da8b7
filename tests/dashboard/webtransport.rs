//! The JavaScript client and the dashboard over WebTransport in headless Chromium (issue 31):
//! a page on another origin asks `/api/quic`, trusts the self-signed certificate by its hash,
//! gets frames as datagrams — wire v2 in protocol version 9 (the default), every frame
//! acknowledged; wire v1 in version 7, keyframes acknowledged — and decodes the poses a
//! websocket client of the same page decodes, tick for tick; with the server's UDP port out of
//! reach it falls back to the websocket and says why; the dashboard shows the transport.

use crate::browser::*;
use crate::common;
use serde_json::Value;

/// A server at 60 ticks a second whose WebTransport endpoint listens on `quic`.
async fn quic_server(quic: &str) -> posecast_server::startup::Server {
    let quic = quic.parse().unwrap();
    common::kit_builder(60.0)
        .configure(move |c| c.quic_listen = Some(quic))
        .start()
        .await
        .unwrap()
        .into_server()
}

/// A page recording, per tick, the avatar's rotations from its default client (`auto`:
/// protocol version 9, over WebTransport wire v2 frames as datagrams), from a websocket-only
/// client (`ws`: version 9, which on a websocket is 7: wire v2) and from a WebTransport-only
/// client asking for version 7 (`wt7`: wire v1 datagrams), with the clients' transports, and
/// how often a client showed a pose not newer than the one before (`backwards`).
fn page(addr: std::net::SocketAddr, quic_timeout_ms: u32) -> String {
    format!(
        r#"<!doctype html><meta charset="utf-8"><title>posecast.js over WebTransport</title>
<script type="module">
import * as sdk from "http://{addr}/sdk/posecast.js";
const url = "ws://{addr}/ws";
window.seen = {{ auto: {{}}, ws: {{}}, wt7: {{}} }};
window.counts = {{ auto: 0, ws: 0, wt7: 0 }};
window.backwards = {{ auto: 0, ws: 0, wt7: 0 }};
/** @param {{string}} name @param {{object}} options */
function record(name, options) {{
  const client = new sdk.Client({{ url, quicTimeoutMs: {quic_timeout_ms}, ...options }});
  let newest = -1;
  client.on("frame", (f) => {{
    const p = f.avatars.find((a) => a.avatar === "avatar");
    if (!p) return;
    if (f.seq <= newest) window.backwards[name]++;
    newest = Math.max(newest, f.seq);
    if (window.counts[name] < 600) {{
      window.seen[name][f.seq] = p.rotations;
      window.counts[name]++;
    }}
  }});
  client.subscribe("default");
  client.connect();
  return client;
}}
window.auto = record("auto", {{}});
window.ws = record("ws", {{ transport: "websocket" }});
window.wt7 = record("wt7", {{ transport: "webtransport", version: 7 }});
</script>"#
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_client_streams_over_webtransport_and_decodes_the_websockets_poses() {
    let server = quic_server("127.0.0.1:0").await;
    let (_driver, b) = browser().await;
    b.goto(&serve_origin(page(server.addr, 60_000), None, Vec::new()).await)
        .await
        .unwrap();
    wait_js(
        &b,
        120,
        "window.counts.auto >= 120 && window.counts.ws >= 120 && window.counts.wt7 >= 120",
    )
    .await;
    let transports = b
        .execute(
            "return [[auto, ws, wt7].map((c) => c.transport), auto.webtransportFailure, \
                     [auto, ws, wt7].map((c) => c.welcome.version)];",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(
        transports,
        serde_json::json!([
            ["webtransport", "websocket", "webtransport"],
            null,
            [9, 9, 7]
        ])
    );
    // The frames came as datagrams; the page acknowledged every v2 frame (version 9) and the
    // v1 keyframes (version 7).
    let addr = server.addr;
    let datagrams = common::metric(addr, r#"posecast_quic_frames_total{via="datagram"}"#).await;
    assert!(datagrams >= 240.0, "{datagrams} datagrams");
    let frame_acks = common::metric(addr, "posecast_quic_frame_acks_total").await;
    assert!(frame_acks >= 120.0, "{frame_acks} frame acknowledgements");
    let acks = common::metric(addr, "posecast_quic_key_acks_total").await;
    assert!(acks >= 1.0, "{acks} keyframe acknowledgements");
    // Version 9: mostly deltas (the server names only frames the page acknowledged: without
    // them every frame is a keyframe sent again), decoded as datagrams (their decoder keeps
    // 64 frames an avatar in the order they came); no client showed an older pose after a
    // newer one. (A frame that comes before `subscribed`, on the stream, shows nothing.)
    let stats = b
        .execute(
            "return [auto.stats.frames, auto.stats.keyframes, window.backwards, \
                     [auto, ws].map((c) => c.decoder2.datagrams)];",
            vec![],
        )
        .await
        .unwrap();
    let (frames, keyframes) = (stats[0].as_f64().unwrap(), stats[1].as_f64().unwrap());
    assert!(frames >= 120.0 && keyframes < frames / 4.0, "{stats}");
    assert_eq!(stats[2], serde_json::json!({"auto": 0, "ws": 0, "wt7": 0}));
    assert_eq!(stats[3], serde_json::json!([true, false]));
    // Each WebTransport client decodes the websocket client's rotations on every tick both saw.
    let seen = b.execute("return window.seen;", vec![]).await.unwrap();
    let ws = &seen["ws"];
    for over in ["auto", "wt7"] {
        let mut compared = 0;
        for (seq, rotations) in seen[over].as_object().unwrap() {
            if let Some(other) = ws.get(seq) {
                assert_eq!(
                    rotations, other,
                    "tick {seq}: WebTransport ({over}) and websocket differ"
                );
                compared += 1;
            }
        }
        assert!(compared >= 60, "{over}: only {compared} ticks in common");
    }
    assert_eq!(
        common::metric(addr, "posecast_quic_datagrams_ignored_total").await,
        0.0
    );
    // The clock's round trip: pings went on the stream, pongs came back.
    wait_js(&b, 120, "window.auto.rttMs !== null").await;

    // The dashboard says which transport it uses.
    b.goto(&format!("http://{addr}/?debug")).await.unwrap();
    let shown = wait_js(
        &b,
        120,
        "document.getElementById('transport').textContent === 'WebTransport' && document.getElementById('transport').textContent",
    )
    .await;
    assert_eq!(shown, Value::from("WebTransport"));
    assert_eq!(errors(&b).await, serde_json::json!([]));
    server.stop().await;
}

/// The endpoint listens on 127.0.0.2 and the page reaches the server at 127.0.0.1: the UDP
/// port is out of its reach, as behind a firewall that passes TCP only. The page client
/// falls back to the websocket, says why, and streams; the dashboard shows WebSocket.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_client_falls_back_to_the_websocket_when_udp_is_blocked() {
    let server = quic_server("127.0.0.2:0").await;
    let (_driver, b) = browser().await;
    b.goto(&serve_origin(page(server.addr, 1_000), None, Vec::new()).await)
        .await
        .unwrap();
    wait_js(&b, 120, "window.counts.auto >= 30").await;
    let transport = b
        .execute(
            "return [window.auto.transport, window.auto.webtransportFailure];",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(transport[0], "websocket", "{transport}");
    let why = transport[1].as_str().unwrap_or_default();
    assert!(why.contains("https://127.0.0.1:"), "{transport}");
    b.goto(&format!("http://{}/", server.addr)).await.unwrap();
    wait_js(
        &b,
        120,
        "document.getElementById('transport').textContent === 'WebSocket'",
    )
    .await;
    server.stop().await;
}
