// The posecast dashboard. It uses only the public protocol: the websocket at /ws (JSON
// frames, commands with ack/error) and the REST API (mesh download, uploads), so anything it
// does a third-party dashboard can do too.
//
// `?debug` exposes `window.posecast` (errors seen, frame and render counters, where each avatar
// was drawn) for the tests.

import { Connection, ServerError } from "./connection.js";
import { Viewer } from "./viewer.js";
import { parseGlb } from "./glb.js";
import { quatAxisAngle, quatFromEulerXYZ, eulerXYZFromQuat, DEG } from "./math.js";

const params = new URLSearchParams(location.search);
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

const $ = (id) => document.getElementById(id);
const el = (tag, props = {}, ...children) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(props)) {
    if (k === "dataset") Object.assign(e.dataset, v);
    else if (k in e) e[k] = v;
    else e.setAttribute(k, v);
  }
  e.append(...children);
  return e;
};

// ---------------------------------------------------------------------------------------------
// Tokens (sessionStorage: gone when the tab closes).

const TOKEN_KEYS = { view: "posecast.token.view", control: "posecast.token.control" };
const tokens = {
  get view() { return sessionStorage.getItem(TOKEN_KEYS.view) || ""; },
  get control() { return sessionStorage.getItem(TOKEN_KEYS.control) || ""; },
  /** Tokens to present in the hello, in order: control first (it may view too), then view. */
  forHello() {
    return [...new Set([this.control, this.view].filter(Boolean))];
  },
  /** The token for REST reads (mesh) and writes (upload). */
  forRest(write) {
    return (write ? this.control || this.view : this.view || this.control) || null;
  },
};

// A link like `/#control=TOKEN` (the server prints one when it generates its control token)
// stores the token for this tab and takes it out of the address bar and history.
{
  const hash = new URLSearchParams(location.hash.slice(1));
  let found = false;
  for (const k of ["view", "control"]) {
    const v = hash.get(k);
    if (v) {
      sessionStorage.setItem(TOKEN_KEYS[k], v);
      found = true;
    }
  }
  if (found) history.replaceState(null, "", location.pathname + location.search);
}

// ---------------------------------------------------------------------------------------------
// State.

const state = {
  scenes: [],
  assets: [],
  selected: null, // avatar id
  joint: null,
  descriptions: new Map(), // avatar id → description
  poses: new Map(), // avatar id → latest JSON pose
  dofInfo: new Map(), // "asset/joint" → { count, limits: [{min, max}], values: [] }
  meshes: new Map(), // description hash → Promise of the parsed mesh
};

const wsUrl = `${location.protocol === "https:" ? "wss:" : "ws:"}//${location.host}/ws`;
const conn = new Connection(wsUrl, () => tokens.forHello());
const viewer = new Viewer($("preview"), { prefer2d: params.get("renderer") === "2d" });
$("renderer").textContent = viewer.mode === "webgl2" ? "WebGL2" : "2D canvas";

if (params.has("debug")) {
  window.posecast = {
    errors,
    get state() { return conn.state; },
    get frames() { return conn.frames; },
    get rendered() { return viewer.renderedFrames; },
    get renderer() { return viewer.mode; },
    get meshLoaded() { return !!viewer.mesh; },
    /** Per avatar drawn: `{avatar, root, screen}`, its root joint in world space and on the canvas. */
    get drawn() { return viewer.drawn; },
    get rtt() { return conn.rtt; },
  };
}

function notice(text, kind = "info") {
  const list = $("notice");
  list.prepend(el("li", { className: kind }, `${new Date().toLocaleTimeString()} — ${text}`));
  while (list.children.length > 6) list.lastChild.remove();
}

function describeError(e) {
  if (e instanceof ServerError) {
    if (e.code === "unauthorized") return `Refused (unauthorized): ${e.message}. Check the token.`;
    if (e.code === "forbidden") return `Refused (forbidden): ${e.message}. This token may not do that.`;
    return `${e.code}: ${e.message}`;
  }
  return String(e?.message ?? e);
}

/** Runs a command that changes something; reports failures; refreshes the lists after. */
async function run(command) {
  try {
    const result = await conn.command(command);
    refreshSoon();
    return result;
  } catch (e) {
    const text = describeError(e);
    notice(`${command.op} failed — ${text}`, "error");
    if (e.code === "unauthorized" || e.code === "forbidden") $("auth-status").textContent = text;
    throw e;
  }
}

