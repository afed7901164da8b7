//! Recorded clips (`record` … `stop_recording`) in the data folder: `DIR/recordings/<rig>/
//! <clip>.glb`, each the rig's skin with the clip as its one animation (the same file
//! `GET /api/assets/{rig}/clips/{clip}.glb` serves), so an operator can open it in any glTF
//! tool. At start, after the rigs are loaded and before the scenes (which may play them), each
//! file's animation is read back onto its rig without normalisation: the file is written in
//! the rig's normalised frames, so the clip comes back as recorded (to the f32 rounding the
//! export tests bound).

use super::atomic::{self, write_atomic};
use super::{Store, Unusable, set_aside};
use crate::clip::Clip;
use crate::rig::Rig;
use crate::world::World;
use std::io;
use std::path::{Path, PathBuf};
use tracing::{info, warn};

/// What [`save`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Saved {
    /// Stored: the file's size.
    Stored(u64),
    /// Not stored: the file (this size) would not fit in the room left.
    NoRoom(u64),
}

/// Stores recorded clip `clip` of `rig` durably under `recordings` (`DIR/recordings`), if its
/// file fits in `room` bytes. Blocking: call it off the async workers.
///
/// # Errors
/// The clip could not be written as glTF, or an I/O error.
pub fn save(recordings: &Path, rig: &Rig, clip: &Clip, room: u64) -> io::Result<Saved> {
    let bytes = crate::export::clip_glb(rig, clip).map_err(io::Error::other)?;
    let size = bytes.len() as u64;
    if size > room {
        return Ok(Saved::NoRoom(size));
    }
    let dir = recordings.join(&rig.name);
    std::fs::create_dir_all(&dir)?;
    atomic::sync_dir(recordings)?;
    write_atomic(&dir.join(format!("{}.glb", clip.name())), &bytes)?;
    Ok(Saved::Stored(size))
}

impl Store {
    /// `DIR/recordings`.
    #[must_use]
    pub fn recordings_dir(&self) -> Option<PathBuf> {
        self.root().map(|r| r.join("recordings"))
    }

    /// Puts every stored recording back on its rig (see the module doc). A file whose rig is
    /// not loaded is left alone (the rig may come back); one that cannot be read or does not
    /// fit its rig is moved aside.
    pub fn restore_recordings(&self, world: &World) {
        let Some(dir) = self.recordings_dir() else {
            return;
        };
        for rig_dir in sorted_entries(&dir).into_iter().filter(|p| p.is_dir()) {
            let Some(name) = rig_dir.file_name().and_then(|n| n.to_str()) else {
                continue;
            };
            let Some(rig) = world.library.get(name) else {
                warn!(
                    rig = name,
                    "stored recordings not loaded: no rig of that name"
                );
                continue;
            };
            for file in sorted_entries(&rig_dir) {
                if file.extension().is_none_or(|e| e != "glb") {
                    continue;
                }
                let loaded = read_recording(&rig, &file).and_then(|clip| {
                    let (clip_name, seconds) = (clip.name().to_owned(), clip.duration());
                    let size = std::fs::metadata(&file).map_or(0, |m| m.len());
                    world
                        .add_clip(name, clip)
                        .map_err(|e| Unusable::Content(e.to_string()))?;
                    Ok((clip_name, seconds, size))
                });
                match loaded {
                    Ok((clip, seconds, size)) => {
                        self.add_upload_bytes(size);
                        info!(rig = name, clip, seconds, "restored recording");
                    }
                    Err(reason) => set_aside(&file, &reason.to_string()),
                }
            }
        }
    }
}

/// A folder's entries in name order (none when it cannot be read).
fn sorted_entries(dir: &Path) -> Vec<PathBuf> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|entries| entries.filter_map(Result::ok).map(|e| e.path()).collect())
        .unwrap_or_default();
    paths.retain(|p| {
        p.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| !n.starts_with('.') && !n.contains(".corrupt") && !n.ends_with(".tmp"))
    });
    paths.sort();
    paths
}

/// The clip a stored recording holds, checked against the rig it belongs to: the same joints
/// in the same order, and the clip named as the file.
fn read_recording(rig: &Rig, path: &Path) -> Result<Clip, Unusable> {
    let file = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let stem = path
        .file_stem()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let bytes = std::fs::read(path).map_err(|source| Unusable::Read {
        file: file.clone(),
        source,
    })?;
    recording_from_bytes(rig, &stem, &bytes)
}

/// Recorded clip `stem` of `rig` from a recording file's bytes: the same joints in the same
/// order as the rig, and a clip named `stem`.
///
/// # Errors
/// Not a glTF binary, no skin, not the rig's joints, or no clip of that name.
pub fn recording_from_bytes(rig: &Rig, stem: &str, bytes: &[u8]) -> Result<Clip, Unusable> {
    let file = format!("{stem}.glb");
    let asset = crate::import::gltf::from_slice(&file, bytes)
        .map_err(|e| Unusable::Content(e.to_string()))?
        .into_iter()
        .next()
        .ok_or_else(|| Unusable::Content(format!("{file} holds no skin")))?;
    if asset.skeleton.names() != rig.skeleton().names() {
        return Err(Unusable::Content(format!(
            "{file}: its joints are not rig {}'s",
            rig.name
        )));
    }
    asset
        .clips
        .into_iter()
        .find(|c| c.name() == stem)
        .ok_or_else(|| Unusable::Content(format!("{file} holds no clip named {stem}")))
}
