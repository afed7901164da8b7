//! Importers, one file per format, all producing [`Asset`]s.
//!
//! - [`gltf`]: glTF 2.0 (`.gltf` with embedded or external buffers, `.glb`), VRM (`.vrm`) and
//!   VRM animations (`.vrma`).
//! - [`skel`], [`skin`], [`anim`], [`morph`], assembled by [`cse169`] and
//!   [`files::skel_with_morphs`]: the UCSD CSE169 course formats.
//! - [`bvh`]: Biovision hierarchy motion capture.
//!
//! Every importer works on bytes or text so the server can import uploads; [`load_path`]
//! adds the file-system conventions. Malformed input gives an [`ImportError`] naming the file
//! and the place, never a panic; counts in files are checked against the remaining input
//! before anything is allocated for them.

mod accessor;
pub mod anim;
pub mod bvh;
pub mod cse169;
mod error;
pub mod files;
pub mod gltf;
pub mod morph;
pub mod skel;
pub mod skin;
mod text;

pub use error::ImportError;

use std::path::{Path, PathBuf};

use crate::asset::Asset;

/// Largest file [`load_path`] reads.
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// Loads the assets in a file, by extension (case-insensitive):
/// - `.gltf` / `.glb`: one asset per skin (see [`gltf::from_slice`]); external buffers are
///   read relative to the file's folder.
/// - `.vrm`: a GLB, as `.glb`; `.vrma` (a VRM animation): one skeleton-only asset with clips
///   ([`gltf::vrma`]).
/// - `.skel`: one asset. A `.skin` with the same stem in the same folder is its mesh,
///   `<stem>.anim` and `<stem>_*.anim` there are its clips (e.g. `wasp.skel`, `wasp.skin`,
///   `wasp_walk.anim`), and `<stem>.morph` and `<stem>_*.morph` there are morph targets of
///   its mesh (`wasp_smile.morph`: target `wasp_smile`), each in name order. A `.morph` beside
///   a `.skel` without a `.skin` is an error.
/// - `.bvh`: one asset with one clip.
///
/// A `.skin`, `.anim` or `.morph` alone is refused: it needs its `.skel`.
pub fn load_path(path: &Path) -> Result<Vec<Asset>, ImportError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    let name = file_name(path);
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("asset")
        .to_owned();
    match ext.as_str() {
        "gltf" | "glb" | "vrm" | "vrma" => {
            let bytes = read(path)?;
            let dir = path.parent().unwrap_or(Path::new("."));
            let external = |uri: &str| read(&dir.join(uri));
            gltf::from_slice_with_base(&name, &bytes, Some(&external))
        }
        "bvh" => Ok(vec![bvh::parse(&name, &read_text(path)?)?]),
        "skel" => {
            let skin_path = path.with_extension("skin");
            let skin = if skin_path.is_file() {
                Some((file_name(&skin_path), read_text(&skin_path)?))
            } else {
                None
            };
            let companions = |ext: &str| {
                siblings(path, &stem, ext)
                    .iter()
                    .map(|p| Ok((file_name(p), read_text(p)?)))
                    .collect::<Result<Vec<_>, ImportError>>()
            };
            Ok(vec![files::skel_with_morphs(
                &name,
                &read_text(path)?,
                skin,
                companions("anim")?,
                companions("morph")?,
            )?])
        }
        "skin" | "anim" | "morph" => Err(ImportError::Unsupported {
            file: name,
            message: format!("a .{ext} file needs its .skel: load the .skel instead"),
        }),
        _ => Err(ImportError::UnknownFormat {
            path: path.to_owned(),
        }),
    }
}

fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// `<stem>.<ext>` and `<stem>_*.<ext>` (extension in any case) beside `skel`, in name order.
fn siblings(skel: &Path, stem: &str, ext: &str) -> Vec<PathBuf> {
    let dir = skel.parent().unwrap_or(Path::new("."));
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let prefix = format!("{stem}_");
    let mut found: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            let has_ext = p
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| e.eq_ignore_ascii_case(ext));
            let s = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
            has_ext && (s == stem || s.starts_with(&prefix))
        })
        .collect();
    found.sort();
    found
}

pub(crate) fn read(path: &Path) -> Result<Vec<u8>, ImportError> {
    let io = |source| ImportError::Io {
        path: path.to_owned(),
        source,
    };
    let len = std::fs::metadata(path).map_err(io)?.len();
    if len > MAX_FILE_BYTES {
        return Err(io(std::io::Error::other(format!(
            "file is {len} bytes, more than the {MAX_FILE_BYTES} limit"
        ))));
    }
    std::fs::read(path).map_err(io)
}

fn read_text(path: &Path) -> Result<String, ImportError> {
    let bytes = read(path)?;
    String::from_utf8(bytes).map_err(|e| ImportError::Io {
        path: path.to_owned(),
        source: std::io::Error::new(std::io::ErrorKind::InvalidData, e),
    })
}