const selectedAvatar = () => {
  for (const s of state.scenes) for (const a of s.avatars) if (a.avatar === state.selected) return a;
  return null;
};

// ---------------------------------------------------------------------------------------------
// Connection state, latency, frames/s.

conn.addEventListener("state", (e) => {
  const { state: s, detail } = e.detail;
  const pill = $("conn-state");
  pill.className = `pill ${s}`;
  pill.textContent = {
    online: "online",
    connecting: "connecting…",
    offline: "offline — reconnecting",
    refused: "refused",
  }[s] ?? s;
  pill.title = detail;
  $("offline").hidden = s === "online";
  $("offline").textContent = s === "refused" ? `Refused — ${detail}` : "Offline — reconnecting…";
  if (s !== "online") setControlsEnabled(false);
});

conn.addEventListener("refused", (e) => {
  const { code, message, token } = e.detail;
  const which = token && token === tokens.control ? "control token" : token ? "view token" : "no token";
  const text = `The server refused the ${which} (${code}): ${message}`;
  $("auth-status").textContent = text;
  notice(text, "error");
});

conn.addEventListener("welcome", async () => {
  // Keep the refusal of a control token visible when the view token was taken instead.
  if (!tokens.control || conn.usedToken === tokens.control) $("auth-status").textContent = "";
  renderAccess();
  setControlsEnabled(true);
  await refresh(true);
});

function renderAccess() {
  const a = conn.access;
  if (!a) {
    $("access").textContent = conn.usedToken ? "Connected with a token." : "Connected (no token).";
    return;
  }
  const list = (v) => (v == null ? "all" : v.join(", ") || "none");
  $("access").textContent =
    `This connection may view: ${a.view ? "yes" : "no"} · control: ${a.control ? "yes" : "no"}` +
    ` · scenes: ${list(a.scenes)} · avatars: ${list(a.avatars)}`;
}

function canControl() {
  return conn.state === "online" && (conn.access ? conn.access.control : true);
}

function setControlsEnabled(on) {
  const control = on && canControl();
  for (const id of ["playback-controls", "joint-controls"]) $(id).disabled = !control;
  $("upload-submit").disabled = false;
}

let lastFrames = 0;
setInterval(() => {
  $("fps").textContent = `${conn.frames - lastFrames} frames/s`;
  lastFrames = conn.frames;
}, 1000);
conn.addEventListener("pong", (e) => {
  $("latency").textContent = `RTT ${e.detail.toFixed(1)} ms`;
});

// ---------------------------------------------------------------------------------------------
// Scenes, avatars and their state (list_scenes once a second and after each change).

let refreshTimer = null;
function refreshSoon() {
  clearTimeout(refreshTimer);
  refreshTimer = setTimeout(() => refresh(false), 50);
}

async function refresh(withAssets) {
  if (conn.state !== "online") return;
  try {
    const [scenes, assets] = await Promise.all([
      conn.command({ op: "list_scenes" }),
      withAssets || !state.assets.length ? conn.command({ op: "list_assets" }) : Promise.resolve(state.assets),
    ]);
    state.scenes = scenes ?? [];
    state.assets = assets ?? [];
    if (!selectedAvatar()) {
      const all = state.scenes.flatMap((s) => s.avatars);
      select(all.find((a) => a.avatar === state.selected)?.avatar ?? all[0]?.avatar ?? null);
    }
    renderScenes();
    renderPlayback(withAssets);
  } catch (e) {
    if (e.code !== "offline") notice(`Listing failed — ${describeError(e)}`, "error");
  }
}
setInterval(() => {
  if (!document.hidden) refresh(false);
}, 1000);

function summary(a) {
  const clip = a.clip ? `${a.clip_asset ? `${a.clip_asset}:` : ""}${a.clip}` : "no clip";
  const flags = [a.paused ? "paused" : "playing", a.looping ? "loop" : "once", `×${a.speed}`];
  const over = a.overrides.length ? ` · overrides: ${a.overrides.join(", ")}` : "";
  return `${clip} @ ${a.time.toFixed(2)} s · ${flags.join(" · ")}${over}`;
}

