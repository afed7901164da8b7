//! Uploading assets: an in-memory file set is imported ([`posecast_rigs::import::files`]), normalised
//! like the rigs loaded at start ([`posecast_rigs::library::prepare`]), stored durably, and only then added to
//! the library and acknowledged. On any failure nothing changes: no library entry, no file
//! left in the data folder.
//!
//! In a cluster (`--nats`) an upload, its added clips and its new options are also put where
//! every server reads them ([`crate::state::Cluster::share_asset`]) before the answer, and the
//! other servers load them with [`adopt_shared`].
//!
//! Uploads come over REST only (`service::upload`); the websocket keeps its 64 KiB message
//! bound, which is what lets a connection's reader stay small and never buffer a model.

use crate::state::Services;
use crate::store::assets::{self, AssetMeta};
use posecast_core::error::Error;
use posecast_proto::command::AssetInfo;
use posecast_rigs::import::files::{self, FileSet};
use posecast_rigs::library::{check_name, prepare_with};
use posecast_rigs::rig::{PipelineOptions, Rig};
use std::sync::Arc;

/// Whether `name` is taken: a loaded rig `name` or `name#…`, an upload, or a stored folder.
fn taken(state: &Services, name: &str) -> bool {
    let prefix = format!("{name}#");
    state.world.library.get(name).is_some()
        || state
            .world
            .library
            .all()
            .iter()
            .any(|r| r.name.starts_with(&prefix))
        || state.store.uploads().contains_key(name)
        || state
            .store
            .assets_dir()
            .is_some_and(|d| d.join(name).exists())
}

fn conflict(name: &str) -> Error {
    Error::Conflict(format!("an asset named {name} exists"))
}

/// The rig quotas ([`posecast_rigs::rig::Rig::check_quotas`]), counted in the metrics when refused.
fn check_rig(state: &Services, rig: &Rig) -> Result<(), Error> {
    rig.check_quotas(&state.config.quotas)
        .map_err(|(quota, e)| {
            state.metrics.quota_refused(quota);
            e
        })
}

/// Refuses a file set larger than [`posecast_core::quota::Quotas::max_asset_bytes`].
fn check_asset_bytes(state: &Services, name: &str, bytes: u64) -> Result<(), Error> {
    let max = state.config.quotas.max_asset_bytes;
    if bytes > max {
        return Err(state.metrics.refuse_quota(
            posecast_core::quota::Quota::AssetBytes,
            format!("asset {name} would hold {bytes} bytes"),
            max,
        ));
    }
    Ok(())
}

/// Refuses `more` bytes past [`posecast_core::quota::Quotas::max_upload_total_bytes`] (called under
/// the assets lock, so concurrent uploads cannot overshoot together).
fn check_total_bytes(state: &Services, name: &str, more: u64) -> Result<(), Error> {
    let max = state.config.quotas.max_upload_total_bytes;
    let now = state.store.upload_bytes() + state.takes.held_bytes();
    if now.saturating_add(more) > max {
        return Err(state.metrics.refuse_quota(
            posecast_core::quota::Quota::UploadTotalBytes,
            format!("uploads, recordings and takes hold {now} bytes and {name} adds {more}"),
            max,
        ));
    }
    Ok(())
}

