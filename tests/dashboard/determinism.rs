//! Issue 28 goal 3: the wire v2 decoders reconstruct identical values forever. Ten minutes of
//! random motion (60 Hz, 36,000 ticks) of three avatars (numbers 1, 2 and 40) — two at the
//! finest precision, one on a subscription's coarse per-joint grid — sent to a reader with
//! random drop patterns (single frames, bursts, gaps of seconds; after a gap a keyframe or a
//! delta against the last frame it decoded, up to depth 8; deltas whose base it lacks, which it
//! refuses) are decoded by `posecast_proto::frame2::Frame2Decoder` here and by the JavaScript
//! client's `server/sdk/frames2.js` in headless Chromium, frame by frame. The deltas are packed
//! (protocol version 7, frame kind 3: every chunk in one bit stream, the server time a
//! difference from the base frame's), a few of kind 2 among them; server times jitter and now
//! and then go back, and the page must read each frame's seq and server time exactly.
//!
//! The coder predicts from decoded integer levels (closed loop in integers: the grid, the
//! prediction and the Rice codes use no floating point), so the two decoders hold the same
//! state forever and their rotations may differ only by the last float rounding (f64 in the
//! page, f32 here). A decoder whose state drifted by one level would differ by at least a
//! level's angle (≈ 0.003°) from then on. The Rust side is also checked against the source
//! motion: every rotation within its joint's bound (the finest's, or its grid step's).

use crate::browser::*;
use glam::{Quat, Vec3};
use posecast_proto::frame::{AvatarPose, FrameHeader, FrameKind};
use posecast_proto::frame2::{self, Frame2Decoder, PackedDeltas, QuantPose};
use posecast_proto::placement::Placement;
use posecast_proto::precision::{
    Steps, near_rotation_step_for, rotation_bound_degrees, translation_bound,
};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use std::path::Path;
use std::sync::Arc;

/// Ten minutes at 60 Hz.
const TICKS: u64 = 36_000;

/// The page and the Rust decoder read the same levels (f64 there, f32 here): float rounding
/// only (as `server/web/check/stream.mjs`).
const SAME_BITS_DEGREES: f64 = 5e-4;

/// A small deterministic generator (a failure reproduces).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }

    fn below(&mut self, n: u64) -> u64 {
        (f64::from(self.next()) * n as f64) as u64
    }

    fn vec3(&mut self) -> Vec3 {
        Vec3::new(
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
            self.range(-1.0, 1.0),
        )
    }

    fn quat(&mut self) -> Quat {
        Quat::from_scaled_axis(self.vec3() * 3.0).normalize()
    }
}

/// One avatar's motion: per joint an angular velocity that wanders (smooth), some joints
/// spinning steadily about a fixed axis (through 180° and on), now and then a jump; the root
/// translation walks and now and then teleports.
struct Motion {
    pose: AvatarPose,
    velocity: Vec<Vec3>,
    spinning: Vec<bool>,
}

impl Motion {
    fn new(rng: &mut Rng, num: u32, joints: usize) -> Self {
        Self {
            pose: AvatarPose {
                avatar_num: num,
                hash: 0xdead_0000_0000_0000 + u64::from(num),
                rotations: (0..joints).map(|_| rng.quat()).collect(),
                translations: vec![rng.vec3(), rng.vec3() * 0.1],
                scales: Vec::new(),
                placement: Placement::IDENTITY,
                weights: Vec::new(),
            },
            velocity: (0..joints).map(|_| rng.vec3() * 0.03).collect(),
            spinning: (0..joints).map(|j| j % 7 == 3).collect(),
        }
    }

