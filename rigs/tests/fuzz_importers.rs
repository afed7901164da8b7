//! Mutated real files into every importer: byte flips, truncations, token deletions and
//! duplications, digit substitutions and huge or non-finite numbers. Each import must return
//! `Ok` or `Err`, never panic; clips that import are sampled at odd times too.
//!
//! Deterministic (a fixed xorshift seed per file) and bounded: `CASES` mutants per file.

#![allow(clippy::unwrap_used)]

use std::panic::{AssertUnwindSafe, catch_unwind};

use posecast_proto::Transform;
use posecast_proto::testing::require_testdata;
use posecast_rigs::asset::Asset;
use posecast_rigs::import::{anim, bvh, files, gltf, skel, skin};

const CASES: usize = 300;

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

const HUGE: [&str; 8] = [
    "1e38",
    "-1e39",
    "99999999999999999999",
    "4294967296",
    "NaN",
    "inf",
    "65536",
    "-0",
];

/// Whitespace-separated token spans of `bytes`.
fn token_spans(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut spans = Vec::new();
    let mut start = None;
    for (i, b) in bytes.iter().enumerate() {
        if b.is_ascii_whitespace() {
            if let Some(s) = start.take() {
                spans.push((s, i));
            }
        } else if start.is_none() {
            start = Some(i);
        }
    }
    if let Some(s) = start {
        spans.push((s, bytes.len()));
    }
    spans
}

/// One mutant of `original` and a description of the mutation.
fn mutate(original: &[u8], rng: &mut Rng, binary: bool) -> (Vec<u8>, String) {
    let mut b = original.to_vec();
    let kind = rng.below(if binary { 4 } else { 6 });
    let spans = if binary { Vec::new() } else { token_spans(&b) };
    match kind {
        0 => {
            let flips = 1 + rng.below(8);
            for _ in 0..flips {
                let i = rng.below(b.len());
                b[i] = rng.next() as u8;
            }
            (b, format!("{flips} byte flips"))
        }
        1 => {
            let at = rng.below(b.len());
            b.truncate(at);
            (b, format!("truncated at {at}"))
        }
        2 => {
            // Digit substitution keeps lengths (and GLB chunk sizes) intact but changes
            // counts, offsets and indices.
            let digits: Vec<usize> = b
                .iter()
                .enumerate()
                .filter(|(_, c)| c.is_ascii_digit())
                .map(|(i, _)| i)
                .collect();
            let n = 1 + rng.below(4);
            for _ in 0..n {
                if !digits.is_empty() {
                    let i = digits[rng.below(digits.len())];
                    b[i] = b'0' + rng.below(10) as u8;
                }
            }
            (b, format!("{n} digit substitutions"))
        }
        3 => {
            // Overwrite a window with 9s (large numbers in the same length).
            let i = rng.below(b.len());
            let len = (1 + rng.below(6)).min(b.len() - i);
            for c in &mut b[i..i + len] {
                if c.is_ascii_digit() {
                    *c = b'9';
                }
            }
            (b, format!("9s at {i}"))
        }
        4 if !spans.is_empty() => {
            let (s, e) = spans[rng.below(spans.len())];
            let dup = rng.below(2) == 0;
            if dup {
                let tok = b[s..e].to_vec();
                b.splice(e..e, [b" ".as_slice(), &tok].concat());
            } else {
                b.drain(s..e);
            }
            (
                b,
                format!(
                    "token at {s} {}",
                    if dup { "duplicated" } else { "deleted" }
                ),
            )
        }
        _ if !spans.is_empty() => {
            let (s, e) = spans[rng.below(spans.len())];
            let huge = HUGE[rng.below(HUGE.len())];
            b.splice(s..e, huge.bytes());
            (b, format!("token at {s} replaced by {huge}"))
        }
        _ => (b, "unchanged".to_owned()),
    }
}

