//! Importing a set of files held in memory (an upload, or an uploaded asset restored from the
//! data folder): the same conventions as [`super::load_path`], with every companion file looked
//! up in the set and never on the file system.
//!
//! A set holds exactly one main file, which gives the format:
//! - one `.glb` (or `.vrm`, or `.vrma`, which are GLBs), or one `.gltf` plus the `.bin` (and image) files
//!   its buffer URIs name;
//! - one `.bvh`;
//! - one `.skel`, at most one `.skin` (its mesh), any number of `.anim` files (its clips,
//!   named by file stem, in name order) and any number of `.morph` files (morph targets of the
//!   `.skin`, named by file stem, in name order; a `.morph` without a `.skin` is refused).
//!   Unlike a folder, an upload belongs together, so the `.skin`, `.anim` and `.morph` names
//!   need not share the `.skel`'s stem.

use std::collections::BTreeMap;

use posecast_proto::morph::MorphTarget;

use super::gltf::listed;
use super::{ImportError, anim, bvh, cse169, gltf, morph, skel, skin};
use crate::asset::Asset;

/// Longest file name in a set.
pub const MAX_FILE_NAME: usize = 128;

/// Most displacement vectors the `.morph` files of one `.skin` may make, counting two per
/// vertex per target (positions and normals): a sparse `.morph` of a few bytes makes a full
/// list per target, so file sizes alone do not bound the memory (2²⁴ vectors: 192 MiB).
pub const MAX_MORPH_VECTORS: usize = 1 << 24;

/// Files by name (a plain file name: no folders).
#[derive(Debug, Default, Clone)]
pub struct FileSet {
    files: BTreeMap<String, Vec<u8>>,
}

/// A file's extension, lower case (`""` when it has none).
#[must_use]
pub fn extension(name: &str) -> String {
    name.rsplit_once('.')
        .map(|(_, e)| e.to_ascii_lowercase())
        .unwrap_or_default()
}

/// A file's name without its extension.
#[must_use]
pub fn stem(name: &str) -> &str {
    name.rsplit_once('.').map_or(name, |(s, _)| s)
}

impl FileSet {
    /// An empty set.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a file. The name must be a plain file name (1–128 letters, digits, `-`, `_`,
    /// `.` or space, not starting with `.`), unique in the set.
    ///
    /// # Errors
    /// [`ImportError::Unsupported`] naming the file.
    pub fn insert(&mut self, name: &str, bytes: Vec<u8>) -> Result<(), ImportError> {
        let ok = !name.is_empty()
            && name.len() <= MAX_FILE_NAME
            && !name.starts_with('.')
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | ' '));
        if !ok {
            return Err(ImportError::Unsupported {
                file: name.to_owned(),
                message: format!(
                    "file names must be 1-{MAX_FILE_NAME} letters, digits, '-', '_', '.' or \
                     spaces, not starting with '.'"
                ),
            });
        }
        if self.files.contains_key(name) {
            return Err(ImportError::Unsupported {
                file: name.to_owned(),
                message: "the same file name appears twice".to_owned(),
            });
        }
        self.files.insert(name.to_owned(), bytes);
        Ok(())
    }

    /// A file's bytes.
    #[must_use]
    pub fn get(&self, name: &str) -> Option<&[u8]> {
        self.files.get(name).map(Vec::as_slice)
    }

    /// Every file, by name.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &[u8])> {
        self.files.iter().map(|(n, b)| (n.as_str(), b.as_slice()))
    }

    /// Number of files.
    #[must_use]
    pub fn len(&self) -> usize {
        self.files.len()
    }

    /// Whether the set is empty.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// Total bytes.
    #[must_use]
    pub fn total_bytes(&self) -> usize {
        self.files.values().map(Vec::len).sum()
    }

    /// The main file (`.glb`, `.gltf`, `.bvh` or `.skel`).
    ///
    /// # Errors
    /// No main file (a `.skin`, `.anim` or `.morph` alone is refused: it needs its `.skel`),
    /// more than one, or a file the main file's format does not use.
    pub fn main_file(&self) -> Result<&str, ImportError> {
        let mains: Vec<&str> = self
            .files
            .keys()
            .map(String::as_str)
            .filter(|n| {
                matches!(
                    extension(n).as_str(),
                    "glb" | "gltf" | "vrm" | "vrma" | "bvh" | "skel"
                )
            })
            .collect();
        let main = match mains.as_slice() {
            [one] => *one,
            [] => {
                let first = self.files.keys().next().cloned().unwrap_or_default();
                let ext = extension(&first);
                let message = if matches!(ext.as_str(), "skin" | "anim" | "morph") {
                    format!("a .{ext} file needs its .skel: upload the .skel with it")
                } else {
                    "no .glb, .gltf, .vrm, .vrma, .bvh or .skel file".to_owned()
                };
                return Err(ImportError::Unsupported {
                    file: first,
                    message,
                });
            }
            [first, second, ..] => {
                return Err(ImportError::Unsupported {
                    file: (*second).to_owned(),
                    message: format!("one asset per upload: {first} is already its main file"),
                });
            }
        };
        let main_ext = extension(main);
        for name in self.files.keys().filter(|n| n.as_str() != main) {
            let ext = extension(name);
            let fits = match main_ext.as_str() {
                "gltf" => !matches!(ext.as_str(), "skin" | "anim" | "morph"),
                "skel" => matches!(ext.as_str(), "skin" | "anim" | "morph"),
                _ => false,
            };
            if !fits {
                return Err(ImportError::Unsupported {
                    file: name.clone(),
                    message: format!("a .{main_ext} upload ({main}) does not use this file"),
                });
            }
        }
        Ok(main)
    }
}

