// @ts-check
// Clock offset and round trip from ping/pong (the JavaScript twin of posecast-client's
// `net/clock.rs`): for a ping sent at client time t0, answered at server time ts and received
// at t1, rtt = t1 − t0 and offset = ts − (t0 + t1)/2 (server = client + offset). Each sample
// bounds the true offset to [offset − rtt/2, offset + rtt/2]; the estimate is the middle of the
// intersection of the last 64 samples' bounds (every exchange narrows it, whichever way the
// link's delay leaned), or — when they do not meet (a clock that stepped) — the median offset of
// the fastest quarter (at most 16) of them.

/** Samples kept. */
export const CLOCK_WINDOW = 64;
/** Most samples the fallback takes the median of. */
export const BEST_OF = 16;

export class ClockEstimator {
  constructor() {
    /** @type {{rtt: number, offset: number}[]} */
    this.samples = [];
  }

  /**
   * Adds one exchange (µs, any epoch shared by t0 and t1).
   * @param {number} t0Us
   * @param {number} serverUs
   * @param {number} t1Us
   */
  add(t0Us, serverUs, t1Us) {
    if (!(t1Us >= t0Us) || !Number.isFinite(serverUs)) return;
    if (this.samples.length === CLOCK_WINDOW) this.samples.shift();
    this.samples.push({ rtt: t1Us - t0Us, offset: serverUs - (t0Us + t1Us) / 2 });
  }

  /** @returns {number} `server − client`, µs (0 before any sample). */
  offsetUs() {
    if (this.samples.length === 0) return 0;
    let lo = -Infinity;
    let hi = Infinity;
    for (const s of this.samples) {
      lo = Math.max(lo, s.offset - s.rtt / 2);
      hi = Math.min(hi, s.offset + s.rtt / 2);
    }
    if (lo <= hi) return (lo + hi) / 2;
    const byRtt = [...this.samples].sort((a, b) => a.rtt - b.rtt);
    const k = Math.min(byRtt.length, Math.min(BEST_OF, Math.max(1, Math.floor(byRtt.length / 4))));
    const offsets = byRtt
      .slice(0, k)
      .map((s) => s.offset)
      .sort((a, b) => a - b);
    const mid = Math.floor(offsets.length / 2);
    return offsets.length % 2 === 1 ? offsets[mid] : (offsets[mid - 1] + offsets[mid]) / 2;
  }

  /** @returns {number | null} The smallest recent round trip, µs. */
  rttUs() {
    let best = null;
    for (const s of this.samples) if (best === null || s.rtt < best) best = s.rtt;
    return best;
  }
}
