//! Retargeted clips, baked away from the tick: off every scene lock and off the async
//! workers (on tokio's blocking pool, one bake at a time), and cached per (source rig, clip,
//! target rig) under a memory bound.
//!
//! `play … from_asset` on a long clip used to bake inside the scene lock on a runtime worker:
//! a 27,510 s clip stalled every scene's stream for up to a second per command. Now
//! the server's `control::execute_durable` bakes first ([`RetargetCache::bake`]) and the command
//! only looks the result up. Rigs are keyed by identity (`Arc` pointer, checked through a
//! `Weak`), so a rig replaced by an upload never serves a stale bake.

use posecast_core::error::Error;
use posecast_rigs::clip::Clip;
use posecast_rigs::rig::Rig;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use tokio::sync::Semaphore;

/// Default bound on the bytes of cached baked clips: 256 MiB.
pub const DEFAULT_CACHE_BYTES: usize = 256 << 20;

/// The clip `clip` of rig `source`, retargeted onto `target` (matching H-Anim joints in world
/// space relative to both rigs' neutral pose, baked at 30 Hz; see [`posecast_rigs::rig::retarget()`]).
/// CPU-heavy for long clips: call it from the blocking pool, never under a scene lock.
///
/// # Errors
/// `unknown_clip` when `source` has no such clip; `not_humanoid` when one rig is a humanoid
/// and the other is not; `invalid_value` when the rigs cannot be matched otherwise.
pub fn retarget(source: &Rig, target: &Rig, clip: &str) -> Result<Clip, Error> {
    let c = source.clip(clip).ok_or_else(|| Error::UnknownClip {
        rig: source.name.clone(),
        clip: clip.to_owned(),
    })?;
    let mut out = posecast_rigs::rig::retarget(source.view(), c, target.view()).map_err(|e| {
        e.to_error(&format!(
            "cannot retarget {clip} from {} onto {}",
            source.name, target.name
        ))
    })?;
    out.set_name(format!("{}:{clip}", source.name));
    Ok(out)
}

/// Approximate heap bytes of a baked clip: a quaternion and a time per key per joint (baked
/// clips are linear quaternion tracks at a fixed rate, plus one root translation track).
#[must_use]
pub fn baked_bytes(clip: &Clip) -> usize {
    let keys = (f64::from(clip.duration())
        * f64::from(posecast_rigs::rig::retarget::DEFAULT_RATE_HZ))
    .ceil();
    let keys = (keys as usize).clamp(1, posecast_rigs::rig::retarget::MAX_KEYS) + 1;
    keys * (clip.joint_count() + 1) * (16 + 4)
}

/// [`baked_bytes`] of the clip `clip` of `source` once baked onto `target`, before baking it:
/// keys from the source clip's duration, tracks from the target's joints.
fn estimated_bytes(source: &Rig, clip: &str, target: &Rig) -> usize {
    let duration = source.clip(clip).map_or(0.0, |c| c.duration());
    let keys =
        (f64::from(duration) * f64::from(posecast_rigs::rig::retarget::DEFAULT_RATE_HZ)).ceil();
    let keys = (keys as usize).clamp(1, posecast_rigs::rig::retarget::MAX_KEYS) + 1;
    keys * (target.skeleton().len() + 1) * (16 + 4)
}

type Key = (usize, String, usize);

#[derive(Debug)]
struct Entry {
    source: Weak<Rig>,
    target: Weak<Rig>,
    clip: Arc<Clip>,
    bytes: usize,
    last_used: u64,
}

#[derive(Debug, Default)]
struct Inner {
    entries: HashMap<Key, Entry>,
    bytes: usize,
    uses: u64,
}

/// Baked retargeted clips, least recently used evicted past the byte bound.
#[derive(Debug)]
pub struct RetargetCache {
    inner: Mutex<Inner>,
    limit: usize,
    /// One bake at a time: a flood of `play … from_asset` uses one core, not all of them.
    baking: Arc<Semaphore>,
}

impl Default for RetargetCache {
    fn default() -> Self {
        Self::new(DEFAULT_CACHE_BYTES)
    }
}

fn key(source: &Arc<Rig>, clip: &str, target: &Arc<Rig>) -> Key {
    (
        Arc::as_ptr(source) as usize,
        clip.to_owned(),
        Arc::as_ptr(target) as usize,
    )
}

