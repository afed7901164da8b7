//! Uploaded assets on disk: `assets/<name>/` holds the files as uploaded and a `meta.json`
//! naming which of them make the asset. `meta.json` is written last, so it is the commit
//! point: a new asset folder appears by one rename of a complete temporary folder, and clip
//! files added later count only once the rewritten `meta.json` lists them.

use super::atomic::{self, sync_dir};
use super::{Store, UPLOAD_TMP_PREFIX, Unusable, set_aside};
use crate::scene::unix_micros;
use crate::world::World;
use posecast_rigs::import::files::FileSet;
use posecast_rigs::rig::PipelineOptions;
use serde::{Deserialize, Serialize};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use tracing::{info, warn};

/// Version of `meta.json`.
pub const ASSET_FORMAT: u32 = 1;
/// The meta file's name inside an asset folder.
pub const META: &str = "meta.json";

/// `assets/<name>/meta.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AssetMeta {
    /// [`ASSET_FORMAT`].
    pub format: u32,
    /// The upload's name (equals the folder's).
    pub name: String,
    /// The files that make the asset, in the folder.
    pub files: Vec<String>,
    /// The rigs it gave when stored (several for a multi-skin glTF).
    pub rigs: Vec<String>,
    /// When it was last written, µs since the Unix epoch.
    pub saved_us: u64,
    /// The pipeline options it is normalised with (given with the upload or by
    /// `configure_asset`); absent: the defaults.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub options: Option<PipelineOptions>,
    /// The name of the token that uploaded it (whose quota it counts against); absent: the
    /// server's own, or written by an older version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub owner: Option<String>,
}

impl AssetMeta {
    /// The meta of `set` uploaded as `name`, giving `rigs`.
    #[must_use]
    pub fn new(name: &str, set: &FileSet, rigs: Vec<String>) -> Self {
        Self {
            format: ASSET_FORMAT,
            name: name.to_owned(),
            files: set.iter().map(|(n, _)| n.to_owned()).collect(),
            rigs,
            saved_us: unix_micros(),
            options: None,
            owner: None,
        }
    }

    /// The same meta owned by `owner`.
    #[must_use]
    pub fn with_owner(mut self, owner: Option<&str>) -> Self {
        self.owner = owner.map(str::to_owned);
        self
    }

    /// The same meta with `options` (none when they are the defaults).
    #[must_use]
    pub fn with_options(mut self, options: &PipelineOptions) -> Self {
        self.options = (*options != PipelineOptions::default()).then(|| options.clone());
        self
    }

    fn bytes(&self) -> io::Result<Vec<u8>> {
        serde_json::to_vec_pretty(self).map_err(io::Error::other)
    }
}

