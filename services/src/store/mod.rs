//! Persistence: scenes and uploaded assets survive a restart, and a mutating command is
//! acknowledged only once its change is on disk.
//!
//! # Layout of the data folder (`--data DIR`, default `./posecast-data`)
//!
//! ```text
//! DIR/posecast.json          {"format": 1}: written once the folder is initialised
//! DIR/posecast.lock          held (flock) by the server using the folder: a second one refuses
//! DIR/scenes/<scene>.json    one file per scene (see snapshot::SceneFile)
//! DIR/assets/<name>/         an uploaded asset: its original files as uploaded …
//! DIR/assets/<name>/meta.json  … and which of them make the asset (see assets::AssetMeta)
//! DIR/recordings/<rig>/<clip>.glb  a recorded clip: the rig's skin and the clip (`recordings`)
//! ```
//!
//! A scene file holds the scene id, the time it was written (µs since the Unix epoch) and per
//! avatar: id, asset, the clip playing (name, `from_asset`, clip time, speed, looping,
//! paused) and its joint overrides by joint name as quaternions. On restore a playing clock is
//! moved on by the time the server was down, so it shows what it would show had it kept
//! running. Every file carries a `format` version.
//!
//! # Durability
//!
//! Every file is written to `x.tmp`, `sync_all`ed, renamed over `x`, and the folder is fsynced
//! (`atomic`). A mutating command goes through [`crate::control::execute_durable`]: the
//! change is made in memory, then under the store's lock the scene is snapshotted and written,
//! and only then acknowledged. Because the snapshot is taken after the change and under the
//! lock, a later write always contains every earlier acknowledged change (no lost updates when
//! two connections change one scene at once). The write runs on the blocking pool, never on a
//! tokio worker. When the write fails the command answers `internal`, **but the in-memory
//! change stays**: the server keeps running as commanded and the next successful write of that
//! scene stores it.
//!
//! # Restore at start
//!
//! In the background once the server listens (`restore`): built-in rig and
//! `--assets` folders first, then uploaded assets, then recorded clips, then scenes. On the first
//! start with a new folder the built-in `default` scene is created and stored; later, what is
//! stored wins (a deleted `default` stays deleted). A file that cannot be read (truncated,
//! not JSON, unknown format version, an asset that no longer imports) is logged with
//! `tracing::warn!`, moved aside to `<file>.corrupt` and skipped; the rest still loads. An
//! avatar whose asset is gone, or a clip or joint its rig no longer has, is skipped alone.
//! Scene and avatar *numbers* (in binary frames) are not stored; ids are.
//!
//! Uploads are read, imported and dropped: memory holds their rigs, not their files
//! (`store::Upload`); adding clips reads the files again from `assets/<name>/`.

pub(crate) mod assets;
pub(crate) mod atomic;
#[cfg(test)]
mod names_tests;
pub mod owners;
pub mod recordings;
pub mod snapshot;

use crate::scene::unix_micros;
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::msg::SceneId;
use posecast_rigs::import::files::FileSet;
use std::collections::{BTreeMap, BTreeSet};
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};
use tracing::{info, warn};

/// Version of the data folder layout (in `posecast.json`).
pub const DATA_FORMAT: u32 = 1;

/// The lock file a running server holds in its data folder (see [`Store::open`]).
pub const LOCK_FILE: &str = "posecast.lock";

const MARKER: &str = "posecast.json";
/// Temporary upload folders under `assets/` start with this (never a valid asset name).
pub(crate) const UPLOAD_TMP_PREFIX: &str = ".upload-";