/// Imports a file set (see the module doc). Asset names follow the main file's stem, as with
/// [`super::load_path`].
///
/// # Errors
/// The set is not one asset, or an importer refused a file (the error names file and place).
pub fn import_set(set: &FileSet) -> Result<Vec<Asset>, ImportError> {
    let main = set.main_file()?;
    let bytes = set.get(main).unwrap_or_default();
    match extension(main).as_str() {
        "glb" | "gltf" | "vrm" | "vrma" => {
            let external = |uri: &str| {
                set.get(uri)
                    .map(<[u8]>::to_vec)
                    .ok_or_else(|| ImportError::Unsupported {
                        file: main.to_owned(),
                        message: format!("buffer file {uri:?} was not uploaded with it"),
                    })
            };
            gltf::from_slice_with_base(main, bytes, Some(&external))
        }
        "bvh" => Ok(vec![bvh::parse(main, text(main, bytes)?)?]),
        _ => {
            let skin = set
                .iter()
                .filter(|(n, _)| extension(n) == "skin")
                .map(|(n, b)| Ok((n.to_owned(), text(n, b)?.to_owned())))
                .collect::<Result<Vec<_>, ImportError>>()?;
            if skin.len() > 1 {
                return Err(ImportError::Unsupported {
                    file: skin[1].0.clone(),
                    message: "a .skel takes at most one .skin".to_owned(),
                });
            }
            let with_ext = |ext: &str| {
                set.iter()
                    .filter(|(n, _)| extension(n) == ext)
                    .map(|(n, b)| Ok((n.to_owned(), text(n, b)?.to_owned())))
                    .collect::<Result<Vec<_>, ImportError>>()
            };
            Ok(vec![skel_with_morphs(
                main,
                text(main, bytes)?,
                skin.into_iter().next(),
                with_ext("anim")?,
                with_ext("morph")?,
            )?])
        }
    }
}

/// A `.skel` with its optional `.skin` and its `.anim` clips, each `(file name, text)`; clips
/// are named by file stem. Shared by folders and uploads.
///
/// # Errors
/// Any file refused by its importer.
pub fn skel_with_companions(
    skel_name: &str,
    skel_text: &str,
    skin: Option<(String, String)>,
    anims: Vec<(String, String)>,
) -> Result<Asset, ImportError> {
    skel_with_morphs(skel_name, skel_text, skin, anims, Vec::new())
}