impl RetargetCache {
    /// An empty cache holding at most `limit` bytes of baked clips (a single larger clip is
    /// still served, just not kept).
    #[must_use]
    pub fn new(limit: usize) -> Self {
        Self {
            inner: Mutex::new(Inner::default()),
            limit,
            baking: Arc::new(Semaphore::new(1)),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        // Every update below is a whole insert or remove: a poisoned lock is still consistent.
        self.inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The cached bake of `clip` from `source` onto `target`, if any. Cheap: safe under a
    /// scene lock.
    #[must_use]
    pub fn get(&self, source: &Arc<Rig>, clip: &str, target: &Arc<Rig>) -> Option<Arc<Clip>> {
        let mut inner = self.lock();
        inner.uses += 1;
        let uses = inner.uses;
        let entry = inner.entries.get_mut(&key(source, clip, target))?;
        // The pointers match; the rigs must also still be the same allocations.
        let alive = entry
            .source
            .upgrade()
            .is_some_and(|s| Arc::ptr_eq(&s, source))
            && entry
                .target
                .upgrade()
                .is_some_and(|t| Arc::ptr_eq(&t, target));
        if !alive {
            return None;
        }
        entry.last_used = uses;
        Some(entry.clip.clone())
    }

    /// Refuses a bake larger than the whole cache: it could not be kept, so every `play` of it
    /// would bake again (a long clip onto a rig of many joints reaches gigabytes).
    fn check_size(&self, source: &Rig, clip: &str, target: &Rig) -> Result<(), Error> {
        let bytes = estimated_bytes(source, clip, target);
        if bytes > self.limit {
            return Err(posecast_core::quota::Quota::RetargetBytes.exceeded(
                format!(
                    "{clip} of {} baked onto {} ({} joints) would take {bytes} bytes",
                    source.name,
                    target.name,
                    target.skeleton().len()
                ),
                self.limit,
            ));
        }
        Ok(())
    }

    fn insert(&self, source: &Arc<Rig>, target: &Arc<Rig>, name: &str, clip: Arc<Clip>) {
        let bytes = baked_bytes(&clip);
        if bytes > self.limit {
            return;
        }
        let mut inner = self.lock();
        inner.uses += 1;
        let last_used = inner.uses;
        // Entries whose rigs are gone can never be hit again.
        inner
            .entries
            .retain(|_, e| e.source.strong_count() > 0 && e.target.strong_count() > 0);
        if let Some(old) = inner.entries.insert(
            key(source, name, target),
            Entry {
                source: Arc::downgrade(source),
                target: Arc::downgrade(target),
                clip,
                bytes,
                last_used,
            },
        ) {
            inner.bytes -= old.bytes;
        }
        inner.bytes = inner.entries.values().map(|e| e.bytes).sum::<usize>();
        while inner.bytes > self.limit {
            let Some(oldest) = inner
                .entries
                .iter()
                .min_by_key(|(_, e)| e.last_used)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            if let Some(e) = inner.entries.remove(&oldest) {
                inner.bytes -= e.bytes;
            }
        }
    }

    /// Bytes and entries held.
    #[must_use]
    pub fn usage(&self) -> (usize, usize) {
        let inner = self.lock();
        (inner.bytes, inner.entries.len())
    }

    /// Gets or bakes on the calling thread (start-up restore and in-memory callers that are
    /// not on an async worker).
    ///
    /// # Errors
    /// As [`retarget`].
    pub fn bake_blocking(
        &self,
        source: &Arc<Rig>,
        clip: &str,
        target: &Arc<Rig>,
    ) -> Result<Arc<Clip>, Error> {
        if let Some(c) = self.get(source, clip, target) {
            return Ok(c);
        }
        self.check_size(source, clip, target)?;
        let baked = Arc::new(retarget(source, target, clip)?);
        self.insert(source, target, clip, baked.clone());
        Ok(baked)
    }

    /// Gets or bakes on tokio's blocking pool, one bake at a time; concurrent requests for
    /// the same clip wait for the first and share its result.
    ///
    /// # Errors
    /// As [`retarget`]; `internal` if the bake task panicked.
    pub async fn bake(
        &self,
        source: Arc<Rig>,
        clip: &str,
        target: Arc<Rig>,
    ) -> Result<Arc<Clip>, Error> {
        if let Some(c) = self.get(&source, clip, &target) {
            return Ok(c);
        }
        self.check_size(&source, clip, &target)?;
        // Owned, and moved into the blocking task below: a caller that gives up (a client that
        // disconnects) must not free the slot while its bake still runs.
        let permit = self
            .baking
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Error::Internal("the retargeting pool is closed".into()))?;
        // Someone may have baked it while this waited.
        if let Some(c) = self.get(&source, clip, &target) {
            return Ok(c);
        }
        let (s, t, name) = (source.clone(), target.clone(), clip.to_owned());
        let baked = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            retarget(&s, &t, &name)
        })
        .await
        .map_err(|e| Error::Internal(format!("retargeting failed: {e}")))??;
        let baked = Arc::new(baked);
        self.insert(&source, &target, clip, baked.clone());
        Ok(baked)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::ErrorCode;

    /// A rig named `name` whose only clip is the built-in walk stretched to `seconds`.
    fn rig(name: &str, seconds: f32) -> Arc<Rig> {
        let mut rig = posecast_rigs::builtin::rig().unwrap();
        let walk = rig.clip("walk").unwrap();
        let clip = Clip::new("long", walk.channels().to_vec(), Some((0.0, seconds))).unwrap();
        rig.name = name.into();
        rig.clips = vec![Arc::new(clip)];
        Arc::new(rig)
    }

    #[test]
    fn a_bake_larger_than_the_cache_is_refused_before_baking() {
        let (source, target) = (rig("src", 3600.0), rig("tgt", 1.0));
        let cache = RetargetCache::new(1 << 20);
        let e = cache.bake_blocking(&source, "long", &target).unwrap_err();
        assert_eq!(e.code(), ErrorCode::QuotaExceeded, "{e:?}");
        assert!(
            e.to_string().contains("retarget_bytes"),
            "{}",
            e.to_string()
        );
        assert_eq!(cache.usage(), (0, 0));
    }

    #[test]
    fn bakes_are_cached_per_rig_identity_and_evicted_past_the_bound() {
        let (a, b, target) = (rig("a", 2.0), rig("b", 2.0), rig("t", 1.0));
        let one = baked_bytes(&retarget(&a, &target, "long").unwrap());
        // Room for one bake: the second evicts the first.
        let cache = RetargetCache::new(one + one / 2);
        let first = cache.bake_blocking(&a, "long", &target).unwrap();
        assert!(Arc::ptr_eq(
            &first,
            &cache.get(&a, "long", &target).unwrap()
        ));
        cache.bake_blocking(&b, "long", &target).unwrap();
        assert!(cache.get(&a, "long", &target).is_none());
        assert_eq!(cache.usage().1, 1);
        // A rig replaced under the same name is another rig: no stale hit.
        let a2 = rig("a", 2.0);
        assert!(cache.get(&a2, "long", &target).is_none());
    }
}