/// The data folder, or nothing (in-memory only), and the lock that orders writes to it.
#[derive(Debug)]
pub struct Store {
    root: Option<PathBuf>,
    /// The data folder's lock file, held (an advisory exclusive lock) while this server runs:
    /// a second server on the same folder refuses to start ([`Store::open`]).
    held: std::sync::Mutex<Option<std::fs::File>>,
    lock: std::sync::Arc<tokio::sync::Mutex<()>>,
    assets_lock: tokio::sync::Mutex<()>,
    /// Scenes whose acks wait for the next write (group commit, see [`Store::persist_scene`]).
    open_batch: std::sync::Mutex<Batch>,
    batches_written: std::sync::atomic::AtomicU64,
    /// Bytes of every uploaded asset's files (the `upload_total_bytes` quota).
    upload_bytes: std::sync::atomic::AtomicU64,
    /// Every uploaded asset by name: what is needed to add clips to it later, never its
    /// files when they are on disk.
    uploads: std::sync::Mutex<BTreeMap<String, Upload>>,
    /// Stored recordings by (rig, clip): their size and owner (for quotas and `delete_clip`).
    recordings: std::sync::Mutex<BTreeMap<(String, String), recordings::StoredRecording>>,
    /// What each token holds ([`owners::Owners`]).
    owners: std::sync::Mutex<owners::Owners>,
}

/// What the store keeps in memory of an uploaded asset. With a data folder that is no bytes:
/// adding clips re-reads the files from `assets/<name>/` ([`Store::read_upload`]), so a
/// server with gigabytes of uploads holds only their rigs. Without one (`--no-persist`)
/// memory is the only copy, so a `.skel` upload — the one kind clips are added to — keeps its
/// files; other uploads keep none.
#[derive(Debug, Clone)]
pub(crate) struct Upload {
    /// The file that gives the upload's format (`""` if the set had none).
    pub main: String,
    /// The files, only without a data folder and only for a `.skel`.
    pub files: Option<FileSet>,
    /// The pipeline options its rigs were normalised with.
    pub options: posecast_rigs::rig::PipelineOptions,
    /// The token that uploaded it (its `meta.json`'s `owner`).
    pub owner: Option<String>,
    /// Bytes of its files, as counted in the quotas.
    pub bytes: u64,
}

/// Acks waiting for one scene write: the scenes to write and where the result goes.
#[derive(Debug)]
struct Batch {
    scenes: BTreeSet<SceneId>,
    done: tokio::sync::watch::Sender<Option<Result<(), Error>>>,
}

impl Default for Batch {
    fn default() -> Self {
        Self {
            scenes: BTreeSet::new(),
            done: tokio::sync::watch::Sender::new(None),
        }
    }
}

/// Why a stored file or folder cannot be used: it is then moved aside (`set_aside`) and the
/// rest of the data folder still loads.
#[derive(Debug, thiserror::Error)]
pub enum Unusable {
    /// A file could not be read.
    #[error("{file}: {source}")]
    Read {
        /// The file, relative to what is being read.
        file: String,
        /// Why.
        source: io::Error,
    },
    /// A file is not the JSON it should be.
    #[error("{file}: {source}")]
    Json {
        /// The file.
        file: String,
        /// Why.
        source: serde_json::Error,
    },
    /// Written by another version of posecast.
    #[error("{file}: format {found:?} is not {expected} (written by another version?)")]
    Format {
        /// The file.
        file: String,
        /// Its `format` field.
        found: Option<u64>,
        /// The format this version reads.
        expected: u32,
    },
    /// The file names another scene or asset than its own file or folder name.
    #[error("{file} names {found:?}, not {expected:?}")]
    Misnamed {
        /// The file.
        file: String,
        /// The name inside.
        found: String,
        /// The name of the file or folder.
        expected: String,
    },
    /// The content is wrong (a field, an import, a restore): the reason.
    #[error("{0}")]
    Content(String),
    /// There is no data folder to read from.
    #[error("no data folder to read it from")]
    NoDataFolder,
}

fn internal(what: &str, e: &io::Error) -> Error {
    Error::Internal(format!(
        "{what}: {e} (the change is in effect but not stored)"
    ))
}

impl Store {
    /// A store over `root` (None: in-memory only, every write is a no-op).
    #[must_use]
    pub fn new(root: Option<PathBuf>) -> Self {
        Self {
            root,
            held: std::sync::Mutex::new(None),
            lock: std::sync::Arc::new(tokio::sync::Mutex::new(())),
            assets_lock: tokio::sync::Mutex::new(()),
            open_batch: std::sync::Mutex::new(Batch::default()),
            batches_written: std::sync::atomic::AtomicU64::new(0),
            upload_bytes: std::sync::atomic::AtomicU64::new(0),
            uploads: std::sync::Mutex::new(BTreeMap::new()),
            recordings: std::sync::Mutex::new(BTreeMap::new()),
            owners: std::sync::Mutex::new(owners::Owners::default()),
        }
    }