let sceneSignature = "";
function renderScenes() {
  const signature = JSON.stringify(state.scenes.map((s) => [s.scene, s.avatars.map((a) => a.avatar)]));
  const root = $("scene-list");
  if (signature !== sceneSignature) {
    sceneSignature = signature;
    root.replaceChildren();
    if (!state.scenes.length) root.append(el("p", { className: "muted" }, "No scenes."));
    for (const s of state.scenes) {
      root.append(el("h3", {}, `Scene ${s.scene}`));
      const ul = el("ul", { className: "avatar-list" });
      for (const a of s.avatars) {
        const b = el("button", { type: "button", dataset: { avatar: a.avatar } },
          el("strong", {}, a.avatar), ` (${a.asset})`, el("span", { className: "avatar-summary" }));
        b.addEventListener("click", () => select(a.avatar));
        ul.append(el("li", {}, b));
      }
      if (!s.avatars.length) ul.append(el("li", { className: "muted" }, "no avatars"));
      root.append(ul);
    }
  }
  for (const s of state.scenes) for (const a of s.avatars) {
    const b = root.querySelector(`button[data-avatar="${CSS.escape(a.avatar)}"]`);
    if (!b) continue;
    b.setAttribute("aria-pressed", String(a.avatar === state.selected));
    b.querySelector(".avatar-summary").textContent = `${summary(a)} · ${s.subscribers} subscribers`;
  }
}

function select(avatar) {
  if (state.selected === avatar && avatar !== null) return;
  state.selected = avatar;
  state.joint = null;
  const a = selectedAvatar();
  conn.subscribeOnly(a ? a.scene : null);
  showScene(a ? a.scene : null);
  viewer.select(avatar);
  $("preview-avatar").textContent = a ? `— ${a.avatar}` : "";
  const desc = avatar ? state.descriptions.get(avatar) : null;
  if (desc) onDescription(desc);
  else $("joint-tree").replaceChildren();
  renderJoint();
  renderScenes();
  renderPlayback(true);
}

// ---------------------------------------------------------------------------------------------
// Playback.

let clipSignature = "";
function renderPlayback(rebuild) {
  const a = selectedAvatar();
  const dl = $("avatar-state");
  dl.replaceChildren();
  if (!a) {
    dl.append(el("dt", {}, "Avatar"), el("dd", {}, "none selected"));
    return;
  }
  const rows = [
    ["Avatar", `${a.avatar} (rig ${a.asset}, scene ${a.scene})`],
    ["Clip", a.clip ? (a.clip_asset ? `${a.clip} (retargeted from ${a.clip_asset})` : a.clip) : "none"],
    ["Time", `${a.time.toFixed(2)} s`],
    ["Speed", String(a.speed)],
    ["State", `${a.paused ? "paused" : "playing"}, ${a.looping ? "looping" : "not looping"}`],
    ["Overrides", a.overrides.length ? a.overrides.join(", ") : "none"],
  ];
  for (const [k, v] of rows) dl.append(el("dt", {}, k), el("dd", { dataset: { field: k.toLowerCase() } }, v));

  const select = $("clip-select");
  const signature = JSON.stringify([a.avatar, a.asset, state.assets.map((x) => [x.name, x.clips.map((c) => c.name)])]);
  if (rebuild || signature !== clipSignature) {
    clipSignature = signature;
    const keep = select.value;
    select.replaceChildren();
    const own = state.assets.find((x) => x.name === a.asset);
    const others = state.assets.filter((x) => x.name !== a.asset && x.clips.length);
    const group = (label, asset, from) => {
      const g = el("optgroup", { label });
      for (const c of asset.clips) {
        g.append(el("option", { value: JSON.stringify([from, c.name]) }, `${c.name} (${c.duration.toFixed(2)} s)`));
      }
      return g;
    };
    if (own) select.append(group(`${own.name} (own clips)`, own, null));
    for (const x of others) select.append(group(`Retargeted from ${x.name}`, x, x.name));
    const current = JSON.stringify([a.clip_asset ?? null, a.clip]);
    if ([...select.options].some((o) => o.value === keep)) select.value = keep;
    else if ([...select.options].some((o) => o.value === current)) select.value = current;
  }
  const seek = $("seek");
  const duration = clipDuration(a);
  if (document.activeElement !== seek) {
    seek.max = String(duration || 1);
    seek.value = String(a.time);
    $("seek-out").textContent = `${a.time.toFixed(2)} s`;
  }
}

