// @ts-check
// Clock offset and round trip from ping/pong, NTP-style (the JavaScript twin of
// posecast-client's `net/clock.rs`): for a ping sent at client time t0, answered at server time
// ts and received at t1, rtt = t1 − t0 and offset = ts − (t0 + t1)/2 (server = client +
// offset). The estimate is the sample with the smallest round trip among the last 16, whose
// error is at most rtt / 2.

/** Samples kept. */
export const CLOCK_WINDOW = 16;

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

  best() {
    let best = null;
    for (const s of this.samples) if (!best || s.rtt < best.rtt) best = s;
    return best;
  }

  /** @returns {number} `server − client`, µs (0 before any sample). */
  offsetUs() {
    return this.best()?.offset ?? 0;
  }

  /** @returns {number | null} The smallest recent round trip, µs. */
  rttUs() {
    return this.best()?.rtt ?? null;
  }
}