    fn step(&mut self, rng: &mut Rng) {
        for ((q, w), &spin) in self
            .pose
            .rotations
            .iter_mut()
            .zip(&mut self.velocity)
            .zip(&self.spinning)
        {
            if spin {
                // About a fixed axis at 0.1 rad a tick: through 180° every half minute.
                *q = (Quat::from_scaled_axis(w.normalize_or(Vec3::Y) * 0.1) * *q).normalize();
                continue;
            }
            let r = rng.next();
            if r < 0.0005 {
                *q = rng.quat();
            } else {
                *w = (*w * 0.98 + rng.vec3() * 0.004).clamp_length_max(0.2);
                let noise = if r < 0.05 {
                    rng.vec3() * 0.02
                } else {
                    Vec3::ZERO
                };
                *q = (Quat::from_scaled_axis(*w + noise) * *q).normalize();
            }
        }
        self.pose.translations[0] += rng.vec3() * 0.01;
        if rng.next() < 0.001 {
            self.pose.translations[0] = rng.vec3() * 50.0;
        }
        self.pose.translations[1] = rng.vec3() * 0.1;
    }
}

/// What the reader does at a tick: gets it, or misses it (and how many more after it).
struct Drops {
    missing: u64,
}

impl Drops {
    fn misses(&mut self, rng: &mut Rng) -> bool {
        if self.missing > 0 {
            self.missing -= 1;
            return true;
        }
        let r = rng.next();
        self.missing = if r < 0.08 {
            // A single frame.
            1
        } else if r < 0.1 {
            // A burst: a slow reader's superseded frames.
            2 + rng.below(30)
        } else if r < 0.1005 {
            // A stall of up to ten seconds.
            60 + rng.below(540)
        } else {
            0
        };
        if self.missing > 0 {
            self.missing -= 1;
            true
        } else {
            false
        }
    }
}

/// Each tick's server time (index: seq): 60 Hz with up to ±0.5 ms of jitter, now and then a
/// step back of up to 2 ms (a clock corrected).
fn server_times(seed: u64) -> Vec<u64> {
    let mut rng = Rng(seed);
    let mut t = 1_764_000_000_000_000u64;
    (0..=TICKS)
        .map(|_| {
            t = if rng.next() < 0.002 {
                t - 1 - rng.below(2_000)
            } else {
                t + 16_667 - 500 + rng.below(1_000)
            };
            t
        })
        .collect()
}

fn header(kind: FrameKind, seq: u64, base_seq: u64, times: &[u64]) -> FrameHeader {
    FrameHeader {
        kind,
        scene_num: 3,
        seq,
        server_time_us: times[seq as usize],
        base_seq,
    }
}

/// A keyframe or a delta of kind 2 with these chunks.
fn frame_bytes(header: &FrameHeader, body: &[u8], avatars: usize) -> Vec<u8> {
    let mut out = Vec::new();
    frame2::write_header(header, avatars, &mut out);
    out.extend_from_slice(body);
    out
}

/// A delta of `now` against `history` (newest first, each with its seq), packed (kind 3) or
/// of kind 2.
fn delta_bytes(
    avatars: &[Motion],
    now: &[QuantPose],
    history: &[(u64, &[QuantPose])],
    seq: u64,
    times: &[u64],
    packed: bool,
) -> Vec<u8> {
    let base_seq = history[0].0;
    let header = header(FrameKind::Delta, seq, base_seq, times);
    let mut out = Vec::new();
    if packed {
        let mut p = PackedDeltas::new(&header, times[base_seq as usize], avatars.len(), &mut out);
        for (a, (m, q)) in avatars.iter().zip(now).enumerate() {
            let h: Vec<&QuantPose> = history.iter().map(|(_, f)| &f[a]).collect();
            assert!(p.push(m.pose.avatar_num, q, &h));
        }
        p.finish();
    } else {
        frame2::write_header(&header, avatars.len(), &mut out);
        for (a, (m, q)) in avatars.iter().zip(now).enumerate() {
            let h: Vec<&QuantPose> = history.iter().map(|(_, f)| &f[a]).collect();
            assert!(frame2::encode_delta(m.pose.avatar_num, q, &h, &mut out));
        }
    }
    out
}