fn exercise(assets: &[Asset]) {
    for a in assets {
        let rest = a.skeleton.rest();
        let mut out = vec![Transform::IDENTITY; rest.len()];
        for c in &a.clips {
            let mut s = c.sampler();
            for t in [
                c.start(),
                c.end(),
                -1e30,
                1e30,
                f32::NAN,
                f32::INFINITY,
                0.37,
            ] {
                c.sample(t, rest, &mut out);
                s.sample(c, t, rest, &mut out);
            }
        }
    }
}

fn fuzz(rel: &str, seed: u64, binary: bool, import: &dyn Fn(&[u8]) -> Option<Vec<Asset>>) {
    let Some(path) = require_testdata(rel) else {
        return;
    };
    let original = std::fs::read(&path).unwrap();
    fuzz_bytes(rel, &original, seed, binary, import);
}

fn fuzz_bytes(
    rel: &str,
    original: &[u8],
    seed: u64,
    binary: bool,
    import: &dyn Fn(&[u8]) -> Option<Vec<Asset>>,
) {
    assert!(import(original).is_some(), "{rel} must import unmutated");
    let mut rng = Rng(seed);
    let (mut ok, mut err) = (0, 0);
    for case in 0..CASES {
        let (bytes, what) = mutate(original, &mut rng, binary);
        let result = catch_unwind(AssertUnwindSafe(|| {
            let assets = import(&bytes);
            if let Some(a) = &assets {
                exercise(a);
            }
            assets.is_some()
        }));
        match result {
            Ok(true) => ok += 1,
            Ok(false) => err += 1,
            Err(_) => panic!("{rel}: case {case} ({what}) panicked"),
        }
    }
    eprintln!("{rel}: {ok} imported, {err} refused");
}

fn text(bytes: &[u8]) -> Option<String> {
    String::from_utf8(bytes.to_vec()).ok()
}