function clipDuration(a) {
  if (!a.clip) return 0;
  const asset = state.assets.find((x) => x.name === (a.clip_asset ?? a.asset));
  return asset?.clips.find((c) => c.name === a.clip)?.duration ?? 0;
}

function num(id, fallback) {
  const v = Number($(id).value);
  return Number.isFinite(v) ? v : fallback;
}

$("play").addEventListener("click", () => {
  const a = selectedAvatar();
  if (!a || !$("clip-select").value) return;
  const [from, clip] = JSON.parse($("clip-select").value);
  const command = { op: "play", avatar: a.avatar, clip, speed: num("speed", 1), looping: $("looping").checked, fade: num("fade", 0.25) };
  if (from) command.from_asset = from;
  run(command).then(() => notice(`Playing ${from ? `${from}:` : ""}${clip} on ${a.avatar}`)).catch(() => {});
});
for (const op of ["pause", "resume", "stop"]) {
  $(op).addEventListener("click", () => {
    const a = selectedAvatar();
    if (a) run({ op, avatar: a.avatar }).catch(() => {});
  });
}
$("set-speed").addEventListener("click", () => {
  const a = selectedAvatar();
  if (a) run({ op: "set_speed", avatar: a.avatar, speed: num("speed", 1) }).catch(() => {});
});
$("seek").addEventListener("input", () => {
  $("seek-out").textContent = `${Number($("seek").value).toFixed(2)} s`;
});
$("seek").addEventListener("change", () => {
  const a = selectedAvatar();
  if (a) run({ op: "seek", avatar: a.avatar, time: Number($("seek").value) }).catch(() => {});
});

// ---------------------------------------------------------------------------------------------
// Descriptions, frames, mesh.

/** The preview shows every avatar of the watched scene, each where it stands. */
function showScene(scene) {
  if (viewer.scene === scene) return;
  viewer.setScene(scene);
  const s = state.scenes.find((x) => x.scene === scene);
  for (const a of s?.avatars ?? []) {
    const desc = state.descriptions.get(a.avatar);
    if (desc) showAvatar(desc);
  }
}

function showAvatar(desc) {
  viewer.setAvatar(desc);
  loadMesh(desc);
}

conn.addEventListener("description", (e) => {
  const desc = e.detail.avatar;
  state.descriptions.set(desc.id, desc);
  if (e.detail.scene === viewer.scene) showAvatar(desc);
  if (desc.id === state.selected) onDescription(desc);
});

function onDescription(desc) {
  buildJointTree(desc);
}

conn.addEventListener("frame", (e) => {
  const shown = e.detail.scene === viewer.scene;
  for (const pose of e.detail.avatars) {
    state.poses.set(pose.avatar, pose);
    if (shown) viewer.setPose(pose.avatar, pose);
  }
});

conn.addEventListener("avatar_removed", (e) => {
  state.descriptions.delete(e.detail.avatar);
  viewer.removeAvatar(e.detail.avatar);
  refreshSoon();
});

/** Fetches and parses each rig's mesh once (by description hash); shows it when it arrives. */
function loadMesh(desc) {
  if (!desc.mesh_url) return;
  let mesh = state.meshes.get(desc.hash);
  if (!mesh) {
    mesh = fetchMesh(desc.mesh_url);
    state.meshes.set(desc.hash, mesh);
    mesh.catch(() => state.meshes.delete(desc.hash));
  }
  mesh.then(
    (m) => {
      viewer.setMesh(desc.hash, m);
    },
    (e) => notice(`Mesh of ${desc.id} not shown (skeleton only): ${e.message}`, "error"),
  );
}

