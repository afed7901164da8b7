//! A take for other tools (issue 32): `GET /api/takes/{take}.glb` (every avatar's mesh and
//! skin, one animation moving them all) and `GET /api/takes/{take}/{avatar}.bvh`, both over a
//! time range.
//!
//! The take's frames are read in order ([`TakeReader`]) and each avatar's decoded poses —
//! what the scene's subscribers received — become a clip of its rig with one key per frame
//! ([`Recorder`], roots in scene space: placements move them, so every avatar keeps its place
//! in the scene). Blocking: run it on the blocking pool.

use crate::scene::replay::TakeSource;
use posecast_core::error::Error;
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::AvatarId;
use posecast_rigs::clip::Clip;
use posecast_rigs::library::Library;
use posecast_rigs::rig::Rig;
use posecast_sim::avatar::recording::{RecordLimits, Recorder};
use posecast_stream::take::{TakeIndex, TakeReader};
use std::sync::Arc;

/// Most bytes of samples an export may gather (longer ranges: ask for less with `from`/`to`):
/// about 40 minutes of 10 avatars of 23 joints at 60 Hz.
pub const MAX_EXPORT_BYTES: usize = 256 << 20;

/// Take exports that may run at once; more wait their turn, so a burst of export requests
/// holds at most this many times [`MAX_EXPORT_BYTES`].
pub const CONCURRENT_EXPORTS: usize = 2;

/// Waits for a turn to export ([`CONCURRENT_EXPORTS`]); hold it while exporting. (`None`
/// only if the semaphore were closed, which it never is.)
pub async fn turn() -> Option<tokio::sync::SemaphorePermit<'static>> {
    static TURNS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(CONCURRENT_EXPORTS);
    TURNS.acquire().await.ok()
}

/// A time range of a take, seconds from its first frame (`?from=&to=`).
#[derive(Debug, Clone, Copy, Default, serde::Deserialize)]
pub struct Range {
    /// Start (default: the take's start).
    pub from: Option<f64>,
    /// End (default: the take's end).
    pub to: Option<f64>,
}

/// One avatar of a take, as exported: its description in the take, its rig now, its motion.
#[derive(Debug)]
pub struct Exported {
    /// The avatar as recorded.
    pub description: AvatarDescription,
    /// The rig it was made of (from the library; checked to have the recorded joints).
    pub rig: Arc<Rig>,
    /// Its motion over the range, keyed at every frame it was in.
    pub clip: Clip,
}

/// The avatars of take `take` (all, or `only`) over `range` as clips of their rigs.
///
/// # Errors
/// `invalid_value` (a range that is not finite, or ends before it starts, or is too long to
/// export at once), `unknown_avatar` (`only` is not in the take), `unknown_asset`/`conflict`
/// (a rig is gone or changed), `unknown_take` (the take cannot be read on).
pub fn clips(
    take: &str,
    index: Arc<TakeIndex>,
    source: TakeSource,
    library: &Library,
    range: Range,
    only: Option<&AvatarId>,
) -> Result<Vec<Exported>, Error> {
    let duration = index.duration();
    let from = range.from.unwrap_or(0.0);
    let to = range.to.unwrap_or(duration);
    if !from.is_finite() || !to.is_finite() || to < from {
        return Err(Error::invalid(format!(
            "the range {from}–{to} s is not a range of seconds"
        )));
    }
    let Some(first_seq) = index.first_seq() else {
        return Err(Error::invalid(format!("take {take} has no frames")));
    };
    let rate = f64::from(index.header.tick_rate);
    let start = index.frame_at(from).unwrap_or(0);
    let end = index.frame_at(to).unwrap_or(0);
    let mut reader = TakeReader::new(source, index.clone());
    let mut recorders: Vec<(AvatarDescription, Recorder)> = Vec::new();
    let mut gathered = 0usize;
    for i in start..=end {
        let t = (index.frames[i].seq - first_seq) as f64 / rate;
        let poses = reader.poses(i).map_err(|e| Error::UnknownTake {
            take: take.to_owned(),
            unreadable: Some(e.to_string()),
        })?;
        for p in poses {
            if only.is_some_and(|id| id != &p.description.id) {
                continue;
            }
            let at = match recorders.iter().position(|(d, _)| d.id == p.description.id) {
                Some(at) => at,
                None => {
                    let limits = RecordLimits {
                        max_seconds: f64::MAX,
                        max_bytes: MAX_EXPORT_BYTES,
                    };
                    let recorder = Recorder::new(take, &p.description, limits).in_scene_space();
                    recorders.push(((*p.description).clone(), recorder));
                    recorders.len() - 1
                }
            };
            let (_, recorder) = &mut recorders[at];
            recorder
                .push((t - from).max(0.0), &p.pose)
                .map_err(|e| Error::invalid(format!("avatar {}: {e}", p.description.id)))?;
            gathered += 16 * p.pose.rotations.len();
            if recorder.is_full() || gathered > MAX_EXPORT_BYTES {
                return Err(Error::invalid(format!(
                    "the range {from}–{to} s is too long to export at once: ask for less with from and to"
                )));
            }
        }
    }
    if let Some(id) = only
        && recorders.is_empty()
    {
        return Err(Error::UnknownAvatar(id.clone()));
    }
    recorders
        .into_iter()
        .map(|(description, recorder)| {
            let rig = rig_of(take, library, &description)?;
            let clip = recorder
                .finish()
                .map_err(|e| Error::invalid(format!("avatar {}: {e}", description.id)))?;
            Ok(Exported {
                description,
                rig,
                clip,
            })
        })
        .collect()
}

/// The rig avatar `d` of take `take` was made of, if the library still has it as it was.
///
/// # Errors
/// `unknown_asset`, `conflict`.
pub fn rig_of(take: &str, library: &Library, d: &AvatarDescription) -> Result<Arc<Rig>, Error> {
    let rig = library.get(&d.name).ok_or_else(|| Error::UnknownAsset {
        asset: d.name.clone(),
        needed_by: Some(format!("avatar {} of take {take}", d.id)),
    })?;
    let names = rig.skeleton().names();
    if names.len() != d.joint_names.len() || names.iter().zip(&d.joint_names).any(|(a, b)| a != b) {
        return Err(Error::Conflict(format!(
            "rig {} is not the one avatar {} of take {take} was recorded with (its joints changed)",
            d.name, d.id
        )));
    }
    Ok(rig)
}
