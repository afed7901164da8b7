//! Random skeletons, transforms and poses for property tests (here and in other crates'
//! tests, through the `testing` feature).

use crate::fk::forward_kinematics;
use crate::skeleton::Skeleton;
use crate::transform::Transform;
use glam::{Mat4, Quat, Vec3};
use proptest::prelude::*;
use std::ops::Range;

/// Uniform `f32`s in `range`, drawn through integers (2²⁴ steps, shrinking towards the
/// start). proptest's own `f32` range sampler trips a debug assertion in
/// `float_samplers.rs` on some random seeds (seen with proptest 1.11, reported upstream for
/// 1.10), which made test runs fail at random; every float strategy here goes through this.
pub fn f32s(range: Range<f32>) -> impl Strategy<Value = f32> + Clone {
    const STEPS: u32 = 1 << 24;
    let (lo, hi) = (f64::from(range.start), f64::from(range.end));
    (0..STEPS).prop_map(move |i| (lo + (hi - lo) * f64::from(i) / f64::from(STEPS)) as f32)
}

/// Any finite f32, drawn from random bit patterns: magnitudes spread evenly over every
/// exponent (subnormals up to ±3.4e38), which is what finds overflow in `|q|²` or `t · speed`.
pub fn finite_f32s() -> impl Strategy<Value = f32> + Clone {
    any::<u32>()
        .prop_map(f32::from_bits)
        .prop_filter("finite", |v| v.is_finite())
}

/// A uniformly random unit quaternion (normalised 4-D Gaussian-ish box sample).
pub fn arb_quat() -> impl Strategy<Value = Quat> {
    prop::array::uniform4(f32s(-1.0..1.0))
        .prop_filter("not near zero", |v| {
            v.iter().map(|x| x * x).sum::<f32>() > 0.01
        })
        .prop_map(|v| Quat::from_array(v).normalize())
}

/// A random transform: translation within ±1, any rotation, scale in [0.8, 1.25].
pub fn arb_transform() -> impl Strategy<Value = Transform> {
    (
        prop::array::uniform3(f32s(-1.0..1.0)),
        arb_quat(),
        prop::array::uniform3(f32s(0.8..1.25)),
    )
        .prop_map(|(t, rotation, s)| Transform {
            translation: Vec3::from(t),
            rotation,
            scale: Vec3::from(s),
        })
}

/// A rigid random transform (unit scale).
pub fn arb_rigid() -> impl Strategy<Value = Transform> {
    (prop::array::uniform3(f32s(-1.0..1.0)), arb_quat())
        .prop_map(|(t, r)| Transform::from_translation_rotation(Vec3::from(t), r))
}

/// `n` random transforms.
pub fn arb_transforms(n: usize) -> impl Strategy<Value = Vec<Transform>> {
    prop::collection::vec(arb_transform(), n)
}

/// `n` random rigid transforms.
pub fn arb_rigid_transforms(n: usize) -> impl Strategy<Value = Vec<Transform>> {
    prop::collection::vec(arb_rigid(), n)
}

/// Random parent lists: joint `j`'s parent is any earlier joint, or none (a new root) with
/// probability about 1 in 20, so forests and deep chains both occur.
pub fn arb_parents(count: Range<usize>) -> impl Strategy<Value = Vec<Option<usize>>> {
    count.prop_flat_map(|n| {
        prop::collection::vec((0.0f64..1.0, 0.0f64..1.0), n).prop_map(|draws| {
            draws
                .iter()
                .enumerate()
                .map(|(j, &(root, pick))| {
                    if j == 0 || root < 0.05 {
                        None
                    } else {
                        // Favour recent joints so chains get long.
                        let back = ((pick * pick) * j as f64) as usize;
                        Some(j - 1 - back.min(j - 1))
                    }
                })
                .collect()
        })
    })
}

/// A random skeleton whose bind pose is its rest pose (`B_j = W_j(rest)`), with scaled joints.
pub fn arb_skeleton(count: Range<usize>) -> impl Strategy<Value = Skeleton> {
    arb_parents(count).prop_flat_map(|parents| {
        let n = parents.len();
        (Just(parents), arb_transforms(n))
            .prop_map(|(parents, rest)| skeleton_bound_at_rest(parents, rest))
    })
}

