//! Uploaded assets shared by the cluster: JetStream object store `posecast_assets`, one object
//! per upload, named as the upload, holding a bundle of its files and pipeline options.
//!
//! An upload (or its new clips, or its new options) is put there before it is acknowledged;
//! every server looks at the bucket every third of the lease time (at start before it owns
//! any scene) and imports what changed with the bundle's options, as the uploading server did.
//! Objects are compared by their `nuid`, which every put renews.
//!
//! Recorded clips (`stop_recording`) go into the same bucket as objects named
//! `recording:<rig>/<clip>` (`:` is not allowed in an upload's name) holding the glTF file the
//! data folder keeps; every server puts them on its rig as it restores them at start.
//!
//! A bundle: `PCA1`, a little-endian `u32` header length, the header (JSON: format, name,
//! options, each file's name and size) and the files' bytes one after the other. One object is
//! one put, so a reader sees every file of one version or the previous version, never a mix.

use super::{Cluster, lock, unavailable};
use crate::state::Services;
use crate::store::snapshot::SceneFile;
use async_nats::jetstream::object_store::{self, ObjectMetadata};
use futures_util::StreamExt;
use posecast_core::error::Error;
use posecast_rigs::import::files::FileSet;
use posecast_rigs::rig::PipelineOptions;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use tokio::io::AsyncReadExt;
use tracing::{info, warn};

/// The bucket of uploaded assets.
pub(super) const ASSETS_BUCKET: &str = "posecast_assets";
const MAGIC: &[u8; 4] = b"PCA1";
/// Version of the bundle's header.
const BUNDLE_FORMAT: u32 = 1;
/// Bound on a bundle's header (names and options; the files are bounded by the quota).
const MAX_HEADER: usize = 1 << 20;

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Header {
    format: u32,
    name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    options: Option<PipelineOptions>,
    files: Vec<Entry>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    name: String,
    size: u64,
}

/// Upload `name`'s bundle.
fn encode(name: &str, files: &FileSet, options: &PipelineOptions) -> Result<Vec<u8>, Error> {
    let header = Header {
        format: BUNDLE_FORMAT,
        name: name.to_owned(),
        options: (*options != PipelineOptions::default()).then(|| options.clone()),
        files: files
            .iter()
            .map(|(n, b)| Entry {
                name: n.to_owned(),
                size: b.len() as u64,
            })
            .collect(),
    };
    let json = serde_json::to_vec(&header).map_err(|e| Error::internal("cannot serialise", &e))?;
    let len = u32::try_from(json.len())
        .map_err(|_| Error::internal("asset header too long", &json.len()))?;
    let mut out = Vec::with_capacity(8 + json.len() + files.total_bytes());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(&json);
    for (_, bytes) in files.iter() {
        out.extend_from_slice(bytes);
    }
    Ok(out)
}

/// A bundle's name, files and options; the reason when it is not a well-formed bundle.
fn decode(bytes: &[u8]) -> Result<(String, FileSet, PipelineOptions), String> {
    let rest = bytes
        .strip_prefix(MAGIC.as_slice())
        .ok_or("not a posecast asset bundle (no PCA1 magic)")?;
    let (len, rest) = rest
        .split_first_chunk::<4>()
        .ok_or("bundle cut short in its header length")?;
    let len = u32::from_le_bytes(*len) as usize;
    if len > MAX_HEADER || len > rest.len() {
        return Err(format!(
            "bundle header of {len} bytes (at most {MAX_HEADER}, {} left)",
            rest.len()
        ));
    }
    let (json, mut data) = rest.split_at(len);
    let header: Header = serde_json::from_slice(json).map_err(|e| format!("bundle header: {e}"))?;
    if header.format != BUNDLE_FORMAT {
        return Err(format!(
            "bundle format {} (this server reads {BUNDLE_FORMAT})",
            header.format
        ));
    }
    let mut set = FileSet::new();
    for entry in &header.files {
        let size = usize::try_from(entry.size).unwrap_or(usize::MAX);
        if size > data.len() {
            return Err(format!(
                "file {} of {size} bytes but {} left in the bundle",
                entry.name,
                data.len()
            ));
        }
        let (file, more) = data.split_at(size);
        set.insert(&entry.name, file.to_vec())
            .map_err(|e| e.to_string())?;
        data = more;
    }
    if !data.is_empty() {
        return Err(format!("{} bytes after the last file", data.len()));
    }
    Ok((header.name, set, header.options.unwrap_or_default()))
}

