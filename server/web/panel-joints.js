// @ts-check
// The selected avatar's joint tree and the selected joint's controls: DOF sliders within the
// rig's limits (`set_joint_dofs`), or Euler rotation sliders for rigs without joint types
// (`set_joint_rotation`); world-space nudges; releasing overrides. While the page drives the
// avatar live (drive.js), the sliders set the joint's rotation in the live pose instead.

import { $, el, num } from "./ui.js";
import { quatAxisAngle, quatFromEulerXYZ, eulerXYZFromQuat, DEG } from "../sdk/posecast.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./protocol.js").JointInfo} JointInfo */
/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */

/**
 * What the sliders of one joint show: its DOFs (null: a rig without joint types, set by
 * Euler X, Y, Z instead), their limits and values in degrees.
 * @typedef {{count: number | null, limits: {min: number, max: number}[], values: number[]}} DofState
 */

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, run } = ctx;
  const tree = $("joint-tree");
  /** @type {Map<string, DofState>} "rig/joint" → its sliders' state. */
  const dofInfo = new Map();
  /** @type {AvatarDescription | null} */
  let built = null;

  const selectedDesc = () => store.get().descriptions.get(store.get().selected ?? "") ?? null;
  /** @param {string} joint */
  const dofKey = (joint) => `${store.selectedAvatar()?.state.asset}/${joint}`;

  /** @param {AvatarDescription | null} desc */
  const buildTree = (desc) => {
    built = desc;
    tree.replaceChildren();
    if (!desc) return;
    /** @type {number[]} */
    const depth = [];
    desc.joint_names.forEach((name, j) => {
      const p = desc.parents[j];
      depth[j] = p >= 0 ? depth[p] + 1 : 0;
      const b = el("button", { type: "button", tabIndex: -1, dataset: { joint: name } }, name);
      b.style.setProperty("--depth", String(depth[j]));
      b.addEventListener("click", () => selectJoint(name));
      tree.append(el("li", {}, b));
    });
    const first = tree.querySelector("button");
    if (first) first.tabIndex = 0;
    applyFilter();
    markJoints();
  };

  const buttons = () => /** @type {HTMLButtonElement[]} */ ([...tree.querySelectorAll("button")]);

  tree.addEventListener("keydown", (e) => {
    const shown = buttons().filter((b) => !b.parentElement?.hidden);
    const i = shown.indexOf(/** @type {HTMLButtonElement} */ (document.activeElement));
    if (i < 0) return;
    /** @type {Record<string, number>} */
    const moves = { ArrowDown: i + 1, ArrowUp: i - 1, Home: 0, End: shown.length - 1 };
    const to = moves[e.key];
    if (to === undefined) return;
    e.preventDefault();
    const b = shown[Math.max(0, Math.min(shown.length - 1, to))];
    for (const x of shown) x.tabIndex = -1;
    b.tabIndex = 0;
    b.focus();
  });

  const applyFilter = () => {
    const f = $("joint-filter", HTMLInputElement).value.trim().toLowerCase();
    for (const b of buttons()) {
      if (b.parentElement) b.parentElement.hidden = !!f && !(b.dataset.joint ?? "").toLowerCase().includes(f);
    }
  };
  $("joint-filter").addEventListener("input", applyFilter);

  const markJoints = () => {
    const overrides = new Set(store.selectedAvatar()?.state.overrides ?? []);
    const joint = store.get().joint;
    for (const b of buttons()) {
      b.classList.toggle("overridden", overrides.has(b.dataset.joint ?? ""));
      b.setAttribute("aria-current", String(b.dataset.joint === joint));
    }
  };

  /** @param {string} name */
  const selectJoint = async (name) => {
    store.set({ joint: name });
    for (const b of buttons()) b.tabIndex = b.dataset.joint === name ? 0 : -1;
    await probeDofs(name);
    renderJoint();
  };

  /**
   * The joint's DOFs, their limits and current values (`get_joint`). A joint of a rig without
   * joint types has none and is set by rotation instead (Euler X, Y, Z sliders).
   * @param {string} joint
   */
  const probeDofs = async (joint) => {
    const entry = store.selectedAvatar();
    if (!entry) return;
    /** @type {JointInfo} */
    let info;
    try {
      info = /** @type {JointInfo} */ (await ctx.conn.command({ op: "get_joint", avatar: entry.state.avatar, joint }));
    } catch {
      return; // offline or refused (already shown): asked again when selected again
    }
    const typed = info.joint_type != null && info.dofs.length > 0;
    /** @param {number | null} v @param {number} fallback */
    const deg = (v, fallback) => (v == null ? fallback : v / DEG);
    dofInfo.set(dofKey(joint), {
      count: typed ? info.dofs.length : null,
      limits: typed
        ? info.dofs.map((d) => ({ min: deg(d.min, -180), max: deg(d.max, 180) }))
        : [0, 1, 2].map(() => ({ min: -180, max: 180 })),
      values: typed ? info.dofs.map((d) => Math.round((d.value / DEG) * 10) / 10) : [0, 0, 0],
    });
  };

  const renderJoint = () => {
    const box = $("dof-controls");
    box.replaceChildren();
    const joint = store.get().joint;
    $("joint-title").textContent = joint ? `Joint ${joint}` : "No joint selected";
    $("dof-note").textContent = "";
    if (!joint) return;
    if (driving()) {
      renderLive(box, joint);
      return;
    }
    const info = dofInfo.get(dofKey(joint));
    if (!info) {
      $("dof-note").textContent = "Could not ask the server about this joint.";
      return;
    }
    const byDofs = info.count !== null;
    if (!byDofs) {
      // Start the rotation sliders at the streamed rotation.
      const q = streamed(joint);
      if (q) info.values = eulerXYZFromQuat(q).map((v) => Math.round(v / DEG));
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
    showPose();
  };

  /** Whether the page drives the selected avatar live. */
  const driving = () => !!store.get().driving && store.get().driving === store.get().selected;

  /**
   * Rotation sliders (Euler X, Y, Z from the streamed rotation) that set `joint` in the page's
   * live pose; the rig's DOF limits still apply on the server, after the live pose.
   * @param {HTMLElement} box
   * @param {string} joint
   */
  const renderLive = (box, joint) => {
    const q = streamed(joint);
    const values = q ? eulerXYZFromQuat(q).map((v) => Math.round(v / DEG)) : [0, 0, 0];
    ["Rotate X (°)", "Rotate Y (°)", "Rotate Z (°)"].forEach((label, i) => {
      const id = `dof-${i}`;
      const input = el("input", { id, type: "range", step: "1", className: "dof-input" });
      input.min = "-180";
      input.max = "180";
      input.value = String(values[i]);
      const out = el("output", { id: `${id}-out`, htmlFor: id }, `${values[i].toFixed(1)}°`);
      input.addEventListener("input", () => {
        values[i] = Number(input.value);
        out.textContent = `${values[i].toFixed(1)}°`;
        ctx.drive.set(joint, quatFromEulerXYZ(values[0] * DEG, values[1] * DEG, values[2] * DEG));
      });
      box.append(el("div", { className: "dof" }, el("label", { htmlFor: id }, label), input, out));
    });
    $("dof-note").textContent =
      "Driving live: the sliders set this joint's local rotation (Euler X, Y, Z) in the page's pose; the rig's DOF limits still apply.";
    showPose();
  };

  /**
   * The joint's streamed local rotation, if a frame carried it.
   * @param {string} joint
   */
  const streamed = (joint) => {
    const desc = selectedDesc();
    const pose = store.get().poses.get(store.get().selected ?? "");
    const j = desc?.joint_names.indexOf(joint) ?? -1;
    return pose && j >= 0 ? pose.rotations[j] ?? null : null;
  };

  let busy = false;
  let again = false;
  /**
   * Sends the sliders' values; at most one command in flight, the newest values win.
   * @param {string} joint
   * @param {DofState} info
   */
  const sendJoint = async (joint, info) => {
    if (busy) {
      again = true;
      return;
    }
    const entry = store.selectedAvatar();
    if (!entry) return;
    const avatar = entry.state.avatar;
    busy = true;
    const sent = [...info.values];
    try {
      if (info.count !== null) {
        const r = /** @type {{values?: number[]}} */ (await run({ op: "set_joint_dofs", avatar, joint, values: sent.map((v) => v * DEG) }));
        applyClamp(joint, info, sent, (r?.values ?? []).map((v) => v / DEG));
      } else {
        const q = quatFromEulerXYZ(sent[0] * DEG, sent[1] * DEG, sent[2] * DEG);
        await run({ op: "set_joint_rotation", avatar, joint, rotation: q });
      }
    } catch {
      /* reported by run() */
    } finally {
      busy = false;
    }
    if (again) {
      again = false;
      sendJoint(joint, info);
    }
  };

  /**
   * The server clamped `sent` to `applied`: remember those limits and show them.
   * @param {string} joint
   * @param {DofState} info
   * @param {number[]} sent
   * @param {number[]} applied
   */
  const applyClamp = (joint, info, sent, applied) => {
    let changed = false;
    applied.forEach((v, i) => {
      if (Math.abs(v - sent[i]) < 0.05) return;
      const lim = info.limits[i];
      if (sent[i] > v && v < lim.max) lim.max = v;
      if (sent[i] < v && v > lim.min) lim.min = v;
      info.values[i] = v;
      changed = true;
    });
    if (!changed || store.get().joint !== joint) return;
    applied.forEach((v, i) => {
      const input = document.getElementById(`dof-${i}`);
      if (!(input instanceof HTMLInputElement)) return;
      input.min = String(Math.floor(info.limits[i].min * 10) / 10);
      input.max = String(Math.ceil(info.limits[i].max * 10) / 10);
      input.step = "0.1";
      input.value = String(v);
      $(`dof-${i}-out`).textContent = `${v.toFixed(1)}°`;
    });
    $("dof-note").textContent = `${info.count} DOFs; clamped by the server to ${applied.map((v) => `${v.toFixed(1)}°`).join(", ")}.`;
  };

  const showPose = () => {
    const joint = store.get().joint;
    const q = joint ? streamed(joint) : null;
    if (!q) {
      $("joint-pose").textContent = "";
      return;
    }
    const e = eulerXYZFromQuat(q).map((v) => (v / DEG).toFixed(1));
    $("joint-pose").textContent = `streamed local rotation [${q.map((v) => v.toFixed(3)).join(", ")}] · Euler XYZ ${e.join("°, ")}°`;
  };

  // A new avatar (or its rig arrived): a new tree, no joint. Changes of its state: the marks.
  store.on(["selected", "descriptions"], () => {
    const desc = selectedDesc();
    if (desc !== built) {
      buildTree(desc);
      if (store.get().joint && !desc?.joint_names.includes(store.get().joint ?? "")) store.set({ joint: null });
      renderJoint();
    }
  });
  store.on(["scenes", "joint"], markJoints);
  store.on(["driving"], renderJoint);
  let frames = 0;
  store.on(["frame"], () => {
    if (frames++ % 4 === 0) showPose(); // 15 Hz is plenty for text
  });

  $("nudge").addEventListener("click", (e) => {
    const b = /** @type {HTMLElement | null} */ (/** @type {HTMLElement} */ (e.target).closest("button"));
    const entry = store.selectedAvatar();
    const joint = store.get().joint;
    if (!b || !entry || !joint) return;
    /** @type {[number, number, number]} */
    const axis = [0, 0, 0];
    axis[Number(b.dataset.axis)] = 1;
    const angle = Number(b.dataset.sign) * num("nudge-step", 15) * DEG;
    run({ op: "rotate_joint_world", avatar: entry.state.avatar, joint, rotation: quatAxisAngle(axis, angle) }).catch(() => {});
  });
  $("release").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    const joint = store.get().joint;
    if (entry && joint) run({ op: "release", avatar: entry.state.avatar, joint }).catch(() => {});
  });
  $("release-all").addEventListener("click", () => {
    const entry = store.selectedAvatar();
    if (entry) run({ op: "release", avatar: entry.state.avatar }).catch(() => {});
  });
}
