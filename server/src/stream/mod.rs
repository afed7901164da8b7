//! Fan-out to connections: [`outbox`], the bounded per-connection queue.

pub mod outbox;