/// Refuses `bytes` more for `what` past the server's byte quota or `caller`'s token quota
/// (bytes or objects). Called under the assets lock.
///
/// # Errors
/// `quota_exceeded` naming the quota.
pub fn check_room(
    state: &Services,
    caller: &crate::auth::Caller,
    what: &str,
    bytes: u64,
) -> Result<(), Error> {
    let max = state.config.quotas.max_upload_total_bytes;
    let now = state.store.upload_bytes() + state.takes.held_bytes();
    if now.saturating_add(bytes) > max {
        return Err(state.metrics.refuse_quota(
            posecast_core::quota::Quota::UploadTotalBytes,
            format!("uploads, recordings and takes hold {now} bytes and {what} adds {bytes}"),
            max,
        ));
    }
    if let crate::auth::Caller::Token(t) = caller {
        let used = state.store.owners().usage(Some(&t.name));
        if let Some(max) = t.quota.max_bytes
            && used.bytes.saturating_add(bytes) > max
        {
            return Err(state.metrics.refuse_quota(
                posecast_core::quota::Quota::TokenBytes,
                format!(
                    "token {} holds {} bytes and {what} adds {bytes}",
                    t.name, used.bytes
                ),
                max,
            ));
        }
        if let Some(max) = t.quota.max_objects
            && used.objects >= max
        {
            return Err(state.metrics.refuse_quota(
                posecast_core::quota::Quota::TokenObjects,
                format!(
                    "token {} holds {} uploads and recordings; {what} is one more",
                    t.name, used.objects
                ),
                max,
            ));
        }
    }
    Ok(())
}

/// Uploads a new asset: import, normalise with `options`, store (options included), add to
/// the library. Returns the new rigs.
///
/// # Errors
/// A bad name, `conflict` when it is taken, `import_failed`,
/// `internal` when storing fails. Nothing changes on error.
pub async fn upload(
    state: &Arc<Services>,
    caller: &crate::auth::Caller,
    name: &str,
    set: FileSet,
    options: PipelineOptions,
) -> Result<Vec<AssetInfo>, Error> {
    check_name(name)?;
    if taken(state, name) {
        return Err(conflict(name));
    }
    check_asset_bytes(state, name, set.total_bytes() as u64)?;
    let owned = name.to_owned();
    let opts = options.clone();
    let (set, rigs) = tokio::task::spawn_blocking(move || {
        let rigs = prepare_with(&owned, &set, &opts);
        (set, rigs)
    })
    .await
    .map_err(|e| Error::internal("import task failed", &e))?;
    let rigs = rigs?;
    for rig in &rigs {
        check_rig(state, rig)?;
    }
    let _guard = state.store.assets_lock().await;
    if taken(state, name)
        || rigs
            .iter()
            .any(|r| state.world.library.get(&r.name).is_some())
    {
        return Err(conflict(name));
    }
    let bytes = set.total_bytes() as u64;
    check_total_bytes(state, name, bytes)?;
    check_room(state, caller, &format!("upload {name}"), bytes)?;
    // In a cluster, where every server reads it first: a failure there changes nothing.
    if let Some(cluster) = state.cluster() {
        cluster.share_asset(name, &set, &options).await?;
    }
    let set = match state.store.assets_dir() {
        Some(dir) => {
            let meta = AssetMeta::new(name, &set, rigs.iter().map(|r| r.name.clone()).collect())
                .with_options(&options)
                .with_owner(caller.owner());
            let saved = tokio::task::spawn_blocking(move || {
                assets::save_new(&dir, &set, &meta).map(|()| set)
            })
            .await
            .map_err(|e| Error::internal("store task failed", &e))
            .and_then(|r| r.map_err(|e| Error::internal("cannot store the upload", &e)));
            match (saved, state.cluster()) {
                (Ok(set), _) => set,
                (Err(e), Some(cluster)) => {
                    cluster.unshare_asset(name).await;
                    return Err(e);
                }
                (Err(e), None) => return Err(e),
            }
        }
        None => set,
    };
    state.store.add_upload_bytes(bytes);
    state.store.owners().add(caller.owner(), bytes);
    let infos = rigs
        .into_iter()
        .map(|rig| state.world.library.insert(rig).info())
        .collect();
    state.store.remember_upload(name, set, options);
    state.store.set_upload_owner(name, caller.owner(), bytes);
    Ok(infos)
}

