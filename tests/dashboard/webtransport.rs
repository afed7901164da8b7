//! The JavaScript client and the dashboard over WebTransport in headless Chromium (issue 31):
//! a page on another origin asks `/api/quic`, trusts the self-signed certificate by its hash,
//! gets frames as datagrams and acknowledges keyframes, and decodes the poses a websocket
//! client of the same page decodes, tick for tick; with the server's UDP port out of reach it
//! falls back to the websocket and says why; the dashboard shows the transport.

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

/// A page recording, per tick, the avatar's rotations from its default client (`auto`) and
/// from a websocket-only client asking for protocol version 1 (the frames a WebTransport
/// session gets: wire v1), with both clients' transports.
fn page(addr: std::net::SocketAddr, quic_timeout_ms: u32) -> String {
    format!(
        r#"<!doctype html><meta charset="utf-8"><title>posecast.js over WebTransport</title>
<script type="module">
import * as sdk from "http://{addr}/sdk/posecast.js";
const url = "ws://{addr}/ws";
window.seen = {{ auto: {{}}, ws: {{}} }};
window.counts = {{ auto: 0, ws: 0 }};
/** @param {{string}} name @param {{object}} options */
function record(name, options) {{
  const client = new sdk.Client({{ url, quicTimeoutMs: {quic_timeout_ms}, ...options }});
  client.on("frame", (f) => {{
    const p = f.avatars.find((a) => a.avatar === "avatar");
    if (p && window.counts[name] < 600) {{
      window.seen[name][f.seq] = p.rotations;
      window.counts[name]++;
    }}
  }});
  client.subscribe("default");
  client.connect();
  return client;
}}
window.auto = record("auto", {{}});
window.ws = record("ws", {{ transport: "websocket", version: 1 }});
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
        "window.counts.auto >= 120 && window.counts.ws >= 120",
    )
    .await;
    let transports = b
        .execute(
            "return [window.auto.transport, window.ws.transport, window.auto.webtransportFailure];",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(
        transports,
        serde_json::json!(["webtransport", "websocket", null])
    );
    let seen = b.execute("return window.seen;", vec![]).await.unwrap();
    let (auto, ws) = (seen["auto"].as_object().unwrap(), &seen["ws"]);
    let mut compared = 0;
    for (seq, rotations) in auto {
        if let Some(other) = ws.get(seq) {
            assert_eq!(
                rotations, other,
                "tick {seq}: WebTransport and websocket differ"
            );
            compared += 1;
        }
    }
    assert!(compared >= 60, "only {compared} ticks in common");
    // The frames came as datagrams, and the page acknowledged keyframes.
    let addr = server.addr;
    let datagrams = common::metric(addr, r#"posecast_quic_frames_total{via="datagram"}"#).await;
    assert!(datagrams >= 120.0, "{datagrams} datagrams");
    let acks = common::metric(addr, "posecast_quic_key_acks_total").await;
    assert!(acks >= 1.0, "{acks} keyframe acknowledgements");
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
