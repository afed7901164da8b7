//! What a server loads at start, in the background once it listens: the built-in rig, every
//! `--assets` folder, the stored uploads, then the stored scenes, then — on a first start —
//! the `default` scene and the data folder's marker. The order is the one the store's module
//! doc promises ([`crate::store`]); [`crate::readiness`] counts the progress.
//!
//! Loading runs on a thread of its own rather than tokio's blocking pool: importing is
//! CPU-bound (seconds for gigabytes of uploads) and must not hold an async worker, and a
//! process asked to stop during a long start must be able to exit — the runtime waits for
//! its blocking-pool tasks when it shuts down, never for this thread. A binary may start that
//! thread first thing ([`prepare`]): it imports the built-in avatar while the server starts,
//! then takes the plan.

use crate::state::Services;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_rigs::builtin::{BUILTIN_ASSET, BuiltinError};
use posecast_rigs::import;
use posecast_rigs::rig::{PipelineOptions, Rig};
use posecast_sim::avatar::playback::Layer;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError, mpsc};
use tracing::{info, warn};

/// The scene created at start.
pub const DEFAULT_SCENE: &str = "default";
/// The built-in avatar's id in the default scene.
pub const DEFAULT_AVATAR: &str = "avatar";

/// One thing to load.
#[derive(Debug)]
enum Source {
    /// The built-in avatar.
    Builtin,
    /// An importable file of an `--assets` folder.
    File(PathBuf),
    /// A stored upload's folder.
    Upload(PathBuf),
}

/// Everything a start loads, listed (not read) before the server listens so `/healthz` can
/// tell the total from its first answer.
#[derive(Debug)]
pub struct Plan {
    sources: Vec<Source>,
    first_start: bool,
}

impl Plan {
    /// Lists what `state`'s configuration and data folder hold. `first_start`: the data folder
    /// is new (or there is none), so the default scene is created once the rest is loaded.
    #[must_use]
    pub fn new(state: &Services, first_start: bool) -> Self {
        let mut sources = Vec::new();
        if state.config.builtin {
            sources.push(Source::Builtin);
        }
        for dir in &state.config.asset_dirs {
            sources.extend(importable_files(dir).into_iter().map(Source::File));
        }
        sources.extend(state.store.stored_uploads().into_iter().map(Source::Upload));
        Self {
            sources,
            first_start,
        }
    }

    /// How many asset sources it holds.
    #[must_use]
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Whether it holds no asset source (scenes and the built-in avatar are loaded all the
    /// same).
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }
}

/// Loads `plan` on a thread of its own and marks `state` ready (or failed) when done: the
/// thread [`prepare`] started, if there is one, else a new one. Scenes restored there start
/// their tick tasks on the current tokio runtime.
///
/// # Errors
/// The thread cannot be started.
pub fn spawn(state: Arc<Services>, plan: Plan) -> std::io::Result<()> {
    let mut job = Job {
        state,
        plan,
        runtime: tokio::runtime::Handle::current(),
    };
    let prepared = PREPARED
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .take();
    if let Some(prepared) = prepared {
        match prepared.send(job) {
            Ok(()) => return Ok(()),
            // The prepared thread has ended (it never should): a new one does the job.
            Err(mpsc::SendError(back)) => job = back,
        }
    }
    std::thread::Builder::new()
        .name(THREAD_NAME.into())
        .spawn(move || load(job, None))
        .map(|_| ())
}

/// Starts the loading thread ahead of the server, before its runtime, its state and its
/// listener exist, so that the built-in avatar's import — the longest step of a start
/// (1–2 ms, all of it cold code and fresh memory) — runs beside all that instead of after
/// it; the next [`spawn`] hands this thread the rest of its work instead of starting one.
/// The `posecast` binary calls it first thing. The import is wasted when the configuration
/// turns out not to load the built-in avatar (`--no-builtin`), and dropped.
///
/// # Errors
/// The thread cannot be started (then [`spawn`] starts one, as without this).
pub fn prepare() -> std::io::Result<()> {
    let (jobs, job) = mpsc::sync_channel::<Job>(1);
    std::thread::Builder::new()
        .name(THREAD_NAME.into())
        .spawn(move || {
            let builtin = std::panic::catch_unwind(posecast_rigs::builtin::rig);
            // No job: the server did not start (the process is ending).
            if let Ok(job) = job.recv() {
                load(job, Some(builtin));
            }
        })?;
    *PREPARED.lock().unwrap_or_else(PoisonError::into_inner) = Some(jobs);
    Ok(())
}

const THREAD_NAME: &str = "posecast-restore";

/// The way to the thread [`prepare`] started, until [`spawn`] hands it its job.
static PREPARED: Mutex<Option<mpsc::SyncSender<Job>>> = Mutex::new(None);

/// A loading thread's work.
struct Job {
    state: Arc<Services>,
    plan: Plan,
    runtime: tokio::runtime::Handle,
}

/// The built-in avatar as [`prepare`] imported it, panic included.
type Imported = std::thread::Result<Result<Rig, BuiltinError>>;

