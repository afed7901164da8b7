//! The session driven through channels instead of a TCP socket: message order, refusals,
//! close codes and a slow reader, checked without a network.

use super::*;
use crate::config::Config;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll, Waker};
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

/// Set while the test's end does not read; the sink's waker to call when it reads again.
#[derive(Default)]
struct Gate {
    blocked: AtomicBool,
    waker: std::sync::Mutex<Option<Waker>>,
}

/// A websocket whose peer is the test: what the test sends arrives as client messages;
/// what the session sends goes to the test. While the gate is closed, the sink is not
/// ready (a client that does not read).
struct ChannelSocket {
    incoming: UnboundedReceiver<Result<Message, axum::Error>>,
    outgoing: UnboundedSender<Message>,
    gate: Arc<Gate>,
}

impl Stream for ChannelSocket {
    type Item = Result<Message, axum::Error>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.incoming.poll_recv(cx)
    }
}

impl Sink<Message> for ChannelSocket {
    type Error = axum::Error;
    fn poll_ready(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        if self.gate.blocked.load(Ordering::SeqCst) {
            *self.gate.waker.lock().unwrap() = Some(cx.waker().clone());
            Poll::Pending
        } else {
            Poll::Ready(Ok(()))
        }
    }
    fn start_send(self: Pin<&mut Self>, item: Message) -> Result<(), Self::Error> {
        self.outgoing
            .send(item)
            .map_err(|_| axum::Error::new("the test stopped listening"))
    }
    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.poll_ready(cx)
    }
    fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }
}

/// The test's end of one session.
struct Peer {
    send: UnboundedSender<Result<Message, axum::Error>>,
    recv: UnboundedReceiver<Message>,
    gate: Arc<Gate>,
    session: tokio::task::JoinHandle<()>,
}

impl Peer {
    fn text(&self, json: &str) {
        self.send
            .send(Ok(Message::Text(json.into())))
            .expect("session gone");
    }

    /// The next message the session sent (5 s at most), skipping pings (the adaptive rate's
    /// round-trip probes, which a websocket library answers on its own).
    async fn next(&mut self) -> Message {
        loop {
            let m = tokio::time::timeout(Duration::from_secs(5), self.recv.recv())
                .await
                .expect("nothing sent within 5 s")
                .expect("the session ended");
            if !matches!(m, Message::Ping(_)) {
                return m;
            }
        }
    }

    /// The next message, parsed; a binary frame gives `None`.
    async fn next_json(&mut self) -> Option<serde_json::Value> {
        match self.next().await {
            Message::Text(t) => Some(serde_json::from_str(t.as_str()).unwrap()),
            Message::Binary(_) => None,
            other => panic!("expected a text or binary message, got {other:?}"),
        }
    }

    fn set_blocked(&self, blocked: bool) {
        self.gate.blocked.store(blocked, Ordering::SeqCst);
        if !blocked && let Some(w) = self.gate.waker.lock().unwrap().take() {
            w.wake();
        }
    }
}

/// A ready server state holding scene `s` with the built-in avatar `a`, ticking at 30 Hz.
fn state() -> Arc<AppState> {
    let state = AppState::new(Config {
        tick_rate: 30.0,
        ..Config::default()
    });
    state
        .world
        .library
        .insert(posecast_rigs::builtin::rig().expect("built-in rig"));
    state.readiness.begin(0);
    state.readiness.finish(Ok(()));
    let scene = SceneId("s".into());
    state.world.create_scene(scene.clone()).expect("scene");
    state
        .world
        .add_avatar(
            &scene,
            posecast_rigs::builtin::BUILTIN_ASSET,
            Some(posecast_proto::msg::AvatarId("a".into())),
        )
        .expect("avatar");
    state
}

