// @ts-check
// The header (connection, round trip, frames per second, renderer), the offline overlay, what
// the connection may do and — when the server refused a token — why, and which controls are
// enabled.

import { $ } from "./ui.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./store.js").State} State */

/** Fieldsets that change the world: enabled only with control. */
const CONTROLS = ["playback-controls", "joint-controls", "place-controls", "face-controls", "add-controls", "scene-controls"];

/**
 * @param {State} s
 * @returns {boolean} Whether commands may be tried (the server still checks each).
 */
export function canControl(s) {
  return s.conn === "online" && !!s.access?.control;
}

/**
 * Why this page only watches, for people; "" when it may control.
 * @param {State} s
 * @returns {string}
 */
export function refusalText(s) {
  if (s.conn !== "online" || canControl(s)) return "";
  const refused = s.refusals.map(
    (r) => `The server refused the ${r.kind} token (${r.code}: ${r.message}).`,
  );
  if (refused.length) {
    return `Watching only — ${refused.join(" ")} A server that restarted without --control-token ` +
      "generated a new one: open the #control=… link it printed, or paste the token under Access.";
  }
  return s.access?.name
    ? `Watching only: token ${s.access.name} may not change anything.`
    : "Watching only: give a control token under Access to change anything.";
}

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, conn, viewer } = ctx;
  $("renderer").textContent = viewer.mode === "webgl2" ? "WebGL2" : "2D canvas";
  store.on(["conn", "connDetail", "access", "refusals"], (s) => {
    const pill = $("conn-state");
    const watching = s.conn === "online" && !canControl(s);
    pill.className = `pill ${watching ? "watching" : s.conn}`;
    pill.textContent = {
      online: watching ? "watching" : "online",
      connecting: "connecting…",
      offline: "offline — reconnecting",
      refused: "refused",
      closed: "closed",
    }[s.conn];
    pill.title = s.connDetail;
    const offline = $("offline");
    offline.hidden = s.conn === "online";
    offline.textContent = s.conn === "refused" ? `Refused — ${s.connDetail}` : s.conn === "connecting" ? "Connecting…" : "Offline — reconnecting…";
    const status = $("auth-status");
    status.textContent = s.conn === "refused"
      ? `Refused: ${s.refusals.map((r) => `the ${r.kind} token (${r.code}: ${r.message})`).join("; ") || s.connDetail}. Give another token under Access.`
      : refusalText(s);
    status.className = `auth-status ${s.refusals.length || s.conn === "refused" ? "error" : "muted"}`;
    renderAccess(s);
    const control = canControl(s);
    for (const id of CONTROLS) $(id, HTMLFieldSetElement).disabled = !control;
    document.body.classList.toggle("can-control", control);
  });

  store.on(["conn", "transport", "transportNote"], (s) => {
    const el = $("transport");
    el.textContent = s.conn !== "online" || !s.transport ? "–" : s.transport === "webtransport" ? "WebTransport" : "WebSocket";
    el.dataset.transport = s.transport ?? "";
    el.title = s.transport === "webtransport"
      ? "WebTransport (QUIC): frames as datagrams, a lost packet costs its own tick only"
      : s.transportNote
        ? `WebSocket: the server offers WebTransport, but ${s.transportNote}`
        : "WebSocket (TCP)";
  });

  let lastFrames = 0;
  setInterval(() => {
    $("fps").textContent = `${conn.stats.frames - lastFrames} frames/s`;
    lastFrames = conn.stats.frames;
    if (conn.rttMs !== null) $("latency").textContent = `RTT ${conn.rttMs.toFixed(1)} ms`;
  }, 1000);
}

/** @param {State} s */
function renderAccess(s) {
  const a = s.access;
  if (!a) {
    $("access").textContent = "";
    return;
  }
  /** @param {string[] | null | undefined} v */
  const list = (v) => (v == null ? "all" : v.join(", ") || "none");
  $("access").textContent =
    `This connection (${a.name ? `token ${a.name}` : "no token"}) may view: ${a.view ? "yes" : "no"} · ` +
    `control: ${a.control ? "yes" : "no"} · scenes: ${list(a.scenes)} · avatars: ${list(a.avatars)}`;
}
