//! The commands that make or delete stored objects — `stop_recording`, `delete_clip`,
//! `delete_asset` — with the quotas they count against: the server's `upload_total_bytes`
//! and the token's own ([`crate::auth::TokenQuota`], issue 37).
//!
//! `stop_recording` runs off the scene's tick path: the avatar's recorder is taken under the
//! scene's lock (a pointer move), and turning its samples into a clip, writing that as glTF
//! and storing it run on the blocking pool. The clip joins its rig only once it is stored, so
//! a refusal — `quota_exceeded`, `storage_full`, `internal` — leaves no trace: the name is
//! free again, nothing half-written is restored, and the take is discarded (the error says
//! so).

use crate::auth::Caller;
use crate::changes;
use crate::state::Services;
use crate::store::recordings::{self, StoredRecording};
use crate::world::command::take_recording;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, RecordingInfo};
use posecast_proto::msg::AvatarId;

/// `stop_recording` (see the module doc).
///
/// # Errors
/// `unknown_avatar`, `not_allowed_now` (not recording), `invalid_value` (nothing recorded),
/// `conflict`, `quota_exceeded`, `storage_full` or `internal`; the take is then discarded.
pub(super) async fn stop_recording(
    state: &Services,
    caller: &Caller,
    avatar: &AvatarId,
) -> Result<CommandResult, Error> {
    let command = Command::StopRecording {
        avatar: avatar.clone(),
    };
    let before = changes::before(state, &command);
    let (rig_name, recorder) = take_recording(&state.world, avatar)?;
    let (frames, dropped) = (recorder.frames(), recorder.dropped());
    let rig = state.world.library.require(&rig_name)?;
    let store = state.store.recordings_dir();
    // The slow part, on the blocking pool: samples to clip, clip to glTF.
    let (clip, glb) = tokio::task::spawn_blocking(move || {
        let clip = recorder
            .finish()
            .map_err(|e| Error::invalid(format!("nothing to keep: {e}")))?;
        let glb = match store {
            Some(_) => Some(
                posecast_rigs::export::clip_glb(&rig, &clip)
                    .map_err(|e| Error::internal("cannot write the recording as glTF", &e))?,
            ),
            None => None,
        };
        Ok::<_, Error>((clip, glb))
    })
    .await
    .map_err(|e| Error::internal("recording task failed", &e))??;
    let info = RecordingInfo {
        asset: rig_name.clone(),
        clip: clip.name().to_owned(),
        duration: clip.duration(),
        frames,
        dropped,
    };
    // Uploads and recordings share one byte budget, checked and spent under one lock; the
    // lock also orders stops of two takes of one name (one is stored, the other refused).
    let _guard = state.store.assets_lock().await;
    if let Some(rig) = state.world.library.get(&rig_name)
        && rig.clip(&info.clip).is_some()
    {
        return Err(Error::Conflict(format!(
            "rig {rig_name} already has a clip {}",
            info.clip
        )));
    }
    if let (Some(dir), Some(glb)) = (state.store.recordings_dir(), glb) {
        let bytes = glb.len() as u64;
        crate::ingest::check_room(state, caller, &format!("recording {}", info.clip), bytes)?;
        let owner = caller.owner().map(str::to_owned);
        let (rig_for_file, clip_for_file) = (rig_name.clone(), info.clip.clone());
        let owner_for_file = owner.clone();
        tokio::task::spawn_blocking(move || {
            recordings::save(
                &dir,
                &rig_for_file,
                &clip_for_file,
                &glb,
                owner_for_file.as_deref(),
            )
        })
        .await
        .map_err(|e| Error::internal("store task failed", &e))?
        .map_err(|e| {
            Error::storing(
                &format!("cannot store recording {} (it is discarded)", info.clip),
                &e,
            )
        })?;
        state.store.add_upload_bytes(bytes);
        state.store.owners().add(owner.as_deref(), bytes);
        state.store.recordings().insert(
            (rig_name.clone(), info.clip.clone()),
            StoredRecording { bytes, owner },
        );
    }
    if let Err(e) = state.world.add_clip(&rig_name, clip) {
        // The rig went (delete_asset) while the take was written: take the file back.
        forget_recording(state, &rig_name, &info.clip).await;
        return Err(e);
    }
    let result = CommandResult::Recorded(Box::new(info));
    changes::after(state, &command, before, &result);
    Ok(result)
}

