//! Takes of whole scenes (`record_scene`, issue 32): where they are kept and how they are
//! written. The commands themselves are `control::takes`; the file format is
//! [`posecast_stream::take`]; a replay is [`crate::scene::replay`].
//!
//! - **Where**: `<data>/takes/<name>.take`, or memory on a server without a data folder (gone
//!   at exit, like everything else there).
//! - **Writing**: the scene's feed hands every frame it encoded for binary subscribers to a
//!   [`Sink`] under its lock; the sink only queues the bytes. A writer thread per take appends
//!   them as they come (a SIGKILL loses only what was still queued: records are whole or torn
//!   at the tail, which reading ignores) and syncs the file at least once a second (a power
//!   cut loses at most the last second). A queue past [`MAX_QUEUED_BYTES`] (the disk cannot
//!   keep up) or a failed write ends the take there, complete up to its last record.
//! - **Limits**: a take ends by itself after `max_seconds` of frames, or when its bytes would
//!   pass the data quota (`--max-upload-total-bytes`, which uploads and recordings share);
//!   its bytes count toward that quota from then until it is deleted.

pub mod export;

use posecast_core::error::Error;
use posecast_proto::command::{TakeDriver, TakeInfo};
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{AvatarId, SceneId, check_id};
use posecast_stream::feed::TakeSink;
use posecast_stream::take::{self, TakeHeader, TakeIndex};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, mpsc};
use std::time::{Duration, Instant};

use prometheus_client::metrics::counter::Counter;

/// Most bytes a take may have queued for its writer before it ends (the disk is not keeping
/// up with the scene).
pub const MAX_QUEUED_BYTES: u64 = 64 << 20;
/// How often a take being written is synced to disk, at least.
pub const SYNC_INTERVAL: Duration = Duration::from_secs(1);
/// The extension of take files.
const EXTENSION: &str = "take";
/// The extension of the file naming the cluster's copy a take file is.
const SHARED: &str = "shared";

/// Takes, stored and being recorded.
#[derive(Debug)]
pub struct Takes {
    /// `<data>/takes`, or `None`: takes live in memory.
    dir: Option<PathBuf>,
    inner: Mutex<Inner>,
    /// Bytes the takes hold (stored, in memory, being written): part of the data quota.
    held: Arc<AtomicU64>,
    /// Bytes written to takes, and takes that ended by themselves (`/metrics`).
    written: Counter,
    ended: Counter,
}

#[derive(Debug, Default)]
struct Inner {
    /// Takes kept in memory (no data folder), by name.
    memory: HashMap<String, Arc<Mutex<Vec<u8>>>>,
    /// Takes being recorded, by scene.
    recording: HashMap<SceneId, Active>,
    /// Each stored take's description and index, with the size it was read at.
    read: HashMap<String, (u64, Arc<TakeIndex>)>,
    /// On a server of a cluster: the takes kept here that are the cluster's copy (recorded
    /// here and shared, or fetched), by name → the object's id in the cluster's store
    /// (`<name>.shared` beside the take file holds it). A take not here was recorded here and
    /// is not shared yet.
    shared: HashMap<String, String>,
}

/// What a take being recorded has so far (shared by its sink and its writer).
#[derive(Debug, Default)]
struct Progress {
    frames: AtomicU64,
    first_seq: AtomicU64,
    last_seq: AtomicU64,
    /// Bytes handed to the writer (written or queued).
    bytes: AtomicU64,
    /// Bytes written.
    written: AtomicU64,
    /// Set when the take ended by itself (a limit, a failed write); why is in `why`.
    ended: AtomicBool,
    why: Mutex<Option<String>>,
    avatars: Mutex<Vec<AvatarId>>,
    /// Counts the take in `/metrics` when it ends by itself.
    ended_counter: Counter,
}

impl Progress {
    fn end(&self, why: String) {
        if !self.ended.swap(true, Ordering::SeqCst) {
            self.ended_counter.inc();
        }
        let mut w = self
            .why
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        w.get_or_insert(why);
    }
}

#[derive(Debug)]
struct Active {
    take: String,
    header: TakeHeader,
    progress: Arc<Progress>,
    writer: Option<std::thread::JoinHandle<()>>,
}

impl Active {
    /// Whether its writer still runs (the feed still holds its sink, or bytes are queued).
    fn writing(&self) -> bool {
        self.writer.as_ref().is_some_and(|w| !w.is_finished())
    }
}