fn connect(state: &Arc<AppState>) -> Peer {
    let (send, incoming) = unbounded_channel();
    let (outgoing, recv) = unbounded_channel();
    let gate = Arc::new(Gate::default());
    let socket = ChannelSocket {
        incoming,
        outgoing,
        gate: gate.clone(),
    };
    let session = tokio::spawn(serve_on(socket, state.clone(), None, None));
    Peer {
        send,
        recv,
        gate,
        session,
    }
}

fn close_code_of(m: &Message) -> Option<u16> {
    match m {
        Message::Close(Some(frame)) => Some(frame.code),
        _ => None,
    }
}

const HELLO: &str = r#"{"type":"hello","version":1,"encoding":"json"}"#;

#[tokio::test]
async fn hello_then_subscribe_gives_welcome_subscribed_description_then_frames() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(HELLO);
    assert_eq!(peer.next_json().await.unwrap()["type"], "welcome");
    peer.text(r#"{"type":"subscribe","scene":"s"}"#);
    let subscribed = peer.next_json().await.unwrap();
    assert_eq!(subscribed["type"], "subscribed", "{subscribed}");
    let description = peer.next_json().await.unwrap();
    assert_eq!(description["type"], "description", "{description}");
    assert_eq!(description["avatar"]["id"], "a");
    let frame = peer.next_json().await.unwrap();
    assert_eq!(frame["type"], "frame", "{frame}");
    assert_eq!(frame["avatars"][0]["avatar"], "a");
    state.shutdown();
}

#[tokio::test]
async fn a_first_message_other_than_hello_is_refused_with_1008() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(r#"{"type":"subscribe","scene":"s"}"#);
    let error = peer.next_json().await.unwrap();
    assert_eq!(error["code"], "not_allowed_now", "{error}");
    assert_eq!(close_code_of(&peer.next().await), Some(1008));
    // The session ends without the client's answering close (after the linger).
    tokio::time::timeout(Duration::from_secs(5), peer.session)
        .await
        .expect("session still running")
        .unwrap();
    assert_eq!(state.open_connections(), 0);
}

#[tokio::test]
async fn a_wrong_version_is_refused_with_1008() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(r#"{"type":"hello","version":99,"encoding":"json"}"#);
    let error = peer.next_json().await.unwrap();
    assert_eq!(error["code"], "unsupported_version", "{error}");
    assert_eq!(close_code_of(&peer.next().await), Some(1008));
}