/// The stream as the reader received it (`[ok u8][length u32 LE][bytes]` each: `ok` 0 for a
/// delta it must refuse), what the Rust decoder made of each frame it accepted (every
/// rotation's x, y, z, w, then every translation's x, y, z, as f32 LE; and its seq and server
/// time, u64 LE), with the counts.
struct Stream {
    frames: Vec<u8>,
    expected: Vec<u8>,
    times: Vec<u8>,
    decoded: u64,
    packed: u64,
    refused: u64,
    keyframes: u64,
    backwards: u64,
}

fn stream(seed: u64) -> Stream {
    let mut rng = Rng(seed);
    let mut avatars = [
        Motion::new(&mut rng, 1, 23),
        Motion::new(&mut rng, 2, 31),
        Motion::new(&mut rng, 40, 9),
    ];
    let times = server_times(seed ^ 0x7137);
    // The second avatar on a subscription's grid (protocol version 6): per-joint steps from
    // the finest to the coarsest, each joint's coarser step near an axis for the same bound
    // (rotations cross between the two grids as they move), a coarse translation step.
    let rotations: Vec<u8> = (0..31)
        .map(|j| {
            if j % 5 == 0 {
                1
            } else {
                1 + rng.below(255) as u8
            }
        })
        .collect();
    let steps = Arc::new(Steps {
        near: rotations
            .iter()
            .map(|&m| near_rotation_step_for(rotation_bound_degrees(m)).max(m))
            .collect(),
        rotations,
        translation: 37,
    });
    let bound = |a: usize, j: usize| {
        if a == 1 {
            rotation_bound_degrees(steps.rotations[j])
        } else {
            MAX_ERROR_DEGREES
        }
    };
    let mut decoder = Frame2Decoder::new();
    // The reader's last frames (newest first, as the decoder keeps them) and their seqs.
    let mut history: Vec<(u64, Vec<QuantPose>)> = Vec::new();
    let mut drops = Drops { missing: 0 };
    let mut out = Stream {
        frames: Vec::new(),
        expected: Vec::new(),
        times: Vec::new(),
        decoded: 0,
        packed: 0,
        refused: 0,
        keyframes: 0,
        backwards: 0,
    };
    let mut previous: Option<Vec<QuantPose>> = None;
    for seq in 1..=TICKS {
        for m in &mut avatars {
            m.step(&mut rng);
        }
        let now: Vec<QuantPose> = avatars
            .iter()
            .enumerate()
            .map(|(a, m)| {
                let q = QuantPose::from_pose(&m.pose);
                if a == 1 { q.coarsen(&steps) } else { q }
            })
            .collect();
        let last = previous.replace(now.clone());
        if drops.misses(&mut rng) {
            continue;
        }
        let newest = history.first().map(|(s, _)| *s);
        // Now and then the stream's own delta against the tick before, which this reader
        // lacks after a miss: refused (a packed one because the reader's last frame is not
        // its base, whose time it needs), and nothing changes.
        if let (Some(last), Some(newest)) = (&last, newest)
            && newest + 1 != seq
            && rng.next() < 0.2
        {
            let packed = rng.next() < 0.8;
            let bytes = delta_bytes(&avatars, &now, &[(seq - 1, last)], seq, &times, packed);
            assert!(decoder.decode(&bytes).is_err(), "tick {seq}");
            out.frames.push(0);
            out.frames
                .extend_from_slice(&(bytes.len() as u32).to_le_bytes());
            out.frames.extend_from_slice(&bytes);
            out.refused += 1;
        }
        let gap = newest.is_some_and(|s| s + 1 != seq);
        let key = history.is_empty() || seq % 1200 == 0 || gap && rng.next() < 0.3;
        let bytes = if key {
            let mut body = Vec::new();
            for (p, q) in avatars.iter().zip(&now) {
                frame2::encode_key(p.pose.avatar_num, p.pose.hash, q, &mut body);
            }
            history.clear();
            out.keyframes += 1;
            frame_bytes(
                &header(FrameKind::Key, seq, seq, &times),
                &body,
                avatars.len(),
            )
        } else {
            // Against the newest frame it decoded, predicting from up to depth 8 of them;
            // packed but for about one in ten.
            let depth = 1 + rng.below(history.len() as u64) as usize;
            let held: Vec<(u64, &[QuantPose])> = history[..depth]
                .iter()
                .map(|(s, f)| (*s, f.as_slice()))
                .collect();
            let packed = rng.next() < 0.9;
            out.packed += u64::from(packed);
            if packed && times[seq as usize] < times[held[0].0 as usize] {
                out.backwards += 1;
            }
            delta_bytes(&avatars, &now, &held, seq, &times, packed)
        };
        let frame = decoder
            .decode(&bytes)
            .unwrap_or_else(|e| panic!("tick {seq}: {e}"));
        assert_eq!(frame.header.server_time_us, times[seq as usize]);
        out.times.extend_from_slice(&seq.to_le_bytes());
        out.times
            .extend_from_slice(&frame.header.server_time_us.to_le_bytes());
        out.frames.push(1);
        out.frames
            .extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        out.frames.extend_from_slice(&bytes);
        for (a, (got, m)) in frame.avatars.iter().zip(&avatars).enumerate() {
            for (j, (q, source)) in got.rotations.iter().zip(&m.pose.rotations).enumerate() {
                let error = angle_between_degrees(*q, *source);
                assert!(
                    error <= bound(a, j),
                    "tick {seq}, avatar {a}, joint {j}: {error}° from the source (bound {}°)",
                    bound(a, j)
                );
                for c in q.to_array() {
                    out.expected.extend_from_slice(&c.to_le_bytes());
                }
            }
            let t_bound = translation_bound(if a == 1 { steps.translation } else { 1 });
            for (t, source) in got.translations.iter().zip(&m.pose.translations) {
                // (f32 holds a position 50 m out to about 4 µm.)
                let error = f64::from((*t - *source).abs().max_element());
                assert!(
                    error <= t_bound + 1e-5,
                    "tick {seq}, avatar {a}: translation {t} from {source}"
                );
                for c in t.to_array() {
                    out.expected.extend_from_slice(&c.to_le_bytes());
                }
            }
        }
        history.insert(0, (seq, now));
        history.truncate(frame2::MAX_DEPTH);
        out.decoded += 1;
    }
    out
}