/// How a take may grow.
#[derive(Debug, Clone, Copy)]
pub struct TakeLimits {
    /// Most frames (ticks).
    pub max_frames: u64,
    /// Most bytes.
    pub max_bytes: u64,
}

/// The sink a scene's feed records a take into ([`posecast_stream::feed::Feed::record`]).
#[derive(Debug)]
pub struct Sink {
    queue: mpsc::Sender<Vec<u8>>,
    progress: Arc<Progress>,
    limits: TakeLimits,
    held: Arc<AtomicU64>,
}

impl TakeSink for Sink {
    fn append(
        &mut self,
        records: Vec<u8>,
        seq: u64,
        avatars: Option<&[Arc<AvatarDescription>]>,
    ) -> bool {
        let p = &self.progress;
        if p.ended.load(Ordering::SeqCst) {
            return false;
        }
        let frames = p.frames.load(Ordering::Relaxed);
        if frames >= self.limits.max_frames {
            p.end(format!("its limit of {frames} frames was reached"));
            return false;
        }
        let n = records.len() as u64;
        let bytes = p.bytes.load(Ordering::Relaxed);
        if bytes + n > self.limits.max_bytes {
            p.end(format!(
                "the data quota was reached ({} bytes for this take)",
                self.limits.max_bytes
            ));
            return false;
        }
        if bytes.saturating_sub(p.written.load(Ordering::Relaxed)) + n > MAX_QUEUED_BYTES {
            p.end("the disk did not keep up with the scene".into());
            return false;
        }
        if frames == 0 {
            p.first_seq.store(seq, Ordering::Relaxed);
        }
        p.last_seq.store(seq, Ordering::Relaxed);
        if let Some(list) = avatars {
            let mut seen = p
                .avatars
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            for d in list {
                if !seen.contains(&d.id) {
                    seen.push(d.id.clone());
                }
            }
        }
        p.frames.fetch_add(1, Ordering::Relaxed);
        self.queue(records)
    }

    fn append_event(&mut self, record: Vec<u8>) -> bool {
        let p = &self.progress;
        if p.ended.load(Ordering::SeqCst) {
            return false;
        }
        if p.bytes.load(Ordering::Relaxed) + record.len() as u64 > self.limits.max_bytes {
            p.end(format!(
                "the data quota was reached ({} bytes for this take)",
                self.limits.max_bytes
            ));
            return false;
        }
        self.queue(record)
    }
}

impl Sink {
    /// Hands `records` to the writer, counting their bytes. Whether to go on.
    fn queue(&mut self, records: Vec<u8>) -> bool {
        let n = records.len() as u64;
        self.progress.bytes.fetch_add(n, Ordering::Relaxed);
        self.held.fetch_add(n, Ordering::Relaxed);
        if self.queue.send(records).is_err() {
            self.progress.end("its writer stopped".into());
            return false;
        }
        true
    }
}

/// Where a take's writer puts its bytes.
enum Target {
    File(std::fs::File),
    Memory(Arc<Mutex<Vec<u8>>>),
}

impl Target {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        match self {
            Self::File(f) => f.write_all(bytes),
            Self::Memory(m) => {
                m.lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .extend_from_slice(bytes);
                Ok(())
            }
        }
    }

    fn sync(&mut self) -> std::io::Result<()> {
        match self {
            Self::File(f) => f.sync_data(),
            Self::Memory(_) => Ok(()),
        }
    }
}

/// The writer thread: appends what the sink queues, syncs at least every
/// [`SYNC_INTERVAL`], and once more when the sink is dropped.
fn write(
    mut target: Target,
    queue: mpsc::Receiver<Vec<u8>>,
    progress: Arc<Progress>,
    written: Counter,
) {
    let mut synced = Instant::now();
    let mut dirty = false;
    loop {
        let wait = SYNC_INTERVAL.saturating_sub(synced.elapsed());
        let done = match queue.recv_timeout(wait) {
            Ok(records) => {
                if let Err(e) = target.write(&records) {
                    progress.end(format!("writing it failed: {e}"));
                    break;
                }
                progress
                    .written
                    .fetch_add(records.len() as u64, Ordering::Relaxed);
                written.inc_by(records.len() as u64);
                dirty = true;
                false
            }
            Err(mpsc::RecvTimeoutError::Timeout) => false,
            Err(mpsc::RecvTimeoutError::Disconnected) => true,
        };
        if dirty && (done || synced.elapsed() >= SYNC_INTERVAL) {
            if let Err(e) = target.sync() {
                progress.end(format!("syncing it failed: {e}"));
                break;
            }
            synced = Instant::now();
            dirty = false;
        }
        if done {
            break;
        }
    }
}