    /// The data folder.
    #[must_use]
    pub fn root(&self) -> Option<&Path> {
        self.root.as_deref()
    }

    /// `DIR/scenes`.
    #[must_use]
    pub fn scenes_dir(&self) -> Option<PathBuf> {
        self.root.as_ref().map(|r| r.join("scenes"))
    }

    /// `DIR/assets`.
    #[must_use]
    pub fn assets_dir(&self) -> Option<PathBuf> {
        self.root.as_ref().map(|r| r.join("assets"))
    }

    /// Serialises writes of scene files: every durable ack waits here, so nothing slow may
    /// hold it (uploads use [`Store::assets_lock`]).
    pub async fn lock(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.lock.lock().await
    }

    /// Serialises changes to uploaded assets (name checks, re-imports, their files). Separate
    /// from [`Store::lock`] so a CPU-heavy re-import never delays a durable ack.
    pub async fn assets_lock(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.assets_lock.lock().await
    }

    pub(crate) fn uploads(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Upload>> {
        self.uploads
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The stored recordings by (rig, clip).
    pub(crate) fn recordings(
        &self,
    ) -> std::sync::MutexGuard<'_, BTreeMap<(String, String), recordings::StoredRecording>> {
        self.recordings
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// What each token holds.
    pub(crate) fn owners(&self) -> std::sync::MutexGuard<'_, owners::Owners> {
        self.owners
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Records upload `name` made of `set` (see [`Upload`] for what is kept of it).
    pub(crate) fn remember_upload(
        &self,
        name: &str,
        set: FileSet,
        options: posecast_rigs::rig::PipelineOptions,
    ) {
        let main = set.main_file().map(str::to_owned).unwrap_or_default();
        let keep = self.root.is_none() && posecast_rigs::import::files::extension(&main) == "skel";
        let bytes = set.total_bytes() as u64;
        let mut uploads = self.uploads();
        // Adding clips or options keeps who uploaded it.
        let owner = uploads.get(name).and_then(|u| u.owner.clone());
        let upload = Upload {
            main,
            files: keep.then_some(set),
            options,
            owner,
            bytes,
        };
        uploads.insert(name.to_owned(), upload);
    }

    /// Notes who uploaded `name` (and its bytes).
    pub(crate) fn set_upload_owner(&self, name: &str, owner: Option<&str>, bytes: u64) {
        if let Some(u) = self.uploads().get_mut(name) {
            u.owner = owner.map(str::to_owned);
            u.bytes = bytes;
        }
    }

    /// Who uploaded `name`.
    pub(crate) fn upload_owner(&self, name: &str) -> Option<String> {
        self.uploads().get(name).and_then(|u| u.owner.clone())
    }

    /// Who uploaded `name` and its bytes; `None` when it is no upload.
    pub(crate) fn upload_owner_and_bytes(&self, name: &str) -> Option<(Option<String>, u64)> {
        self.uploads().get(name).map(|u| (u.owner.clone(), u.bytes))
    }

    /// Forgets upload `name` (deleted) and frees its bytes.
    pub(crate) fn forget_upload(&self, name: &str, owner: Option<&str>, bytes: u64) {
        if self.uploads().remove(name).is_some() {
            self.sub_upload_bytes(bytes);
            self.owners().remove(owner, bytes);
        }
    }

    /// Creates the folders, removes temporary files a crash left behind (never acknowledged),
    /// and tells whether this is the first start (no `posecast.json` yet). Without a data
    /// folder every start is a first start.
    ///
    /// # Errors
    /// The folders cannot be created or read.
    pub fn open(&self) -> io::Result<bool> {
        let Some(root) = &self.root else {
            return Ok(true);
        };
        std::fs::create_dir_all(root)?;
        self.take_lock(root)?;
        for dir in [root.join("scenes"), root.join("assets")] {
            std::fs::create_dir_all(&dir)?;
        }
        for entry in std::fs::read_dir(root.join("scenes"))?.filter_map(Result::ok) {
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "tmp") {
                std::fs::remove_file(&path)?;
            }
        }
        for entry in std::fs::read_dir(root.join("assets"))?.filter_map(Result::ok) {
            if entry
                .file_name()
                .to_string_lossy()
                .starts_with(UPLOAD_TMP_PREFIX)
            {
                std::fs::remove_dir_all(entry.path())?;
            }
        }
        Ok(!root.join(MARKER).is_file())
    }

    /// Takes the folder's lock file (`DIR/posecast.lock`) before anything in the folder is
    /// touched: two servers writing one folder would overwrite each other's scenes. The lock
    /// is the kernel's (`flock`), so it goes with the process however it ends — no stale
    /// lock after a crash. The file holds the holder's process id, for people.
    fn take_lock(&self, root: &Path) -> io::Result<()> {
        let path = root.join(LOCK_FILE);
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                return Err(io::Error::new(
                    io::ErrorKind::ResourceBusy,
                    format!(
                        "another posecast server{} uses this data folder (it holds {})",
                        if holder.is_empty() {
                            String::new()
                        } else {
                            format!(" (process {holder})")
                        },
                        path.display()
                    ),
                ));
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(e),
        }
        file.set_len(0)?;
        (&file).write_all(format!("{}\n", std::process::id()).as_bytes())?;
        *self
            .held
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(file);
        Ok(())
    }