async function fetchMesh(url) {
  const token = tokens.forRest(false);
  const r = await fetch(url, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
  if (!r.ok) throw new Error(`${r.status} ${await errorMessage(r)}`);
  return parseGlb(await r.arrayBuffer());
}

async function errorMessage(response) {
  const text = await response.text();
  try {
    const body = JSON.parse(text);
    if (body && body.message) return `${body.code ? `${body.code}: ` : ""}${body.message}`;
  } catch {
    /* not JSON */
  }
  return text || response.statusText;
}

$("show-mesh").addEventListener("change", (e) => {
  viewer.showMesh = e.target.checked;
  viewer.dirty = true;
});
$("show-skeleton").addEventListener("change", (e) => {
  viewer.showSkeleton = e.target.checked;
  viewer.dirty = true;
});

// ---------------------------------------------------------------------------------------------
// Joint tree and per-joint controls.

function buildJointTree(desc) {
  const ul = $("joint-tree");
  ul.replaceChildren();
  const depth = [];
  desc.joint_names.forEach((name, j) => {
    const p = desc.parents[j];
    depth[j] = p >= 0 ? depth[p] + 1 : 0;
    const b = el("button", { type: "button", tabIndex: -1, dataset: { joint: name } }, name);
    b.style.setProperty("--depth", String(depth[j]));
    b.addEventListener("click", () => selectJoint(name));
    ul.append(el("li", {}, b));
  });
  const first = ul.querySelector("button");
  if (first) first.tabIndex = 0;
  applyFilter();
  markJoints();
}

function treeButtons() {
  return [...$("joint-tree").querySelectorAll("button")].filter((b) => !b.parentElement.hidden);
}

$("joint-tree").addEventListener("keydown", (e) => {
  const buttons = treeButtons();
  const i = buttons.indexOf(document.activeElement);
  if (i < 0) return;
  const to = { ArrowDown: i + 1, ArrowUp: i - 1, Home: 0, End: buttons.length - 1 }[e.key];
  if (to === undefined) return;
  e.preventDefault();
  const b = buttons[Math.max(0, Math.min(buttons.length - 1, to))];
  for (const x of buttons) x.tabIndex = -1;
  b.tabIndex = 0;
  b.focus();
});

function applyFilter() {
  const f = $("joint-filter").value.trim().toLowerCase();
  for (const b of $("joint-tree").querySelectorAll("button")) {
    b.parentElement.hidden = !!f && !b.dataset.joint.toLowerCase().includes(f);
  }
}
$("joint-filter").addEventListener("input", applyFilter);

function markJoints() {
  const overrides = new Set(selectedAvatar()?.overrides ?? []);
  for (const b of $("joint-tree").querySelectorAll("button")) {
    b.classList.toggle("overridden", overrides.has(b.dataset.joint));
    b.setAttribute("aria-current", String(b.dataset.joint === state.joint));
  }
}

async function selectJoint(name) {
  state.joint = name;
  for (const b of $("joint-tree").querySelectorAll("button")) b.tabIndex = b.dataset.joint === name ? 0 : -1;
  markJoints();
  await probeDofs(name);
  renderJoint();
}

function dofKey(joint) {
  return `${selectedAvatar()?.asset}/${joint}`;
}

/**
 * The joint's DOFs, their limits and current values (`get_joint`). A joint of a rig without
 * joint types has none and is set by rotation instead (Euler X, Y, Z sliders).
 */
async function probeDofs(joint) {
  const a = selectedAvatar();
  if (!a) return;
  let info;
  try {
    info = await conn.command({ op: "get_joint", avatar: a.avatar, joint });
  } catch {
    return; // offline or refused (already reported): ask again when selected again
  }
  const typed = info.joint_type != null && info.dofs.length > 0;
  const deg = (v, fallback) => (v == null ? fallback : v / DEG);
  state.dofInfo.set(dofKey(joint), {
    count: typed ? info.dofs.length : null,
    limits: typed
      ? info.dofs.map((d) => ({ min: deg(d.min, -180), max: deg(d.max, 180) }))
      : [0, 1, 2].map(() => ({ min: -180, max: 180 })),
    values: typed ? info.dofs.map((d) => Math.round((d.value / DEG) * 10) / 10) : [0, 0, 0],
  });
}

function renderJoint() {
  const box = $("dof-controls");
  box.replaceChildren();
  const joint = state.joint;
  $("joint-title").textContent = joint ? `Joint ${joint}` : "No joint selected";
  $("dof-note").textContent = "";
  if (!joint) return;
  const info = state.dofInfo.get(dofKey(joint));
  if (!info) {
    $("dof-note").textContent = "Could not ask the server about this joint.";
    return;
  }
  const byDofs = info.count !== null;
  if (!byDofs) {
    // Start the rotation sliders at the streamed rotation.
    const pose = state.poses.get(state.selected);
    const j = viewer.desc?.joint_names.indexOf(joint) ?? -1;
    if (pose && j >= 0) info.values = eulerXYZFromQuat(pose.rotations[j]).map((v) => Math.round(v / DEG));
  }
  const labels = byDofs ? info.limits.map((_, i) => `DOF ${i} (°)`) : ["Rotate X (°)", "Rotate Y (°)", "Rotate Z (°)"];
  labels.forEach((label, i) => {
    const id = `dof-${i}`;
    const input = el("input", { id, type: "range", step: "1", className: "dof-input" });
    input.min = String(Math.floor(info.limits[i].min));
    input.max = String(Math.ceil(info.limits[i].max));
    input.value = String(info.values[i]);
    const out = el("output", { id: `${id}-out`, htmlFor: id }, `${Number(input.value).toFixed(1)}°`);
    input.addEventListener("input", () => {
      info.values[i] = Number(input.value);
      out.textContent = `${info.values[i].toFixed(1)}°`;
      sendJoint(joint, info);
    });
    box.append(el("div", { className: "dof" }, el("label", { htmlFor: id }, label), input, out));
  });
  $("dof-note").textContent = byDofs
    ? `${info.count} DOFs (set_joint_dofs); the sliders span the rig's limits, which the server enforces.`
    : "This rig has no joint types: the sliders set the local rotation (Euler X, Y, Z).";
  updateJointPose();
}

let jointBusy = false;
let jointDirty = false;
/** Sends the sliders' values; at most one command in flight, the newest values win. */
async function sendJoint(joint, info) {
  if (jointBusy) {
    jointDirty = true;
    return;
  }
  const a = selectedAvatar();
  if (!a) return;
  jointBusy = true;
  const sent = [...info.values];
  try {
    if (info.count !== null) {
      const r = await run({ op: "set_joint_dofs", avatar: a.avatar, joint, values: sent.map((v) => v * DEG) });
      applyClamp(joint, info, sent, (r?.values ?? []).map((v) => v / DEG));
    } else {
      const q = quatFromEulerXYZ(sent[0] * DEG, sent[1] * DEG, sent[2] * DEG);
      await run({ op: "set_joint_rotation", avatar: a.avatar, joint, rotation: q });
    }
  } catch {
    /* reported by run() */
  } finally {
    jointBusy = false;
  }
  if (jointDirty) {
    jointDirty = false;
    sendJoint(joint, info);
  }
}

/** The server clamped `sent` to `applied`: remember those limits and show them. */
function applyClamp(joint, info, sent, applied) {
  let changed = false;
  applied.forEach((v, i) => {
    if (Math.abs(v - sent[i]) < 0.05) return;
    const lim = info.limits[i];
    if (sent[i] > v && v < lim.max) lim.max = v;
    if (sent[i] < v && v > lim.min) lim.min = v;
    info.values[i] = v;
    changed = true;
  });
  if (!changed || state.joint !== joint) return;
  applied.forEach((v, i) => {
    const input = $(`dof-${i}`);
    if (!input) return;
    input.min = String(Math.floor(info.limits[i].min * 10) / 10);
    input.max = String(Math.ceil(info.limits[i].max * 10) / 10);
    input.step = "0.1";
    input.value = String(v);
    $(`dof-${i}-out`).textContent = `${v.toFixed(1)}°`;
  });
  $("dof-note").textContent = `${info.count} DOFs; clamped by the server to ${applied.map((v) => `${v.toFixed(1)}°`).join(", ")}.`;
}

function updateJointPose() {
  const joint = state.joint;
  const pose = state.poses.get(state.selected);
  const j = viewer.desc?.joint_names.indexOf(joint) ?? -1;
  if (!joint || !pose || j < 0 || !pose.rotations[j]) {
    $("joint-pose").textContent = "";
    return;
  }
  const q = pose.rotations[j];
  const e = eulerXYZFromQuat(q).map((v) => (v / DEG).toFixed(1));
  $("joint-pose").textContent = `streamed local rotation [${q.map((v) => v.toFixed(3)).join(", ")}] · Euler XYZ ${e.join("°, ")}°`;
}
setInterval(() => {
  updateJointPose();
  markJoints();
}, 250);

$("nudge").addEventListener("click", (e) => {
  const b = e.target.closest("button");
  const a = selectedAvatar();
  if (!b || !a || !state.joint) return;
  const axis = [0, 0, 0];
  axis[Number(b.dataset.axis)] = 1;
  const angle = Number(b.dataset.sign) * num("nudge-step", 15) * DEG;
  run({ op: "rotate_joint_world", avatar: a.avatar, joint: state.joint, rotation: quatAxisAngle(axis, angle) }).catch(() => {});
});
$("release").addEventListener("click", () => {
  const a = selectedAvatar();
  if (a && state.joint) run({ op: "release", avatar: a.avatar, joint: state.joint }).catch(() => {});
});
$("release-all").addEventListener("click", () => {
  const a = selectedAvatar();
  if (a) run({ op: "release", avatar: a.avatar }).catch(() => {});
});

// ---------------------------------------------------------------------------------------------
// Tokens form.

$("token-view").value = tokens.view;
$("token-control").value = tokens.control;
$("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  for (const k of ["view", "control"]) {
    const v = $(`token-${k}`).value.trim();
    if (v) sessionStorage.setItem(TOKEN_KEYS[k], v);
    else sessionStorage.removeItem(TOKEN_KEYS[k]);
  }
  $("auth-status").textContent = "";
  state.dofInfo.clear();
  notice("Tokens changed: reconnecting.");
  conn.restart();
});
$("token-forget").addEventListener("click", () => {
  $("token-view").value = "";
  $("token-control").value = "";
  $("token-form").requestSubmit();
});

