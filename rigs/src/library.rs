//! The rigs the server can put in scenes ([`Rig`]s: imported, normalised assets with their
//! clips), by name.

pub use crate::rig::{JointLimits, Rig};

use crate::clip::Clip;
use crate::import::ImportError;
use crate::import::files::{self, FileSet};
use crate::rig::PipelineOptions;
use posecast_core::error::Error;
use posecast_proto::msg::check_id;
use std::collections::BTreeMap;
use std::sync::{Arc, RwLock};

/// Every loaded rig, by name.
#[derive(Debug, Default)]
pub struct Library {
    rigs: RwLock<BTreeMap<String, Arc<Rig>>>,
}

impl Library {
    /// An empty library.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds or replaces a rig.
    pub fn insert(&self, rig: Rig) -> Arc<Rig> {
        let rig = Arc::new(rig);
        self.rigs
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .insert(rig.name.clone(), rig.clone());
        rig
    }

    /// Adds `clip` to rig `name`: the rig is replaced by one with the clip (avatars made
    /// from now on get it; the caller moves existing ones over). Returns the new rig.
    ///
    /// # Errors
    /// `unknown_asset`, or `conflict` when the rig has a clip of that name.
    pub fn add_clip(&self, name: &str, clip: Clip) -> Result<Arc<Rig>, Error> {
        self.add_clips(name, vec![clip])
    }

    /// [`Library::add_clip`] for several clips, in one new rig.
    ///
    /// # Errors
    /// `unknown_asset`, or `conflict` when the rig has a clip of one of those names (then
    /// none is added).
    pub fn add_clips(&self, name: &str, clips: Vec<Clip>) -> Result<Arc<Rig>, Error> {
        let mut rigs = self
            .rigs
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let rig = rigs.get(name).ok_or_else(|| Error::unknown_asset(name))?;
        let mut seen = std::collections::BTreeSet::new();
        for clip in &clips {
            if rig.clip(clip.name()).is_some() || !seen.insert(clip.name()) {
                return Err(Error::Conflict(format!(
                    "rig {name} already has a clip {}",
                    clip.name()
                )));
            }
        }
        let rig = Arc::new(rig.with_clips(clips));
        rigs.insert(name.to_owned(), rig.clone());
        Ok(rig)
    }

    /// Takes clip `clip` off rig `name` (the rig is replaced by one without it). Returns the
    /// new rig.
    ///
    /// # Errors
    /// `unknown_asset` or `unknown_clip`.
    pub fn remove_clip(&self, name: &str, clip: &str) -> Result<Arc<Rig>, Error> {
        let mut rigs = self
            .rigs
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let rig = rigs.get(name).ok_or_else(|| Error::unknown_asset(name))?;
        let rig = Arc::new(rig.without_clip(clip).ok_or_else(|| Error::UnknownClip {
            rig: name.to_owned(),
            clip: clip.to_owned(),
        })?);
        rigs.insert(name.to_owned(), rig.clone());
        Ok(rig)
    }

    /// Removes rig `name` from the library (`delete_asset`); the rigs it was.
    pub fn remove(&self, name: &str) -> Option<Arc<Rig>> {
        self.rigs
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .remove(name)
    }

    /// The rig named `name`, or the typed error every caller reports.
    ///
    /// # Errors
    /// `unknown_asset`.
    pub fn require(&self, name: &str) -> Result<Arc<Rig>, Error> {
        self.get(name).ok_or_else(|| Error::unknown_asset(name))
    }

    /// A rig by name.
    #[must_use]
    pub fn get(&self, name: &str) -> Option<Arc<Rig>> {
        self.rigs
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(name)
            .cloned()
    }

    /// Every rig, by name.
    #[must_use]
    pub fn all(&self) -> Vec<Arc<Rig>> {
        self.rigs
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .values()
            .cloned()
            .collect()
    }
}

fn import_failed(e: &ImportError) -> Error {
    Error::ImportFailed(e.to_string())
}

/// Checks an upload's name: an id ([`check_id`]) that does not start with `.` (a hidden or
/// parent folder) and does not contain `.corrupt` (how bad stored files are set aside).
///
/// # Errors
/// `invalid_value`.
pub fn check_name(name: &str) -> Result<(), Error> {
    check_id("asset", name).map_err(|e| Error::invalid_field("asset", e.message))?;
    if name.starts_with('.') || name.contains(".corrupt") {
        return Err(Error::invalid_field(
            "asset",
            "asset names must not start with '.' or contain '.corrupt'",
        ));
    }
    Ok(())
}

/// The rig name an imported asset gets when uploaded as `name`: the main file's stem becomes
/// `name`, so `model.glb` gives `name` and a multi-skin `model.glb` gives `name#<skin>`.
fn rename(asset: &str, main_stem: &str, name: &str) -> String {
    match asset.strip_prefix(main_stem) {
        Some(rest) if rest.starts_with('#') => format!("{name}{rest}"),
        _ => name.to_owned(),
    }
}

/// Imports and normalises a file set as asset `name` with the default pipeline (CPU-bound:
/// call it off the async workers).
///
/// # Errors
/// As [`prepare_with`].
pub fn prepare(name: &str, set: &FileSet) -> Result<Vec<Rig>, Error> {
    prepare_with(name, set, &PipelineOptions::default())
}

/// Imports and normalises a file set as asset `name` with `options` (CPU-bound: call it off
/// the async workers). The rigs remember the upload they came from.
///
/// # Errors
/// `import_failed` with the importer's message (file and place) or the
/// normalisation's.
pub fn prepare_with(
    name: &str,
    set: &FileSet,
    options: &PipelineOptions,
) -> Result<Vec<Rig>, Error> {
    let main = set.main_file().map_err(|e| import_failed(&e))?;
    let main_stem = files::stem(main).to_owned();
    let imported = files::import_set(set).map_err(|e| import_failed(&e))?;
    imported
        .into_iter()
        .map(|mut asset| {
            asset.name = rename(&asset.name, &main_stem, name);
            let rig_name = asset.name.clone();
            let mut rig = Rig::from_asset(asset, options).map_err(|e| {
                Error::ImportFailed(format!("{main}: rig {rig_name}: normalisation failed: {e}"))
            })?;
            rig.upload = Some(name.to_owned());
            Ok(rig)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names() {
        assert_eq!(rename("model", "model", "x"), "x");
        assert_eq!(rename("model#skin3", "model", "x"), "x#skin3");
        assert_eq!(rename("other", "model", "x"), "x");
        assert!(check_name("..").is_err());
        assert!(check_name("a.corrupt").is_err());
        assert!(check_name("a.corrupt.1").is_err());
        assert!(check_name("a/b").is_err());
        assert!(check_name("wasp-2.v1").is_ok());
    }
}