    /// Gives the data folder's lock back (the server stopped; a process that exits gives it
    /// back anyway).
    pub fn release(&self) {
        self.held
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
    }

    /// Records that the folder is initialised (after the first start stored its scenes).
    ///
    /// # Errors
    /// The write failed.
    pub fn mark_initialised(&self) -> io::Result<()> {
        match &self.root {
            Some(root) => atomic::write_atomic(
                &root.join(MARKER),
                format!("{{\"format\": {DATA_FORMAT}}}\n").as_bytes(),
            ),
            None => Ok(()),
        }
    }

    fn scene_path(&self, id: &SceneId) -> Option<PathBuf> {
        self.scenes_dir().map(|d| d.join(format!("{}.json", id.0)))
    }

    /// What to do to make scene `id`'s file match memory: its snapshot, or `None` to delete.
    fn scene_bytes(world: &World, id: &SceneId) -> io::Result<Option<Vec<u8>>> {
        match world.scene(id) {
            // Replays are not stored: a restart ends them.
            Ok(scene) if scene.lock().replay.is_some() => Ok(None),
            Ok(scene) => {
                let file = snapshot::snapshot(&scene, unix_micros());
                serde_json::to_vec_pretty(&file)
                    .map(Some)
                    .map_err(io::Error::other)
            }
            Err(_) => Ok(None),
        }
    }

    fn write_scene(path: &Path, bytes: Option<&[u8]>) -> io::Result<()> {
        match bytes {
            Some(b) => atomic::write_atomic(path, b),
            None => atomic::remove_durable(path),
        }
    }