/// A random rigid skeleton (no scale anywhere) bound at rest.
pub fn arb_rigid_skeleton(count: Range<usize>) -> impl Strategy<Value = Skeleton> {
    arb_parents(count).prop_flat_map(|parents| {
        let n = parents.len();
        (Just(parents), arb_rigid_transforms(n))
            .prop_map(|(parents, rest)| skeleton_bound_at_rest(parents, rest))
    })
}

/// Builds a skeleton named `j0..` whose inverse binds are the inverses of its rest-pose worlds.
///
/// # Panics
/// If the parents are not ordered (the generators above always are).
#[must_use]
pub fn skeleton_bound_at_rest(parents: Vec<Option<usize>>, rest: Vec<Transform>) -> Skeleton {
    let n = parents.len();
    let names = (0..n).map(|j| format!("j{j}")).collect();
    let provisional = Skeleton::new(
        names,
        parents.clone(),
        rest.clone(),
        vec![Mat4::IDENTITY; n],
    )
    .expect("generated skeleton is valid");
    let mut world = vec![Mat4::IDENTITY; n];
    forward_kinematics(&provisional, &rest, &mut world);
    let names = (0..n).map(|j| format!("j{j}")).collect();
    Skeleton::new(
        names,
        parents,
        rest,
        world.iter().map(Mat4::inverse).collect(),
    )
    .expect("generated skeleton is valid")
}

/// `|a - b| ≤ tol · (1 + max|b|)` element-wise.
#[must_use]
pub fn mat_close(a: &Mat4, b: &Mat4, tol: f32) -> bool {
    let scale = 1.0 + b.to_cols_array().iter().fold(0.0f32, |m, v| m.max(v.abs()));
    a.abs_diff_eq(*b, tol * scale)
}

/// Whether a missing input (test data, a tool, a GPU adapter) must fail the run instead of
/// skipping: CI sets `CI=true`, and a test that passes by skipping there proves nothing.
#[must_use]
pub fn strict() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "false" && v != "0")
}

/// Reports a test that cannot run here: a panic under [`strict`] (CI), a note otherwise. The
/// reason also goes, one line per skip, to the file `POSECAST_SKIP_LOG` names when it is set:
/// `cargo test` hides a passing test's output, so `scripts/test` counts the skips from there
/// and prints them after the run.
///
/// # Panics
/// Under `CI=true`, always.
pub fn skip(reason: &str) {
    if let Some(log) = std::env::var_os("POSECAST_SKIP_LOG")
        && let Err(e) = note_skip(std::path::Path::new(&log), reason)
    {
        eprintln!("cannot note the skip in {}: {e}", log.to_string_lossy());
    }
    assert!(!strict(), "CI=true and a test input is missing: {reason}");
    eprintln!("SKIPPING: {reason}");
}

/// Appends `reason` as one line to `log`: one write in append mode, so tests running in
/// parallel never interleave within a line.
fn note_skip(log: &std::path::Path, reason: &str) -> std::io::Result<()> {
    use std::io::Write;
    let line = format!("{}\n", reason.replace('\n', " "));
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)?
        .write_all(line.as_bytes())
}

/// [`testdata`] when the file exists; otherwise [`skip`] (a failure under `CI=true`) and `None`.
#[must_use]
pub fn require_testdata(relative: &str) -> Option<std::path::PathBuf> {
    let path = testdata(relative);
    if path.exists() {
        Some(path)
    } else {
        skip(&format!(
            "{} is absent (../shared/testdata not beside the repository)",
            path.display()
        ));
        None
    }
}

/// The shared third-party test files (`../shared/testdata` beside the repository), read in
/// place. `relative` is a path inside that folder, e.g. `"gltf/CesiumMan/glTF/CesiumMan.gltf"`.
#[must_use]
pub fn testdata(relative: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/testdata")
        .join(relative)
}

