// @ts-check
// The posecast dashboard. It uses only the public protocol, through the JavaScript client the
// server serves at /sdk/posecast.js (../sdk/: the websocket at /ws with binary frames, pushed
// scene changes, commands with ack/error) and the REST API (mesh download, uploads), so
// anything it does a third-party dashboard can do too.
//
// The parts: the client (../sdk/posecast.js), tokens.js, store.js (the one store every panel
// reads), sync.js (server messages → store and preview), viewer.js (the WebGL2 / 2D preview)
// and one module per panel. `?debug` exposes `window.posecast` (errors seen, frame and render
// counters, commands sent, where each avatar was drawn, the camera, the timeline) for the tests.

import { Client, forwardKinematics, jointPositions } from "../sdk/posecast.js";
import { Viewer } from "./viewer.js";
import { Store } from "./store.js";
import { Sync } from "./sync.js";
import { PageDrive } from "./drive.js";
import { $, notice, describeError } from "./ui.js";
import * as tokens from "./tokens.js";
import * as status from "./panel-status.js";
import * as access from "./panel-access.js";
import * as scenes from "./panel-scenes.js";
import * as playback from "./panel-playback.js";
import * as timeline from "./panel-timeline.js";
import * as place from "./panel-place.js";
import * as joints from "./panel-joints.js";
import * as face from "./panel-face.js";
import * as upload from "./panel-upload.js";
import * as takes from "./panel-takes.js";

const params = new URLSearchParams(location.search);
/** @type {string[]} */
const errors = [];
if (params.has("debug")) {
  window.addEventListener("error", (e) => errors.push(`error: ${e.message} at ${e.filename}:${e.lineno}`));
  window.addEventListener("unhandledrejection", (e) => errors.push(`unhandled rejection: ${e.reason}`));
  document.addEventListener("securitypolicyviolation", (e) => errors.push(`CSP: ${e.violatedDirective} ${e.blockedURI}`));
  const consoleError = console.error.bind(console);
  console.error = (...args) => {
    errors.push(args.map(String).join(" "));
    consoleError(...args);
  };
}

tokens.takeFromHash();
const store = new Store();
const conn = new Client({ tokens: tokens.forHello, encoding: "binary", name: "posecast-dashboard" });
const viewer = new Viewer($("preview", HTMLCanvasElement), { prefer2d: params.get("renderer") === "2d" });
const sync = new Sync(store, conn, viewer);
const drive = new PageDrive(conn);

/** @type {import("./ui.js").Ctx} */
const ctx = {
  store,
  conn,
  viewer,
  drive,
  select: (avatar) => sync.select(avatar),
  watch: (scene) => {
    sync.watch(scene);
    const first = scene ? store.get().scenes?.get(scene)?.keys().next().value : undefined;
    sync.select(first ?? null);
  },
  run: async (command) => {
    try {
      return await conn.command(command);
    } catch (e) {
      notice(`${command.op} failed — ${describeError(e)}`, "error");
      throw e;
    }
  },
  refreshAssets: () => sync.refreshAssets(),
};

for (const panel of [status, access, scenes, playback, timeline, place, joints, face, upload, takes]) panel.mount(ctx);

// The page's own drive ends when the server says the avatar is no longer driven (released
// from elsewhere, removed) or the connection drops (the server ended it then).
store.on(["scenes", "conn"], (s) => {
  const avatar = drive.avatar;
  if (!avatar) return;
  const entry = store.avatar(avatar);
  if (s.conn === "online" && entry?.state.driven) return;
  drive.forget();
  store.set({ driving: null });
  notice(`The page no longer drives ${avatar}.`);
});

// The preview's header, camera focus and display toggles.
/** @type {string | null} */
let focused = null;
store.on(["selected", "watched", "focus"], (s) => {
  $("preview-avatar").textContent = s.watched ? `— scene ${s.watched}${s.selected ? ` · ${s.selected}` : ""}` : "";
  // Only a new focus moves the camera: picking another avatar keeps the user's view.
  if (s.focus !== focused) viewer.focusOn(s.focus);
  focused = s.focus;
  $("frame-all").setAttribute("aria-pressed", String(s.focus === null));
});
$("frame-all").addEventListener("click", () => {
  store.set({ focus: null });
  viewer.focusOn(null); // re-frame even when already framing the whole scene
});
$("show-mesh", HTMLInputElement).addEventListener("change", (e) => {
  viewer.showMesh = /** @type {HTMLInputElement} */ (e.target).checked;
  viewer.dirty = true;
});
$("show-skeleton", HTMLInputElement).addEventListener("change", (e) => {
  viewer.showSkeleton = /** @type {HTMLInputElement} */ (e.target).checked;
  viewer.dirty = true;
});

// A `#control=…` link opened in this tab: the new token takes effect at once.
tokens.watchHash(() => {
  access.showTokens();
  notice("New token from the address: reconnecting.");
  conn.restart();
});

if (params.has("debug")) {
  /** @type {any} */ (window).posecast = {
    errors,
    get state() { return conn.state; },
    get frames() { return conn.stats.frames; },
    get rendered() { return viewer.renderedFrames; },
    get renderer() { return viewer.mode; },
    get meshLoaded() { return !!viewer.mesh; },
    /** Per avatar drawn: `{avatar, root, screen}`, its root joint in world space and on the canvas. */
    get drawn() { return viewer.drawn; },
    get rtt() { return conn.rttMs; },
    /** Commands sent, by op. */
    get sent() { return { ...conn.stats.commands }; },
    get camera() { return viewer.camera; },
    get timeline() { return { ...timeline.shownTime }; },
    /** The Takes panel: `{list, replay, shownTime, recording, renders}` (panel-takes.js). */
    get takes() { return { ...takes.view }; },
    get selected() { return store.get().selected; },
    /**
     * Aims the camera at one joint of a shown avatar from `distance` metres in front (+Z), as
     * if the user had (for close-ups in tests); false when the avatar is not posed yet.
     */
    aimAtJoint(/** @type {string} */ id, /** @type {string} */ joint, /** @type {number} */ distance) {
      const a = viewer.avatars.get(id);
      const j = a?.desc.joint_names.indexOf(joint) ?? -1;
      if (!a?.pose || j < 0) return false;
      const p = jointPositions(forwardKinematics(a.desc, a.pose))[j];
      Object.assign(viewer, { focus: null, target: [...p], distance, yaw: 0, pitch: 0, moved: true, framed: true, dirty: true });
      return true;
    },
    /** An avatar's morph weights in its newest streamed frame (protocol version 4), by channel. */
    weights(/** @type {string} */ id) { return conn.latest(id)?.weights ?? null; },
    /** The avatar the page drives live and the poses it has sent. */
    get driving() { return { avatar: drive.avatar, sent: drive.sent }; },
    get watched() { return store.get().watched; },
    get access() { return store.get().access; },
  };
}

conn.connect();
