//! `--link`: the clients reach the server through an emulated link (`posecast-linkemu`, in this
//! process), one run per condition, and a table of what viewers got: delivered frames per
//! second per client (min and mean), frame age p50/p99, the worst freeze (longest time
//! without a new frame), the share of displayed poses the client library's jitter buffer
//! (`client/src/net/jitter.rs`, rendering at 60 Hz) interpolates between two received frames,
//! and the worst *displayed* freeze: the longest the rendering showed one pose (held, where
//! the buffer had nothing to interpolate between and had extrapolated its 100 ms).
//!
//! Frame ages are arrival − the frame's `server_time_us` (one machine, one clock) of the
//! frames a viewer would show: a keyframe that arrives (within 2 ms) together with the delta
//! right behind it that refers to it (a paced viewer that skipped the keyframe's tick gets both at once) is not
//! shown and not counted.

use crate::client::{Arrival, ClientStats};
use posecast_client::net::jitter::{JitterBuffer, Sampled};

/// The conditions of `--link-suite`: the (none, delay, jitter, 1 % and 5 % loss, a
/// 2 Mbit/s link shared by every client).
pub const SUITE: [&str; 6] = [
    "none",
    "delay=25ms",
    "delay=25ms,jitter=10ms",
    "delay=25ms,jitter=10ms,loss=1%",
    "delay=25ms,jitter=10ms,loss=5%",
    "rate=2mbit",
];

/// One condition's figures.
#[derive(Debug, Clone)]
pub struct Row {
    /// The link description.
    pub link: String,
    /// The clients' transport.
    pub transport: &'static str,
    /// Clients that delivered figures.
    pub clients: usize,
    /// Shown frames per second per client: the least and the mean.
    pub fps_min: f64,
    /// See `fps_min`.
    pub fps_mean: f64,
    /// Frame age, ms.
    pub age_p50: f64,
    /// See `age_p50`.
    pub age_p99: f64,
    /// Longest time any client went without a new frame, ms.
    pub worst_freeze: f64,
    /// Longest time any client's 60 Hz rendering held one pose (consecutive held samples ×
    /// the render interval), ms: 0 when every shown pose was interpolated or extrapolated.
    pub displayed_freeze: f64,
    /// Share of the displayed poses that were interpolated (the rest extrapolated or held).
    pub interpolated: f64,
    /// Share held (a repeated received pose).
    pub held: f64,
    /// Mean bytes of a frame received (a part of one over datagrams), and the share of them
    /// that were keyframes.
    pub frame_bytes: f64,
    /// See `frame_bytes`.
    pub key_share: f64,
}

/// Frames this close arrived together (one write of the server's).
const TOGETHER_US: u64 = 2_000;

