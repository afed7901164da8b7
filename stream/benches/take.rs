//! The cost of recording a scene's take (`posecast_stream::take`) and of reading it back.
//!
//! A scene of 10 built-in avatars walking (staggered clip start times) ticked at 60 Hz, a
//! keyframe every 60 ticks, each frame's chunks encoded once by the real `ChunkEncoder` (what a
//! server's binary v1 subscribers get) and recorded with `write_frame`. Prints:
//!
//! 1. the bytes a minute of take costs (and per frame, against the same frames on the wire);
//! 2. the CPU time of `write_frame` per avatar-tick (the chunks already encoded: recording
//!    costs no second encode);
//! 3. the time to index an hour-long take (216,000 frames) with `TakeIndex::scan` from its file
//!    — generated first under the target's temp folder; if generating takes over a minute, the
//!    take is cut at the first whole ten minutes past that and the table says so;
//! 4. the time of `TakeReader::poses(i)` for random `i` over the whole take (a seek: the
//!    keyframe before `i`, then `i`), p50 / p99 / max, goal ≤ 50 ms; and of reading on in
//!    order.
//!
//! CPU times are this thread's (`CLOCK_THREAD_CPUTIME_ID`), so other work on the shared cores
//! does not inflate them; the index and seek times are wall time (the file was just written,
//! so it is in the page cache: the figures are the format's cost, not the disk's).
//!
//! Run: `cargo bench -p posecast-stream --bench take`. Prints a table; asserts nothing but
//! that what it wrote reads back.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use posecast_proto::frame::{ChunkEncoder, FrameHeader, FrameKind, HEADER_BYTES};
use posecast_proto::msg::AvatarId;
use posecast_rigs::rig::Rig;
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::playback::Layer;
use posecast_stream::take::{
    TakeHeader, TakeIndex, TakeReader, write_avatars, write_frame, write_start,
};
use std::io::Write;
use std::sync::Arc;
use std::time::{Duration, Instant};

const RATE: f64 = 60.0;
const KEY_INTERVAL: u64 = 60;
const AVATARS: usize = 10;
/// Ticks in a minute.
const MINUTE: u64 = 60 * RATE as u64;

/// This thread's CPU time.
fn thread_cpu() -> Duration {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Duration::new(
        u64::try_from(t.tv_sec).unwrap_or(0),
        u32::try_from(t.tv_nsec).unwrap_or(0),
    )
}

/// The scene: its avatars, one chunk encoder each, and the tick's chunks.
struct Scene {
    avatars: Vec<Avatar>,
    encoders: Vec<ChunkEncoder>,
    chunks: Vec<Vec<u8>>,
}

impl Scene {
    fn new(rig: &Arc<Rig>) -> Self {
        let walk = rig.clip("walk").expect("the built-in avatar walks").clone();
        let avatars = (0..AVATARS)
            .map(|i| {
                let mut a = Avatar::new(AvatarId(format!("a{i}")), i as u32 + 1, rig.clone());
                let start = (i as f32 * 0.137) % walk.duration().max(1e-3);
                a.play(Layer::new(walk.clone(), None, start, 1.0, true), 0.0);
                a
            })
            .collect();
        Self {
            avatars,
            encoders: vec![ChunkEncoder::new(); AVATARS],
            chunks: vec![Vec::new(); AVATARS],
        }
    }

    /// Ticks every avatar to `seq` and encodes its chunk, as a scene's tick does.
    fn tick(&mut self, seq: u64) -> FrameHeader {
        let key = seq.is_multiple_of(KEY_INTERVAL);
        let kind = if key {
            FrameKind::Key
        } else {
            FrameKind::Delta
        };
        for ((a, enc), chunk) in self
            .avatars
            .iter_mut()
            .zip(&mut self.encoders)
            .zip(&mut self.chunks)
        {
            a.tick(seq as f64 / RATE);
            chunk.clear();
            enc.encode(a.pose(), kind, chunk);
        }
        FrameHeader {
            kind,
            scene_num: 1,
            seq,
            server_time_us: 1_764_000_000_000_000 + seq * 16_667,
            base_seq: seq - seq % KEY_INTERVAL,
        }
    }

    fn pieces(&self) -> impl Iterator<Item = (u32, &[u8], &[f32])> {
        self.avatars
            .iter()
            .zip(&self.chunks)
            .map(|(a, c)| (a.num(), c.as_slice(), a.pose().weights.as_slice()))
    }

