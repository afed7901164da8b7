//! Whether the server has finished what it loads at start, and how far it has got.
//!
//! A server listens before it loads anything (`posecast_server::startup::Server::start`); rigs and
//! stored scenes are restored in the background (`restore`). Until then `GET
//! /healthz` answers 503 with the progress, and every request that reads or changes scenes or
//! assets waits here (see the guide, `docs/src/reference/persistence.md`).

use posecast_core::error::Error;
use std::sync::atomic::{AtomicUsize, Ordering};
use tokio::sync::watch;

/// Where start-up is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Phase {
    /// Loading rigs and restoring scenes.
    Starting,
    /// Everything stored is restored; requests are served.
    Ready,
    /// Start-up failed (e.g. the first start could not store the default scene); the reason.
    Failed(String),
    /// The server was shut down before it was ready.
    Stopped,
}

/// Start-up progress, shared by the loader and every request that waits for it.
#[derive(Debug)]
pub struct Readiness {
    phase: watch::Sender<Phase>,
    loaded: AtomicUsize,
    total: AtomicUsize,
}

impl Default for Readiness {
    /// Ready: a state built by hand (unit tests) has nothing to load.
    fn default() -> Self {
        Self {
            phase: watch::Sender::new(Phase::Ready),
            loaded: AtomicUsize::new(0),
            total: AtomicUsize::new(0),
        }
    }
}

impl Readiness {
    /// The current phase.
    #[must_use]
    pub fn phase(&self) -> Phase {
        self.phase.borrow().clone()
    }

    /// Whether the server is ready.
    #[must_use]
    pub fn is_ready(&self) -> bool {
        *self.phase.borrow() == Phase::Ready
    }

    /// Asset sources (the built-in rig, files of `--assets` folders, stored uploads) done so
    /// far — loaded or skipped — and how many there are.
    #[must_use]
    pub fn progress(&self) -> (usize, usize) {
        (
            self.loaded.load(Ordering::Relaxed),
            self.total.load(Ordering::Relaxed),
        )
    }

    /// Start-up begins with `total` asset sources to load.
    pub fn begin(&self, total: usize) {
        self.loaded.store(0, Ordering::Relaxed);
        self.total.store(total, Ordering::Relaxed);
        self.phase.send_replace(Phase::Starting);
    }

    /// One more asset source is done.
    pub(crate) fn source_done(&self) {
        self.loaded.fetch_add(1, Ordering::Relaxed);
    }

    /// Start-up ended: ready, or failed with the reason. A server already stopped stays
    /// stopped.
    pub fn finish(&self, result: Result<(), String>) {
        self.phase.send_if_modified(|p| {
            if *p != Phase::Starting {
                return false;
            }
            *p = match result {
                Ok(()) => Phase::Ready,
                Err(reason) => Phase::Failed(reason),
            };
            true
        });
    }

    /// The server shuts down: a start-up still in progress stops (the loader gives up at its
    /// next step) and whoever waits for it is answered.
    pub fn stop(&self) {
        self.phase.send_if_modified(|p| {
            let starting = *p == Phase::Starting;
            if starting {
                *p = Phase::Stopped;
            }
            starting
        });
    }

    /// Whether start-up should give up (the server is shutting down).
    #[must_use]
    pub(crate) fn stopped(&self) -> bool {
        *self.phase.borrow() == Phase::Stopped
    }

    /// Waits until start-up has ended; returns how.
    pub async fn settled(&self) -> Phase {
        let mut rx = self.phase.subscribe();
        // The sender lives as long as `self`, so this cannot fail while we borrow it.
        match rx.wait_for(|p| *p != Phase::Starting).await {
            Ok(p) => p.clone(),
            Err(_) => Phase::Stopped,
        }
    }

    /// Waits until the server is ready.
    ///
    /// # Errors
    /// `internal` when start-up failed or the server shut down first.
    pub async fn wait(&self) -> Result<(), Error> {
        match self.settled().await {
            // `settled` returns only once start-up has ended, so never `Starting`.
            Phase::Ready | Phase::Starting => Ok(()),
            Phase::Failed(reason) => Err(Error::Internal(format!(
                "the server failed to start: {reason}"
            ))),
            Phase::Stopped => Err(Error::Internal(
                "the server shut down before it finished starting".into(),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::ErrorCode;
    use std::time::Duration;

    #[tokio::test]
    async fn waiters_are_answered_when_start_up_ends() {
        let r = std::sync::Arc::new(Readiness::default());
        assert!(r.is_ready(), "a hand-built state has nothing to load");
        r.begin(3);
        let waiter = tokio::spawn({
            let r = r.clone();
            async move { r.wait().await }
        });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!waiter.is_finished(), "answered while starting");
        r.source_done();
        assert_eq!(r.progress(), (1, 3));
        r.finish(Ok(()));
        assert!(waiter.await.unwrap().is_ok());
        // Ready stays ready: a shutdown afterwards is not a failed start.
        r.stop();
        assert_eq!(r.phase(), Phase::Ready);
    }

    #[tokio::test]
    async fn a_shutdown_during_start_up_answers_the_waiters_with_an_error() {
        let r = std::sync::Arc::new(Readiness::default());
        r.begin(1);
        let waiter = tokio::spawn({
            let r = r.clone();
            async move { r.wait().await }
        });
        r.stop();
        assert!(r.stopped());
        let e = waiter.await.unwrap().unwrap_err();
        assert_eq!(e.code(), ErrorCode::Internal);
        // The loader finishing late does not turn a stopped server into a ready one.
        r.finish(Ok(()));
        assert_eq!(r.phase(), Phase::Stopped);
    }

    #[tokio::test]
    async fn a_failed_start_up_names_the_reason() {
        let r = Readiness::default();
        r.begin(0);
        r.finish(Err("data folder x is not usable".into()));
        let e = r.wait().await.unwrap_err();
        assert!(e.to_string().contains("data folder x"), "{}", e.to_string());
    }
}