    /// Makes scene `id`'s file match memory (written, or removed when the scene is gone) and
    /// returns once that is on disk. The snapshot is taken under the store lock, after the
    /// caller's change.
    ///
    /// **Group commit**: the scene joins the open batch; whoever takes the store lock first
    /// writes the whole batch (every scene in it, each once, one folder fsync) and every
    /// member of the batch gets that write's result. Acks that arrive while a write is in
    /// progress share the next write instead of queueing one fsync each.
    ///
    /// # Errors
    /// `internal` when the write fails (the in-memory state is unchanged by this).
    pub async fn persist_scene(&self, world: &World, id: &SceneId) -> Result<(), Error> {
        let Some(dir) = self.scenes_dir() else {
            return Ok(());
        };
        let mut done = {
            let mut open = self.batch();
            open.scenes.insert(id.clone());
            open.done.subscribe()
        };
        // Owned: it moves into the write below, so the lock is held until the files are
        // written even if this caller is cancelled (a REST client that disconnects).
        let guard = self.lock.clone().lock_owned().await;
        // A writer that held the lock before us may have taken our batch already.
        if let Some(result) = done.borrow_and_update().clone() {
            return result;
        }
        let mut batch = std::mem::take(&mut *self.batch());
        batch.scenes.insert(id.clone());
        self.batches_written
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        // Snapshots now, under the lock and after every change of the batch.
        let mut files = Vec::with_capacity(batch.scenes.len());
        for scene in &batch.scenes {
            match Self::scene_bytes(world, scene) {
                Ok(bytes) => files.push((dir.join(format!("{}.json", scene.0)), bytes)),
                Err(e) => {
                    let e = internal("cannot store the scene", &e);
                    batch.done.send(Some(Err(e.clone()))).ok();
                    return Err(e);
                }
            }
        }
        // The write, its answer to the whole batch and the lock's release happen together on
        // the blocking pool: nothing in between can be cancelled, so no second writer ever
        // writes the same files at once and every member of the batch hears the result.
        let done = batch.done;
        tokio::task::spawn_blocking(move || {
            let _guard = guard;
            let result = atomic::write_many_atomic(&dir, &files)
                .map_err(|e| internal("cannot store the scene", &e));
            // Receivers may all be gone (their commands were cancelled): nothing to tell then.
            done.send(Some(result.clone())).ok();
            result
        })
        .await
        .map_err(|e| internal("cannot store the scene", &io::Error::other(e)))?
    }

