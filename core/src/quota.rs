//! Quotas: how much of the server one deployment lets its clients use. Every limit is
//! configurable (flags and environment in the binary); a request past one is refused with the
//! typed error `quota_exceeded` (HTTP 429) naming the quota and its value, changes nothing,
//! and is counted in `posecast_quota_refused_total{quota=…}`.
//!
//! Restoring stored state at start is not refused: lowering a quota keeps what exists and
//! only stops growth.

use crate::error::Error;

/// The limits (see each field's default).
#[derive(Debug, Clone, PartialEq)]
pub struct Quotas {
    /// Scenes on the server (default 256).
    pub max_scenes: usize,
    /// Avatars in one scene (default 1,024; a binary frame counts avatars in a u16).
    pub max_avatars_per_scene: usize,
    /// Joints of any rig loaded or uploaded (default 1,024: production face and body rigs stay
    /// well under it; a 10,000-joint rig made every viewer download a 1.23 MB description).
    pub max_joints: usize,
    /// Joints of a rig that a *limited* token (one limited to avatars or scenes) may place in
    /// a scene (default 256): one user's avatar cannot burden everyone who watches.
    pub limited_max_joints: usize,
    /// Clip duration × joints, joint-seconds, per clip (default 1,000,000: e.g. a 27,510 s
    /// clip of 31 joints fits; memory and baking time grow with it).
    pub max_clip_joint_seconds: f64,
    /// Bytes of one uploaded asset's files, added clips included (default 64 MiB).
    pub max_asset_bytes: u64,
    /// Bytes of all uploaded assets together (default 1 GiB).
    pub max_upload_total_bytes: u64,
}

impl Default for Quotas {
    fn default() -> Self {
        Self {
            max_scenes: 256,
            max_avatars_per_scene: 1024,
            max_joints: 1024,
            limited_max_joints: 256,
            max_clip_joint_seconds: 1_000_000.0,
            max_asset_bytes: 64 << 20,
            max_upload_total_bytes: 1 << 30,
        }
    }
}

/// Which quota refused a request (the `quota` label of the metric).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quota {
    /// [`Quotas::max_scenes`].
    Scenes,
    /// [`Quotas::max_avatars_per_scene`].
    AvatarsPerScene,
    /// [`Quotas::max_joints`].
    Joints,
    /// [`Quotas::limited_max_joints`].
    LimitedJoints,
    /// [`Quotas::max_clip_joint_seconds`].
    ClipJointSeconds,
    /// [`Quotas::max_asset_bytes`].
    AssetBytes,
    /// [`Quotas::max_upload_total_bytes`].
    UploadTotalBytes,
    /// A retargeted clip larger than the bake cache (`posecast_sim::bake::DEFAULT_CACHE_BYTES`).
    RetargetBytes,
    /// Bytes of the uploads and recordings one token made (its access-file `max_bytes`).
    TokenBytes,
    /// Uploads and recordings one token made (its access-file `max_objects`).
    TokenObjects,
}

impl Quota {
    /// Every quota, in metric order.
    pub const ALL: [Quota; 10] = [
        Quota::Scenes,
        Quota::AvatarsPerScene,
        Quota::Joints,
        Quota::LimitedJoints,
        Quota::ClipJointSeconds,
        Quota::AssetBytes,
        Quota::UploadTotalBytes,
        Quota::RetargetBytes,
        Quota::TokenBytes,
        Quota::TokenObjects,
    ];

    /// Its name in errors and metrics.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Quota::Scenes => "scenes",
            Quota::AvatarsPerScene => "avatars_per_scene",
            Quota::Joints => "joints",
            Quota::LimitedJoints => "limited_joints",
            Quota::ClipJointSeconds => "clip_joint_seconds",
            Quota::AssetBytes => "asset_bytes",
            Quota::UploadTotalBytes => "upload_total_bytes",
            Quota::RetargetBytes => "retarget_bytes",
            Quota::TokenBytes => "token_bytes",
            Quota::TokenObjects => "token_objects",
        }
    }

    /// Its index in [`Quota::ALL`].
    #[must_use]
    pub fn index(self) -> usize {
        Quota::ALL.iter().position(|&q| q == self).unwrap_or(0)
    }

    /// The typed refusal: `quota_exceeded`, naming the quota, what was asked and the limit.
    #[must_use]
    pub fn exceeded(self, what: impl std::fmt::Display, limit: impl std::fmt::Display) -> Error {
        Error::Quota {
            quota: self.name(),
            detail: what.to_string(),
            limit: limit.to_string(),
        }
    }
}

/// A per-connection command rate limit: a token bucket of `burst` commands refilled at
/// `per_second`. A command past it is refused with `rate_limited` and `retry_after_ms`, the
/// time until one token is back; nothing else about the connection changes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandRate {
    /// Sustained commands per second.
    pub per_second: f64,
    /// Commands that may arrive at once.
    pub burst: f64,
}

