//! Writing into the socket from wherever output is queued (issue 38): a websocket's outbox with
//! a socket attached ([`super::outbox::Outbox::attach_direct`]) writes each frame, control
//! message and close frame into the socket itself, at once, on the thread that queued it — the
//! tick's fan-out for frames. No writer task wakes per frame: the writer
//! ([`run_direct`]) runs only when the socket is full (it waits for room, then writes what
//! waits) and to close.
//!
//! Frames are websocket frames built here: a server's frames are not masked, so a frame is a
//! 2–10 byte header and the message's own bytes, written with one vectored write — the
//! payload, shared by every subscriber of the frame, is never copied in user space.

use super::outbox::Outbox;
use axum::extract::ws::Message;
use bytes::Bytes;
use std::io::{self, IoSlice};
use std::time::Duration;

/// How long the close frame may take to go out before the writer gives up on the peer.
pub const CLOSE_SEND_TIMEOUT: Duration = Duration::from_secs(1);

/// A socket written without waiting: what [`Outbox`] writes into from any thread.
pub trait DirectWrite: Send + Sync + std::fmt::Debug {
    /// Writes as much of `bufs` as the socket takes now, in order: `WouldBlock` when it takes
    /// nothing, any other error when it failed for good.
    ///
    /// # Errors
    /// The socket's.
    fn try_write_vectored(&self, bufs: &[IoSlice<'_>]) -> io::Result<usize>;
}

/// A [`DirectWrite`] that can also be waited on until it has room (the writer task's side).
pub trait DirectSocket: DirectWrite {
    /// Resolves when the socket may take more (it may still say `WouldBlock`: readiness is a
    /// hint).
    fn writable(&self) -> impl Future<Output = io::Result<()>> + Send;
}

/// Opcodes of RFC 6455 §5.2.
const TEXT: u8 = 0x1;
const BINARY: u8 = 0x2;
const CLOSE: u8 = 0x8;
const PING: u8 = 0x9;
const PONG: u8 = 0xA;

/// The header of an unmasked, final websocket frame: its bytes and how many of them count.
#[must_use]
pub fn header(opcode: u8, len: usize) -> ([u8; 10], usize) {
    let mut h = [0u8; 10];
    h[0] = 0x80 | opcode;
    if len < 126 {
        h[1] = len as u8;
        (h, 2)
    } else if let Ok(short) = u16::try_from(len) {
        h[1] = 126;
        h[2..4].copy_from_slice(&short.to_be_bytes());
        (h, 4)
    } else {
        h[1] = 127;
        h[2..10].copy_from_slice(&(len as u64).to_be_bytes());
        (h, 10)
    }
}

/// A message's opcode and payload, when the payload is one slice of it (all but a close).
#[must_use]
pub fn parts(m: &Message) -> Option<(u8, &[u8])> {
    Some(match m {
        Message::Text(t) => (TEXT, t.as_str().as_bytes()),
        Message::Binary(b) => (BINARY, b),
        Message::Ping(b) => (PING, b),
        Message::Pong(b) => (PONG, b),
        Message::Close(_) => return None,
    })
}

/// A message as one websocket frame's bytes (header and payload, copied).
#[must_use]
pub fn framed(m: &Message) -> Bytes {
    let payload: Vec<u8>;
    let (opcode, body) = match parts(m) {
        Some(p) => p,
        None => {
            payload = match m {
                Message::Close(Some(c)) => {
                    let mut p = c.code.to_be_bytes().to_vec();
                    p.extend_from_slice(c.reason.as_str().as_bytes());
                    p
                }
                _ => Vec::new(),
            };
            (CLOSE, payload.as_slice())
        }
    };
    let (h, n) = header(opcode, body.len());
    let mut out = Vec::with_capacity(n + body.len());
    out.extend_from_slice(&h[..n]);
    out.extend_from_slice(body);
    Bytes::from(out)
}

/// The writer of an outbox with a socket attached: waits while the socket is full, then
/// writes what waits; on close, writes what is queued and the close frame (1008 when the
/// client stopped reading, the reader's choice or 1000 otherwise), giving up after
/// [`CLOSE_SEND_TIMEOUT`]. Returns when the socket failed or the close frame is out.
pub async fn run_direct<S: DirectSocket>(outbox: &Outbox, socket: &S) {
    use super::outbox::DirectState;
    let mut first = true;
    loop {
        let notified = outbox.notified();
        if !std::mem::take(&mut first) {
            outbox.count_writer_wake();
        }
        match outbox.direct_state() {
            DirectState::Failed => return,
            DirectState::Closed => break,
            DirectState::Held => {
                tokio::select! {
                    ready = socket.writable() => {
                        if ready.is_err() {
                            return;
                        }
                        outbox.resume();
                    }
                    () = notified => {}
                }
            }
            DirectState::Idle => notified.await,
        }
    }
    outbox.queue_close_frame();
    let deadline = tokio::time::Instant::now() + CLOSE_SEND_TIMEOUT;
    loop {
        match outbox.resume() {
            DirectState::Held => match tokio::time::timeout_at(deadline, socket.writable()).await {
                Ok(Ok(())) => {}
                _ => return,
            },
            DirectState::Failed | DirectState::Idle | DirectState::Closed => return,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::extract::ws::CloseFrame;
    use std::sync::Arc;

    use crate::outbox::{DirectState, OutFrame};
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

    /// A socket that takes `budget` more bytes, then says `WouldBlock`.
    #[derive(Debug, Default)]
    struct Socket {
        taken: Mutex<Vec<u8>>,
        budget: Mutex<usize>,
        writes: AtomicU64,
        fail: AtomicBool,
    }

    impl Socket {
        fn allow(&self, more: usize) {
            *self.budget.lock().unwrap() += more;
        }
        fn taken(&self) -> Vec<u8> {
            std::mem::take(&mut *self.taken.lock().unwrap())
        }
    }

    impl DirectWrite for Socket {
        fn try_write_vectored(&self, bufs: &[IoSlice<'_>]) -> io::Result<usize> {
            if self.fail.load(Ordering::Relaxed) {
                return Err(io::ErrorKind::ConnectionReset.into());
            }
            self.writes.fetch_add(1, Ordering::Relaxed);
            let mut budget = self.budget.lock().unwrap();
            if *budget == 0 {
                return Err(io::ErrorKind::WouldBlock.into());
            }
            let mut taken = self.taken.lock().unwrap();
            let mut n = 0;
            for b in bufs {
                let k = b.len().min(*budget - n);
                taken.extend_from_slice(&b[..k]);
                n += k;
            }
            *budget -= n;
            Ok(n)
        }
    }

    #[derive(Debug, Default)]
    struct Sent(AtomicU64, AtomicU64);
    impl crate::Counters for Sent {
        fn frames_offered(&self, _: u64, _: u64) {}
        fn json_encoded(&self, _: u64) {}
        fn sent(&self, messages: u64, bytes: u64) {
            self.0.fetch_add(messages, Ordering::Relaxed);
            self.1.fetch_add(bytes, Ordering::Relaxed);
        }
    }

    fn frame(byte: u8, len: usize, key: bool) -> OutFrame {
        OutFrame {
            message: Message::Binary(Bytes::from(vec![byte; len])),
            key,
        }
    }

    fn attached(budget: usize) -> (Outbox, Arc<Socket>, Arc<Sent>) {
        let o = Outbox::new();
        let socket = Arc::new(Socket::default());
        socket.allow(budget);
        let sent = Arc::new(Sent::default());
        o.attach_direct(socket.clone(), sent.clone());
        (o, socket, sent)
    }

    /// With room in the socket, a queued message is written by the one who queued it, framed,
    /// in one write: no writer is needed.
    #[test]
    fn a_message_goes_out_when_it_is_queued() {
        let (o, socket, sent) = attached(1 << 20);
        o.push_control(Message::Text("hi".into()));
        o.push_frame(1, frame(7, 300, true));
        let expected = [
            framed(&Message::Text("hi".into())),
            framed(&frame(7, 300, true).message),
        ]
        .concat();
        assert_eq!(socket.taken(), expected);
        assert_eq!(socket.writes.load(Ordering::Relaxed), 2);
        assert_eq!(o.direct_state(), DirectState::Idle);
        assert_eq!(o.pending_frames(), 0);
        assert_eq!(o.control_bytes(), 0);
        assert_eq!(
            (
                sent.0.load(Ordering::Relaxed),
                sent.1.load(Ordering::Relaxed)
            ),
            (2, 302)
        );
    }

    /// A socket that takes part of a message holds the outbox: the rest goes first once it has
    /// room, frames queued meanwhile replace each other as in the writer's outbox (counted as
    /// dropped while held), and the bytes that reach the socket are whole frames in order.
    #[test]
    fn a_full_socket_holds_the_rest_and_frames_replace_each_other() {
        let (o, socket, _) = attached(100);
        o.push_frame(1, frame(1, 300, true));
        assert_eq!(o.direct_state(), DirectState::Held);
        o.push_frame(1, frame(2, 50, false));
        o.push_frame(1, frame(3, 50, false));
        o.push_frame(1, frame(4, 50, false));
        assert_eq!(o.dropped_while_held(), 1);
        o.push_control(Message::Text("ack".into()));
        assert_eq!(socket.taken().len(), 100);
        socket.allow(1 << 20);
        assert_eq!(o.resume(), DirectState::Idle);
        let rest = socket.taken();
        let mut whole = framed(&frame(1, 300, true).message)[100..].to_vec();
        for m in [
            Message::Text("ack".into()),
            frame(3, 50, false).message,
            frame(4, 50, false).message,
        ] {
            whole.extend_from_slice(&framed(&m));
        }
        assert_eq!(rest, whole);
        assert_eq!(o.direct_state(), DirectState::Idle);
    }

    /// A socket with no room at all takes nothing and loses nothing; closing then sends what
    /// was queued and the close frame asked for, after the part of a message already begun.
    #[test]
    fn closing_finishes_the_message_begun_then_sends_the_close_frame() {
        let (o, socket, _) = attached(3);
        o.push_control(Message::Text("error".into()));
        o.push_frame(1, frame(9, 10, true));
        o.close_with(1009, "message too big");
        o.push_frame(1, frame(8, 10, true));
        assert_eq!(o.direct_state(), DirectState::Closed);
        o.queue_close_frame();
        socket.allow(1 << 20);
        assert_eq!(o.resume(), DirectState::Idle);
        let close = Message::Close(Some(axum::extract::ws::CloseFrame {
            code: 1009,
            reason: "message too big".into(),
        }));
        assert_eq!(
            socket.taken(),
            [framed(&Message::Text("error".into())), framed(&close)].concat()
        );
    }

    /// A failed socket drops what is queued and reports it; nothing more is written.
    #[test]
    fn a_failed_socket_ends_the_writer() {
        let (o, socket, _) = attached(0);
        o.push_frame(1, frame(1, 10, true));
        socket.fail.store(true, Ordering::Relaxed);
        socket.allow(100);
        assert_eq!(o.resume(), DirectState::Failed);
        assert_eq!(o.pending_frames(), 0);
        o.push_control(Message::Text("x".into()));
        assert!(socket.taken().is_empty());
        assert_eq!(o.direct_state(), DirectState::Failed);
    }

    /// Headers of RFC 6455 §5.2 for each length form, at the edges.
    #[test]
    fn headers_take_the_shortest_length_form() {
        assert_eq!(header(BINARY, 0).0[..2], [0x82, 0]);
        assert_eq!(header(BINARY, 125).0[..2], [0x82, 125]);
        let (h, n) = header(TEXT, 126);
        assert_eq!((&h[..n], n), (&[0x81, 126, 0, 126][..], 4));
        let (h, n) = header(BINARY, 65_535);
        assert_eq!(&h[..n], &[0x82, 126, 0xFF, 0xFF]);
        let (h, n) = header(BINARY, 65_536);
        assert_eq!(&h[..n], &[0x82, 127, 0, 0, 0, 0, 0, 1, 0, 0]);
    }

    /// Each message frames as tungstenite's own writer frames it (the reference a client's
    /// reader follows), including a close frame's code and reason.
    #[test]
    fn frames_match_tungstenites_writer() {
        use axum_tungstenite_ref as t;
        let cases = [
            Message::Text("hello".into()),
            Message::Binary(Bytes::from(vec![7u8; 300])),
            Message::Binary(Bytes::from(vec![1u8; 70_000])),
            Message::Ping(Bytes::from_static(b"p")),
            Message::Pong(Bytes::new()),
            Message::Close(Some(CloseFrame {
                code: 1008,
                reason: "client is not reading".into(),
            })),
        ];
        for m in cases {
            let theirs: t::Message = match &m {
                Message::Text(s) => t::Message::text(s.as_str()),
                Message::Binary(b) => t::Message::binary(b.clone()),
                Message::Ping(b) => t::Message::Ping(b.clone()),
                Message::Pong(b) => t::Message::Pong(b.clone()),
                Message::Close(c) => {
                    t::Message::Close(c.as_ref().map(|c| t::protocol::CloseFrame {
                        code: c.code.into(),
                        reason: c.reason.as_str().to_owned().into(),
                    }))
                }
            };
            let mut buf = Vec::new();
            let frame = match theirs {
                t::Message::Text(s) => t::protocol::frame::Frame::message(
                    s,
                    t::protocol::frame::coding::OpCode::Data(
                        t::protocol::frame::coding::Data::Text,
                    ),
                    true,
                ),
                t::Message::Binary(b) => t::protocol::frame::Frame::message(
                    b,
                    t::protocol::frame::coding::OpCode::Data(
                        t::protocol::frame::coding::Data::Binary,
                    ),
                    true,
                ),
                t::Message::Ping(b) => t::protocol::frame::Frame::ping(b),
                t::Message::Pong(b) => t::protocol::frame::Frame::pong(b),
                t::Message::Close(c) => t::protocol::frame::Frame::close(c),
                t::Message::Frame(f) => f,
            };
            frame.format(&mut buf).unwrap();
            assert_eq!(framed(&m).as_ref(), buf.as_slice(), "{m:?}");
        }
    }
}