#[tokio::test]
async fn bad_input_after_hello_gets_an_error_and_the_session_goes_on() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(HELLO);
    peer.next().await;
    peer.text(r#"{"type":"command","id":7,"command":{"op":"no_such_op"}}"#);
    let error = peer.next_json().await.unwrap();
    assert_eq!(
        (error["code"].as_str(), error["id"].as_u64()),
        (Some("bad_message"), Some(7)),
        "{error}"
    );
    peer.send
        .send(Ok(Message::Binary(vec![1, 2, 3].into())))
        .unwrap();
    let error = peer.next_json().await.unwrap();
    assert_eq!(error["code"], "unexpected_binary", "{error}");
    peer.text(r#"{"type":"command","id":8,"command":{"op":"get_avatar","avatar":"a"}}"#);
    let ack = peer.next_json().await.unwrap();
    assert_eq!(
        (ack["type"].as_str(), ack["id"].as_u64()),
        (Some("ack"), Some(8))
    );
    assert_eq!(ack["result"]["avatar"], "a", "{ack}");
    state.shutdown();
}

/// Version 3 tags an ack's result with its kind; 1 and 2 send the bare value, as before.
#[tokio::test]
async fn acks_are_tagged_from_version_3_and_bare_before() {
    use crate::auth::{Role, Secret, TokenRule};
    let state = AppState::new(Config {
        access: crate::auth::AccessConfig {
            open_view: true,
            tokens: vec![Arc::new(TokenRule::new(
                "ops",
                Secret::new("control-token-1"),
                Role::Control,
            ))],
            mint: None,
        },
        ..Config::default()
    });
    state
        .world
        .library
        .insert(posecast_rigs::builtin::rig().expect("built-in rig"));
    state.readiness.begin(0);
    state.readiness.finish(Ok(()));
    let scene = SceneId("s".into());
    state.world.create_scene(scene.clone()).expect("scene");
    let avatar = Some(posecast_proto::msg::AvatarId("a".into()));
    state
        .world
        .add_avatar(&scene, posecast_rigs::builtin::BUILTIN_ASSET, avatar)
        .expect("avatar");
    for version in [1, 2, 3] {
        let mut peer = connect(&state);
        peer.text(&format!(
            r#"{{"type":"hello","version":{version},"encoding":"json","token":"control-token-1"}}"#
        ));
        assert_eq!(peer.next_json().await.unwrap()["type"], "welcome");
        peer.text(r#"{"type":"command","id":1,"command":{"op":"get_avatar","avatar":"a"}}"#);
        let ack = peer.next_json().await.unwrap();
        assert_eq!(ack["result"]["avatar"], "a", "{ack}");
        peer.text(r#"{"type":"command","id":2,"command":{"op":"place_avatar","avatar":"a","position":[1.0,0.0,0.0],"rotation":[0.0,0.0,0.0,1.0]}}"#);
        let done = peer.next_json().await.unwrap();
        assert_eq!(done["id"], 2, "{done}");
        assert!(done["result"].is_null(), "{done}");
        if version >= 3 {
            assert_eq!(ack["kind"], "avatar", "{ack}");
            assert_eq!(done["kind"], "done", "{done}");
        } else {
            assert!(ack.get("kind").is_none(), "{ack}");
            assert!(done.get("kind").is_none(), "{done}");
        }
    }
    state.shutdown();
}

#[tokio::test]
async fn the_client_closing_gets_a_normal_close_and_shutdown_gets_1001() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(HELLO);
    peer.next().await;
    peer.send.send(Ok(Message::Close(None))).unwrap();
    assert_eq!(close_code_of(&peer.next().await), Some(1000));
    tokio::time::timeout(Duration::from_secs(5), peer.session)
        .await
        .expect("session still running")
        .unwrap();

    let mut peer = connect(&state);
    peer.text(HELLO);
    peer.next().await;
    state.shutdown();
    assert_eq!(close_code_of(&peer.next().await), Some(1001));
}

/// A client that stops reading while frames keep coming gets, once it reads again, the
/// newest frames rather than the backlog: the outbox keeps a keyframe and two deltas per scene.
#[tokio::test]
async fn a_reader_that_stalls_gets_the_newest_frame_not_a_backlog() {
    let state = state();
    let mut peer = connect(&state);
    peer.text(r#"{"type":"hello","version":1,"encoding":"binary"}"#);
    peer.next().await;
    peer.text(r#"{"type":"subscribe","scene":"s"}"#);
    peer.next().await; // subscribed
    peer.next().await; // description
    assert!(peer.next_json().await.is_none(), "a binary frame");
    peer.set_blocked(true);
    // 30 Hz for half a second: about 15 ticks while nothing is read.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (pending, dropped) = state.outbox_extremes();
    let bound = 1 + posecast_stream::outbox::MAX_PENDING_DELTAS;
    assert!(pending <= bound, "{pending} frames wait for one scene");
    assert!(
        dropped >= 5,
        "only {dropped} frames replaced in 0.5 s at 30 Hz"
    );
    peer.set_blocked(false);
    // What arrives now is what the slot holds (and one in flight), not the ~15 ticked while
    // blocked.
    tokio::time::sleep(Duration::from_millis(20)).await;
    let mut burst = 0;
    while let Ok(m) = peer.recv.try_recv() {
        burst += usize::from(!matches!(m, Message::Ping(_)));
    }
    assert!(
        burst <= bound + 1,
        "{burst} messages after the stall ({dropped} replaced)"
    );
    state.shutdown();
}
