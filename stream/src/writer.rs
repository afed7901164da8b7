//! The writer half of a connection: drains its [`Outbox`] into a websocket sink.
//!
//! Generic over the sink so the outbox rules can be tested against a peer that never reads
//! (a sink that is never ready) — a loopback socket cannot show that: its kernel buffers
//! absorb megabytes before a write blocks.

use super::outbox::{Next, Outbox, message_len};
use crate::Counters;
use axum::extract::ws::{CloseFrame, Message, close_code};
use futures_util::{Sink, SinkExt};
use std::pin::Pin;
use std::task::{Context, Poll};

/// How long the close frame may take to go out before the writer gives up on the peer.
const CLOSE_SEND_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(1);

/// Sends what the outbox hands out, in order, until the outbox closes (then a close frame:
/// 1008 when the client stopped reading, the reader's choice or 1000 otherwise) or the sink
/// fails (the peer is gone).
pub async fn run_writer<S>(outbox: &Outbox, sink: S, metrics: &dyn Counters)
where
    S: Sink<Message> + Unpin,
{
    let mut sink = Watched { sink, outbox };
    loop {
        match outbox.next().await {
            Next::Send(messages) => {
                metrics.writer_woke();
                let count = messages.len() as u64;
                let mut bytes = 0u64;
                for m in messages {
                    bytes += message_len(&m) as u64;
                    if sink.feed(m).await.is_err() {
                        return;
                    }
                }
                if sink.flush().await.is_err() {
                    return;
                }
                metrics.sent(count, bytes);
            }
            Next::Close { overflowed } => {
                let frame = if overflowed {
                    CloseFrame {
                        code: close_code::POLICY,
                        reason: "client is not reading".into(),
                    }
                } else {
                    // The reader may have chosen the code (1001, 1002, 1007, 1008, 1009).
                    outbox.close_frame().unwrap_or(CloseFrame {
                        code: close_code::NORMAL,
                        reason: "bye".into(),
                    })
                };
                // The peer may already be gone, or not reading at all: nothing is left to do
                // then, and a peer that never reads must not hold this task forever.
                tokio::time::timeout(CLOSE_SEND_TIMEOUT, sink.send(Message::Close(Some(frame))))
                    .await
                    .ok();
                return;
            }
        }
    }
}

/// The writer's sink, telling its outbox whether the socket holds it
/// ([`Outbox::set_socket_full`]): a write or flush that cannot finish (the socket's buffer is
/// full) is pending until there is room.
struct Watched<'a, S> {
    sink: S,
    outbox: &'a Outbox,
}

impl<S> Watched<'_, S> {
    fn held<T>(&self, poll: Poll<T>) -> Poll<T> {
        self.outbox.set_socket_full(poll.is_pending());
        poll
    }
}

impl<S: Sink<Message> + Unpin> Sink<Message> for Watched<'_, S> {
    type Error = S::Error;

    fn poll_ready(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        let poll = Pin::new(&mut self.sink).poll_ready(cx);
        self.held(poll)
    }

    fn start_send(mut self: Pin<&mut Self>, item: Message) -> Result<(), S::Error> {
        Pin::new(&mut self.sink).start_send(item)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        let poll = Pin::new(&mut self.sink).poll_flush(cx);
        self.held(poll)
    }

    fn poll_close(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        Pin::new(&mut self.sink).poll_close(cx)
    }
}
