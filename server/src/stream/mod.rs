//! Fan-out to connections: [`outbox`], the bounded per-connection queue, and [`writer`], the
//! task that drains it into the websocket.

pub mod outbox;
pub mod writer;
