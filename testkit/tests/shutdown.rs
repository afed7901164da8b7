//! A test that panics still shuts its server down: dropping a `TestServer` sends every
//! websocket its close frame 1001, closes the listener and stops the VMC inputs (their UDP
//! ports are free again), while the runtime runs on.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use futures_util::{SinkExt, StreamExt};
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, PROTOCOL_VERSION};
use posecast_server::config::VmcIn;
use posecast_testkit::TestServer;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_test_closes_its_websockets_and_listener() {
    let (url_tx, url_rx) = tokio::sync::oneshot::channel();
    let (go_tx, go_rx) = tokio::sync::oneshot::channel::<()>();
    // The "test" that panics while it holds the server.
    let test = tokio::spawn(async move {
        let server = TestServer::builder()
            .configure(|c| {
                c.vmc_in = vec![VmcIn::new(
                    ([127, 0, 0, 1], 0).into(),
                    AvatarId("avatar".into()),
                )];
            })
            .start()
            .await
            .unwrap();
        let vmc = server.vmc.inputs[0];
        url_tx.send((server.addr, server.ws_url(), vmc)).unwrap();
        go_rx.await.ok();
        panic!("the test failed");
    });
    let (addr, url, vmc) = url_rx.await.unwrap();
    let (mut ws, _) = tokio_tungstenite::connect_async(url.as_str())
        .await
        .unwrap();
    let hello = ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        encoding: Encoding::Json,
        token: None,
        client: None,
    };
    ws.send(Message::Text(serde_json::to_string(&hello).unwrap().into()))
        .await
        .unwrap();
    go_tx.send(()).unwrap();
    let outcome = test.await;
    assert!(
        outcome.is_err_and(|e| e.is_panic()),
        "the test task did not panic"
    );
    // The runtime lives on; the dropped server must still have said goodbye.
    let close = tokio::time::timeout(Duration::from_secs(10), async {
        while let Some(Ok(m)) = ws.next().await {
            if let Message::Close(frame) = m {
                return frame.map(|f| f.code);
            }
        }
        None
    })
    .await
    .expect("no close frame within 10 s of the panic");
    assert_eq!(close, Some(CloseCode::Away));
    // And the listener is closed (within the 2 s drain time, with room for a loaded machine).
    let mut refused = false;
    for _ in 0..100 {
        if tokio::net::TcpStream::connect(addr).await.is_err() {
            refused = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(refused, "{addr} still accepts connections after the panic");
    // The VMC input's UDP port is free again: its task was stopped, not left running.
    let mut rebound = false;
    for _ in 0..100 {
        if tokio::net::UdpSocket::bind(vmc).await.is_ok() {
            rebound = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(
        rebound,
        "the VMC input {vmc} still holds its port after the panic"
    );
}