/// The page: imports only `frames2.js` (and `math.js` for the angle), fetches the stream and
/// the Rust decoder's values and decodes frame by frame.
const PAGE: &str = r#"<!doctype html><meta charset="utf-8"><title>determinism</title>
<script>
// A module that fails to load or throws ends the wait with its error.
addEventListener("error", (e) => { window.result = { error: String(e.message) }; });
addEventListener("unhandledrejection", (e) => { window.result = { error: String(e.reason) }; });
</script>
<script type="module">
import { Frame2Decoder } from "/node_modules/frames2.js";
import { quatAngleDegrees } from "/node_modules/math.js";
const load = async (path) => new Uint8Array(await (await fetch(path)).arrayBuffer());
const [frames, expectedBytes, timeBytes] = await Promise.all([load("/frames.bin"), load("/expected.bin"), load("/times.bin")]);
const expected = new Float32Array(expectedBytes.buffer, expectedBytes.byteOffset, expectedBytes.byteLength / 4);
// Each accepted frame's seq and server time (exact: compared as BigInt).
const times = new BigUint64Array(timeBytes.buffer, timeBytes.byteOffset, timeBytes.byteLength / 8);
const view = new DataView(frames.buffer, frames.byteOffset, frames.byteLength);
const decoder = new Frame2Decoder();
let at = 0, e = 0, decoded = 0, packed = 0, refused = 0, worst = 0, worstTranslation = 0, failures = 0;
const first = [];
const fail = (what) => { failures++; if (first.length < 10) first.push(what); };
while (at < frames.byteLength) {
  const ok = view.getUint8(at) === 1;
  const length = view.getUint32(at + 1, true);
  const bytes = frames.subarray(at + 5, at + 5 + length);
  at += 5 + length;
  let frame;
  try {
    frame = decoder.decode(bytes);
  } catch (err) {
    if (ok) fail(`frame ${decoded + refused}: ${err}`); else refused++;
    continue;
  }
  if (!ok) { fail(`seq ${frame.seq}: a delta without its base was accepted`); continue; }
  if (bytes[1] === 3) packed++;
  const [seq, time] = [times[2 * decoded], times[2 * decoded + 1]];
  if (BigInt(frame.seq) !== seq || BigInt(frame.server_time_us) !== time) {
    fail(`frame ${decoded}: seq ${frame.seq} at ${frame.server_time_us} µs, expected ${seq} at ${time} µs`);
  }
  for (const a of frame.avatars) {
    for (const q of a.rotations) {
      const d = quatAngleDegrees(q, [expected[e], expected[e + 1], expected[e + 2], expected[e + 3]]);
      e += 4;
      if (!(d <= worst)) worst = d;
      if (!(d <= SAME)) fail(`seq ${frame.seq} avatar ${a.num}: ${q} (${d}°)`);
    }
    for (const t of a.translations) {
      for (const x of t) {
        const d = Math.abs(x - expected[e++]);
        if (!(d <= worstTranslation)) worstTranslation = d;
        if (!(d <= 1e-5 * Math.max(1, Math.abs(x)))) fail(`seq ${frame.seq} avatar ${a.num}: translation ${t}`);
      }
    }
  }
  decoded++;
}
window.result = { decoded, packed, refused, worst, worstTranslation, failures, first, consumed: e === expected.length && 2 * decoded === times.length };
</script>"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ten_minutes_of_random_motion_and_drops_decode_identically_in_rust_and_in_the_page() {
    let s = stream(0x2028_0003);
    // The drop patterns did what they are for.
    assert!(
        s.decoded > TICKS / 2 && s.decoded < TICKS * 95 / 100 && s.refused > 100,
        "{} decoded, {} refused",
        s.decoded,
        s.refused
    );
    // Most deltas packed, some of kind 2; some packed ones going back in time.
    assert!(
        s.packed > s.decoded * 3 / 4 && s.packed < s.decoded - s.keyframes && s.backwards > 5,
        "{} packed, {} going back",
        s.packed,
        s.backwards
    );
    eprintln!(
        "{TICKS} ticks: the reader decoded {} frames ({} keyframes, {} packed deltas, {} of them \
         back in time), refused {}; {} bytes",
        s.decoded,
        s.keyframes,
        s.packed,
        s.backwards,
        s.refused,
        s.frames.len()
    );
    let sdk = Path::new(env!("CARGO_MANIFEST_DIR")).join("server/sdk");
    let page = serve_origin(
        PAGE.replace("SAME", &SAME_BITS_DEGREES.to_string()),
        Some(sdk),
        vec![
            ("/frames.bin", s.frames),
            ("/expected.bin", s.expected),
            ("/times.bin", s.times),
        ],
    )
    .await;
    let (_driver, b) = browser().await;
    b.goto(&page).await.unwrap();
    let result = wait_js(&b, 600, "window.result").await;
    eprintln!("in the page: {result}");
    assert!(result.get("error").is_none(), "{result}");
    assert_eq!(result["failures"], 0, "{result}");
    assert_eq!(result["decoded"], s.decoded, "{result}");
    assert_eq!(result["packed"], s.packed, "{result}");
    assert_eq!(result["refused"], s.refused, "{result}");
    assert_eq!(result["consumed"], true, "{result}");
    b.close().await.unwrap();
}
