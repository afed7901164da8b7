//! The one error type of every importer: what went wrong, in which file, and where.

use std::path::PathBuf;

use posecast_proto::{MeshError, SkeletonError};

use crate::clip::ClipError;

/// Why a file could not be imported. Every variant names the file (as given to the importer)
/// and, where there is one, the place: line, accessor, node, mesh or channel.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be read: missing, unreadable, over the size limit, or (for a text
    /// format) not UTF-8.
    #[error("{path}: {source}")]
    Io {
        /// The path as given.
        path: PathBuf,
        /// What the read reported.
        source: std::io::Error,
    },
    /// The file's extension names no format an importer reads.
    #[error(
        "{path}: unknown file type (expected .gltf, .glb, .vrm, .vrma, .skel, .skin, .anim, .morph or .bvh)"
    )]
    UnknownFormat {
        /// The path as given.
        path: PathBuf,
    },
    /// A token that does not fit the grammar.
    #[error("{file}: line {line}: expected {expected}, found {found:?}")]
    Syntax {
        /// The file's name as given to the importer.
        file: String,
        /// The line of the token, from 1.
        line: usize,
        /// What the grammar allows there.
        expected: String,
        /// The token found instead.
        found: String,
    },
    /// The input stopped early.
    #[error("{file}: unexpected end of file, expected {expected}")]
    Eof {
        /// The file's name as given to the importer.
        file: String,
        /// What the grammar still needed.
        expected: String,
    },
    /// A count in the file that the rest of the file cannot hold (checked before allocating).
    #[error("{file}: line {line}: {what} count {count} needs more data than the file has")]
    Count {
        /// The file's name as given to the importer.
        file: String,
        /// The line of the count, from 1.
        line: usize,
        /// What is counted (vertices, keys, frames, …).
        what: String,
        /// The count the file gives.
        count: usize,
    },
    /// A value that parses but makes no sense (joint out of range, singular matrix, …).
    #[error("{file}: line {line}: {message}")]
    Invalid {
        /// The file's name as given to the importer.
        file: String,
        /// The line of the value, from 1; 0 for a problem of the whole file (counts that
        /// disagree).
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The joints the file describes do not make a valid [`posecast_proto::Skeleton`].
    #[error("{file}: skeleton: {source}")]
    Skeleton {
        /// The file's name as given to the importer.
        file: String,
        /// Why the skeleton was refused.
        source: SkeletonError,
    },
    /// A mesh in the file does not make a valid [`posecast_proto::SkinnedMesh`].
    #[error("{file}: mesh {mesh:?}: {source}")]
    Mesh {
        /// The file's name as given to the importer.
        file: String,
        /// The mesh's label: its glTF name (or index), `#primitive` when it has several; the
        /// file's name for a `.skin`.
        mesh: String,
        /// Why the mesh was refused.
        source: MeshError,
    },
    /// An animation's keys do not make a valid curve or clip.
    #[error("{file}: {place}: {source}")]
    Clip {
        /// The file's name as given to the importer.
        file: String,
        /// Where in the file: `"animation 2 (walk)"`, `"channel 4 (line 31)"`, `"joint 7"`, ….
        place: String,
        /// Why the curve or clip was refused.
        source: ClipError,
    },
    /// The glTF JSON or GLB container is malformed.
    #[error("{file}: glTF: {source}")]
    Gltf {
        /// The file's name as given to the importer.
        file: String,
        /// What the glTF reader reported.
        source: gltf::Error,
    },
    /// The glTF document breaks the specification's rules: the first problems (at most
    /// [`ImportError::MAX_LISTED`]) and how many there are, so a file with thousands of them
    /// gives a message of a few lines.
    #[error("{file}: invalid glTF: {}", listed(problems, *count))]
    GltfInvalid {
        /// The file's name as given to the importer.
        file: String,
        /// The first problems, each a path in the document and what is wrong there.
        problems: Vec<String>,
        /// How many problems there are in all.
        count: usize,
    },
    /// A glTF accessor is out of range, of the wrong type, or holds bad values.
    #[error("{file}: accessor {accessor}: {message}")]
    Accessor {
        /// The file's name as given to the importer.
        file: String,
        /// The accessor's index in the document.
        accessor: usize,
        /// What is wrong with it.
        message: String,
    },
    /// A glTF buffer's data is missing, undecodable, not a safe relative path, or shorter than
    /// it declares.
    #[error("{file}: buffer {buffer}: {message}")]
    Buffer {
        /// The file's name as given to the importer.
        file: String,
        /// The buffer's index in the document.
        buffer: usize,
        /// What is wrong with it.
        message: String,
    },
    /// A glTF node has a transform or a place in the hierarchy the importer cannot use.
    #[error("{file}: node {node}: {message}")]
    Node {
        /// The file's name as given to the importer.
        file: String,
        /// The node's index in the document.
        node: usize,
        /// What is wrong with it.
        message: String,
    },
    /// A VRM animation's `VRMC_vrm_animation` extension is malformed or does not fit the
    /// document (a bone on a missing node, a bone twice, no hips, …).
    #[error("{file}: {source}")]
    VrmAnimation {
        /// The file's name as given to the importer.
        file: String,
        /// What is wrong with the extension.
        source: crate::import::gltf::vrma::VrmaError,
    },
    /// A file-level problem with no narrower place (e.g. a glTF without skins).
    #[error("{file}: {message}")]
    Unsupported {
        /// The file's name as given to the importer.
        file: String,
        /// What the file has that the importer does not support.
        message: String,
    },
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