/// Adds `.anim` clips (named by file stem) to an uploaded `.skel` asset. The asset is
/// re-imported with the new files, so the clips go through the same normalisation as the
/// originals; the new rig replaces the old one for avatars added from now on (avatars already
/// in scenes keep the rig, and the clips, they were created with).
///
/// # Errors
/// Unknown asset, an asset that is not an uploaded `.skel`, a file that is not `.anim`
/// (typed: `.bvh` clips have other joints, so they are uploaded as their own asset and played
/// with `from_asset` retargeting), a clip name that exists (`conflict`), or an
/// import failure. Nothing changes on error.
pub async fn add_clips(
    state: &Arc<Services>,
    name: &str,
    clips: FileSet,
) -> Result<AssetInfo, Error> {
    if clips.is_empty() {
        return Err(Error::invalid("no clip files in the request"));
    }
    for (file, _) in clips.iter() {
        match files::extension(file).as_str() {
            "anim" => {}
            "bvh" => {
                return Err(Error::invalid(format!(
                    "{file}: a .bvh has its own skeleton; upload it as an asset and play its clip with from_asset (retargeting)"
                )));
            }
            _ => {
                return Err(Error::invalid(format!(
                    "{file}: clips are added as .anim files"
                )));
            }
        }
    }
    let _guard = state.store.assets_lock().await;
    let rig = state.world.library.require(name)?;
    let upload = state.store.uploads().get(name).cloned().ok_or_else(|| {
        Error::invalid(format!(
            "{name} was not uploaded: clips can be added to uploaded assets only"
        ))
    })?;
    if files::extension(&upload.main) != "skel" {
        return Err(Error::invalid(format!(
            "{name} is not a .skel asset: .anim clips need a CSE169 skeleton"
        )));
    }
    // The original files are on disk (the store keeps no bytes when there is a data folder):
    // read them again, under the assets lock so they are the ones the rig was made from.
    let original = match upload.files {
        Some(files) => files,
        None if state.cluster().is_some() => shared_files(state, name).await?,
        None => {
            let reading = state.clone();
            let owned = name.to_owned();
            tokio::task::spawn_blocking(move || reading.store.read_upload(&owned))
                .await
                .map_err(|e| Error::internal("read task failed", &e))?
                .map_err(|e| {
                    Error::internal(&format!("cannot read the stored files of {name}"), &e)
                })?
        }
    };
    check_asset_bytes(
        state,
        name,
        (original.total_bytes() + clips.total_bytes()) as u64,
    )?;
    let added = clips.total_bytes() as u64;
    check_total_bytes(state, name, added)?;
    let mut combined = original;
    for (file, bytes) in clips.iter() {
        let clip = files::stem(file);
        if rig.clip(clip).is_some() {
            return Err(Error::Conflict(format!(
                "rig {name} already has a clip {clip}"
            )));
        }
        combined
            .insert(file, bytes.to_vec())
            .map_err(|e| Error::Conflict(e.to_string()))?;
    }
    let owned = name.to_owned();
    let options = upload.options.clone();
    let opts = options.clone();
    let (combined, rigs) = tokio::task::spawn_blocking(move || {
        let rigs = prepare_with(&owned, &combined, &opts);
        (combined, rigs)
    })
    .await
    .map_err(|e| Error::internal("import task failed", &e))?;
    let new_rig = rigs?
        .into_iter()
        .next()
        .ok_or_else(|| Error::internal("import gave no rig", &name))?;
    check_rig(state, &new_rig)?;
    if let Some(cluster) = state.cluster() {
        cluster.share_asset(name, &combined, &options).await?;
    }
    if let Some(dir) = state.store.assets_dir()
        && dir.join(name).is_dir()
    {
        let meta = AssetMeta::new(name, &combined, vec![name.to_owned()])
            .with_options(&options)
            .with_owner(state.store.upload_owner(name).as_deref());
        let dir = dir.join(name);
        tokio::task::spawn_blocking(move || assets::add_files(&dir, &clips, &meta))
            .await
            .map_err(|e| Error::internal("store task failed", &e))?
            .map_err(|e| Error::internal("cannot store the clips", &e))?;
    }
    state.store.add_upload_bytes(added);
    let owner = state.store.upload_owner(name);
    state.store.owners().grow(owner.as_deref(), added);
    let info = state.world.library.insert(new_rig).info();
    state.store.remember_upload(name, combined, options);
    Ok(info)
}

