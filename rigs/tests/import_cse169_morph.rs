//! CSE169 `.morph` files: sparse and dense entries, normals, the errors, how they are grouped
//! with a `.skel` and `.skin` (uploads and folders), the notes, and their displacements through
//! normalisation. Expected values are derived by hand from the texts written here and from
//! `triangle.skin` in ../shared/testdata/cse169 (read in place).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;

use glam::Vec3;
use posecast_proto::SkinnedMesh;
use posecast_proto::testing::require_testdata;
use posecast_rigs::import::files::{self, FileSet};
use posecast_rigs::import::{self, ImportError, morph, skel, skin};
use posecast_rigs::rig::{PipelineOptions, Rig};

const ONE_JOINT: &str = "balljoint root { }";

/// A unit quad in z = 0 on one joint; vertex 0's normal is written unnormalised (0 0 2).
const QUAD_SKIN: &str = "positions 4 {
    0 0 0
    1 0 0
    0 1 0
    1 1 0
}
normals 4 {
    0 0 2
    0 0 1
    0 0 1
    0 0 1
}
skinweights 4 {
    1 0 1
    1 0 1
    1 0 1
    1 0 1
}
triangles 2 {
    0 1 2
    2 1 3
}
bindings 1 {
    matrix {
        1 0 0
        0 1 0
        0 0 1
        0 0 0
    }
}
";

/// Moves vertex 1 to (1.5, 0, 0.25) and vertex 3 to (1, 2, 0), turns vertex 3's normal to +Y.
const QUAD_SMILE: &str = "positions 2 {
    1 1.5 0 0.25
    3 1 2 0
}
normals 1 {
    3 0 1 0
}
";

/// Triangle.skin: positions (0,0,0) (1,0,0) (0,1,0), normals (-1,-1,1) (1,-1,1) (0,1,1).
/// Dense: vertex 0 to (0,0,1), vertex 1 stays, vertex 2 to (0,2,0); every normal to +Z.
const TRIANGLE_DENSE: &str = "positions 3 {
    0 0 1
    1 0 0
    0 2 0
}
normals 3 {
    0 0 1
    0 0 1
    0 0 1
}
";

/// The same target as [`TRIANGLE_DENSE`], sparse, normals first.
const TRIANGLE_SPARSE: &str = "normals 3 {
    2 0 0 1
    0 0 0 1
    1 0 0 1
}
positions 2 {
    0 0 0 1
    2 0 2 0
}
";

fn testdata(rel: &str) -> Option<String> {
    Some(std::fs::read_to_string(require_testdata(rel)?).unwrap())
}

fn quad() -> SkinnedMesh {
    let s = skel::parse("quad.skel", ONE_JOINT).unwrap();
    skin::parse("quad.skin", QUAD_SKIN, &s.skeleton)
        .unwrap()
        .mesh
}

fn close(a: &[Vec3], b: &[Vec3]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.abs_diff_eq(*y, 1e-6))
}

#[test]
fn sparse_entries_give_hand_derived_displacements_and_zero_elsewhere() {
    let t = morph::parse("quad_smile.morph", QUAD_SMILE, &quad()).unwrap();
    assert_eq!(t.name, "quad_smile");
    // Δp = p' − p: (1.5, 0, 0.25) − (1, 0, 0); (1, 2, 0) − (1, 1, 0); 0 and 2 unlisted.
    assert_eq!(
        t.positions,
        vec![
            Vec3::ZERO,
            Vec3::new(0.5, 0.0, 0.25),
            Vec3::ZERO,
            Vec3::new(0.0, 1.0, 0.0)
        ]
    );
    // Δn = (0, 1, 0) − (0, 0, 1) for vertex 3 only.
    assert_eq!(
        t.normals,
        vec![
            Vec3::ZERO,
            Vec3::ZERO,
            Vec3::ZERO,
            Vec3::new(0.0, 1.0, -1.0)
        ]
    );
}