/// Runs `job` on this thread and marks its server ready (or failed).
fn load(job: Job, builtin: Option<Imported>) {
    let Job {
        state,
        plan,
        runtime,
    } = job;
    let _runtime = runtime.enter();
    let began = std::time::Instant::now();
    // A panic while loading must not leave requests waiting for ever.
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        run(&state, plan, builtin).map_err(|e| e.to_string())
    }))
    .unwrap_or_else(|_| Err("loading panicked (see the log)".to_owned()));
    match &result {
        Ok(()) if state.readiness.stopped() => {
            info!("start-up loading stopped: the server is shutting down");
        }
        Ok(()) => info!(
            rigs = state.world.library.all().len(),
            scenes = state.world.scenes().len(),
            seconds = began.elapsed().as_secs_f64(),
            "ready"
        ),
        Err(e) => warn!(error = %e, "start-up failed"),
    }
    state.readiness.finish(result);
}

/// Loads the plan in order; gives up between steps when the server shuts down. `builtin`:
/// the built-in avatar imported already ([`prepare`]).
fn run(state: &Services, plan: Plan, mut builtin: Option<Imported>) -> std::io::Result<()> {
    for source in plan.sources {
        if state.readiness.stopped() {
            return Ok(());
        }
        match source {
            Source::Builtin => load_builtin(&state.world, builtin.take()),
            Source::File(path) => load_file(&state.world, &path),
            Source::Upload(dir) => state.store.restore_upload(&state.world, &dir),
        }
        state.readiness.source_done();
    }
    if state.readiness.stopped() {
        return Ok(());
    }
    state.store.restore_recordings(&state.world);
    state.takes.restore();
    // In a cluster (`--nats`) scenes live in NATS, where every server reads them
    // (`crate::cluster`), not in this server's folder.
    let clustered = !state.config.nats.is_empty();
    if !clustered {
        state.store.restore_scenes(&state.world);
    }
    if plan.first_start && !state.readiness.stopped() {
        if state.config.builtin && !clustered {
            create_default_scene(state);
        }
        for scene in state.world.scenes() {
            state
                .store
                .persist_scene_now(&state.world, &scene.id)
                .map_err(|e| data_folder_error(state, &e))?;
        }
        state
            .store
            .mark_initialised()
            .map_err(|e| data_folder_error(state, &e))?;
    }
    Ok(())
}

fn load_builtin(world: &crate::world::World, imported: Option<Imported>) {
    let rig = match imported {
        Some(Ok(rig)) => rig,
        // Its panic, here where loading catches it.
        Some(Err(panic)) => std::panic::resume_unwind(panic),
        None => posecast_rigs::builtin::rig(),
    };
    match rig {
        Ok(rig) => {
            world.library.insert(rig);
        }
        Err(e) => warn!(error = %e, "the built-in avatar failed to load"),
    }
}

/// Scene `default` with the built-in avatar playing `idle` (first start only: later, the data
/// folder says which scenes exist). Kept when a stored scene of that name was restored.
fn create_default_scene(state: &Services) {
    let scene = SceneId(DEFAULT_SCENE.into());
    if state.world.library.get(BUILTIN_ASSET).is_none() || state.world.scene(&scene).is_ok() {
        return;
    }
    let added = state.world.create_scene(scene.clone()).and_then(|_| {
        state
            .world
            .add_avatar(&scene, BUILTIN_ASSET, Some(AvatarId(DEFAULT_AVATAR.into())))
    });
    match added {
        Ok((scene, id)) => {
            let mut s = scene.lock();
            if let Some(a) = s.avatar_mut(&id)
                && let Some(idle) = a.rig.clip("idle").cloned()
            {
                a.play(Layer::new(idle, None, 0.0, 1.0, true), 0.0);
            }
        }
        Err(e) => warn!(error = %e, "could not create the default scene"),
    }
}

/// The importable files of a folder (not recursive), in name order; an unreadable folder is
/// logged and gives none.
fn importable_files(dir: &Path) -> Vec<PathBuf> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) => {
            warn!(dir = %dir.display(), error = %e, "cannot read asset folder");
            return Vec::new();
        }
    };
    let mut paths: Vec<_> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|path| {
            let ext = path
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            matches!(
                ext.as_str(),
                "glb" | "gltf" | "vrm" | "vrma" | "bvh" | "skel"
            )
        })
        .collect();
    paths.sort();
    paths
}

/// Loads one file of an `--assets` folder; failures are logged and skipped.
fn load_file(world: &crate::world::World, path: &Path) {
    match import::load_path(path) {
        Ok(assets) => {
            for asset in assets {
                let name = asset.name.clone();
                match posecast_rigs::rig::Rig::from_asset(asset, &PipelineOptions::default()) {
                    Ok(rig) => {
                        info!(asset = %name, joints = rig.skeleton().len(), steps = ?rig.pipeline, "loaded");
                        world.library.insert(rig);
                    }
                    Err(e) => warn!(asset = %name, error = %e, "skipped: normalisation failed"),
                }
            }
        }
        Err(e) => warn!(error = %e, "skipped"),
    }
}

/// `e` with the data folder named: the bare OS error ("Not a directory") does not say which.
pub fn data_folder_error(state: &Services, e: &std::io::Error) -> std::io::Error {
    let folder = state
        .store
        .root()
        .map_or_else(|| "(none)".to_owned(), |p| p.display().to_string());
    std::io::Error::new(
        e.kind(),
        format!("data folder {folder} (--data) is not usable: {e}"),
    )
}