/// One file's report from the Khronos glTF validator ([`validate_gltf`]).
#[derive(Debug)]
pub struct GltfReport {
    /// Errors: a file with any is not valid glTF.
    pub errors: u64,
    /// Warnings.
    pub warnings: u64,
    /// Informational messages.
    pub infos: u64,
    /// Hints.
    pub hints: u64,
    /// The messages (`code`, `severity`, `pointer`, `message`).
    pub messages: Vec<serde_json::Value>,
}

/// Runs the Khronos glTF validator (npm `gltf-validator` through the repository's
/// `scripts/validate-gltf.mjs`; `scripts/test` installs it under `target/npm`) on `files`.
/// `None`, after [`skip`] (a failure under `CI=true`), when node or the validator is missing.
///
/// # Panics
/// When the script's output is not one JSON report per file.
#[must_use]
pub fn validate_gltf(files: &[std::path::PathBuf]) -> Option<Vec<GltfReport>> {
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/validate-gltf.mjs");
    let output = match std::process::Command::new("node")
        .arg(&script)
        .args(files)
        .output()
    {
        Ok(o) => o,
        Err(e) => {
            skip(&format!("node is not installed ({e}): no glTF validation"));
            return None;
        }
    };
    let stderr = String::from_utf8_lossy(&output.stderr);
    if output.status.code() == Some(2) {
        skip(&format!(
            "the glTF validator did not run (scripts/test installs it): {stderr}"
        ));
        return None;
    }
    let count = |v: &serde_json::Value, k: &str| {
        v[k].as_u64()
            .unwrap_or_else(|| panic!("validator report without {k}: {v}"))
    };
    let reports: Vec<GltfReport> = String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(|line| {
            let v: serde_json::Value = serde_json::from_str(line)
                .unwrap_or_else(|e| panic!("validator output {line:?}: {e}; stderr {stderr}"));
            GltfReport {
                errors: count(&v, "errors"),
                warnings: count(&v, "warnings"),
                infos: count(&v, "infos"),
                hints: count(&v, "hints"),
                messages: v["messages"].as_array().cloned().unwrap_or_default(),
            }
        })
        .collect();
    assert_eq!(reports.len(), files.len(), "stderr: {stderr}");
    Some(reports)
}

/// Writes each `(label, bytes)` to a temporary `.glb`, validates them all in one run
/// ([`validate_gltf`]), prints every report and asserts that none has an error.
///
/// # Panics
/// When a file has a validator error, or the files cannot be written.
pub fn assert_valid_gltf(files: &[(&str, Vec<u8>)]) {
    static RUN: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let dir = std::env::temp_dir().join(format!(
        "posecast-gltf-{}-{}",
        std::process::id(),
        RUN.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&dir).expect("a temporary folder");
    let paths: Vec<std::path::PathBuf> = files
        .iter()
        .map(|(label, bytes)| {
            let path = dir.join(format!("{label}.glb"));
            std::fs::write(&path, bytes).expect("a temporary file");
            path
        })
        .collect();
    let reports = validate_gltf(&paths);
    std::fs::remove_dir_all(&dir).ok();
    let Some(reports) = reports else {
        return;
    };
    for ((label, _), r) in files.iter().zip(&reports) {
        eprintln!(
            "{label}: {} errors, {} warnings, {} infos, {} hints",
            r.errors, r.warnings, r.infos, r.hints
        );
        for m in r.messages.iter().take(20) {
            eprintln!("  {m}");
        }
        if r.messages.len() > 20 {
            eprintln!("  … {} more", r.messages.len() - 20);
        }
    }
    for ((label, _), r) in files.iter().zip(&reports) {
        assert_eq!(
            r.errors, 0,
            "{label}: the validator found errors (listed above)"
        );
    }
}

#[cfg(test)]
mod skip_tests {
    #[test]
    fn every_skip_is_one_line_of_the_log() {
        let log = std::env::temp_dir().join(format!("posecast-skips-{}", std::process::id()));
        std::fs::remove_file(&log).ok();
        super::note_skip(&log, "no GPU").unwrap();
        super::note_skip(&log, "two\nlines").unwrap();
        let text = std::fs::read_to_string(&log).unwrap();
        std::fs::remove_file(&log).ok();
        assert_eq!(text, "no GPU\ntwo lines\n");
    }
}