fn read_text(rel: &str) -> Option<String> {
    let path = require_testdata(rel)?;
    Some(std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
}

#[test]
fn gltf_mutants() {
    for (i, rel) in [
        "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/SimpleSkin/glTF-Embedded/SimpleSkin.gltf",
    ]
    .into_iter()
    .enumerate()
    {
        let binary = rel.ends_with(".glb");
        fuzz(rel, 0x9E37_79B9 + i as u64, binary, &|b| {
            match gltf::from_slice("f.glb", b) {
                Ok(a) => Some(a),
                Err(e) => {
                    // The importer's panic guard must not be what catches a mutant.
                    assert!(!e.to_string().contains("parser failed"), "{rel}: {e}");
                    None
                }
            }
        });
    }
}

#[test]
fn skel_mutants() {
    for (i, rel) in ["cse169/test.skel", "cse169/tube.skel", "cse169/wasp.skel"]
        .into_iter()
        .enumerate()
    {
        fuzz(rel, 0xA5A5_0001 + i as u64, false, &|b| {
            let s = skel::parse("f.skel", &text(b)?).ok()?;
            posecast_rigs::import::cse169::assemble("f", s, None, vec![])
                .ok()
                .map(|a| vec![a])
        });
    }
}

#[test]
fn skin_mutants() {
    for (i, (skel_rel, rel)) in [
        ("cse169/tube.skel", "cse169/tube_smooth.skin"),
        ("cse169/wasp.skel", "cse169/wasp.skin"),
    ]
    .into_iter()
    .enumerate()
    {
        let Some(k) = read_text(skel_rel) else { return };
        let s = skel::parse(skel_rel, &k).unwrap();
        fuzz(rel, 0x5EED_0001 + i as u64, false, &|b| {
            let m = skin::parse("f.skin", &text(b)?, &s.skeleton).ok()?;
            let a = posecast_rigs::import::cse169::assemble("f", s.clone(), Some(m), vec![]);
            a.ok().map(|a| vec![a])
        });
    }
    let one = skel::parse("one.skel", "balljoint a { }").unwrap();
    fuzz("cse169/triangle.skin", 0x5EED_0009, false, &|b| {
        skin::parse("f.skin", &text(b)?, &one.skeleton).ok()?;
        Some(vec![])
    });
}

#[test]
fn morph_mutants() {
    // No course .morph ships with the test data: targets written here over its skins, one
    // sparse positions block with dense normals, one dense positions block with sparse normals.
    let (Some(tube_skel), Some(tube_skin)) = (
        read_text("cse169/tube.skel"),
        read_text("cse169/tube_smooth.skin"),
    ) else {
        return;
    };
    let mut bulge = String::from("positions 12 {\n");
    for i in 0..12 {
        bulge.push_str(&format!("{} 0.{i} -0.5 0.25\n", i * 20));
    }
    bulge.push_str("}\nnormals 240 {\n");
    for i in 0..240 {
        bulge.push_str(&format!("0 {} 0.5\n", i % 3));
    }
    bulge.push_str("}\n");
    fuzz_bytes(
        "tube_bulge.morph",
        bulge.as_bytes(),
        0x3090_0001,
        false,
        &|b| {
            files::skel_with_morphs(
                "tube.skel",
                &tube_skel,
                Some(("tube.skin".into(), tube_skin.clone())),
                vec![],
                vec![("tube_bulge.morph".into(), text(b)?)],
            )
            .ok()
            .map(|a| vec![a])
        },
    );
    let Some(triangle) = read_text("cse169/triangle.skin") else {
        return;
    };
    let one = skel::parse("one.skel", "balljoint a { }").unwrap();
    let mesh = skin::parse("triangle.skin", &triangle, &one.skeleton)
        .unwrap()
        .mesh;
    let dense = "positions 3 {\n0 0 1\n1 0 0\n0 2 0\n}\nnormals 2 {\n2 0 0 1\n0 0 0 1\n}\n";
    fuzz_bytes(
        "triangle_up.morph",
        dense.as_bytes(),
        0x3090_0002,
        false,
        &|b| {
            let t = posecast_rigs::import::morph::parse("f.morph", &text(b)?, &mesh).ok()?;
            mesh.clone().with_targets(vec![t]).ok().map(|_| vec![])
        },
    );
}

#[test]
fn anim_mutants() {
    let Some(k) = read_text("cse169/wasp.skel") else {
        return;
    };
    let s = skel::parse("wasp.skel", &k).unwrap();
    fuzz("cse169/wasp_walk.anim", 0xA11A_0001, false, &|b| {
        let clip = anim::parse("f.anim", &text(b)?, &s.skeleton).ok()?;
        let a = posecast_rigs::import::cse169::assemble("f", s.clone(), None, vec![clip]);
        a.ok().map(|a| vec![a])
    });
}

#[test]
fn bvh_mutants() {
    for (i, rel) in [
        "bvh/bvh_anim/test_simple.bvh",
        "bvh/fairmotion/sinusoidal.bvh",
    ]
    .into_iter()
    .enumerate()
    {
        fuzz(rel, 0xB0B0_0001 + i as u64, false, &|b| {
            bvh::parse("f.bvh", &text(b)?).ok().map(|a| vec![a])
        });
    }
    // CMU 01_01 cut to its hierarchy and 40 frames, to keep the run short.
    let Some(cmu) = read_text("bvh/cmu/01_01.bvh") else {
        return;
    };
    let motion = cmu.find("MOTION").unwrap();
    let frames: Vec<&str> = cmu[motion..].lines().skip(3).take(40).collect();
    let short = format!(
        "{}MOTION\nFrames: 40\nFrame Time: .0083333\n{}\n",
        &cmu[..motion],
        frames.join("\n")
    );
    fuzz_bytes(
        "bvh/cmu/01_01.bvh (40 frames)",
        short.as_bytes(),
        0xB0B0_0100,
        false,
        &|b| bvh::parse("f.bvh", &text(b)?).ok().map(|a| vec![a]),
    );
}