/// Normalises uploaded asset `name` again with `options` (`configure_asset`): its files are
/// read again (from the data folder, or memory), imported and normalised; only when that
/// succeeds are the options stored (`meta.json` rewritten atomically) and the rigs replaced.
/// Avatars added from then on use the new rigs; avatars in scenes keep theirs.
///
/// # Errors
/// `unknown_asset`; `not_allowed_now` for an asset that was not uploaded (the built-in and
/// `--assets` rigs) or whose files are not kept (without a data folder only `.skel` uploads
/// keep theirs); `invalid_value` when the options cannot be applied (a `name_map` naming a
/// joint the rig lacks, a bad orientation); `internal` when storing fails. Nothing changes on
/// error.
pub async fn configure(
    state: &Services,
    name: &str,
    options: PipelineOptions,
) -> Result<Vec<AssetInfo>, Error> {
    let _guard = state.store.assets_lock().await;
    let Some(upload) = state.store.uploads().get(name).cloned() else {
        let loaded = state.world.library.get(name);
        return Err(match loaded {
            Some(rig) => Error::NotAllowedNow(match &rig.upload {
                Some(u) => format!("{name} belongs to upload {u}: configure {u}"),
                None => format!(
                    "{name} was not uploaded (built-in or --assets): only uploads can be configured"
                ),
            }),
            None => Error::unknown_asset(name),
        });
    };
    let files = match (upload.files, state.store.assets_dir()) {
        (Some(files), _) => files,
        (None, _) if state.cluster().is_some() => shared_files(state, name).await?,
        (None, Some(dir)) => {
            let dir = dir.join(name);
            tokio::task::spawn_blocking(move || assets::read_asset(&dir))
                .await
                .map_err(|e| Error::internal("read task failed", &e))?
                .map_err(|e| {
                    Error::internal(&format!("cannot read the stored files of {name}"), &e)
                })?
                .1
        }
        (None, None) => {
            return Err(Error::NotAllowedNow(format!(
                "{name}'s files are not kept (the server has no data folder): upload it again                  with these options"
            )));
        }
    };
    let owned = name.to_owned();
    let opts = options.clone();
    let (files, rigs) = tokio::task::spawn_blocking(move || {
        let rigs = prepare_with(&owned, &files, &opts);
        (files, rigs)
    })
    .await
    .map_err(|e| Error::internal("import task failed", &e))?;
    // The files imported before, so a failure now is the options'.
    let rigs = rigs.map_err(|e| match e {
        Error::ImportFailed(m) => Error::invalid(m),
        e => e,
    })?;
    for rig in &rigs {
        check_rig(state, rig)?;
    }
    if let Some(cluster) = state.cluster() {
        cluster.share_asset(name, &files, &options).await?;
    }
    if let Some(dir) = state.store.assets_dir()
        && dir.join(name).is_dir()
    {
        let meta = AssetMeta::new(name, &files, rigs.iter().map(|r| r.name.clone()).collect())
            .with_options(&options)
            .with_owner(state.store.upload_owner(name).as_deref());
        let dir = dir.join(name);
        tokio::task::spawn_blocking(move || assets::add_files(&dir, &FileSet::new(), &meta))
            .await
            .map_err(|e| Error::internal("store task failed", &e))?
            .map_err(|e| Error::internal("cannot store the options", &e))?;
    }
    let infos = rigs
        .into_iter()
        .map(|rig| state.world.library.insert(rig).info())
        .collect();
    state.store.remember_upload(name, files, options);
    Ok(infos)
}

/// Upload `name`'s files as the cluster stores them (its servers other than the one it was
/// uploaded to keep no copy of their own).
async fn shared_files(state: &Services, name: &str) -> Result<FileSet, Error> {
    let Some(cluster) = state.cluster() else {
        return Err(Error::internal("no cluster", &name));
    };
    cluster.shared_asset(name).await?.ok_or_else(|| {
        Error::NotAllowedNow(format!(
            "{name}'s files are not in the cluster's store: upload it again"
        ))
    })
}