    fn batch(&self) -> std::sync::MutexGuard<'_, Batch> {
        self.open_batch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Bytes of every uploaded asset's files.
    #[must_use]
    pub fn upload_bytes(&self) -> u64 {
        self.upload_bytes.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Counts `n` more bytes of uploaded files.
    pub(crate) fn add_upload_bytes(&self, n: u64) {
        self.upload_bytes
            .fetch_add(n, std::sync::atomic::Ordering::Relaxed);
    }

    /// Counts `n` bytes less (a deleted upload or recording).
    pub(crate) fn sub_upload_bytes(&self, n: u64) {
        // Never below 0: a concurrent add always came with its own bytes.
        self.upload_bytes
            .fetch_update(
                std::sync::atomic::Ordering::Relaxed,
                std::sync::atomic::Ordering::Relaxed,
                |v| Some(v.saturating_sub(n)),
            )
            .ok();
    }

    /// Scene writes so far (each a group commit of one or more acks).
    #[must_use]
    pub fn batches_written(&self) -> u64 {
        self.batches_written
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// [`Store::persist_scene`] for start-up, before the server serves anyone.
    ///
    /// # Errors
    /// The write failed.
    pub fn persist_scene_now(&self, world: &World, id: &SceneId) -> io::Result<()> {
        match self.scene_path(id) {
            Some(path) => Self::write_scene(&path, Self::scene_bytes(world, id)?.as_deref()),
            None => Ok(()),
        }
    }

    /// Recreates every stored scene (see the module doc for what is skipped).
    pub fn restore_scenes(&self, world: &World) {
        let Some(dir) = self.scenes_dir() else { return };
        let mut paths: Vec<PathBuf> = match std::fs::read_dir(&dir) {
            Ok(entries) => entries.filter_map(Result::ok).map(|e| e.path()).collect(),
            Err(e) => {
                warn!(dir = %dir.display(), error = %e, "cannot read the scenes folder");
                return;
            }
        };
        paths.retain(|p| p.extension().is_some_and(|e| e == "json"));
        paths.sort();
        let now = unix_micros();
        for path in paths {
            match read_scene_file(&path).and_then(|file| {
                snapshot::restore(world, &file, now)
                    .map_err(|e| Unusable::Content(e.to_string()))?;
                Ok(file)
            }) {
                Ok(file) => {
                    info!(scene = %file.scene, avatars = file.avatars.len(), "scene restored")
                }
                Err(reason) => set_aside(&path, &reason.to_string()),
            }
        }
    }
}

fn read_scene_file(path: &Path) -> Result<snapshot::SceneFile, Unusable> {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default()
        .to_owned();
    let bytes = std::fs::read(path).map_err(|source| Unusable::Read {
        file: name.clone(),
        source,
    })?;
    let value: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|source| Unusable::Json {
            file: name.clone(),
            source,
        })?;
    let format = value.get("format").and_then(serde_json::Value::as_u64);
    if format != Some(u64::from(snapshot::SCENE_FORMAT)) {
        return Err(Unusable::Format {
            file: name,
            found: format,
            expected: snapshot::SCENE_FORMAT,
        });
    }
    let (file, dropped) = snapshot::parse_lenient(&value).map_err(Unusable::Content)?;
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    if file.scene.0 != stem {
        return Err(Unusable::Misnamed {
            file: name,
            found: file.scene.0,
            expected: stem.to_owned(),
        });
    }
    for what in dropped {
        warn!(file = %path.display(), scene = %file.scene, "not restored: {what}");
    }
    Ok(file)
}

/// Logs why a stored file or folder is unusable and moves it aside to `<path>.corrupt`.
pub(crate) fn set_aside(path: &Path, reason: &str) {
    match atomic::move_aside(path) {
        Ok(to) => {
            warn!(file = %path.display(), reason, moved_to = %to.display(), "skipped a stored file that cannot be used")
        }
        Err(e) => {
            warn!(file = %path.display(), reason, error = %e, "skipped a stored file that cannot be used (and could not move it aside)")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::execute_durable;
    use crate::state::Services;
    use posecast_proto::command::Command;

    /// A state storing into `dir`, with the built-in rig.
    fn state_on(dir: &Path) -> std::sync::Arc<Services> {
        let state = Services::new(Config {
            data_dir: Some(dir.to_owned()),
            ..Config::default()
        });
        state.store.open().unwrap();
        state
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        state
    }

    /// One bad value (the `null` quaternion an older server stored) costs that value alone,
    /// never the scene: the file stays in place and everything valid in it is restored.
    #[tokio::test]
    async fn restore_keeps_a_scene_with_bad_values() {
        let dir = tempfile::tempdir().unwrap();
        let state = state_on(dir.path());
        let file = serde_json::json!({
            "format": 1, "scene": "s", "saved_us": 0,
            "avatars": [
                {"id": "a", "asset": "avatar",
                 "playback": {"clip": "idle", "from_asset": null, "time": null, "speed": 1.0, "looping": true, "paused": false},
                 "overrides": {"l_knee": [null, null, null, null], "r_knee": [0.0, 0.0, 0.0, 1.0],
                               "l_elbow": [0.0, 0.0, 0.0, 0.0]}},
                {"asset": "avatar"},
                {"id": "b", "asset": "avatar", "playback": null, "overrides": {}}
            ]
        });
        let path = dir.path().join("scenes/s.json");
        std::fs::write(&path, serde_json::to_vec(&file).unwrap()).unwrap();
        let (_, dropped) = snapshot::parse_lenient(&file).unwrap();
        assert_eq!(dropped.len(), 4, "{dropped:?}");
        for name in [
            "joint l_knee",
            "joint l_elbow",
            "avatar a: playback",
            "avatar #1",
        ] {
            assert!(
                dropped.iter().any(|d| d.contains(name)),
                "{name}: {dropped:?}"
            );
        }
        state.store.restore_scenes(&state.world);
        assert!(path.is_file(), "the scene file was set aside");
        let info = state.world.scene(&SceneId("s".into())).unwrap().info();
        let ids: Vec<&str> = info.avatars.iter().map(|a| a.avatar.0.as_str()).collect();
        assert_eq!(ids, ["a", "b"]);
        assert_eq!(info.avatars[0].overrides, vec!["r_knee".to_string()]);
        assert_eq!(info.avatars[0].clip, None);
    }

    /// A long asset change (an upload's re-import holds the assets lock) never delays a
    /// durable ack: scene writes take another lock.
    #[tokio::test]
    async fn acks_do_not_wait_for_asset_changes() {
        let dir = tempfile::tempdir().unwrap();
        let state = state_on(dir.path());
        let run = |json: &str| {
            let c: Command = serde_json::from_str(json).unwrap();
            let state = state.clone();
            async move { execute_durable(&state, &c).await }
        };
        run(r#"{"op":"create_scene","scene":"s"}"#).await.unwrap();
        let _upload_in_progress = state.store.assets_lock().await;
        let ack = tokio::time::timeout(
            std::time::Duration::from_secs(5),
            run(r#"{"op":"add_avatar","scene":"s","asset":"avatar","avatar":"a"}"#),
        )
        .await;
        assert!(
            matches!(ack, Ok(Ok(_))),
            "the ack waited for the asset lock"
        );
        assert!(dir.path().join("scenes/s.json").is_file());
    }

    /// Many connections changing one scene at once: after every ack, the stored file holds
    /// every acknowledged change (no write overtaken by an older snapshot).
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn concurrent_acks_are_all_in_the_stored_file() {
        let dir = tempfile::tempdir().unwrap();
        let state = state_on(dir.path());
        let run = |json: String| {
            let state = state.clone();
            async move {
                let c: Command = serde_json::from_str(&json).unwrap();
                execute_durable(&state, &c).await.unwrap();
            }
        };
        run(r#"{"op":"create_scene","scene":"s"}"#.into()).await;
        run(r#"{"op":"add_avatar","scene":"s","asset":"avatar","avatar":"a"}"#.into()).await;
        let joints: Vec<String> = state
            .world
            .library
            .get("avatar")
            .unwrap()
            .skeleton()
            .names()
            .to_vec();
        let tasks: Vec<_> = joints
            .iter()
            .map(|j| {
                tokio::spawn(run(format!(
                    r#"{{"op":"set_joint_rotation","avatar":"a","joint":"{j}","rotation":[0,0,0,1]}}"#
                )))
            })
            .collect();
        for t in tasks {
            t.await.unwrap();
        }
        let text = std::fs::read(dir.path().join("scenes/s.json")).unwrap();
        let file: snapshot::SceneFile = serde_json::from_slice(&text).unwrap();
        let stored: Vec<&String> = file.avatars[0].overrides.keys().collect();
        assert_eq!(stored.len(), joints.len(), "lost updates: {stored:?}");
        // Group commit: acks that arrived together shared writes (2 writes set the scene up).
        let writes = state.store.batches_written() - 2;
        assert!(
            writes < joints.len() as u64,
            "{writes} writes for {} acks",
            joints.len()
        );
    }

    /// Write before ack, deterministically (issue 35): while the store's write lock is held —
    /// a write that has not finished — a command is applied but not answered, and its scene
    /// file does not hold it yet; once the lock is released the command is answered, and the
    /// file holds the change by then.
    #[tokio::test]
    async fn the_ack_waits_for_the_write() {
        let dir = tempfile::tempdir().unwrap();
        let state = state_on(dir.path());
        let command = |json: &str| serde_json::from_str::<Command>(json).unwrap();
        execute_durable(&state, &command(r#"{"op":"create_scene","scene":"s"}"#))
            .await
            .unwrap();
        let path = dir.path().join("scenes/s.json");
        let stored =
            |path: &Path| std::fs::read_to_string(path).is_ok_and(|text| text.contains(r#""a""#));
        assert!(!stored(&path));

        let barrier = state.store.lock.clone().lock_owned().await;
        let ack = tokio::spawn({
            let state = state.clone();
            let add = command(r#"{"op":"add_avatar","scene":"s","asset":"avatar","avatar":"a"}"#);
            async move { execute_durable(&state, &add).await }
        });
        // One thread: the command runs only while this test yields, up to the write it waits
        // for.
        let avatar = posecast_proto::msg::AvatarId("a".into());
        while state.world.find_avatar(&avatar).is_err() {
            tokio::task::yield_now().await;
        }
        for _ in 0..100 {
            tokio::task::yield_now().await;
        }
        assert!(!ack.is_finished(), "answered before its write was done");
        assert!(!stored(&path), "written while the store was held");
        drop(barrier);
        ack.await.unwrap().unwrap();
        assert!(stored(&path), "answered, and not on disk");
    }
}