// ---------------------------------------------------------------------------------------------
// Upload (POST /api/assets/{name}, multipart, field "file").

$("upload-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const files = [...$("upload-files").files];
  const out = $("upload-result");
  out.className = "small";
  if (!files.length) {
    out.textContent = "Choose the files first.";
    return;
  }
  // Only .anim files: clips for the existing (.skel) rig named in the form.
  const clipsOnly = files.every((f) => /\.anim$/i.test(f.name));
  const name = $("upload-name").value.trim() || (clipsOnly ? "" : files[0].name.replace(/\.[^.]*$/, "").replace(/[^A-Za-z0-9_-]/g, "_"));
  if (!name) {
    out.textContent = "Name the .skel rig the clips are for.";
    return;
  }
  const form = new FormData();
  for (const f of files) form.append("file", f, f.name);
  const token = tokens.forRest(true);
  out.textContent = clipsOnly
    ? `Adding ${files.map((f) => f.name).join(", ")} to ${name}…`
    : `Uploading ${files.map((f) => f.name).join(", ")} as ${name}…`;
  try {
    const r = await fetch(`/api/assets/${encodeURIComponent(name)}${clipsOnly ? "/clips" : ""}`, {
      method: "POST",
      body: form,
      headers: token ? { Authorization: `Bearer ${token}` } : {},
    });
    if (r.ok) {
      const body = await r.json();
      const result = Array.isArray(body.result) ? body.result : [body.result];
      const list = result.filter(Boolean).map((x) => {
        const kind = x.humanoid === undefined ? "" : x.humanoid ? `; humanoid, ${x.mapped} mapped` : `; not humanoid, ${x.mapped} mapped`;
        return `${x.name} (${x.joints} joints${kind}; clips: ${x.clips.map((c) => c.name).join(", ") || "none"})`;
      });
      // What the importer skipped or approximated (materials, renamed joints, short clips, …).
      const notes = result.filter(Boolean).flatMap((x) => (x.notes ?? []).map((n) => `${x.name}: ${n}`));
      out.className = "small ok";
      out.textContent = `Imported ${list.join("; ")}${notes.length ? `. Notes: ${notes.join("; ")}` : ""}`;
      refresh(true);
    } else {
      const message = r.status === 404 && !(r.headers.get("content-type") ?? "").includes("json")
        ? "this server has no upload endpoint"
        : await errorMessage(r);
      out.className = "small error";
      out.textContent = `Upload refused (${r.status}): ${message}`;
    }
  } catch (err) {
    out.className = "small error";
    out.textContent = `Upload failed: ${err.message}`;
  }
});

conn.start();
