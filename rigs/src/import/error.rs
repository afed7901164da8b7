//! The one error type of every importer: what went wrong, in which file, and where.

use std::path::PathBuf;

use posecast_proto::{MeshError, SkeletonError};

use crate::clip::ClipError;

/// Why a file could not be imported. Every variant names the file (as given to the importer)
/// and, where there is one, the place: line, accessor, node, mesh or channel.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "{path}: unknown file type (expected .gltf, .glb, .vrm, .vrma, .skel, .skin, .anim or .bvh)"
    )]
    UnknownFormat { path: PathBuf },
    /// A token that does not fit the grammar.
    #[error("{file}: line {line}: expected {expected}, found {found:?}")]
    Syntax {
        file: String,
        line: usize,
        expected: String,
        found: String,
    },
    /// The input stopped early.
    #[error("{file}: unexpected end of file, expected {expected}")]
    Eof { file: String, expected: String },
    /// A count in the file that the rest of the file cannot hold (checked before allocating).
    #[error("{file}: line {line}: {what} count {count} needs more data than the file has")]
    Count {
        file: String,
        line: usize,
        what: String,
        count: usize,
    },
    /// A value that parses but makes no sense (joint out of range, singular matrix, …).
    #[error("{file}: line {line}: {message}")]
    Invalid {
        file: String,
        line: usize,
        message: String,
    },
    #[error("{file}: skeleton: {source}")]
    Skeleton { file: String, source: SkeletonError },
    #[error("{file}: mesh {mesh:?}: {source}")]
    Mesh {
        file: String,
        mesh: String,
        source: MeshError,
    },
    #[error("{file}: {place}: {source}")]
    Clip {
        file: String,
        place: String,
        source: ClipError,
    },
    /// The glTF JSON or GLB container is malformed.
    #[error("{file}: glTF: {source}")]
    Gltf { file: String, source: gltf::Error },
    /// The glTF document breaks the specification's rules: the first problems (at most
    /// [`ImportError::MAX_LISTED`]) and how many there are, so a file with thousands of them
    /// gives a message of a few lines.
    #[error("{file}: invalid glTF: {}", listed(problems, *count))]
    GltfInvalid {
        file: String,
        problems: Vec<String>,
        count: usize,
    },
    #[error("{file}: accessor {accessor}: {message}")]
    Accessor {
        file: String,
        accessor: usize,
        message: String,
    },
    #[error("{file}: buffer {buffer}: {message}")]
    Buffer {
        file: String,
        buffer: usize,
        message: String,
    },
    #[error("{file}: node {node}: {message}")]
    Node {
        file: String,
        node: usize,
        message: String,
    },
    /// A VRM animation's `VRMC_vrm_animation` extension is malformed or does not fit the
    /// document (a bone on a missing node, a bone twice, no hips, …).
    #[error("{file}: {source}")]
    VrmAnimation {
        file: String,
        source: crate::import::gltf::vrma::VrmaError,
    },
    /// A file-level problem with no narrower place (e.g. a glTF without skins).
    #[error("{file}: {message}")]
    Unsupported { file: String, message: String },
}

impl ImportError {
    /// Most problems an error lists one by one; the rest are counted.
    pub const MAX_LISTED: usize = 5;
}

/// `a; b; c (and 12 more, 15 in all)`.
fn listed(problems: &[String], count: usize) -> String {
    let mut s = problems.join("; ");
    if count > problems.len() {
        s.push_str(&format!(
            " (and {} more, {count} in all)",
            count - problems.len()
        ));
    }
    s
}