#[test]
fn normals_are_displaced_from_the_skins_normalised_normals() {
    // Vertex 0's normal is written (0, 0, 2): the mesh holds (0, 0, 1), so a morph normal of
    // (0, 0, 1) is no displacement, and (1, 0, 0) is (1, 0, −1).
    let m = quad();
    assert_eq!(m.normals()[0], Vec3::Z);
    let t = morph::parse("a.morph", "positions 0 { } normals 1 { 0 0 0 1 }", &m).unwrap();
    assert_eq!(t.normals, vec![Vec3::ZERO; 4]);
    assert_eq!(t.positions, vec![Vec3::ZERO; 4]);
    let t = morph::parse("a.morph", "positions 0 { } normals 1 { 0 1 0 0 }", &m).unwrap();
    assert_eq!(t.normals[0], Vec3::new(1.0, 0.0, -1.0));
    // Without a normals block the target leaves normals alone.
    let t = morph::parse("a.morph", "positions 1 { 2 0 1 1 }", &m).unwrap();
    assert!(t.normals.is_empty());
    assert_eq!(t.positions[2], Vec3::new(0.0, 0.0, 1.0));
}

#[test]
fn dense_entries_over_triangle_skin() {
    let Some(text) = testdata("cse169/triangle.skin") else {
        return;
    };
    let s = skel::parse("one.skel", ONE_JOINT).unwrap();
    let mesh = skin::parse("triangle.skin", &text, &s.skeleton)
        .unwrap()
        .mesh;
    let t = morph::parse("triangle_up.morph", TRIANGLE_DENSE, &mesh).unwrap();
    assert_eq!(t.name, "triangle_up");
    assert_eq!(
        t.positions,
        vec![
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::ZERO,
            Vec3::new(0.0, 1.0, 0.0)
        ]
    );
    // Δn = +Z − n/|n|: the file's normals over √3, √3 and √2.
    let (a, b) = (1.0 / 3f32.sqrt(), 1.0 / 2f32.sqrt());
    let want = [
        Vec3::new(a, a, 1.0 - a),
        Vec3::new(-a, a, 1.0 - a),
        Vec3::new(0.0, -b, 1.0 - b),
    ];
    assert!(close(&t.normals, &want), "{:?}", t.normals);
    // The sparse form of the same target (sections in the other order) gives the same.
    let sparse = morph::parse("triangle_up.morph", TRIANGLE_SPARSE, &mesh).unwrap();
    assert_eq!(sparse, t);
}

/// The error of parsing `text` over the quad.
fn error(text: &str) -> ImportError {
    morph::parse("bad.morph", text, &quad()).unwrap_err()
}

/// An [`ImportError::Invalid`] on `line` whose message contains `part`.
fn invalid(text: &str, line: usize, part: &str) {
    match error(text) {
        ImportError::Invalid {
            file,
            line: l,
            message,
        } => {
            assert_eq!(file, "bad.morph");
            assert_eq!(l, line, "{message}");
            assert!(message.contains(part), "{message:?} lacks {part:?}");
        }
        e => panic!("expected Invalid on line {line} ({part}), got {e}"),
    }
}

/// An [`ImportError::Syntax`] on `line`, expecting `expected`, finding `found`.
fn syntax(text: &str, line: usize, expected: &str, found: &str) {
    match error(text) {
        ImportError::Syntax {
            file,
            line: l,
            expected: e,
            found: f,
        } => {
            assert_eq!(file, "bad.morph");
            assert_eq!((l, f.as_str()), (line, found), "{e}");
            assert!(e.contains(expected), "{e:?} lacks {expected:?}");
        }
        e => panic!("expected Syntax on line {line}, got {e}"),
    }
}

#[test]
fn an_index_out_of_range_is_refused_with_its_line() {
    invalid(
        "positions 2 {\n0 0 0 0\n4 1 1 1\n}\n",
        3,
        "vertex index 4 is out of range: the skin has 4 vertices",
    );
    invalid("normals 1 {\n9 0 0 1\n}\n", 2, "normals: vertex index 9");
}

#[test]
fn a_duplicate_index_is_refused_with_both_lines() {
    invalid(
        "positions 3 {\n1 0 0 0\n2 0 0 0\n1 5 5 5\n}\n",
        4,
        "vertex 1 is listed twice (first on line 2)",
    );
}