impl Default for CommandRate {
    /// 200 commands per second, bursts of 400: far above a person at a dashboard or a
    /// 90 Hz tracker driving joints one command at a time, far below what floods a server.
    fn default() -> Self {
        Self {
            per_second: 200.0,
            burst: 400.0,
        }
    }
}

impl CommandRate {
    /// Checks the values.
    ///
    /// # Errors
    /// A rate or burst that is not finite and positive (a burst must allow one command).
    pub fn new(per_second: f64, burst: f64) -> Result<Self, String> {
        if !(per_second.is_finite() && per_second >= 1e-3 && burst.is_finite() && burst >= 1.0) {
            return Err(format!(
                "command rate {per_second}/s with burst {burst}: both must be finite, the rate >= 0.001 and the burst >= 1"
            ));
        }
        Ok(Self { per_second, burst })
    }
}

/// One connection's token bucket.
#[derive(Debug, Clone)]
pub struct TokenBucket {
    rate: CommandRate,
    tokens: f64,
    last: std::time::Instant,
}

impl TokenBucket {
    /// A full bucket.
    #[must_use]
    pub fn new(rate: CommandRate) -> Self {
        Self::at(rate, std::time::Instant::now())
    }

    /// A full bucket at time `now`.
    #[must_use]
    pub fn at(rate: CommandRate, now: std::time::Instant) -> Self {
        Self {
            rate,
            tokens: rate.burst,
            last: now,
        }
    }

    /// Takes one token at `now`: `Ok`, or `Err(wait)` with the time until one is back.
    ///
    /// # Errors
    /// The bucket is empty.
    pub fn take_at(&mut self, now: std::time::Instant) -> Result<(), std::time::Duration> {
        let elapsed = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = now;
        self.tokens = (self.tokens + elapsed * self.rate.per_second).min(self.rate.burst);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            Ok(())
        } else {
            // At most a day: a tiny configured rate must not overflow the Duration.
            Err(std::time::Duration::from_secs_f64(
                ((1.0 - self.tokens) / self.rate.per_second).min(86_400.0),
            ))
        }
    }

    /// [`TokenBucket::take_at`] now.
    ///
    /// # Errors
    /// The bucket is empty.
    pub fn take(&mut self) -> Result<(), std::time::Duration> {
        self.take_at(std::time::Instant::now())
    }
}

/// The typed refusal of a rate-limited command, with the retry hint.
#[must_use]
pub fn rate_limited(wait: std::time::Duration) -> Error {
    let ms = u64::try_from(wait.as_millis().max(1)).unwrap_or(u64::MAX);
    Error::RateLimited {
        message: format!("too many commands: try again in {ms} ms"),
        retry_after_ms: ms,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::{ErrorCode, ProtocolError};

    #[test]
    fn names_and_indices_are_distinct() {
        let names: std::collections::BTreeSet<_> = Quota::ALL.iter().map(|q| q.name()).collect();
        assert_eq!(names.len(), Quota::ALL.len());
        for (i, q) in Quota::ALL.iter().enumerate() {
            assert_eq!(q.index(), i);
        }
        let e = Quota::Scenes.exceeded("scene 257", 256);
        assert_eq!(ProtocolError::from(e.clone()).retry_after_ms, None);
        assert_eq!(e.code(), ErrorCode::QuotaExceeded);
        assert!(
            e.to_string().contains("scenes") && e.to_string().contains("256"),
            "{}",
            e.to_string()
        );
    }

    #[test]
    fn bucket_allows_the_burst_then_the_rate() {
        let rate = CommandRate::new(10.0, 3.0).unwrap();
        let t0 = std::time::Instant::now();
        let mut b = TokenBucket::at(rate, t0);
        for _ in 0..3 {
            assert!(b.take_at(t0).is_ok());
        }
        let wait = b.take_at(t0).unwrap_err();
        assert!((wait.as_secs_f64() - 0.1).abs() < 1e-9, "{wait:?}");
        // 0.25 s later: 2.5 tokens back, so two commands pass and the third waits 0.05 s.
        let t1 = t0 + std::time::Duration::from_millis(250);
        assert!(b.take_at(t1).is_ok() && b.take_at(t1).is_ok());
        let wait = b.take_at(t1).unwrap_err();
        assert!((wait.as_secs_f64() - 0.05).abs() < 1e-9, "{wait:?}");
        // Never more than the burst, however long the pause.
        let t2 = t1 + std::time::Duration::from_secs(3600);
        for _ in 0..3 {
            assert!(b.take_at(t2).is_ok());
        }
        assert!(b.take_at(t2).is_err());
        assert!(CommandRate::new(0.0, 1.0).is_err() && CommandRate::new(1.0, 0.5).is_err());
        assert!(CommandRate::new(1e-300, 1.0).is_err());
        assert_eq!(
            ProtocolError::from(rate_limited(wait)).retry_after_ms,
            Some(50)
        );
    }
}
