// @ts-check
// Takes of a whole scene (issue 32): record the watched scene (`record_scene`,
// `stop_recording_scene`), list the takes (`list_takes`), replay one as a new scene
// (`replay`), download it as glTF, delete it (`delete_take`); and, when the watched scene is a
// replay, its timeline (`control_replay`: seek, pause, speed, loop).
//
// While a take records, its running duration and frames come from `get_take`, asked once a
// second (the server's own count: what the file holds, not what this page received). The
// list is read over REST at each connect (`GET /api/takes`, so the page still sends no
// command of its own when it starts) and with `list_takes` after each take command and on
// Refresh; nothing polls otherwise.
//
// A replay's time moves with the stream: at every frame of the watched scene it is the last
// answer's `time` plus the time since that answer times the speed (unless paused; wrapped
// when looping, held at the end otherwise), re-anchored on every answer. The page knows a
// scene is a replay from the `replay` answer it got, or — for a scene whose avatars are all
// named `<scene>.<avatar>`, as a replay's are — by asking `control_replay {scene}`, which
// answers the state, or `not_allowed_now` for a scene that is not one.

import { $, el, notice, describeError } from "./ui.js";
import { getJson } from "./rest.js";
import { canControl } from "./panel-status.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./protocol.js").TakeInfo} TakeInfo */
/** @typedef {import("./protocol.js").ReplayState} ReplayState */

/** How long Delete waits for its confirming second click, ms. */
const CONFIRM_MS = 4000;

/** Replay speeds offered. */
export const SPEEDS = [0.25, 0.5, 1, 2, 4];

/**
 * What the tests read (`window.posecast.takes`): the takes listed, the watched replay's last
 * answer (null when the watched scene is no replay), the time shown on its scrubber, the take
 * recorded in the watched scene (null: none), timeline updates, seeking and scrubbing.
 */
export const view = {
  /** @type {TakeInfo[]} */
  list: [],
  /** @type {ReplayState | null} */
  replay: null,
  /** @type {number | null} */
  shownTime: null,
  /** @type {TakeInfo | null} */
  recording: null,
  renders: 0,
  /** A seek is in flight. */
  seeking: false,
  /** The scrubber is being dragged (its value, not the stream, is shown). */
  scrubbing: false,
};

/**
 * A byte count for people.
 * @param {number} n
 * @returns {string}
 */
export function formatBytes(n) {
  if (n < 1000) return `${n} B`;
  if (n < 1e6) return `${(n / 1e3).toFixed(1)} kB`;
  if (n < 1e9) return `${(n / 1e6).toFixed(1)} MB`;
  return `${(n / 1e9).toFixed(2)} GB`;
}

/**
 * A replay's time `elapsedMs` after its state was answered: advanced at its speed unless
 * paused, wrapped when looping, held at the ends otherwise.
 * @param {ReplayState} state
 * @param {number} elapsedMs
 * @returns {number}
 */
export function replayTimeAt(state, elapsedMs) {
  const d = state.duration;
  const t = state.paused ? state.time : state.time + (Math.max(0, elapsedMs) / 1000) * state.speed;
  if (!(d > 0)) return Math.max(0, t);
  if (state.loop) return ((t % d) + d) % d;
  return Math.min(d, Math.max(0, t));
}

/**
 * A take name made up when the field is empty: the scene and the time of day.
 * @param {string} scene
 * @returns {string}
 */