#[test]
fn count_mismatches_are_refused() {
    // 2 entries of 4 numbers under a count of 3 (12 or 9 numbers expected).
    invalid(
        "\npositions 3 {\n0 0 0 0\n1 0 0 0\n}\n",
        2,
        "count 3 does not match the block's 8 numbers",
    );
    // Dense over 4 vertices with 3 entries: 9 numbers fit 3·3, but the dense form lists all.
    invalid(
        "positions 3 {\n0 0 0\n1 0 0\n0 1 0\n}\n",
        1,
        "dense form (x y z, no indices) lists every vertex, but the count is 3 for a skin of 4",
    );
    // 3 sparse entries (12 numbers) under a count of 4 would read as 4 dense ones.
    invalid(
        "positions 4 {\n0 0 0 1\n1 0 0 1\n2 0 0 1\n}\n",
        1,
        "every line holds 4 numbers",
    );
    // A count the rest of the file cannot hold.
    match error("positions 1000000 {\n0 0 0 0\n}\n") {
        ImportError::Count {
            line, what, count, ..
        } => assert_eq!((line, what.as_str(), count), (1, "positions", 1_000_000)),
        e => panic!("expected Count, got {e}"),
    }
}

#[test]
fn non_finite_numbers_are_refused() {
    for bad in ["nan", "inf", "-infinity", "1e39"] {
        invalid(
            &format!("positions 1 {{\n2 0 {bad} 0\n}}\n"),
            2,
            "of vertex 2",
        );
        invalid(
            &format!("positions 0 {{ }}\nnormals 1 {{\n\n1 0 0 {bad}\n}}\n"),
            4,
            "is not a finite number",
        );
    }
    // Finite values whose displacement is not (3e38 − (−…)): the vertex and line are named.
    let far = "positions 1 {\n0 3e38 0 0\n}\n";
    let skin = QUAD_SKIN.replacen("0 0 0\n", "-3e38 0 0\n", 1);
    let s = skel::parse("q.skel", ONE_JOINT).unwrap();
    let mesh = skin::parse("q.skin", &skin, &s.skeleton).unwrap().mesh;
    let e = morph::parse("far.morph", far, &mesh)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line 2") && e.contains("displacement") && e.contains("not finite"),
        "{e}"
    );
}

#[test]
fn missing_braces_are_refused() {
    syntax("positions 1\n0 0 0 0\n}\n", 2, "`{`", "0");
    // The block runs into the next section: its word is not a number.
    syntax(
        "positions 1 {\n0 0 0 0\nnormals 1 {\n0 0 0 1\n}\n",
        3,
        "a number or `}` closing the positions block of line 1",
        "normals",
    );
    match error("positions 1 {\n0 0 0 0\n") {
        ImportError::Eof { file, expected } => {
            assert_eq!(file, "bad.morph");
            assert!(
                expected.contains("`}` closing the positions block"),
                "{expected}"
            );
        }
        e => panic!("expected Eof, got {e}"),
    }
}

#[test]
fn trailing_garbage_and_unknown_sections_are_refused() {
    syntax(
        "positions 1 {\n0 0 0 0\n}\n1 0 0 0\n",
        4,
        "`positions` or `normals`",
        "1",
    );
    syntax(
        "positions 0 { }\ntexcoords 0 { }\n",
        2,
        "`positions`",
        "texcoords",
    );
    syntax("positions 1 {\n1.5 0 0 0\n}\n", 2, "vertex index", "1.5");
    invalid(
        "positions 0 { }\npositions 0 { }\n",
        2,
        "a second `positions` section",
    );
    match error("normals 0 { }") {
        ImportError::Eof { expected, .. } => assert!(expected.contains("`positions`")),
        e => panic!("expected Eof, got {e}"),
    }
}