fn write_synced(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

/// Stores a new asset durably: every file and the meta into a temporary folder under
/// `assets/`, fsynced, then renamed to `assets/<name>` and `assets/` fsynced. On error the
/// temporary folder is removed and `assets/` is as before.
///
/// # Errors
/// Any I/O error, or [`io::ErrorKind::AlreadyExists`] when `assets/<name>` exists.
pub fn save_new(assets: &Path, set: &FileSet, meta: &AssetMeta) -> io::Result<()> {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let target = assets.join(&meta.name);
    if target.exists() {
        return Err(io::Error::new(
            io::ErrorKind::AlreadyExists,
            format!("{} exists", target.display()),
        ));
    }
    let tmp = assets.join(format!(
        "{UPLOAD_TMP_PREFIX}{}-{}-{}",
        meta.name,
        std::process::id(),
        SEQ.fetch_add(1, Ordering::Relaxed)
    ));
    let result = (|| {
        std::fs::create_dir(&tmp)?;
        for (name, bytes) in set.iter() {
            write_synced(&tmp.join(name), bytes)?;
        }
        write_synced(&tmp.join(META), &meta.bytes()?)?;
        sync_dir(&tmp)?;
        std::fs::rename(&tmp, &target)?;
        sync_dir(assets)
    })();
    if result.is_err() && tmp.exists() {
        // Best effort: a leftover is also removed at the next start.
        if let Err(e) = std::fs::remove_dir_all(&tmp) {
            warn!(dir = %tmp.display(), error = %e, "cannot remove a failed upload's folder");
        }
    }
    result
}

/// Deletes stored asset `name` durably: its folder is renamed to a temporary name (one
/// atomic step, fsynced: after a crash the asset is either there or gone, and a leftover
/// temporary folder is removed at the next start), then removed.
///
/// # Errors
/// Any I/O error but "not found"; the asset is then still there.
pub fn delete(assets: &Path, name: &str) -> io::Result<()> {
    static SEQ: AtomicU64 = AtomicU64::new(0);
    let dir = assets.join(name);
    if !dir.exists() {
        return Ok(());
    }
    let tmp = assets.join(format!(
        "{UPLOAD_TMP_PREFIX}deleted-{name}-{}-{}",
        std::process::id(),
        SEQ.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::rename(&dir, &tmp)?;
    sync_dir(assets)?;
    if let Err(e) = std::fs::remove_dir_all(&tmp) {
        warn!(dir = %tmp.display(), error = %e, "cannot remove a deleted asset's folder (removed at the next start)");
    }
    Ok(())
}

/// Adds files to a stored asset: each written atomically, then the new `meta.json` (which
/// lists them) atomically. A crash before the meta leaves unlisted files that are ignored.
///
/// # Errors
/// Any I/O error.
pub fn add_files(dir: &Path, new: &FileSet, meta: &AssetMeta) -> io::Result<()> {
    for (name, bytes) in new.iter() {
        atomic::write_atomic(&dir.join(name), bytes)?;
    }
    atomic::write_atomic(&dir.join(META), &meta.bytes()?)
}

/// Reads a stored asset folder: its meta and the files it lists.
pub(crate) fn read_asset(dir: &Path) -> Result<(AssetMeta, FileSet), Unusable> {
    let name = dir
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let read = |file: &str| {
        std::fs::read(dir.join(file)).map_err(|source| Unusable::Read {
            file: file.to_owned(),
            source,
        })
    };
    let json = |source| Unusable::Json {
        file: META.to_owned(),
        source,
    };
    let value: serde_json::Value = serde_json::from_slice(&read(META)?).map_err(json)?;
    let format = value.get("format").and_then(serde_json::Value::as_u64);
    if format != Some(u64::from(ASSET_FORMAT)) {
        return Err(Unusable::Format {
            file: META.to_owned(),
            found: format,
            expected: ASSET_FORMAT,
        });
    }
    let meta: AssetMeta = serde_json::from_value(value).map_err(json)?;
    if meta.name != name {
        return Err(Unusable::Misnamed {
            file: META.to_owned(),
            found: meta.name,
            expected: name,
        });
    }
    let mut set = FileSet::new();
    for file in &meta.files {
        set.insert(file, read(file)?)
            .map_err(|e| Unusable::Content(e.to_string()))?;
    }
    Ok((meta, set))
}

impl Store {
    /// The stored uploads' folders, in name order (temporary and set-aside ones left out).
    /// Only lists: nothing is read, so start-up can count them before it listens.
    #[must_use]
    pub fn stored_uploads(&self) -> Vec<PathBuf> {
        let Some(dir) = self.assets_dir() else {
            return Vec::new();
        };
        let mut dirs: Vec<_> = match std::fs::read_dir(&dir) {
            Ok(entries) => entries
                .filter_map(Result::ok)
                .filter(|e| e.path().is_dir())
                .map(|e| e.path())
                .collect(),
            Err(e) => {
                warn!(dir = %dir.display(), error = %e, "cannot read the assets folder");
                return Vec::new();
            }
        };
        dirs.retain(|d| {
            let n = d
                .file_name()
                .map(|n| n.to_string_lossy())
                .unwrap_or_default();
            !n.starts_with('.') && !n.contains(".corrupt")
        });
        dirs.sort();
        dirs
    }

    /// Loads one stored upload (a folder from [`Store::stored_uploads`]) into the library (see
    /// the module doc of [`super`] for what is skipped and moved aside). Its files are read,
    /// imported and dropped: the store remembers the upload, not its bytes.
    pub fn restore_upload(&self, world: &World, dir: &Path) {
        let loaded = read_asset(dir).and_then(|(meta, set)| {
            let options = meta.options.clone().unwrap_or_default();
            let rigs = posecast_rigs::library::prepare_with(&meta.name, &set, &options)
                .map_err(|e| Unusable::Content(e.to_string()))?;
            Ok((meta, set, rigs))
        });
        match loaded {
            Ok((meta, set, rigs)) => {
                if let Some(r) = rigs.iter().find(|r| world.library.get(&r.name).is_some()) {
                    warn!(asset = %meta.name, rig = %r.name, "stored upload not loaded: a rig of that name is already loaded (from --assets?)");
                    return;
                }
                for rig in rigs {
                    info!(asset = %rig.name, joints = rig.skeleton().len(), "restored upload");
                    world.library.insert(rig);
                }
                let bytes = set.total_bytes() as u64;
                self.add_upload_bytes(bytes);
                self.owners().add(meta.owner.as_deref(), bytes);
                let options = meta.options.clone().unwrap_or_default();
                self.remember_upload(&meta.name, set, options);
                self.set_upload_owner(&meta.name, meta.owner.as_deref(), bytes);
            }
            Err(reason) => set_aside(dir, &reason.to_string()),
        }
    }

    /// The files of stored upload `name`, read again from `assets/<name>/` (what its
    /// `meta.json` lists). Blocking: call it off the async workers.
    ///
    /// # Errors
    /// No data folder, or the folder cannot be read (the reason, naming the file).
    pub fn read_upload(&self, name: &str) -> Result<FileSet, Unusable> {
        let dir = self.assets_dir().ok_or(Unusable::NoDataFolder)?;
        read_asset(&dir.join(name)).map(|(_, set)| set)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn save_new_is_all_or_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut set = FileSet::new();
        set.insert("a.bvh", b"HIERARCHY".to_vec()).unwrap();
        let meta = AssetMeta::new("a", &set, vec!["a".into()]);
        save_new(dir.path(), &set, &meta).unwrap();
        let (back, files) = read_asset(&dir.path().join("a")).unwrap();
        assert_eq!(back, meta);
        assert_eq!(files.get("a.bvh").unwrap(), b"HIERARCHY");
        // A second one with the same name fails and leaves nothing behind.
        let e = save_new(dir.path(), &set, &meta).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }
}
