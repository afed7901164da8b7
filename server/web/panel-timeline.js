// @ts-check
// The selected avatar's timeline, moving with the stream: at every frame of its scene the clip
// time is computed from the last pushed state (`time` at tick `seq`, speed, loop; see
// store.js `clipTimeAt`) — the server's own clock rule, so no polling and no drift. Range
// markers along the clip, a running cross-fade shown as a band over the clip times it spans and
// a meter of its progress. Dragging the scrubber seeks (one command in flight, newest wins).

import { $, el, notice, describeError } from "./ui.js";
import { clipTimeAt, fadeAt } from "./store.js";
import { canControl } from "./panel-status.js";

/** @typedef {import("./ui.js").Ctx} Ctx */

/** What the tests read (`window.posecast.timeline`). */
export const shownTime = { time: 0, seq: 0, renders: 0, fade: /** @type {number | null} */ (null) };

/**
 * A tick step giving at most ~8 intervals over `duration` seconds: 1, 2 or 5 × 10ⁿ.
 * @param {number} duration
 * @returns {number}
 */
export function tickStep(duration) {
  const raw = duration / 8;
  const p = 10 ** Math.floor(Math.log10(raw));
  for (const m of [1, 2, 5, 10]) if (m * p >= raw) return m * p;
  return 10 * p;
}

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store } = ctx;
  const seek = $("seek", HTMLInputElement);
  const markers = $("tl-markers");
  const band = $("tl-fade-band");
  let markedFor = "";
  let scrubbing = false;

  store.on(["frame", "scenes", "selected", "assets", "tickRate", "conn", "access"], (s) => {
    const entry = store.selectedAvatar();
    seek.disabled = !entry?.state.clip || !canControl(s);
    if (!entry) {
      $("tl-clip").textContent = "no avatar";
      $("tl-time").textContent = "–";
      $("tl-duration").textContent = "–";
      $("tl-state").textContent = "";
      $("tl-fade").hidden = band.hidden = true;
      return;
    }
    const a = entry.state;
    const duration = store.clipDuration(a);
    const seq = s.frame && s.frame.scene === a.scene ? s.frame.seq : entry.seq ?? 0;
    const t = clipTimeAt(entry, seq, s.tickRate, duration);
    $("tl-clip").textContent = a.clip ? `${a.clip}${a.clip_asset ? ` (from ${a.clip_asset})` : ""}` : "no clip";
    $("tl-time").textContent = `${t.toFixed(2)} s`;
    $("tl-duration").textContent = duration ? `${duration.toFixed(2)} s` : "–";
    $("tl-state").textContent = a.clip ? `${a.paused ? "paused" : "playing"} ×${a.speed} · ${a.looping ? "loop" : "once"}` : "";
    seek.max = String(duration || 1);
    if (!scrubbing) seek.value = String(t);

    // Range markers: ticks along the clip, labelled at both ends.
    const key = `${a.clip}/${duration}`;
    if (key !== markedFor) {
      markedFor = key;
      markers.replaceChildren();
      if (duration > 0) {
        const step = tickStep(duration);
        for (let m = 0; m < duration - step * 0.25; m += step) markers.append(marker(m, duration, m === 0));
        markers.append(marker(duration, duration, true));
      }
    }

    // A cross-fade: its progress, and the clip times it spans (from where the new clip started).
    const w = fadeAt(entry, seq, s.tickRate);
    const fade = a.fade;
    $("tl-fade").hidden = w === null;
    band.hidden = w === null || !(duration > 0);
    if (w !== null && fade) {
      $("tl-fade-text").textContent = `Cross-fade from ${fade.from}${fade.from_asset ? ` (${fade.from_asset})` : ""}: ${Math.round(w * 100)} % of ${fade.duration} s`;
      $("tl-fade-progress").style.width = `${(w * 100).toFixed(1)}%`;
      if (duration > 0) {
        const span = fade.duration * Math.abs(a.speed);
        const start = Math.max(0, Math.min(duration, t - w * span));
        const end = Math.max(start, Math.min(duration, start + span));
        band.style.left = `${(start / duration) * 100}%`;
        band.style.width = `${((end - start) / duration) * 100}%`;
      }
    }
    shownTime.time = t;
    shownTime.seq = seq;
    shownTime.fade = w;
    shownTime.renders++;
  });

  /** @type {number | null} */
  let wanted = null;
  let busy = false;
  /** Seeks to the scrubber's value: one command in flight, the newest value wins. */
  const seekSoon = async () => {
    const entry = store.selectedAvatar();
    wanted = Number(seek.value);
    if (busy || !entry) return;
    busy = true;
    while (wanted !== null) {
      const time = wanted;
      wanted = null;
      try {
        await ctx.conn.command({ op: "seek", avatar: entry.state.avatar, time });
      } catch (e) {
        notice(`seek failed — ${describeError(e)}`, "error");
        wanted = null;
      }
    }
    busy = false;
  };
  seek.addEventListener("pointerdown", () => (scrubbing = true));
  seek.addEventListener("input", () => {
    scrubbing = true;
    $("tl-time").textContent = `${Number(seek.value).toFixed(2)} s`;
    seekSoon();
  });
  seek.addEventListener("change", () => {
    seekSoon().finally(() => (scrubbing = false));
  });
}

/**
 * @param {number} time
 * @param {number} duration
 * @param {boolean} labelled
 * @returns {HTMLElement}
 */
function marker(time, duration, labelled) {
  const label = `${Number(time.toFixed(2))} s`;
  const m = el("span", { className: labelled ? "marker labelled" : "marker", dataset: { time: String(time), label } });
  m.style.left = `${(time / duration) * 100}%`; // CSSOM: allowed by the page's style-src 'self'
  return m;
}