/// Loads an upload another server of the cluster stored ([`crate::state::Cluster::share_asset`])
/// as that server did: normalised with its options, within this server's quotas. A new
/// version (clips added, options changed) replaces the rigs; avatars in scenes keep theirs.
/// The caller holds the store's assets lock. Nothing is written to the data folder: the
/// cluster's store is the upload's copy.
///
/// # Errors
/// A bad name; `conflict` when a rig of that name was loaded here otherwise (built in,
/// `--assets`); a quota; `import_failed`. Nothing changes on error.
pub async fn adopt_shared(
    state: &Services,
    name: &str,
    set: FileSet,
    options: PipelineOptions,
) -> Result<Vec<AssetInfo>, Error> {
    check_name(name)?;
    let prefix = format!("{name}#");
    if let Some(rig) = state
        .world
        .library
        .all()
        .iter()
        .find(|r| (r.name == name || r.name.starts_with(&prefix)) && r.upload.is_none())
    {
        return Err(Error::Conflict(format!(
            "rig {} is loaded here from --assets or built in",
            rig.name
        )));
    }
    let bytes = set.total_bytes() as u64;
    check_asset_bytes(state, name, bytes)?;
    let owned = name.to_owned();
    let opts = options.clone();
    let (set, rigs) = tokio::task::spawn_blocking(move || {
        let rigs = prepare_with(&owned, &set, &opts);
        (set, rigs)
    })
    .await
    .map_err(|e| Error::internal("import task failed", &e))?;
    let rigs = rigs?;
    for rig in &rigs {
        check_rig(state, rig)?;
    }
    if !state.store.uploads().contains_key(name) {
        state.store.add_upload_bytes(bytes);
    }
    let infos = rigs
        .into_iter()
        .map(|rig| state.world.library.insert(rig).info())
        .collect();
    state.store.remember_upload(name, set, options);
    Ok(infos)
}