    /// The take's start: magic, header and avatar list.
    fn start(&self, out: &mut Vec<u8>) {
        write_start(
            &TakeHeader {
                take: "bench".into(),
                scene: "bench".into(),
                tick_rate: RATE as f32,
                started_us: 1_764_000_000_000_000,
            },
            out,
        );
        let list: Vec<_> = self.avatars.iter().map(|a| &*a.description).collect();
        write_avatars(&list, out);
    }
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn ms(d: Duration) -> String {
    format!("{:.3} ms", d.as_secs_f64() * 1e3)
}

fn main() {
    let rig = Arc::new(posecast_rigs::builtin::rig().expect("the built-in avatar"));

    // (1) A minute of take, and (2) write_frame's CPU time on the minute's chunks.
    let mut scene = Scene::new(&rig);
    let mut take = Vec::new();
    scene.start(&mut take);
    let start_bytes = take.len();
    let mut wire = 0usize;
    let mut minute: Vec<(FrameHeader, Vec<Vec<u8>>)> = Vec::new();
    for seq in 0..MINUTE {
        let header = scene.tick(seq);
        write_frame(&header, scene.pieces(), &mut take);
        wire += HEADER_BYTES + scene.chunks.iter().map(Vec::len).sum::<usize>();
        minute.push((header, scene.chunks.clone()));
    }
    let frames_bytes = take.len() - start_bytes;
    let nums: Vec<u32> = scene.avatars.iter().map(Avatar::num).collect();
    let no_weights: Vec<f32> = Vec::new();
    let mut out = Vec::with_capacity(take.len());
    let rounds = 20;
    let cpu = thread_cpu();
    for _ in 0..rounds {
        out.clear();
        for (header, chunks) in &minute {
            let pieces = nums
                .iter()
                .zip(chunks)
                .map(|(&n, c)| (n, c.as_slice(), no_weights.as_slice()));
            write_frame(header, pieces, &mut out);
        }
        std::hint::black_box(&out);
    }
    let per_avatar_tick =
        (thread_cpu() - cpu).as_secs_f64() / (rounds * MINUTE) as f64 / AVATARS as f64;

    println!("| figure | value |");
    println!("|---|---:|");
    println!(
        "| take of {AVATARS} built-in avatars walking, 60 Hz, key every {KEY_INTERVAL} ticks: bytes per minute | {:.2} MB ({} B; start: {start_bytes} B of header and avatar list) |",
        take.len() as f64 / 1e6,
        take.len()
    );
    println!(
        "| per frame (take / the same frame on the wire, v1) | {:.0} B / {:.0} B |",
        frames_bytes as f64 / MINUTE as f64,
        wire as f64 / MINUTE as f64
    );
    println!(
        "| `write_frame` CPU per avatar-tick | {:.1} ns |",
        per_avatar_tick * 1e9
    );

    // (3) An hour of take in a file, indexed.
    let path = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("take-bench.take");
    let mut file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    let mut scene = Scene::new(&rig);
    let mut buf = Vec::new();
    scene.start(&mut buf);
    let generating = Instant::now();
    let mut minutes = 0u64;
    let hour = 60;
    while minutes < hour {
        for tick in 0..MINUTE {
            let header = scene.tick(minutes * MINUTE + tick);
            write_frame(&header, scene.pieces(), &mut buf);
            file.write_all(&buf).unwrap();
            buf.clear();
        }
        minutes += 1;
        if generating.elapsed() > Duration::from_secs(60) && minutes.is_multiple_of(10) {
            break;
        }
    }
    file.flush().unwrap();
    drop(file);
    let generated = generating.elapsed();
    let size = std::fs::metadata(&path).unwrap().len();
    let label = if minutes == hour {
        "an hour".to_owned()
    } else {
        format!("{minutes} minutes (generating an hour would take over a minute)")
    };
    println!(
        "| take generated: {label}, {} frames | {:.1} MB in {:.1} s |",
        minutes * MINUTE,
        size as f64 / 1e6,
        generated.as_secs_f64()
    );
    let wall = Instant::now();
    let cpu = thread_cpu();
    let index = TakeIndex::scan(std::fs::File::open(&path).unwrap()).unwrap();
    let (wall, cpu) = (wall.elapsed(), thread_cpu() - cpu);
    assert_eq!(index.frames.len() as u64, minutes * MINUTE);
    assert_eq!((index.valid_len, index.torn_tail), (size, 0));
    println!(
        "| index of {label}: `TakeIndex::scan` (wall / CPU) | {} / {} ({:.2} GB/s) |",
        ms(wall),
        ms(cpu),
        size as f64 / wall.as_secs_f64() / 1e9
    );

    // (4) Seeks: poses(i) for random i over the whole take; then reading on in order.
    let index = Arc::new(index);
    let frames = index.frames.len();
    let mut reader = TakeReader::new(std::fs::File::open(&path).unwrap(), index.clone());
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut times = Vec::new();
    for _ in 0..2000 {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        let i = (rng % frames as u64) as usize;
        let t = Instant::now();
        let poses = reader.poses(i).unwrap();
        times.push(t.elapsed());
        assert_eq!(poses.len(), AVATARS);
    }
    times.sort();
    println!(
        "| seek: `poses(i)` for 2,000 random i (p50 / p99 / max; goal ≤ 50 ms) | {} / {} / {} |",
        ms(percentile(&times, 0.5)),
        ms(percentile(&times, 0.99)),
        ms(times[times.len() - 1])
    );
    let t = Instant::now();
    let run = frames.min(36_000);
    for i in 0..run {
        reader.poses(i).unwrap();
    }
    println!(
        "| reading on in order: `poses(i)`, `poses(i + 1)`, … ({run} frames) | {:.1} µs per frame |",
        t.elapsed().as_secs_f64() * 1e6 / run as f64
    );
    let _ = std::fs::remove_file(&path);
}