/// The frames a viewer would show (see the module docs).
fn shown(arrivals: &[Arrival]) -> Vec<Arrival> {
    let mut out: Vec<Arrival> = Vec::with_capacity(arrivals.len());
    for a in arrivals {
        // Over datagrams: a tick older than the one shown (a keyframe sent again before a
        // delta, a datagram overtaken on the way) is not shown, and a scene's other parts of
        // a tick already shown complete it rather than show anything new.
        if out.last().is_some_and(|last| a.seq <= last.seq) {
            continue;
        }
        if !a.key
            && let Some(last) = out.last()
            && last.key
            && last.seq == a.base_seq
            && a.arrival_us.saturating_sub(last.arrival_us) <= TOGETHER_US
        {
            out.pop();
        }
        out.push(*a);
    }
    out
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let rank = ((v.len() as f64 * q).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
}

/// What a client's 60 Hz rendering showed ([`playout`]).
#[derive(Debug, Default, PartialEq)]
struct Played {
    /// Samples interpolated, extrapolated and held.
    counts: [u64; 3],
    /// The most held samples in a row.
    longest_hold: u64,
}

/// Plays one client's frames out through a jitter buffer, rendering at 60 Hz from 2 s after
/// its first frame (the buffer learns the link meanwhile) to its last.
fn playout(frames: &[Arrival], tick_rate: f32) -> Played {
    let mut played = Played::default();
    let (Some(first), Some(last)) = (frames.first(), frames.last()) else {
        return played;
    };
    let mut holding = 0;
    let mut buffer = JitterBuffer::new(tick_rate);
    let step = 1e6 / 60.0;
    let start = first.arrival_us as f64 + 2e6;
    let mut now = first.arrival_us as f64;
    let mut next = 0;
    while now <= last.arrival_us as f64 {
        while next < frames.len() && frames[next].arrival_us as f64 <= now {
            let f = frames[next];
            buffer.push(f.stamp_us, f.arrival_us, Vec::new());
            next += 1;
        }
        if now >= start
            && let Some((_, kind)) = buffer.sample_with_kind(buffer.playout_time(now as u64))
        {
            played.counts[match kind {
                Sampled::Interpolated => 0,
                Sampled::Extrapolated => 1,
                Sampled::Held => 2,
            }] += 1;
            holding = if kind == Sampled::Held {
                holding + 1
            } else {
                0
            };
            played.longest_hold = played.longest_hold.max(holding);
        }
        now += step;
    }
    played
}

/// The render interval of [`playout`], ms.
const RENDER_INTERVAL_MS: f64 = 1e3 / 60.0;

/// The figures of one condition from the clients' records over `seconds`.
pub fn row(
    link: &str,
    transport: &'static str,
    stats: &[ClientStats],
    seconds: f64,
    tick_rate: f32,
) -> Row {
    let mut rates = Vec::new();
    let mut ages = Vec::new();
    let mut worst_freeze = 0.0f64;
    let mut longest_hold = 0;
    let mut counts = [0u64; 3];
    let (mut frames_in, mut bytes_in, mut keys_in) = (0u64, 0u64, 0u64);
    for s in stats.iter().filter(|s| s.failure.is_none()) {
        frames_in += s.frames;
        bytes_in += s.bytes;
        keys_in += s.keys;
        let frames = shown(&s.arrivals);
        rates.push(frames.len() as f64 / seconds);
        ages.extend(
            frames
                .iter()
                .map(|f| f.arrival_us.saturating_sub(f.stamp_us) as f64 / 1e3),
        );
        for w in frames.windows(2) {
            worst_freeze = worst_freeze.max((w[1].arrival_us - w[0].arrival_us) as f64 / 1e3);
        }
        let played = playout(&frames, tick_rate);
        for (total, n) in counts.iter_mut().zip(played.counts) {
            *total += n;
        }
        longest_hold = longest_hold.max(played.longest_hold);
    }
    let displayed = counts.iter().sum::<u64>().max(1) as f64;
    Row {
        link: link.to_owned(),
        transport,
        clients: rates.len(),
        fps_min: rates.iter().copied().fold(f64::INFINITY, f64::min),
        fps_mean: rates.iter().sum::<f64>() / rates.len().max(1) as f64,
        age_p50: quantile(&mut ages, 0.5),
        age_p99: quantile(&mut ages, 0.99),
        worst_freeze,
        displayed_freeze: longest_hold as f64 * RENDER_INTERVAL_MS,
        interpolated: counts[0] as f64 / displayed,
        held: counts[2] as f64 / displayed,
        frame_bytes: bytes_in as f64 / frames_in.max(1) as f64,
        key_share: keys_in as f64 / frames_in.max(1) as f64,
    }
}

/// Prints the table (Markdown, as `docs/src/concepts/adaptive-rate.md` has it).
pub fn print(rows: &[Row]) {
    println!(
        "| link | transport | clients | frames/s per client, min / mean | frame age p50 / p99 | worst freeze | worst displayed freeze | interpolated | held | bytes a frame (keyframes) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} | {:.1} / {:.1} | {:.0} / {:.0} ms | {:.0} ms | {:.0} ms | {:.1} % | {:.1} % | {:.0} B ({:.1} %) |",
            r.link,
            r.transport,
            r.clients,
            r.fps_min,
            r.fps_mean,
            r.age_p50,
            r.age_p99,
            r.worst_freeze,
            r.displayed_freeze,
            100.0 * r.interpolated,
            100.0 * r.held,
            r.frame_bytes,
            100.0 * r.key_share
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(seq: u64, base: u64, arrival_ms: u64) -> Arrival {
        Arrival {
            arrival_us: arrival_ms * 1_000,
            stamp_us: seq * 16_667,
            seq,
            base_seq: base,
            key: seq == base,
        }
    }

    #[test]
    fn a_reference_keyframe_is_not_shown_but_a_keyframe_on_its_own_is() {
        let frames = [
            frame(60, 60, 1_000),
            frame(72, 60, 1_200),
            frame(120, 120, 2_000), // the scene's keyframe, delivered late...
            frame(122, 120, 2_000), // ...with the delta after it: the reference
            frame(134, 120, 2_200),
        ];
        let s = shown(&frames);
        let seqs: Vec<u64> = s.iter().map(|f| f.seq).collect();
        assert_eq!(seqs, [60, 72, 122, 134]);
    }

    /// Over datagrams: a keyframe sent again before a delta (an older tick), a datagram
    /// overtaken on the way, and a scene's second part of a tick are not shown.
    #[test]
    fn older_ticks_and_other_parts_of_a_shown_tick_are_not_shown() {
        let frames = [
            frame(60, 60, 1_000),
            frame(60, 60, 1_001), // the keyframe's second part
            frame(61, 60, 1_017),
            frame(60, 60, 1_030), // the keyframe again, before the next delta
            frame(62, 60, 1_034),
            frame(64, 60, 1_067),
            frame(63, 60, 1_070), // overtaken
            frame(65, 60, 1_084),
        ];
        let seqs: Vec<u64> = shown(&frames).iter().map(|f| f.seq).collect();
        assert_eq!(seqs, [60, 61, 62, 64, 65]);
    }

    #[test]
    fn steady_frames_on_a_steady_link_are_all_interpolated() {
        // 60 Hz, 30 ms in transit each: rendering 30 ms + a tick behind finds two frames
        // around every point.
        let frames: Vec<Arrival> = (0..600u64)
            .map(|i| Arrival {
                arrival_us: i * 16_667 + 30_000,
                stamp_us: i * 16_667,
                seq: i,
                base_seq: i - i % 60,
                key: i % 60 == 0,
            })
            .collect();
        let played = playout(&frames, 60.0);
        let [interpolated, extrapolated, held] = played.counts;
        assert!(interpolated > 400, "{interpolated}");
        assert_eq!((extrapolated, held, played.longest_hold), (0, 0, 0));
        let r = row(
            "x",
            "websocket",
            &[ClientStats {
                arrivals: frames,
                ..ClientStats::default()
            }],
            10.0,
            60.0,
        );
        assert!((r.fps_mean - 60.0).abs() < 0.1, "{r:?}");
        assert!((r.age_p50 - 30.0).abs() < 0.01, "{r:?}");
        assert!((r.worst_freeze - 16.667).abs() < 0.01, "{r:?}");
        assert_eq!(r.displayed_freeze, 0.0, "{r:?}");
    }

    /// A lost frame is interpolated across; a stall of 300 ms (a TCP retransmission timeout)
    /// is extrapolated for 100 ms and then held until frames come again: a displayed freeze of
    /// about 300 − 100 − 17 ms (the playout delay, 30 ms of transit and a frame interval,
    /// absorbs none of it: the buffer renders 47 ms behind, the stall ends 300 ms later).
    #[test]
    fn a_stall_is_a_displayed_freeze_and_a_lost_frame_is_not() {
        let steady = |i: u64| Arrival {
            arrival_us: i * 16_667 + 30_000,
            stamp_us: i * 16_667,
            seq: i,
            base_seq: 0,
            key: i == 0,
        };
        // Every 50th frame lost.
        let lossy: Vec<Arrival> = (0..600u64).filter(|i| i % 50 != 7).map(steady).collect();
        let played = playout(&lossy, 60.0);
        assert_eq!(
            (played.counts[2], played.longest_hold),
            (0, 0),
            "{played:?}"
        );
        // Frames 300–317 held back by 300 ms, then all at once.
        let stalled: Vec<Arrival> = (0..600u64)
            .map(|i| {
                let mut a = steady(i);
                if (300..318).contains(&i) {
                    a.arrival_us = steady(318).arrival_us;
                }
                a
            })
            .collect();
        let r = row(
            "x",
            "websocket",
            &[ClientStats {
                arrivals: stalled,
                ..ClientStats::default()
            }],
            10.0,
            60.0,
        );
        assert!(
            (150.0..=250.0).contains(&r.displayed_freeze),
            "{} ms: {r:?}",
            r.displayed_freeze
        );
    }
}