/// Opens object store `name`, creating its stream on the first start (by hand, as the
/// key-value buckets: the client's `create_object_store` asks for account information servers
/// before 2.10 do not give). The layout is the object-store one: chunks and metadata
/// subjects, rollup.
pub(super) async fn open(
    js: &async_nats::jetstream::Context,
    name: &'static str,
) -> Result<Bucket, String> {
    let config = async_nats::jetstream::stream::Config {
        name: format!("OBJ_{name}"),
        subjects: vec![format!("$O.{name}.C.>"), format!("$O.{name}.M.>")],
        discard: async_nats::jetstream::stream::DiscardPolicy::New,
        allow_rollup: true,
        allow_direct: true,
        num_replicas: 1,
        ..Default::default()
    };
    let stream = js.get_or_create_stream(config).await.map_err(|e| {
        format!("cannot create object store {name} ({e}): is JetStream enabled (nats-server -js)?")
    })?;
    js.get_object_store(name)
        .await
        .map(|store| Bucket(store, stream, name))
        .map_err(|e| format!("cannot open object store {name}: {e}"))
}

/// An object store (the client's handle has no `Debug`), its stream, whose last sequence
/// number tells whether anything was put since the last look, and its name.
pub(super) struct Bucket(
    pub(super) object_store::ObjectStore,
    pub(super) async_nats::jetstream::stream::Stream,
    &'static str,
);

impl std::fmt::Debug for Bucket {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.2)
    }
}

/// The object name of recorded clip `clip` of rig `rig`.
fn recording_name(rig: &str, clip: &str) -> String {
    format!("{RECORDING}{rig}/{clip}")
}

/// The prefix of recordings' object names.
const RECORDING: &str = "recording:";

/// Why a bucket object was not loaded: worth retrying (NATS) or not (its content).
enum Unloaded {
    Nats(String),
    Content(String),
}

impl Cluster {
    /// The largest bundle this server reads: its asset quota and the header's bound.
    fn max_bundle(state: &Services) -> u64 {
        state
            .config
            .quotas
            .max_asset_bytes
            .saturating_add(MAX_HEADER as u64 + 8)
    }

    /// Puts upload `name`'s bundle into the bucket; this server has it already.
    pub(super) async fn share(
        &self,
        name: &str,
        files: &FileSet,
        options: &PipelineOptions,
    ) -> Result<(), Error> {
        let bundle = encode(name, files, options)?;
        let meta = ObjectMetadata {
            name: name.to_owned(),
            ..Default::default()
        };
        let put = self
            .conn
            .assets
            .0
            .put(meta, &mut bundle.as_slice())
            .await
            .map_err(|e| unavailable("cannot store the asset in NATS", &e))?;
        if let Some(s) = self.state() {
            s.metrics.cluster.published(bundle.len());
        }
        lock(&self.applied).insert(name.to_owned(), put.nuid);
        Ok(())
    }

    /// Removes upload `name` from the bucket.
    pub(super) async fn unshare(&self, name: &str) {
        if let Err(e) = self.conn.assets.0.delete(name).await {
            warn!(asset = %name, error = %e, "cannot remove the asset from NATS");
        }
        lock(&self.applied).remove(name);
    }

    /// Removes recorded clip `clip` of rig `rig` from the bucket (`delete_clip`).
    pub(super) async fn unshare_recording(&self, rig: &str, clip: &str) {
        self.unshare(&recording_name(rig, clip)).await;
    }

    /// Puts recorded clip `clip` of rig `rig` (its glTF file) into the bucket.
    pub(super) async fn put_recording(
        &self,
        rig: &str,
        clip: &str,
        glb: Vec<u8>,
    ) -> Result<(), Error> {
        let name = recording_name(rig, clip);
        let meta = ObjectMetadata {
            name: name.clone(),
            ..Default::default()
        };
        let put = self
            .conn
            .assets
            .0
            .put(meta, &mut glb.as_slice())
            .await
            .map_err(|e| unavailable("cannot store the recording in NATS", &e))?;
        if let Some(s) = self.state() {
            s.metrics.cluster.published(glb.len());
        }
        lock(&self.applied).insert(name, put.nuid);
        Ok(())
    }

    /// Upload `name`'s bundle as the bucket holds it now (`None`: not there).
    async fn fetch(
        &self,
        state: &Services,
        name: &str,
    ) -> Result<Option<(String, FileSet, PipelineOptions)>, Unloaded> {
        match self.fetch_bytes(state, name).await? {
            Some(bytes) => decode(&bytes).map(Some).map_err(Unloaded::Content),
            None => Ok(None),
        }
    }

