//! Recorded clips (`record` … `stop_recording`) in the data folder: `DIR/recordings/<rig>/
//! <clip>.glb`, each the rig's skin with the clip as its one animation (the same file
//! `GET /api/assets/{rig}/clips/{clip}.glb` serves), so an operator can open it in any glTF
//! tool, and beside it `<clip>.json` ([`RecordingMeta`]: the clip's exact name and the token
//! that made it, whose quota it counts against). At start, after the rigs are loaded and
//! before the scenes (which may play them), each file's animation is read back onto its rig
//! without normalisation: the file is written in the rig's normalised frames, so the clip
//! comes back as recorded (to the f32 rounding the export tests bound).
//!
//! **Names are data, not paths.** `<rig>` and `<clip>` in file names are [`encode_name`]d:
//! letters, digits, `-` and `_` stay, every other byte is `%XX`. So no name can be a hidden
//! file, climb out of its folder, or end in what the store itself appends (`.tmp`,
//! `.corrupt`, `.glb`): `.hidden`, `..x`, `.upload-zz` and `a.corrupt` are stored as
//! `%2Ehidden.glb`, … and restored as they were named (issue 37). Files of an older version,
//! named as the clip, decode to themselves (they hold no `%`).

use super::atomic::{self, write_atomic};
use super::{Store, Unusable, set_aside};
use crate::world::World;
use posecast_rigs::clip::Clip;
use posecast_rigs::rig::Rig;
use serde::{Deserialize, Serialize};
use std::io;
use std::path::{Path, PathBuf};
use tracing::{info, warn};

/// Version of a recording's `<clip>.json`.
pub const RECORDING_FORMAT: u32 = 1;

/// `recordings/<rig>/<clip>.json`: who made the recording (the owner its bytes count against).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMeta {
    /// [`RECORDING_FORMAT`].
    pub format: u32,
    /// The clip's name, exactly as given to `record`.
    pub clip: String,
    /// The name of the token that stopped the recording (`None`: the server itself, or a
    /// command forwarded by another server of a cluster).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub owner: Option<String>,
}