/// An upload of the quad with `morphs` (name, text), its `.skel` and `.skin` named unlike
/// them.
fn upload(morphs: &[(&str, &str)]) -> Result<Vec<posecast_rigs::asset::Asset>, ImportError> {
    let mut set = FileSet::new();
    set.insert("rig.skel", ONE_JOINT.into()).unwrap();
    set.insert("mesh.skin", QUAD_SKIN.into()).unwrap();
    for (name, text) in morphs {
        set.insert(name, text.as_bytes().to_vec()).unwrap();
    }
    files::import_set(&set)
}

#[test]
fn an_upload_attaches_every_morph_to_the_skin_in_name_order_with_a_note() {
    let blink = "positions 1 {\n0 0 0 -1\n}\n";
    let a = upload(&[("smile.morph", QUAD_SMILE), ("blink.morph", blink)])
        .unwrap()
        .remove(0);
    let targets = a.meshes[0].mesh.targets();
    let names: Vec<&str> = targets.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["blink", "smile"]);
    assert_eq!(targets[0].positions[0], Vec3::new(0.0, 0.0, -1.0));
    assert_eq!(targets[1].positions[1], Vec3::new(0.5, 0.0, 0.25));
    assert!(
        a.source
            .notes
            .contains(&"2 morph target(s) from .morph: blink, smile".to_owned()),
        "{:?}",
        a.source.notes
    );
    // Without .morph files there is no such note.
    let a = upload(&[]).unwrap().remove(0);
    assert!(a.meshes[0].mesh.targets().is_empty());
    assert!(
        !a.source.notes.iter().any(|n| n.contains(".morph")),
        "{:?}",
        a.source.notes
    );
}

#[test]
fn an_upload_refuses_morphs_without_a_skin_or_alone_or_twice() {
    let mut set = FileSet::new();
    set.insert("rig.skel", ONE_JOINT.into()).unwrap();
    set.insert("smile.morph", QUAD_SMILE.into()).unwrap();
    let e = files::import_set(&set).unwrap_err();
    assert!(
        matches!(&e, ImportError::Unsupported { file, message }
            if file == "smile.morph" && message.contains("has none: add its .skin")),
        "{e}"
    );
    let mut alone = FileSet::new();
    alone.insert("smile.morph", QUAD_SMILE.into()).unwrap();
    let e = files::import_set(&alone).unwrap_err().to_string();
    assert!(e.contains("a .morph file needs its .skel"), "{e}");
    let mut gltf = FileSet::new();
    gltf.insert("a.gltf", b"{}".to_vec()).unwrap();
    gltf.insert("smile.morph", QUAD_SMILE.into()).unwrap();
    let e = files::import_set(&gltf).unwrap_err().to_string();
    assert!(
        e.contains("smile.morph") && e.contains("does not use this file"),
        "{e}"
    );
    // Two files of one stem would be one channel twice.
    let e = upload(&[("smile.morph", QUAD_SMILE), ("smile.MORPH", QUAD_SMILE)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("a second .morph named \"smile\""), "{e}");
    // A morph error names the .morph file and its line.
    let e = upload(&[("bad.morph", "positions 1 {\n7 0 0 0\n}\n")])
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("bad.morph: line 2: "), "{e}");
}

#[test]
fn more_targets_than_the_memory_budget_allows_are_refused_before_parsing() {
    // 2¹⁶ vertices at two vectors each: 2²⁴ / 2¹⁷ = 128 targets; the 129th file is named.
    let v = 1usize << 16;
    assert_eq!(files::MAX_MORPH_VECTORS, 1 << 24);
    let mut big = format!("positions {v} {{\n");
    big.push_str(&"0 0 0\n".repeat(v));
    big.push_str(&format!("}}\nskinweights {v} {{\n"));
    big.push_str(&"1 0 1\n".repeat(v));
    big.push_str("}\nbindings 1 { matrix { 1 0 0 0 1 0 0 0 1 0 0 0 } }\n");
    let morphs: Vec<(String, String)> = (0..129)
        .map(|i| (format!("m{i:03}.morph"), "garbage".to_owned()))
        .collect();
    let e = files::skel_with_morphs(
        "big.skel",
        ONE_JOINT,
        Some(("big.skin".into(), big)),
        vec![],
        morphs,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.starts_with("m128.morph: 129 .morph files over big.skin (65536 vertices): at most 128"),
        "{e}"
    );
}