    /// Object `name`'s bytes (`None`: not there), bounded by the asset quota.
    async fn fetch_bytes(&self, state: &Services, name: &str) -> Result<Option<Vec<u8>>, Unloaded> {
        let mut object = match self.conn.assets.0.get(name).await {
            Ok(object) => object,
            Err(e) if e.kind() == object_store::GetErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Unloaded::Nats(e.to_string())),
        };
        let max = Self::max_bundle(state);
        if object.info.size as u64 > max {
            return Err(Unloaded::Content(format!(
                "it holds {} bytes, more than this server's asset quota allows ({max} with the bundle's header; --max-asset-bytes)",
                object.info.size
            )));
        }
        let mut bytes = Vec::with_capacity(object.info.size);
        // Bounded whatever the size claimed: a longer object is refused, not read whole.
        (&mut object)
            .take(max + 1)
            .read_to_end(&mut bytes)
            .await
            .map_err(|e| Unloaded::Nats(e.to_string()))?;
        state.metrics.cluster.received(bytes.len());
        if bytes.len() as u64 > max {
            return Err(Unloaded::Content(format!(
                "it holds more than {max} bytes (--max-asset-bytes)"
            )));
        }
        Ok(Some(bytes))
    }

    /// Puts recording object `name` (`recording:<rig>/<clip>`) on its rig. `Ok(false)`: its
    /// rig is not loaded here (yet: it may be an upload still to come).
    async fn load_recording(&self, state: &Services, name: &str) -> Result<bool, Unloaded> {
        let (rig_name, clip) = name
            .strip_prefix(RECORDING)
            .and_then(|rest| rest.rsplit_once('/'))
            .ok_or_else(|| Unloaded::Content("not a recording's name".into()))?;
        let Some(rig) = state.world.library.get(rig_name) else {
            return Ok(false);
        };
        if rig.clip(clip).is_some() {
            // Recorded here, or loaded before.
            return Ok(true);
        }
        let Some(bytes) = self.fetch_bytes(state, name).await? else {
            return Ok(true);
        };
        let clip = crate::store::recordings::recording_from_bytes(&rig, clip, &bytes)
            .map_err(|e| Unloaded::Content(e.to_string()))?;
        state
            .world
            .add_clip(rig_name, clip)
            .map_err(|e| Unloaded::Content(e.to_string()))?;
        Ok(true)
    }

    /// Upload `name`'s files as the bucket holds them.
    pub(super) async fn shared_files(&self, name: &str) -> Result<Option<FileSet>, Error> {
        let Some(state) = self.state() else {
            return Err(Error::Unavailable("the server is stopping".into()));
        };
        match self.fetch(&state, name).await {
            Ok(found) => Ok(found.map(|(_, set, _)| set)),
            Err(Unloaded::Nats(e)) => Err(unavailable("cannot read the asset from NATS", &e)),
            Err(Unloaded::Content(e)) => Err(Error::internal(
                &format!("the cluster's copy of asset {name} is unusable"),
                &e,
            )),
        }
    }

    /// Imports every upload of the bucket this server does not have as stored there: new
    /// ones, and new versions (clips added, options changed) of the others. One that cannot
    /// be used (malformed, over a quota, refused by the importer, or named as a rig this
    /// server loaded itself) is logged once per version and changes nothing here.
    pub(super) async fn sync_assets(&self, state: &Services) -> Result<(), Error> {
        // One request when nothing was put since the last complete look (the usual case),
        // rather than a consumer over every object's metadata.
        let last = self
            .conn
            .assets
            .1
            .get_info()
            .await
            .map_err(|e| unavailable("cannot read the cluster's assets", &e))?
            .state
            .last_sequence;
        if *lock(&self.assets_seen) == Some(last) {
            return Ok(());
        }
        let mut listed = self
            .conn
            .assets
            .0
            .list()
            .await
            .map_err(|e| unavailable("cannot list the cluster's assets", &e))?;
        let mut objects = Vec::new();
        while let Some(info) = listed.next().await {
            let info = info.map_err(|e| unavailable("cannot list the cluster's assets", &e))?;
            if !info.deleted {
                objects.push((info.name, info.nuid));
            }
        }
        // Uploads before recordings: a recording's rig may be an upload of the same look.
        objects.sort_by_key(|(name, _)| name.starts_with(RECORDING));
        let mut waiting = false;
        for (name, nuid) in objects {
            if lock(&self.applied).get(&name) == Some(&nuid) {
                continue;
            }
            if name.starts_with(RECORDING) {
                match self.load_recording(state, &name).await {
                    Ok(true) => {
                        info!(recording = %name, "loaded a recording from the cluster");
                    }
                    Ok(false) => {
                        // Its rig may come later: looked at again at the next look.
                        waiting = true;
                        continue;
                    }
                    Err(Unloaded::Nats(e)) => {
                        return Err(unavailable("cannot read a recording from NATS", &e));
                    }
                    Err(Unloaded::Content(e)) => {
                        warn!(recording = %name, error = %e, "the cluster's recording is not loaded here (nothing changed)");
                    }
                }
                lock(&self.applied).insert(name, nuid);
                continue;
            }
            // Under the assets lock, as uploads here: one that was just shared from here is
            // recorded as applied before the lock is let go.
            let _guard = state.store.assets_lock().await;
            if lock(&self.applied).get(&name) == Some(&nuid) {
                continue;
            }
            let outcome = match self.fetch(state, &name).await {
                Ok(Some((stored_name, set, options))) if stored_name == name => {
                    crate::ingest::adopt_shared(state, &name, set, options)
                        .await
                        .map_err(|e| e.to_string())
                }
                Ok(Some((stored_name, ..))) => {
                    Err(format!("the bundle names asset {stored_name}, not {name}"))
                }
                Ok(None) => continue,
                Err(Unloaded::Nats(e)) => {
                    return Err(unavailable("cannot read an asset from NATS", &e));
                }
                Err(Unloaded::Content(e)) => Err(e),
            };
            match outcome {
                Ok(infos) => {
                    let rigs: Vec<&str> = infos.iter().map(|i| i.name.as_str()).collect();
                    info!(asset = %name, ?rigs, "loaded an upload from the cluster");
                }
                Err(e) => {
                    warn!(asset = %name, error = %e, "the cluster's upload is not loaded here (nothing changed)");
                }
            }
            lock(&self.applied).insert(name, nuid);
        }
        if !waiting {
            *lock(&self.assets_seen) = Some(last);
        }
        Ok(())
    }

    /// The assets a scene's snapshot names (its avatars' rigs and the rigs their clips are
    /// retargeted from) that this server has not loaded, and the clips they play that those
    /// rigs lack here (`rig/clip`: a recording not loaded yet).
    pub(super) fn missing_assets(
        world: &crate::world::World,
        file: &SceneFile,
    ) -> BTreeSet<String> {
        let mut missing = BTreeSet::new();
        for a in &file.avatars {
            let source = a
                .playback
                .as_ref()
                .and_then(|p| p.from_asset.clone())
                .unwrap_or_else(|| a.asset.clone());
            for name in [&a.asset, &source] {
                if world.library.get(name).is_none() {
                    missing.insert(name.clone());
                }
            }
            if let (Some(p), Some(rig)) = (&a.playback, world.library.get(&source))
                && rig.clip(&p.clip).is_none()
            {
                missing.insert(format!("{source}/{}", p.clip));
            }
        }
        missing
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn files() -> FileSet {
        let mut set = FileSet::new();
        set.insert("w.skel", b"balljoint root {}".to_vec()).unwrap();
        set.insert("w_walk.anim", vec![0, 1, 2, 255]).unwrap();
        set
    }

    /// A bundle gives back the name, every file's bytes and the options.
    #[test]
    fn bundles_round_trip() {
        let options = PipelineOptions {
            humanoid: Some(false),
            ..PipelineOptions::default()
        };
        let bytes = encode("w", &files(), &options).unwrap();
        let (name, set, back) = decode(&bytes).unwrap();
        assert_eq!(name, "w");
        assert_eq!(set.get("w.skel"), Some(&b"balljoint root {}"[..]));
        assert_eq!(set.get("w_walk.anim"), Some(&[0u8, 1, 2, 255][..]));
        assert_eq!(set.len(), 2);
        assert_eq!(back, options);
    }

    /// Cut, lengthened or foreign bytes are refused with a reason, never a panic.
    #[test]
    fn malformed_bundles_are_refused() {
        let bytes = encode("w", &files(), &PipelineOptions::default()).unwrap();
        for cut in 0..bytes.len() {
            assert!(decode(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(decode(&longer).unwrap_err().contains("after the last file"));
        assert!(decode(b"glTF....").unwrap_err().contains("magic"));
        let mut huge = b"PCA1".to_vec();
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode(&huge).unwrap_err().contains("header"));
    }
}