function inventName(scene) {
  const now = new Date();
  const hms = [now.getHours(), now.getMinutes(), now.getSeconds()].map((v) => String(v).padStart(2, "0")).join("");
  return `${scene}-${hms}`.replace(/[^A-Za-z0-9_.-]/g, "_").slice(0, 64);
}

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, conn, run } = ctx;
  const result = $("takes-result");
  const recordButton = $("takes-record", HTMLButtonElement);
  const nameInput = $("takes-name", HTMLInputElement);
  const listRoot = $("takes-list", HTMLUListElement);

  /**
   * A line under the controls: what the last take command did, or why it was refused.
   * @param {string} text
   * @param {"ok" | "error" | ""} kind
   */
  const say = (text, kind = "") => {
    result.textContent = text;
    result.className = `small ${kind}`;
  };

  // ---- The list ------------------------------------------------------------------------

  /** @type {Map<string, {li: HTMLLIElement, head: HTMLElement, facts: HTMLElement, duration: HTMLElement, replay: HTMLButtonElement, del: HTMLButtonElement, ask: HTMLFormElement, askInput: HTMLInputElement}>} */
  const items = new Map();

  /** @param {TakeInfo[]} list */
  const setList = (list) => {
    view.list = list;
    render();
  };

  /** @param {TakeInfo} info */
  const updateOne = (info) => {
    const i = view.list.findIndex((t) => t.take === info.take);
    if (i >= 0) view.list[i] = info;
    else view.list.push(info);
    render();
  };

  let listing = false;
  /** Lists the takes again (`list_takes`). */
  const refresh = async () => {
    if (listing) return;
    listing = true;
    try {
      setList(/** @type {TakeInfo[]} */ (/** @type {unknown} */ (await conn.command({ op: "list_takes" }))) ?? []);
    } catch (e) {
      notice(`Listing the takes failed — ${describeError(e)}`, "error");
    } finally {
      listing = false;
    }
  };

  /** @param {string} take */
  const takeItem = (take) => {
    const head = el("strong", { className: "take-name" }, take);
    const duration = el("span", { className: "take-duration mono", dataset: { duration: take } });
    const facts = el("span", { className: "take-facts small muted" });
    const replay = el("button", { type: "button", dataset: { replay: take } }, "Replay");
    const glb = el("a", { href: `/api/takes/${encodeURIComponent(take)}.glb`, download: `${take}.glb`, dataset: { glb: take } }, "Download .glb");
    const del = el("button", { type: "button", className: "danger", dataset: { deleteTake: take } }, "Delete");
    /** @type {ReturnType<typeof setTimeout> | undefined} */
    let timer;
    del.addEventListener("click", () => {
      if (!del.dataset.armed) {
        del.dataset.armed = "1";
        del.textContent = "Delete take?";
        timer = setTimeout(() => {
          delete del.dataset.armed;
          del.textContent = "Delete";
        }, CONFIRM_MS);
        return;
      }
      clearTimeout(timer);
      delete del.dataset.armed;
      del.textContent = "Delete";
      deleteTake(take);
    });
    // Replay asks for the new scene's id first (default `<take>-replay`).
    const askInput = el("input", {
      type: "text", value: `${take}-replay`, pattern: "[A-Za-z0-9_.\\-]{1,64}", maxLength: 64, spellcheck: false,
      required: true, dataset: { replayScene: take }, "aria-label": `Scene for the replay of ${take}`,
    });
    const cancel = el("button", { type: "button" }, "Cancel");
    const ask = el("form", { className: "replay-ask row", hidden: true, autocomplete: "off" },
      el("span", { className: "small" }, "As scene"), askInput,
      el("button", { type: "submit", dataset: { replayStart: take } }, "Start replay"), cancel);
    replay.addEventListener("click", () => {
      ask.hidden = !ask.hidden;
      if (!ask.hidden) askInput.focus();
    });
    cancel.addEventListener("click", () => (ask.hidden = true));
    ask.addEventListener("submit", (e) => {
      e.preventDefault();
      const scene = askInput.value.trim();
      if (scene) startReplay(take, scene).then(() => (ask.hidden = true), () => {});
    });
    const li = el("li", { className: "take", dataset: { take } },
      el("div", { className: "take-head" }, head, duration),
      facts,
      el("div", { className: "take-actions" }, el("span", { className: "control-only" }, replay), glb, el("span", { className: "control-only" }, del)),
      ask);
    return { li, head, facts, duration, replay, del, ask, askInput };
  };

  const render = () => {
    const s = store.get();
    const control = canControl(s);
    const names = new Set(view.list.map((t) => t.take));
    for (const [take, item] of items) {
      if (!names.has(take)) {
        item.li.remove();
        items.delete(take);
      }
    }
    view.list.forEach((t, index) => {
      let item = items.get(t.take);
      if (!item) {
        item = takeItem(t.take);
        items.set(t.take, item);
      }
      const at = listRoot.children[index] ?? null;
      if (at !== item.li) listRoot.insertBefore(item.li, at);
      item.duration.textContent = `${t.duration.toFixed(2)} s`;
      const avatars = t.avatars.length === 1 ? "1 avatar" : `${t.avatars.length} avatars`;
      const flags = [t.recording ? "recording" : "", t.torn_bytes ? `${formatBytes(t.torn_bytes)} cut by a crash` : ""].filter(Boolean);
      item.facts.textContent = [`scene ${t.scene}`, `${t.frames} frames`, `${avatars}${t.avatars.length ? ` (${t.avatars.join(", ")})` : ""}`, formatBytes(t.bytes), ...flags].join(" · ");
      item.facts.title = new Date(t.started_us / 1000).toLocaleString();
      item.li.classList.toggle("recording", t.recording);
      item.replay.disabled = !control || t.recording;
      item.del.disabled = !control;
    });
    $("takes-empty").hidden = view.list.length > 0;
    renderRecording();
  };

  // ---- Recording -----------------------------------------------------------------------

  /** The take being recorded in the watched scene, as last heard. */
  const recordingHere = () => {
    const scene = store.get().watched;
    return view.list.find((t) => t.recording && t.scene === scene) ?? null;
  };

  const renderRecording = () => {
    const s = store.get();
    const here = recordingHere();
    view.recording = here;
    $("takes-scene").textContent = s.watched ? `— scene ${s.watched}` : "";
    recordButton.textContent = here ? "Stop" : "Record";
    recordButton.setAttribute("aria-pressed", String(!!here));
    recordButton.disabled = !canControl(s) || !s.watched || busy;
    nameInput.disabled = !!here;
    $("takes-recording").textContent = here
      ? `● Recording ${here.take}: ${here.duration.toFixed(2)} s · ${here.frames} frames · ${formatBytes(here.bytes)}`
      : "";
    poll();
  };

  let busy = false;
  /** @type {ReturnType<typeof setInterval> | undefined} */
  let pollTimer;
  let polling = false;
  /** While a take records: `get_take` once a second for its running duration and frames. */
  const poll = () => {
    const recording = view.list.some((t) => t.recording);
    if (recording && pollTimer === undefined) {
      pollTimer = setInterval(async () => {
        if (polling || store.get().conn !== "online") return;
        polling = true;
        try {
          for (const t of view.list.filter((x) => x.recording)) {
            const info = /** @type {TakeInfo} */ (/** @type {unknown} */ (await conn.command({ op: "get_take", take: t.take })));
            if (!info.recording) notice(`Take ${info.take} ended (${info.duration.toFixed(2)} s, ${info.frames} frames).`);
            updateOne(info);
          }
        } catch (e) {
          notice(`Reading the take failed — ${describeError(e)}`, "error");
          refresh();
        } finally {
          polling = false;
        }
      }, 1000);
    } else if (!recording && pollTimer !== undefined) {
      clearInterval(pollTimer);
      pollTimer = undefined;
    }
  };

  recordButton.addEventListener("click", async () => {
    const scene = store.get().watched;
    if (!scene || busy) return;
    const here = recordingHere();
    busy = true;
    renderRecording();
    try {
      if (here) {
        const info = /** @type {TakeInfo} */ (await run({ op: "stop_recording_scene", scene }));
        updateOne(info);
        say(`Take ${info.take}: ${info.duration.toFixed(2)} s, ${info.frames} frames, ${formatBytes(info.bytes)}.`, "ok");
      } else {
        const take = nameInput.value.trim() || inventName(scene);
        const info = /** @type {TakeInfo} */ (await run({ op: "record_scene", scene, take }));
        updateOne(info);
        say(`Recording scene ${scene} as take ${info.take}…`, "ok");
      }
    } catch (e) {
      say(`Refused — ${describeError(e)}`, "error");
    } finally {
      busy = false;
      renderRecording();
      refresh();
    }
  });
  $("takes-refresh").addEventListener("click", () => refresh());

  /** @param {string} take */
  const deleteTake = async (take) => {
    try {
      await run({ op: "delete_take", take });
      say(`Take ${take} deleted.`, "ok");
    } catch (e) {
      say(`Delete of ${take} refused — ${describeError(e)}`, "error");
    }
    refresh();
  };

  // ---- Replays -------------------------------------------------------------------------

  /** Scene → its replay's last answer and when it came (performance.now()). */
  /** @type {Map<string, {state: ReplayState, at: number}>} */
  const replays = new Map();
  /** Scenes asked about and found not to be replays. */
  const notReplays = new Set();
  /** Scenes being asked about. */
  const asking = new Set();
  /** Replays' scenes seen listed (their absence from the list now means deleted). */
  const listed = new Set();

  /** @param {ReplayState} state */
  const anchor = (state) => {
    replays.set(state.scene, { state, at: performance.now() });
    notReplays.delete(state.scene);
    showReplay();
  };

  /**
   * @param {string} take
   * @param {string} scene
   */
  const startReplay = async (take, scene) => {
    try {
      const state = /** @type {ReplayState} */ (await run({ op: "replay", take, scene }));
      anchor(state);
      say(`Replaying ${take} as scene ${scene}.`, "ok");
      ctx.watch(scene);
    } catch (e) {
      say(`Replay of ${take} refused — ${describeError(e)}`, "error");
      throw e;
    } finally {
      refresh();
    }
  };

  /** Asks whether the watched scene is a replay when it looks like one and nobody said. */
  const probe = () => {
    const s = store.get();
    const scene = s.watched;
    if (!scene || !canControl(s) || replays.has(scene) || notReplays.has(scene) || asking.has(scene)) return;
    const avatars = [...(s.scenes?.get(scene)?.keys() ?? [])];
    if (!avatars.length || !avatars.every((a) => a.startsWith(`${scene}.`))) return;
    asking.add(scene);
    conn.command({ op: "control_replay", scene }).then(
      (state) => anchor(/** @type {ReplayState} */ (/** @type {unknown} */ (state))),
      (e) => {
        if (e?.code === "not_allowed_now") notReplays.add(scene);
        else if (e?.code !== "offline") notice(`Asking about replay ${scene} failed — ${describeError(e)}`, "error");
      },
    ).finally(() => asking.delete(scene));
  };

  const box = $("replay");
  const seek = $("replay-seek", HTMLInputElement);
  const pause = $("replay-pause", HTMLButtonElement);
  const speed = $("replay-speed", HTMLSelectElement);
  const loop = $("replay-loop", HTMLInputElement);
  speed.replaceChildren(...SPEEDS.map((v) => el("option", { value: String(v) }, `×${v}`)));
  let scrubbing = false;

  /** The watched replay's timeline, at every frame of its scene. */
  const showReplay = () => {
    const s = store.get();
    const r = s.watched ? replays.get(s.watched) : undefined;
    box.hidden = !r;
    $("replay-controls", HTMLFieldSetElement).disabled = !canControl(s);
    if (!r) {
      view.replay = null;
      view.shownTime = null;
      return;
    }
    const st = r.state;
    const t = replayTimeAt(st, performance.now() - r.at);
    $("replay-take").textContent = `Replay of ${st.take}`;
    $("replay-duration").textContent = `${st.duration.toFixed(2)} s`;
    $("replay-state").textContent = `${st.paused ? "paused" : "playing"} ×${st.speed} · ${st.loop ? "loop" : "once"}`;
    pause.textContent = st.paused ? "Resume" : "Pause";
    pause.setAttribute("aria-pressed", String(st.paused));
    if (document.activeElement !== speed) speed.value = SPEEDS.includes(st.speed) ? String(st.speed) : "";
    loop.checked = st.loop;
    seek.max = String(st.duration || 1);
    if (!scrubbing) {
      seek.value = String(t);
      $("replay-time").textContent = `${t.toFixed(2)} s`;
      view.shownTime = t;
    }
    view.replay = st;
    view.renders++;
  };

  /**
   * Sends a `control_replay` of the watched replay and anchors on its answer.
   * @param {{time?: number, paused?: boolean, speed?: number, loop?: boolean}} fields
   */
  const control = async (fields) => {
    const scene = store.get().watched;
    if (!scene || !replays.has(scene)) return;
    try {
      anchor(/** @type {ReplayState} */ (/** @type {unknown} */ (await conn.command({ op: "control_replay", scene, ...fields }))));
    } catch (e) {
      notice(`control_replay failed — ${describeError(e)}`, "error");
      showReplay();
    }
  };

  pause.addEventListener("click", () => {
    const r = replays.get(store.get().watched ?? "");
    if (r) control({ paused: !r.state.paused });
  });
  speed.addEventListener("change", () => control({ speed: Number(speed.value) }));
  loop.addEventListener("change", () => control({ loop: loop.checked }));

  /** @type {number | null} */
  let wanted = null;
  let seeking = false;
  /** Seeks to the scrubber's value: one command in flight, the newest value wins. */
  const seekSoon = async () => {
    wanted = Number(seek.value);
    if (seeking) return;
    seeking = view.seeking = true;
    while (wanted !== null) {
      const time = wanted;
      wanted = null;
      await control({ time });
    }
    seeking = view.seeking = false;
  };
  seek.addEventListener("pointerdown", () => (scrubbing = view.scrubbing = true));
  seek.addEventListener("input", () => {
    scrubbing = view.scrubbing = true;
    $("replay-time").textContent = `${Number(seek.value).toFixed(2)} s`;
    view.shownTime = Number(seek.value);
    seekSoon();
  });
  seek.addEventListener("change", () => {
    seekSoon().finally(() => {
      scrubbing = view.scrubbing = false;
      showReplay();
    });
  });

  // ---- Wiring --------------------------------------------------------------------------

  store.on(["frame", "watched"], () => showReplay());
  store.on(["scenes", "watched", "conn", "access"], (s) => {
    // A deleted scene is no replay any more (a new scene of that name may not be one). A
    // replay's scene may be answered before it is listed: it goes once listed and then gone.
    for (const scene of [...replays.keys(), ...notReplays]) {
      if (!s.scenes) break;
      if (s.scenes.has(scene)) listed.add(scene);
      else if (listed.has(scene) || notReplays.has(scene)) {
        replays.delete(scene);
        notReplays.delete(scene);
        listed.delete(scene);
      }
    }
    probe();
    showReplay();
    render();
  });

  /** @type {unknown} */
  let welcomed = null;
  store.on(["conn"], (s) => {
    if (s.conn !== "online" || !conn.welcome || conn.welcome === welcomed) return;
    welcomed = conn.welcome;
    // Replays do not outlive a server; asked again when one is watched.
    notReplays.clear();
    getJson("/api/takes").then(
      (list) => setList(/** @type {TakeInfo[]} */ (list ?? [])),
      (e) => notice(`Listing the takes failed — ${describeError(e)}`, "error"),
    );
  });
}
