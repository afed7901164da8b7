//! Lingering close: a connection the server ends while the peer's input is still unread is
//! half-closed and drained for a moment, not dropped at once.
//!
//! Closing a TCP socket whose receive queue holds unread bytes makes the kernel answer with a
//! reset (RST), not a FIN, and a reset makes the peer's kernel throw away what it received but
//! its application has not read yet — the answer that explained the close. A websocket that
//! sent a message over 64 KiB is closed while most of that message is unread (the frame's
//! header is enough to refuse it): without this the `message_too_large` error and close 1009
//! were lost whenever the client was still writing (issue 36). The same holds for an HTTP
//! answer to a request whose body is not read (a 413, a refusal).
//!
//! So the socket is shut down for writing (what was sent goes out, then a FIN) and its input
//! read and discarded until the peer closes too, or for [`LINGER`] at most; then it is closed.

use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tracing::trace;

/// How long a closed connection's input is drained at most, waiting for the peer to read
/// what was sent and close its side.
pub const LINGER: Duration = Duration::from_secs(2);

/// Closes `stream`: at once when nothing is unread, else after lingering (on a task that also
/// holds `slot`, the connection's place under the caps, until the descriptor is closed).
pub fn close<G: Send + 'static>(stream: TcpStream, slot: G) {
    let mut probe = [0u8; 512];
    match stream.try_read(&mut probe) {
        // Input is waiting: a plain close would reset the connection.
        Ok(n) if n > 0 => {}
        // Nothing unread (`WouldBlock`), the peer closed (`Ok(0)`) or the socket failed: a
        // plain close is a FIN, or nothing is left to protect.
        _ => return,
    }
    let Ok(runtime) = tokio::runtime::Handle::try_current() else {
        return;
    };
    runtime.spawn(async move {
        let _slot = slot;
        let mut stream = stream;
        let deadline = tokio::time::Instant::now() + LINGER;
        if tokio::time::timeout_at(deadline, stream.shutdown())
            .await
            .is_ok_and(|r| r.is_ok())
        {
            let mut discard = vec![0u8; 4 << 10];
            while let Ok(Ok(n)) = tokio::time::timeout_at(deadline, stream.read(&mut discard)).await
            {
                if n == 0 {
                    break;
                }
            }
        }
        trace!("lingering close done");
    });
}