/// `delete_asset`: upload `name`'s rigs leave the library, its folder (with the recordings
/// made on its rigs) the data folder, and it leaves the cluster's store; its bytes are freed
/// from the server's and its owner's quota.
///
/// # Errors
/// `unknown_asset` (no such upload), `not_allowed_now` (built in or from `--assets`),
/// `forbidden` (another token's), `conflict` (an avatar is made of or plays one of its
/// rigs), `internal`/`storage_full` (the files could not be removed: nothing changed).
pub async fn delete(
    state: &Services,
    caller: &crate::auth::Caller,
    name: &str,
) -> Result<(), Error> {
    let _guard = state.store.assets_lock().await;
    let Some((owner, bytes)) = state.store.upload_owner_and_bytes(name) else {
        return Err(if state.world.library.get(name).is_some() {
            Error::NotAllowedNow(format!(
                "asset {name} is not an upload (built in or from --assets): it cannot be deleted"
            ))
        } else {
            Error::unknown_asset(name)
        });
    };
    state
        .config
        .access
        .authorize_delete(caller, owner.as_deref())?;
    let rigs: Vec<String> = state
        .world
        .library
        .all()
        .into_iter()
        .filter(|r| r.upload.as_deref() == Some(name) || r.name == name)
        .map(|r| r.name.clone())
        .collect();
    for rig in &rigs {
        if let Some(avatar) = state.world.playing(rig, None) {
            return Err(Error::Conflict(format!(
                "avatar {avatar} uses rig {rig} of asset {name}: remove it first"
            )));
        }
    }
    let recordings: Vec<(String, String)> = state
        .store
        .recordings()
        .keys()
        .filter(|(r, _)| rigs.contains(r))
        .cloned()
        .collect();
    if let Some(dir) = state.store.assets_dir() {
        let (assets, recs, owned) = (dir, state.store.recordings_dir(), name.to_owned());
        let gone = recordings.clone();
        tokio::task::spawn_blocking(move || {
            assets::delete(&assets, &owned)?;
            if let Some(recs) = recs {
                for (rig, clip) in &gone {
                    crate::store::recordings::delete(&recs, rig, clip)?;
                }
            }
            Ok::<_, std::io::Error>(())
        })
        .await
        .map_err(|e| Error::internal("store task failed", &e))?
        .map_err(|e| Error::storing("cannot delete the asset", &e))?;
    }
    if let Some(cluster) = state.cluster() {
        cluster.unshare_asset(name).await;
        for (rig, clip) in &recordings {
            cluster.unshare_recording(rig, clip).await;
        }
    }
    for rig in &rigs {
        state.world.library.remove(rig);
    }
    state.store.forget_upload(name, owner.as_deref(), bytes);
    for key in &recordings {
        if let Some(stored) = state.store.recordings().remove(key) {
            state.store.sub_upload_bytes(stored.bytes);
            state
                .store
                .owners()
                .remove(stored.owner.as_deref(), stored.bytes);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    const SKEL: &str = "balljoint root {\n offset 0 0 0\n balljoint tip {\n offset 0 1 0\n }\n}\n";

    fn set(files: &[(&str, String)]) -> FileSet {
        let mut set = FileSet::new();
        for (name, text) in files {
            set.insert(name, text.clone().into_bytes()).unwrap();
        }
        set
    }

    /// An `.anim` of constant zero channels for the two-joint [`SKEL`] (3 + 2·3 channels).
    fn anim() -> String {
        let channel =
            "channel {\n extrapolate constant constant\n keys 1 {\n 0 0 smooth smooth\n }\n}\n";
        format!(
            "animation {{\n range 0 1\n numchannels 9\n{}}}\n",
            channel.repeat(9)
        )
    }

    /// With a data folder the store remembers an upload without its files, and adding clips
    /// reads them back from `assets/<name>/`. Without one, memory is the files' only copy: a
    /// `.skel` upload (the kind clips are added to) keeps them, a `.bvh` keeps none.
    #[tokio::test]
    async fn upload_bytes_stay_in_memory_only_without_a_data_folder() {
        let dir = tempfile::tempdir().unwrap();
        let on_disk = Services::new(Config {
            data_dir: Some(dir.path().to_owned()),
            ..Config::default()
        });
        on_disk.store.open().unwrap();
        upload(
            &on_disk,
            &crate::auth::Caller::Anonymous,
            "r",
            set(&[("r.skel", SKEL.into())]),
            PipelineOptions::default(),
        )
        .await
        .unwrap();
        assert!(on_disk.store.uploads()["r"].files.is_none());
        let info = add_clips(&on_disk, "r", set(&[("wave.anim", anim())]))
            .await
            .unwrap();
        assert_eq!(info.clips[0].name, "wave");
        assert!(on_disk.store.uploads()["r"].files.is_none());
        assert!(dir.path().join("assets/r/wave.anim").is_file());

        let in_memory = Services::new(Config::default());
        upload(
            &in_memory,
            &crate::auth::Caller::Anonymous,
            "r",
            set(&[("r.skel", SKEL.into())]),
            PipelineOptions::default(),
        )
        .await
        .unwrap();
        let kept = in_memory.store.uploads()["r"].files.clone().unwrap();
        assert_eq!(kept.get("r.skel"), Some(SKEL.as_bytes()));
        let info = add_clips(&in_memory, "r", set(&[("wave.anim", anim())]))
            .await
            .unwrap();
        assert_eq!(info.clips[0].name, "wave");
        let bvh = "HIERARCHY\nROOT hip\n{\n OFFSET 0 0 0\n CHANNELS 3 Zrotation Xrotation Yrotation\n \
                   End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n0 0 0\n";
        upload(
            &in_memory,
            &crate::auth::Caller::Anonymous,
            "b",
            set(&[("b.bvh", bvh.into())]),
            PipelineOptions::default(),
        )
        .await
        .unwrap();
        assert!(in_memory.store.uploads()["b"].files.is_none());
    }
}