impl Takes {
    /// Takes in `data/takes` (created when first needed), or in memory without a data folder.
    #[must_use]
    pub fn new(data: Option<&Path>) -> Self {
        Self {
            dir: data.map(|d| d.join("takes")),
            inner: Mutex::new(Inner::default()),
            held: Arc::new(AtomicU64::new(0)),
            written: Counter::default(),
            ended: Counter::default(),
        }
    }

    /// The same, counting bytes written and takes that ended by themselves into `written`
    /// and `ended` (`/metrics`).
    #[must_use]
    pub fn counting(mut self, written: Counter, ended: Counter) -> Self {
        self.written = written;
        self.ended = ended;
        self
    }

    /// Scenes being recorded now.
    #[must_use]
    pub fn recording(&self) -> u64 {
        self.lock()
            .recording
            .values()
            .filter(|a| a.writing() && !a.progress.ended.load(Ordering::SeqCst))
            .count() as u64
    }

    /// Bytes the takes hold now, of the data quota.
    #[must_use]
    pub fn held_bytes(&self) -> u64 {
        self.held.load(Ordering::Relaxed)
    }

    /// Counts the takes found in the data folder at start, and which of them are the
    /// cluster's copies (blocking: lists it).
    pub fn restore(&self) {
        let n = self.stored_bytes();
        self.held.store(n, Ordering::Relaxed);
        for name in self.names() {
            let Some(path) = self.path(&name) else { break };
            if let Ok(nuid) = std::fs::read_to_string(path.with_extension(SHARED)) {
                self.lock().shared.insert(name, nuid.trim().to_owned());
            }
        }
        if n > 0 {
            tracing::info!(takes = self.names().len(), bytes = n, "takes found");
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A copy of take `take`'s bytes, when it is kept in memory.
    fn memory_copy(&self, take: &str) -> Option<Vec<u8>> {
        let m = self.lock().memory.get(take).cloned()?;
        let bytes = m
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        Some(bytes)
    }

    fn path(&self, take: &str) -> Option<PathBuf> {
        self.dir
            .as_ref()
            .map(|d| d.join(format!("{take}.{EXTENSION}")))
    }

    /// The bytes of every stored take (what they hold of the data quota at start).
    #[must_use]
    pub fn stored_bytes(&self) -> u64 {
        self.names()
            .iter()
            .filter_map(|n| self.path(n))
            .filter_map(|p| std::fs::metadata(p).ok())
            .map(|m| m.len())
            .sum()
    }

    /// The names of the takes kept (recording or not), sorted.
    #[must_use]
    pub fn names(&self) -> Vec<String> {
        let mut names: Vec<String> = match &self.dir {
            Some(dir) => std::fs::read_dir(dir)
                .into_iter()
                .flatten()
                .flatten()
                .filter_map(|e| {
                    let name = e.file_name().into_string().ok()?;
                    let stem = name.strip_suffix(&format!(".{EXTENSION}"))?;
                    check_id("take", stem).ok()?;
                    Some(stem.to_owned())
                })
                .collect(),
            None => self.lock().memory.keys().cloned().collect(),
        };
        names.sort();
        names
    }

    /// Starts take `take` of scene `scene` (its first record written): returns the sink for
    /// the scene's feed. Blocking (creates a file).
    ///
    /// # Errors
    /// `invalid_value` (a bad name), `conflict` (a take of that name exists, or the scene is
    /// being recorded), `internal`/`storage_full` (the file cannot be made).
    pub fn begin(
        &self,
        scene: &SceneId,
        take: &str,
        tick_rate: f32,
        limits: TakeLimits,
    ) -> Result<Sink, Error> {
        check_id("take", take).map_err(|e| Error::invalid_field("take", e.message))?;
        let mut inner = self.lock();
        // A take that ended by itself (a limit; its scene deleted) and was not stopped.
        inner.recording.retain(|_, a| a.writing());
        if let Some(a) = inner.recording.get(scene) {
            return Err(Error::Conflict(format!(
                "scene {scene} is being recorded into take {} already",
                a.take
            )));
        }
        let header = TakeHeader {
            take: take.to_owned(),
            scene: scene.0.clone(),
            tick_rate,
            started_us: crate::scene::unix_micros(),
        };
        let mut start = Vec::new();
        take::write_start(&header, &mut start);
        let target = match self.path(take) {
            Some(path) => {
                let dir = path.parent().unwrap_or(Path::new("."));
                std::fs::create_dir_all(dir)
                    .map_err(|e| Error::storing("cannot make the takes folder", &e))?;
                let mut file = std::fs::OpenOptions::new()
                    .write(true)
                    .create_new(true)
                    .open(&path)
                    .map_err(|e| match e.kind() {
                        std::io::ErrorKind::AlreadyExists => {
                            Error::Conflict(format!("take {take} exists"))
                        }
                        _ => Error::storing(&format!("cannot make take {take}"), &e),
                    })?;
                file.write_all(&start)
                    .and_then(|()| file.sync_data())
                    .and_then(|()| crate::store::atomic::sync_dir(dir))
                    .map_err(|e| {
                        std::fs::remove_file(&path).ok();
                        Error::storing(&format!("cannot write take {take}"), &e)
                    })?;
                Target::File(file)
            }
            None => {
                if inner.memory.contains_key(take) {
                    return Err(Error::Conflict(format!("take {take} exists")));
                }
                let bytes = Arc::new(Mutex::new(start.clone()));
                inner.memory.insert(take.to_owned(), bytes.clone());
                Target::Memory(bytes)
            }
        };
        let progress = Arc::new(Progress {
            ended_counter: self.ended.clone(),
            ..Progress::default()
        });
        self.written.inc_by(start.len() as u64);
        progress.bytes.store(start.len() as u64, Ordering::Relaxed);
        self.held.fetch_add(start.len() as u64, Ordering::Relaxed);
        progress
            .written
            .store(start.len() as u64, Ordering::Relaxed);
        let (queue, rx) = mpsc::channel();
        let (p, written) = (progress.clone(), self.written.clone());
        let writer = std::thread::Builder::new()
            .name(format!("take-{take}"))
            .spawn(move || write(target, rx, p, written))
            .map_err(|e| Error::internal("cannot start the take's writer", &e))?;
        inner.recording.insert(
            scene.clone(),
            Active {
                take: take.to_owned(),
                header,
                progress: progress.clone(),
                writer: Some(writer),
            },
        );
        Ok(Sink {
            queue,
            progress,
            limits,
            held: self.held.clone(),
        })
    }

    /// The take scene `scene` is being recorded into, if any.
    #[must_use]
    pub fn recording_of(&self, scene: &SceneId) -> Option<String> {
        self.lock().recording.get(scene).map(|a| a.take.clone())
    }

    /// Whether take `take` is being recorded.
    #[must_use]
    pub fn is_recording(&self, take: &str) -> bool {
        self.lock()
            .recording
            .values()
            .any(|a| a.take == take && a.writing())
    }

    /// Ends scene `scene`'s take once its sink is gone from the feed: waits for its writer to
    /// write and sync everything (blocking). Returns the take's name and why it had ended by
    /// itself, if it had.
    ///
    /// # Errors
    /// `not_allowed_now` when the scene is not being recorded.
    pub fn finish(&self, scene: &SceneId) -> Result<(String, Option<String>), Error> {
        let active =
            self.lock().recording.remove(scene).ok_or_else(|| {
                Error::NotAllowedNow(format!("scene {scene} is not being recorded"))
            })?;
        if let Some(w) = active.writer {
            w.join().ok();
        }
        let why = active
            .progress
            .why
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        Ok((active.take, why))
    }

    /// A take being recorded, described from what its sink has seen.
    fn describe_active(&self, a: &Active) -> TakeInfo {
        let p = &a.progress;
        let frames = p.frames.load(Ordering::Relaxed);
        let span = p
            .last_seq
            .load(Ordering::Relaxed)
            .saturating_sub(p.first_seq.load(Ordering::Relaxed));
        TakeInfo {
            take: a.take.clone(),
            scene: SceneId(a.header.scene.clone()),
            duration: if frames > 1 {
                span as f64 / f64::from(a.header.tick_rate)
            } else {
                0.0
            },
            frames: frames as usize,
            avatars: p
                .avatars
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .clone(),
            bytes: p.bytes.load(Ordering::Relaxed),
            started_us: a.header.started_us,
            recording: a.writing() && !p.ended.load(Ordering::SeqCst),
            torn_bytes: 0,
            drivers: Vec::new(),
        }
    }

    /// Take `take`'s index, read again only when its size changed (blocking: reads the file).
    ///
    /// # Errors
    /// `unknown_take`: no such take, or one that cannot be read (why).
    pub fn index(&self, take: &str) -> Result<Arc<TakeIndex>, Error> {
        check_id("take", take).map_err(|_| Error::UnknownTake {
            take: take.to_owned(),
            unreadable: None,
        })?;
        let unknown = || Error::UnknownTake {
            take: take.to_owned(),
            unreadable: None,
        };
        let size = match self.path(take) {
            Some(p) => std::fs::metadata(&p).map_err(|_| unknown())?.len(),
            None => {
                let m = self.lock().memory.get(take).cloned().ok_or_else(unknown)?;
                memory_len(&m)
            }
        };
        if let Some((at, index)) = self.lock().read.get(take)
            && *at == size
        {
            return Ok(index.clone());
        }
        let index = match self.path(take) {
            Some(p) => {
                let f = std::fs::File::open(&p).map_err(|_| unknown())?;
                TakeIndex::scan(std::io::BufReader::with_capacity(1 << 20, f))
            }
            None => {
                let bytes = self.memory_copy(take).ok_or_else(unknown)?;
                TakeIndex::from_bytes(&bytes)
            }
        }
        .map_err(|e| Error::UnknownTake {
            take: take.to_owned(),
            unreadable: Some(e.to_string()),
        })?;
        let index = Arc::new(index);
        self.lock()
            .read
            .insert(take.to_owned(), (size, index.clone()));
        Ok(index)
    }

    /// The bytes to replay take `take` from (its file opened, or its memory).
    ///
    /// # Errors
    /// `unknown_take`.
    pub fn source(&self, take: &str) -> Result<crate::scene::replay::TakeSource, Error> {
        let unknown = || Error::UnknownTake {
            take: take.to_owned(),
            unreadable: None,
        };
        match self.path(take) {
            Some(p) => std::fs::File::open(p)
                .map(crate::scene::replay::TakeSource::File)
                .map_err(|_| unknown()),
            None => {
                let bytes = self.memory_copy(take).ok_or_else(unknown)?;
                Ok(crate::scene::replay::TakeSource::Memory(bytes.into()))
            }
        }
    }

    /// Take `take` described (blocking: a stored take not read yet is read once).
    ///
    /// # Errors
    /// `unknown_take`.
    pub fn describe(&self, take: &str) -> Result<TakeInfo, Error> {
        {
            let inner = self.lock();
            if let Some(a) = inner
                .recording
                .values()
                .find(|a| a.take == take && a.writing())
            {
                return Ok(self.describe_active(a));
            }
        }
        let index = self.index(take)?;
        let mut avatars: Vec<AvatarId> = Vec::new();
        for d in index.avatar_lists.iter().flatten() {
            if !avatars.contains(&d.id) {
                avatars.push(d.id.clone());
            }
        }
        Ok(TakeInfo {
            take: take.to_owned(),
            scene: SceneId(index.header.scene.clone()),
            duration: index.duration(),
            frames: index.frames.len(),
            avatars,
            bytes: index.valid_len + index.torn_tail,
            started_us: index.header.started_us,
            recording: false,
            torn_bytes: index.torn_tail,
            drivers: drivers(&index),
        })
    }

    /// Every take described; takes that cannot be read are left out (logged).
    #[must_use]
    pub fn list(&self) -> Vec<TakeInfo> {
        let mut infos: Vec<TakeInfo> = self
            .names()
            .iter()
            .filter_map(|n| match self.describe(n) {
                Ok(info) => Some(info),
                Err(e) => {
                    tracing::warn!(take = %n, error = %e, "a take cannot be read");
                    None
                }
            })
            .collect();
        infos.sort_by_key(|t| (t.started_us, t.take.clone()));
        infos
    }

    /// Deletes take `take` (not while it is recorded; the caller checks replays). Returns its
    /// bytes. Blocking.
    ///
    /// # Errors
    /// `unknown_take`, `conflict` (being recorded), `internal`/`storage_full`.
    pub fn delete(&self, take: &str) -> Result<u64, Error> {
        check_id("take", take).map_err(|_| Error::UnknownTake {
            take: take.to_owned(),
            unreadable: None,
        })?;
        if self.is_recording(take) {
            return Err(Error::Conflict(format!(
                "take {take} is being recorded: stop_recording_scene first"
            )));
        }
        let mut inner = self.lock();
        inner.read.remove(take);
        inner.recording.retain(|_, a| a.take != take);
        inner.shared.remove(take);
        match self.path(take) {
            Some(p) => {
                let bytes = std::fs::metadata(&p)
                    .map_err(|_| Error::UnknownTake {
                        take: take.to_owned(),
                        unreadable: None,
                    })?
                    .len();
                // The mark first: a take file without one is a take to share.
                std::fs::remove_file(p.with_extension(SHARED)).ok();
                crate::store::atomic::remove_durable(&p)
                    .map_err(|e| Error::storing(&format!("cannot delete take {take}"), &e))?;
                self.release(bytes);
                Ok(bytes)
            }
            None => {
                let bytes = inner
                    .memory
                    .remove(take)
                    .map(|m| memory_len(&m))
                    .ok_or_else(|| Error::UnknownTake {
                        take: take.to_owned(),
                        unreadable: None,
                    })?;
                self.release(bytes);
                Ok(bytes)
            }
        }
    }

    /// The id of the cluster's copy take `take` is (`None`: recorded here and not shared
    /// yet, or not here).
    #[must_use]
    pub fn shared_as(&self, take: &str) -> Option<String> {
        self.lock().shared.get(take).cloned()
    }

    /// Marks take `take` as the cluster's copy `nuid` (blocking: writes its mark).
    ///
    /// # Errors
    /// `internal`/`storage_full` when the mark cannot be written.
    pub fn mark_shared(&self, take: &str, nuid: &str) -> Result<(), Error> {
        if let Some(p) = self.path(take) {
            crate::store::atomic::write_atomic(&p.with_extension(SHARED), nuid.as_bytes())
                .map_err(|e| Error::storing(&format!("cannot mark take {take} shared"), &e))?;
        }
        self.lock().shared.insert(take.to_owned(), nuid.to_owned());
        Ok(())
    }

    /// Takes recorded here that ended and are not the cluster's yet (blocking: lists them).
    #[must_use]
    pub fn unshared(&self) -> Vec<String> {
        let names = self.names();
        let inner = self.lock();
        names
            .into_iter()
            .filter(|n| !inner.shared.contains_key(n))
            .filter(|n| {
                !inner
                    .recording
                    .values()
                    .any(|a| &a.take == n && a.writing())
            })
            .collect()
    }

    /// Take `take`'s file, when takes are kept in a data folder.
    #[must_use]
    pub fn file(&self, take: &str) -> Option<PathBuf> {
        check_id("take", take).ok()?;
        self.path(take)
    }

    /// Take `take`'s bytes, whole (blocking: reads its file).
    ///
    /// # Errors
    /// `unknown_take`.
    pub fn bytes(&self, take: &str) -> Result<Vec<u8>, Error> {
        let unknown = || Error::UnknownTake {
            take: take.to_owned(),
            unreadable: None,
        };
        check_id("take", take).map_err(|_| unknown())?;
        match self.path(take) {
            Some(p) => std::fs::read(p).map_err(|_| unknown()),
            None => self.memory_copy(take).ok_or_else(unknown),
        }
    }

    /// Keeps `bytes`, the cluster's copy `nuid` of take `take`, here (in place of an older
    /// copy). Blocking.
    ///
    /// # Errors
    /// `invalid_value` (a bad name), `conflict` (a take of that name is recorded here),
    /// `internal`/`storage_full`.
    pub fn install(&self, take: &str, nuid: &str, bytes: &[u8]) -> Result<(), Error> {
        check_id("take", take).map_err(|e| Error::invalid_field("take", e.message))?;
        if self.is_recording(take) {
            return Err(Error::Conflict(format!(
                "take {take} is being recorded on this server"
            )));
        }
        let old = match self.path(take) {
            Some(p) => {
                let old = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                let dir = p.parent().unwrap_or(Path::new("."));
                std::fs::create_dir_all(dir)
                    .map_err(|e| Error::storing("cannot make the takes folder", &e))?;
                // Marked as a copy of no object first: a crash before the real mark leaves
                // a copy that is fetched again at its next use, never one shared as this
                // server's own (which could bring back a take deleted meanwhile).
                self.mark_shared(take, "")?;
                crate::store::atomic::write_atomic(&p, bytes)
                    .map_err(|e| Error::storing(&format!("cannot keep take {take}"), &e))?;
                old
            }
            None => {
                let mut inner = self.lock();
                let old = inner
                    .memory
                    .insert(take.to_owned(), Arc::new(Mutex::new(bytes.to_vec())));
                old.map_or(0, |m| memory_len(&m))
            }
        };
        self.release(old);
        self.held.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        self.lock().read.remove(take);
        self.mark_shared(take, nuid)
    }

    fn release(&self, bytes: u64) {
        self.held
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |v| {
                Some(v.saturating_sub(bytes))
            })
            .ok();
    }
}

/// The length of a take kept in memory.
fn memory_len(m: &Mutex<Vec<u8>>) -> u64 {
    m.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .len() as u64
}

/// Who drove which avatar, from the take's driver events
/// ([`posecast_stream::feed::Feed::note_drivers`]): each pair once, in order of first drive.
fn drivers(index: &TakeIndex) -> Vec<TakeDriver> {
    let mut seen: Vec<TakeDriver> = Vec::new();
    for (_, event) in &index.events {
        let Some(list) = event.get("drivers").and_then(|d| d.as_array()) else {
            continue;
        };
        for d in list {
            if let Ok(d) = serde_json::from_value::<TakeDriver>(d.clone())
                && !seen.contains(&d)
            {
                seen.push(d);
            }
        }
    }
    seen
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> TakeLimits {
        TakeLimits {
            max_frames: 1000,
            max_bytes: 1 << 20,
        }
    }

    /// A take recorded here is to be shared until marked; a copy of the cluster's never is,
    /// even one whose install was cut short; the marks survive a restart.
    #[test]
    fn only_takes_recorded_here_are_shared_and_marks_survive_a_restart() {
        let data = tempfile::tempdir().unwrap();
        let takes = Takes::new(Some(data.path()));
        let scene = SceneId("stage".into());
        let sink = takes.begin(&scene, "ours", 30.0, limits()).unwrap();
        assert!(takes.unshared().is_empty(), "shared while it records");
        drop(sink);
        takes.finish(&scene).unwrap();
        assert_eq!(takes.unshared(), vec!["ours".to_owned()]);
        takes.mark_shared("ours", "N1").unwrap();
        assert!(takes.unshared().is_empty());

        // A copy of another server's take.
        let bytes = takes.bytes("ours").unwrap();
        takes.install("theirs", "N2", &bytes).unwrap();
        assert_eq!(takes.shared_as("theirs").as_deref(), Some("N2"));
        assert!(takes.unshared().is_empty());
        assert_eq!(takes.describe("theirs").unwrap().frames, 0);
        assert_eq!(takes.held_bytes(), 2 * bytes.len() as u64);
        // A newer version replaces it, and the quota counts it once.
        takes.install("theirs", "N3", &bytes).unwrap();
        assert_eq!(takes.held_bytes(), 2 * bytes.len() as u64);

        // An install cut short between its mark and its bytes: a copy of no object.
        let path = data.path().join("takes");
        std::fs::write(path.join("cut.take"), &bytes).unwrap();
        std::fs::write(path.join("cut.shared"), "").unwrap();

        let again = Takes::new(Some(data.path()));
        again.restore();
        assert_eq!(again.shared_as("ours").as_deref(), Some("N1"));
        assert_eq!(again.shared_as("theirs").as_deref(), Some("N3"));
        assert_eq!(again.shared_as("cut").as_deref(), Some(""));
        assert!(again.unshared().is_empty(), "{:?}", again.unshared());
        // Deleting a copy takes its mark.
        again.delete("theirs").unwrap();
        assert!(!path.join("theirs.shared").exists());
        assert_eq!(again.shared_as("theirs"), None);
    }
}