/// A name as it appears in a file name: `[A-Za-z0-9_-]` as is, every other byte of its UTF-8
/// as `%XX` (upper-case hex). Injective, and the result never holds `.` or `/`.
#[must_use]
pub fn encode_name(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    for b in name.bytes() {
        if b.is_ascii_alphanumeric() || b == b'-' || b == b'_' {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// The name [`encode_name`] encoded as `stem`; `None` for a malformed escape or bytes that
/// are not UTF-8. Any other character stands for itself (files of older versions).
#[must_use]
pub fn decode_name(stem: &str) -> Option<String> {
    let bytes = stem.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        if b == b'%' {
            let hex = std::str::from_utf8(bytes.get(i + 1..i + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(b);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// `recordings/<rig>/`.
fn rig_dir(recordings: &Path, rig: &str) -> PathBuf {
    recordings.join(encode_name(rig))
}

/// `recordings/<rig>/<clip>.glb` and `….json`.
fn files(recordings: &Path, rig: &str, clip: &str) -> (PathBuf, PathBuf) {
    let dir = rig_dir(recordings, rig);
    let stem = encode_name(clip);
    (
        dir.join(format!("{stem}.glb")),
        dir.join(format!("{stem}.json")),
    )
}

/// Stores recorded clip `clip` of `rig` (its glTF file `glb`) durably under `recordings`
/// (`DIR/recordings`): the `.glb`, then its `.json`. All or nothing: on any error every file
/// it wrote (temporary ones included) is removed again, so a full disk leaves no half-written
/// recording to restore. Blocking: call it off the async workers.
///
/// # Errors
/// An I/O error (the disk full among them: [`posecast_core::error::is_storage_full`]).
pub fn save(
    recordings: &Path,
    rig: &str,
    clip: &str,
    glb: &[u8],
    owner: Option<&str>,
) -> io::Result<()> {
    let (file, meta_file) = files(recordings, rig, clip);
    let meta = RecordingMeta {
        format: RECORDING_FORMAT,
        clip: clip.to_owned(),
        owner: owner.map(str::to_owned),
    };
    let result = (|| {
        std::fs::create_dir_all(rig_dir(recordings, rig))?;
        atomic::sync_dir(recordings)?;
        write_atomic(&file, glb)?;
        write_atomic(
            &meta_file,
            &serde_json::to_vec_pretty(&meta).map_err(io::Error::other)?,
        )
    })();
    if result.is_err() {
        for path in [&file, &meta_file] {
            for p in [atomic::tmp_path(path), path.clone()] {
                if let Err(e) = atomic::remove_durable(&p) {
                    warn!(file = %p.display(), error = %e, "cannot remove a failed recording's file");
                }
            }
        }
    }
    result
}

/// Removes stored recording `clip` of `rig` (`delete_clip`): the `.glb` first, so a crash
/// half-way leaves a `.json` alone, which restores nothing.
///
/// # Errors
/// An I/O error but "not found".
pub fn delete(recordings: &Path, rig: &str, clip: &str) -> io::Result<()> {
    let (file, meta_file) = files(recordings, rig, clip);
    atomic::remove_durable(&file)?;
    atomic::remove_durable(&meta_file)
}

/// A stored recording as the store counts it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoredRecording {
    /// Size of its `.glb`, bytes.
    pub bytes: u64,
    /// Who made it ([`RecordingMeta::owner`]).
    pub owner: Option<String>,
}

impl Store {
    /// `DIR/recordings`.
    #[must_use]
    pub fn recordings_dir(&self) -> Option<PathBuf> {
        self.root().map(|r| r.join("recordings"))
    }

    /// Puts every stored recording back on its rig (see the module doc), each rig's at once
    /// (one new rig per rig, not one per recording). A file whose rig is not loaded is left
    /// alone (the rig may come back); one that cannot be read or does not fit its rig is
    /// moved aside.
    pub fn restore_recordings(&self, world: &World) {
        let Some(dir) = self.recordings_dir() else {
            return;
        };
        for rig_dir in sorted_entries(&dir).into_iter().filter(|p| p.is_dir()) {
            let Some(name) = rig_dir
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(decode_name)
            else {
                warn!(dir = %rig_dir.display(), "stored recordings not loaded: not a rig's folder name");
                continue;
            };
            let Some(rig) = world.library.get(&name) else {
                warn!(
                    rig = name,
                    "stored recordings not loaded: no rig of that name"
                );
                continue;
            };
            let files: Vec<PathBuf> = sorted_entries(&rig_dir)
                .into_iter()
                .filter(|f| f.extension().is_some_and(|e| e == "glb"))
                .collect();
            let mut clips = Vec::new();
            for (file, read) in files.iter().zip(read_all(&rig, &files)) {
                match read {
                    Ok((clip, stored)) => {
                        if rig.clip(clip.name()).is_some()
                            || clips
                                .iter()
                                .any(|(c, _): &(Clip, _)| c.name() == clip.name())
                        {
                            set_aside(
                                file,
                                &format!("rig {name} already has a clip {}", clip.name()),
                            );
                            continue;
                        }
                        clips.push((clip, stored));
                    }
                    Err(reason) => set_aside(file, &reason.to_string()),
                }
            }
            if clips.is_empty() {
                continue;
            }
            let mut names = Vec::with_capacity(clips.len());
            let mut kept = Vec::with_capacity(clips.len());
            for (clip, stored) in clips {
                info!(
                    rig = name,
                    clip = clip.name(),
                    seconds = clip.duration(),
                    "restored recording"
                );
                self.owners().add(stored.owner.as_deref(), stored.bytes);
                self.add_upload_bytes(stored.bytes);
                names.push((clip.name().to_owned(), stored));
                kept.push(clip);
            }
            if let Err(e) = world.add_clips(&name, kept) {
                warn!(rig = name, error = %e, "stored recordings not loaded");
                continue;
            }
            let mut recordings = self.recordings();
            for (clip, stored) in names {
                recordings.insert((name.clone(), clip), stored);
            }
        }
    }
}

/// What [`read_recording`] made of one file.
type Read = Result<(Clip, StoredRecording), Unusable>;

/// [`read_recording`] of every file, in order, on as many threads as the machine has cores
/// (at most one per file): decoding is the bulk of a restart with a full quota, and each file
/// decodes on its own.
fn read_all(rig: &Rig, files: &[PathBuf]) -> Vec<Read> {
    let threads = std::thread::available_parallelism()
        .map_or(1, std::num::NonZeroUsize::get)
        .min(files.len());
    if threads <= 1 {
        return files.iter().map(|f| read_recording(rig, f)).collect();
    }
    // Each thread takes the next file not yet taken (sizes vary: a 64 MiB take beside 220 kB
    // ones), and the results are put back in the files' order.
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut read: Vec<(usize, Read)> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(file) = files.get(i) else {
                            return out;
                        };
                        out.push((i, read_recording(rig, file)));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|w| {
                w.join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
            })
            .collect()
    });
    read.sort_unstable_by_key(|(i, _)| *i);
    read.into_iter().map(|(_, r)| r).collect()
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
/// in the same order, and the clip named as the file (decoded), with its size and owner.
fn read_recording(rig: &Rig, path: &Path) -> Result<(Clip, StoredRecording), Unusable> {
    let file = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let stem = path
        .file_stem()
        .and_then(|n| n.to_str())
        .unwrap_or_default();
    let name = decode_name(stem)
        .ok_or_else(|| Unusable::Content(format!("{file}: not an encoded clip name")))?;
    let bytes = std::fs::read(path).map_err(|source| Unusable::Read {
        file: file.clone(),
        source,
    })?;
    let owner = read_meta(&path.with_extension("json"), &name)?;
    let clip = recording_from_bytes(rig, &name, &bytes)?;
    Ok((
        clip,
        StoredRecording {
            bytes: bytes.len() as u64,
            owner,
        },
    ))
}

/// The owner a recording's `.json` names (none when there is no such file: written by an
/// older version, or a crash came between the `.glb` and it).
fn read_meta(path: &Path, clip: &str) -> Result<Option<String>, Unusable> {
    let file = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(Unusable::Read { file, source }),
    };
    let meta: RecordingMeta = serde_json::from_slice(&bytes).map_err(|source| Unusable::Json {
        file: file.clone(),
        source,
    })?;
    if meta.format != RECORDING_FORMAT {
        return Err(Unusable::Format {
            file,
            found: Some(u64::from(meta.format)),
            expected: RECORDING_FORMAT,
        });
    }
    if meta.clip != clip {
        return Err(Unusable::Misnamed {
            file,
            found: meta.clip,
            expected: clip.to_owned(),
        });
    }
    Ok(meta.owner)
}

/// Recorded clip `stem` of `rig` from a recording file's bytes: the same joints in the same
/// order as the rig, and a clip named `stem`.
///
/// # Errors
/// Not a glTF binary, no skin, not the rig's joints, or no clip of that name.
pub fn recording_from_bytes(rig: &Rig, stem: &str, bytes: &[u8]) -> Result<Clip, Unusable> {
    let file = format!("{}.glb", encode_name(stem));
    let asset = posecast_rigs::import::gltf::skeletons_and_clips(&file, bytes)
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