/// A fresh folder under the system's temporary folder, removed on drop.
struct Folder(PathBuf);

impl Folder {
    fn new(name: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("posecast-morph-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
    fn write(&self, name: &str, text: &str) -> PathBuf {
        let p = self.0.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }
}

impl Drop for Folder {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[test]
fn a_folder_groups_morphs_by_the_skels_stem_like_anims() {
    let dir = Folder::new("group");
    let skel = dir.write("head.skel", ONE_JOINT);
    dir.write("head.skin", QUAD_SKIN);
    dir.write("head_smile.morph", QUAD_SMILE);
    dir.write("head.morph", "positions 0 { }");
    // Neither `head` nor `head_…`: another asset's.
    dir.write("headless_x.morph", "garbage");
    dir.write("other_smile.morph", "garbage");
    let a = import::load_path(&skel).unwrap().remove(0);
    let names: Vec<&str> = a.meshes[0]
        .mesh
        .targets()
        .iter()
        .map(|t| t.name.as_str())
        .collect();
    assert_eq!(names, ["head", "head_smile"]);
    assert!(
        a.source
            .notes
            .contains(&"2 morph target(s) from .morph: head, head_smile".to_owned())
    );
    // A .morph is loaded through its .skel.
    let e = import::load_path(&dir.0.join("head_smile.morph"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("a .morph file needs its .skel"), "{e}");
    // Without the .skin, the .morph files beside the .skel are an error.
    std::fs::remove_file(dir.0.join("head.skin")).unwrap();
    let e = import::load_path(&skel).unwrap_err().to_string();
    assert!(e.contains("head.skel has none: add its .skin"), "{e}");
}

#[test]
fn normalisation_moves_morphed_vertices_as_it_moves_rest_vertices() {
    let Some(text) = testdata("cse169/triangle.skin") else {
        return;
    };
    let a = files::skel_with_morphs(
        "tri.skel",
        ONE_JOINT,
        Some(("triangle.skin".into(), text.clone())),
        vec![],
        vec![("up.morph".into(), TRIANGLE_DENSE.into())],
    )
    .unwrap();
    // Z up, centimetres: a world point p becomes 0.01 · (x, z, −y) (−90° about X, scaled).
    let options: PipelineOptions = serde_json::from_value(serde_json::json!({
        "up_axis": {"up": "+z"}, "metres_per_unit": 0.01, "neutral": "keep"
    }))
    .unwrap();
    let f = |p: Vec3| 0.01 * Vec3::new(p.x, p.z, -p.y);
    let rig = Rig::from_asset(a, &options).unwrap();
    let mesh = &rig.asset.meshes[0].mesh;
    let file_rest = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let file_morph = [Vec3::Z, Vec3::X, Vec3::new(0.0, 2.0, 0.0)];
    let rest: Vec<Vec3> = file_rest.iter().map(|&p| f(p)).collect();
    assert!(close(mesh.positions(), &rest), "{:?}", mesh.positions());
    let t = &mesh.targets()[0];
    let morphed: Vec<Vec3> = mesh
        .positions()
        .iter()
        .zip(&t.positions)
        .map(|(p, d)| *p + *d)
        .collect();
    let want: Vec<Vec3> = file_morph.iter().map(|&p| f(p)).collect();
    assert!(close(&morphed, &want), "{morphed:?} vs {want:?}");
    // Normals turn without the scale: at weight 1 the normal is the file's +Z rotated, and
    // (x, z, −y) of (0, 0, 1) is (0, 1, 0).
    for (v, (n, d)) in mesh.normals().iter().zip(&t.normals).enumerate() {
        let got = (*n + *d).normalize();
        assert!(got.abs_diff_eq(Vec3::Y, 1e-5), "vertex {v}: {got}");
    }
    // The rig's morph channels (the avatar description's `morph_targets`).
    let channels = posecast_proto::morph::channels(rig.asset.meshes.iter().map(|m| &m.mesh));
    assert_eq!(channels, ["up"]);
}