/// [`skel_with_companions`] with `.morph` files, each `(file name, text)`: morph targets of the
/// `.skin`'s mesh ([`morph::parse`]), named by file stem, in the order given (callers give name
/// order). The asset's notes say how many were kept and their names.
///
/// # Errors
/// Any file refused by its importer; a `.morph` without a `.skin`; two `.morph` files with one
/// stem (`a.morph`, `a.MORPH`), which would be one channel twice; more targets than
/// [`MAX_MORPH_VECTORS`] allows for the skin's vertex count.
pub fn skel_with_morphs(
    skel_name: &str,
    skel_text: &str,
    skin: Option<(String, String)>,
    anims: Vec<(String, String)>,
    morphs: Vec<(String, String)>,
) -> Result<Asset, ImportError> {
    let skel = skel::parse(skel_name, skel_text)?;
    let skin = skin
        .map(|(name, text)| skin::parse(&name, &text, &skel.skeleton).map(|s| (name, s)))
        .transpose()?;
    let (skin, morph_note) = match (skin, morphs.first()) {
        (None, Some((first, _))) => {
            return Err(ImportError::Unsupported {
                file: first.clone(),
                message: format!(
                    "a .morph moves the vertices of a .skin, and {skel_name} has none: add \
                     its .skin"
                ),
            });
        }
        (Some((skin_name, skin)), Some(_)) => {
            let (skin, note) = with_targets(&skin_name, skin, &morphs)?;
            (Some(skin), Some(note))
        }
        (skin, None) => (skin.map(|(_, s)| s), None),
    };
    let mut clips = Vec::with_capacity(anims.len());
    let mut notes = Vec::new();
    for (name, text) in anims {
        let (mut clip, n) = anim::parse_noted(&name, &text, &skel.skeleton)?;
        clip.set_name(stem(&name));
        clips.push(clip);
        notes.extend(n);
    }
    let mut asset = cse169::assemble(stem(skel_name), skel, skin, clips)?;
    asset.source.notes.extend(notes);
    asset.source.notes.extend(morph_note);
    Ok(asset)
}

/// `skin` with the targets of `morphs` (in their order), and the note that lists them.
fn with_targets(
    skin_name: &str,
    mut skin: skin::Skin,
    morphs: &[(String, String)],
) -> Result<(skin::Skin, String), ImportError> {
    let vertices = skin.mesh.vertex_count();
    let allowed = MAX_MORPH_VECTORS / vertices.saturating_mul(2).max(1);
    if let Some((name, _)) = morphs.get(allowed) {
        return Err(ImportError::Unsupported {
            file: name.clone(),
            message: format!(
                "{} .morph files over {skin_name} ({vertices} vertices): at most {allowed} \
                 (every target holds a displacement per vertex, {MAX_MORPH_VECTORS} in all)",
                morphs.len()
            ),
        });
    }
    let mut targets: Vec<MorphTarget> = Vec::with_capacity(morphs.len());
    for (name, text) in morphs {
        let target = morph::parse(name, text, &skin.mesh)?;
        if targets.iter().any(|t| t.name == target.name) {
            return Err(ImportError::Unsupported {
                file: name.clone(),
                message: format!(
                    "a second .morph named {:?}: one name is one channel",
                    target.name
                ),
            });
        }
        targets.push(target);
    }
    let names: Vec<String> = targets.iter().map(|t| t.name.clone()).collect();
    skin.mesh = skin
        .mesh
        .with_targets(targets)
        .map_err(|source| ImportError::Mesh {
            file: skin_name.to_owned(),
            mesh: skin_name.to_owned(),
            source,
        })?;
    let note = format!(
        "{} morph target(s) from .morph: {}",
        names.len(),
        listed(&names)
    );
    Ok((skin, note))
}

fn text<'a>(name: &str, bytes: &'a [u8]) -> Result<&'a str, ImportError> {
    std::str::from_utf8(bytes).map_err(|e| ImportError::Unsupported {
        file: name.to_owned(),
        message: format!("not UTF-8 text: {e}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn main_file_rules() {
        let mut set = FileSet::new();
        set.insert("wasp.skin", b"x".to_vec()).unwrap();
        let e = set.main_file().unwrap_err().to_string();
        assert!(e.contains("needs its .skel"), "{e}");
        set.insert("wasp.skel", b"x".to_vec()).unwrap();
        assert_eq!(set.main_file().unwrap(), "wasp.skel");
        set.insert("a.glb", b"x".to_vec()).unwrap();
        assert!(set.main_file().is_err());
        assert!(set.insert("../etc", Vec::new()).is_err());
        assert!(set.insert("a/b.glb", Vec::new()).is_err());
        assert!(set.insert("a.glb", Vec::new()).is_err());
    }
}
