//! The writer half of a connection: drains its [`Outbox`] into a websocket sink.
//!
//! Generic over the sink so the outbox rules can be tested against a peer that never reads
//! (a sink that is never ready) — a loopback socket cannot show that: its kernel buffers
//! absorb megabytes before a write blocks.

use super::outbox::{Next, Outbox, message_len};
use crate::metrics::Metrics;
use axum::extract::ws::{CloseFrame, Message, close_code};
use futures_util::{Sink, SinkExt};

/// Sends what the outbox hands out, in order, until the outbox closes (then a close frame:
/// 1008 when the client stopped reading, 1000 otherwise) or the sink fails (the peer is gone).
pub async fn run_writer<S>(outbox: &Outbox, mut sink: S, metrics: &Metrics)
where
    S: Sink<Message> + Unpin,
{
    loop {
        match outbox.next().await {
            Next::Send(messages) => {
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
                    CloseFrame {
                        code: close_code::NORMAL,
                        reason: "bye".into(),
                    }
                };
                // The peer may already be gone; there is nothing left to do then.
                sink.send(Message::Close(Some(frame))).await.ok();
                return;
            }
        }
    }
}