/// Removes stored recording `clip` of `rig` from the data folder and the counts (best
/// effort: a file left behind is restored at the next start, which is what was acknowledged
/// last).
async fn forget_recording(state: &Services, rig: &str, clip: &str) {
    let Some(stored) = state
        .store
        .recordings()
        .remove(&(rig.to_owned(), clip.to_owned()))
    else {
        return;
    };
    state.store.sub_upload_bytes(stored.bytes);
    state
        .store
        .owners()
        .remove(stored.owner.as_deref(), stored.bytes);
    if let Some(dir) = state.store.recordings_dir() {
        let (rig, clip) = (rig.to_owned(), clip.to_owned());
        match tokio::task::spawn_blocking(move || recordings::delete(&dir, &rig, &clip)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => tracing::warn!(error = %e, "cannot remove a recording's files"),
            Err(e) => tracing::warn!(error = %e, "cannot remove a recording's files"),
        }
    }
}

/// `delete_clip`: a stored recording leaves its rig, the data folder and the cluster's store.
///
/// # Errors
/// `unknown_asset`, `unknown_clip` (not a recording), `forbidden` (another token's),
/// `conflict` (an avatar plays it), `internal`/`storage_full` (the files could not be removed:
/// the clip stays).
pub(super) async fn delete_clip(
    state: &Services,
    caller: &Caller,
    rig: &str,
    clip: &str,
) -> Result<(), Error> {
    let _guard = state.store.assets_lock().await;
    let rig_now = state.world.library.require(rig)?;
    if rig_now.clip(clip).is_none() {
        return Err(Error::UnknownClip {
            rig: rig.to_owned(),
            clip: clip.to_owned(),
        });
    }
    let key = (rig.to_owned(), clip.to_owned());
    let stored = state.store.recordings().get(&key).cloned();
    let is_recording = stored.is_some() || !rig_now.asset.clips.iter().any(|c| c.name() == clip);
    if !is_recording {
        return Err(Error::NotAllowedNow(format!(
            "clip {clip} comes with asset {rig}'s files: delete the asset instead"
        )));
    }
    let owner = stored.as_ref().and_then(|s| s.owner.as_deref());
    state.config.access.authorize_delete(caller, owner)?;
    if let Some(avatar) = state.world.playing(rig, Some(clip)) {
        return Err(Error::Conflict(format!(
            "avatar {avatar} plays clip {clip} of rig {rig}: stop it first"
        )));
    }
    if let (Some(dir), Some(_)) = (state.store.recordings_dir(), &stored) {
        let (r, c) = (rig.to_owned(), clip.to_owned());
        tokio::task::spawn_blocking(move || recordings::delete(&dir, &r, &c))
            .await
            .map_err(|e| Error::internal("store task failed", &e))?
            .map_err(|e| Error::storing("cannot delete the recording", &e))?;
    }
    if let Some(cluster) = state.cluster() {
        cluster.unshare_recording(rig, clip).await;
    }
    state.world.remove_clip(rig, clip, false)?;
    if let Some(stored) = state.store.recordings().remove(&key) {
        state.store.sub_upload_bytes(stored.bytes);
        state
            .store
            .owners()
            .remove(stored.owner.as_deref(), stored.bytes);
    }
    Ok(())
}

/// `delete_asset`: an upload's rigs leave the library, its folder and its rigs' recordings
/// the data folder, and it leaves the cluster's store.
///
/// # Errors
/// `unknown_asset` (not an upload), `forbidden`, `conflict` (an avatar uses it), or
/// `internal`.
pub(super) async fn delete_asset(
    state: &Services,
    caller: &Caller,
    name: &str,
) -> Result<(), Error> {
    crate::ingest::delete(state, caller, name).await
}
