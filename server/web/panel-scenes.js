// @ts-check
// Scenes and their avatars: pick the avatar to control (and watch its scene), follow one with
// the camera, remove avatars and delete scenes (a second click confirms), create scenes, add
// avatars (rig, id, clip, position, facing). The list changes when the server pushes a change.

import { $, el, notice } from "./ui.js";
import { quatAxisAngle, DEG } from "../sdk/posecast.js";
import { num } from "./ui.js";

/** @typedef {import("./ui.js").Ctx} Ctx */
/** @typedef {import("./store.js").State} State */
/** @typedef {import("./protocol.js").AvatarState} AvatarState */
/** @typedef {import("./protocol.js").Quat} Quat */

/** How long a destructive button waits for its confirming second click, ms. */
const CONFIRM_MS = 4000;

/**
 * The angle (degrees) about Y of a placement rotation.
 * @param {Quat} q
 * @returns {number}
 */
export function yawDegrees(q) {
  return (2 * Math.atan2(q[1], q[3])) / DEG;
}

/**
 * One line about an avatar for the list (its clip time moves in the timeline, not here).
 * @param {AvatarState} a
 * @returns {string}
 */
function summary(a) {
  const clip = a.clip ? `${a.clip_asset ? `${a.clip_asset}:` : ""}${a.clip}` : "no clip";
  const flags = [a.paused ? "paused" : "playing", a.looping ? "loop" : "once", `×${a.speed}`];
  if (a.driver) flags.push(`driven by ${a.driver.name} (${a.driver.via})`);
  else if (a.driven) flags.push("holding a live pose");
  if (a.recording) flags.push(`recording ${a.recording}`);
  const [x, , z] = a.placement.position;
  const over = a.overrides.length ? ` · overrides: ${a.overrides.join(", ")}` : "";
  return `${clip} · ${flags.join(" · ")} · at (${x.toFixed(1)}, ${z.toFixed(1)})${over}`;
}

/**
 * Who watches a scene, for its heading: "watched by alice ×2, bob, 3 anonymous".
 * @param {import("./protocol.js").Viewer[]} viewers
 * @returns {string}
 */
export function watchedBy(viewers) {
  if (!viewers.length) return "nobody watching";
  const parts = viewers.map((v) => {
    const who = v.name ?? (v.connections === 1 ? "anonymous viewer" : "anonymous");
    return v.name ? (v.connections > 1 ? `${who} ×${v.connections}` : who) : `${v.connections} ${who}`;
  });
  return `watched by ${parts.join(", ")}`;
}

/**
 * A button that acts on its second click within CONFIRM_MS.
 * @param {string} label
 * @param {string} confirm
 * @param {Record<string, string>} dataset
 * @param {() => void} act
 * @returns {HTMLButtonElement}
 */
function confirmButton(label, confirm, dataset, act) {
  const b = el("button", { type: "button", className: "danger", dataset }, label);
  /** @type {ReturnType<typeof setTimeout> | undefined} */
  let timer;
  b.addEventListener("click", () => {
    if (b.dataset.armed) {
      clearTimeout(timer);
      delete b.dataset.armed;
      b.textContent = label;
      act();
      return;
    }
    b.dataset.armed = "1";
    b.textContent = confirm;
    timer = setTimeout(() => {
      delete b.dataset.armed;
      b.textContent = label;
    }, CONFIRM_MS);
  });
  return b;
}

/**
 * Puts `node` at position `index` of `parent`, moving nothing already in place (a moved node
 * loses the keyboard focus).
 * @param {Element} parent
 * @param {Element} node
 * @param {number} index
 */
function place(parent, node, index) {
  const at = parent.children[index] ?? null;
  if (at !== node) parent.insertBefore(node, at);
}

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, run } = ctx;
  const root = $("scene-list");
  /** @type {Map<string, {box: HTMLElement, list: HTMLUListElement, empty: HTMLElement, name: HTMLButtonElement, viewers: HTMLElement, avatars: Map<string, {li: HTMLLIElement, pick: HTMLButtonElement, text: HTMLElement, focus: HTMLButtonElement}>}>} */
  const shown = new Map();

  /** @param {string} scene */
  const sceneBox = (scene) => {
    const name = el("button", { type: "button", className: "scene-name", dataset: { scene } }, `Scene ${scene}`);
    name.addEventListener("click", () => ctx.watch(scene));
    const del = confirmButton("Delete", "Delete scene?", { deleteScene: scene }, () => {
      run({ op: "delete_scene", scene }).then(() => notice(`Scene ${scene} deleted.`), () => {});
    });
    const list = el("ul", { className: "avatar-list" });
    const empty = el("p", { className: "muted small" }, "no avatars");
    const viewers = el("p", { className: "muted small viewers", dataset: { viewers: scene } });
    const box = el("div", { className: "scene", dataset: { scene } },
      el("div", { className: "scene-head" }, name, el("span", { className: "actions control-only" }, del)), viewers, list, empty);
    return { box, list, empty, name, viewers, avatars: new Map() };
  };

  /** @param {string} avatar */
  const avatarItem = (avatar) => {
    const pick = el("button", { type: "button", className: "pick", dataset: { avatar } });
    pick.addEventListener("click", () => ctx.select(avatar));
    const text = el("span", { className: "avatar-summary" });
    const focus = el("button", { type: "button", className: "focus", title: "Camera follows this avatar", dataset: { focus: avatar } }, "Focus");
    focus.addEventListener("click", () => {
      const following = store.get().focus === avatar;
      if (!following) ctx.select(avatar);
      store.set({ focus: following ? null : avatar });
    });
    const remove = confirmButton("Remove", "Remove?", { remove: avatar }, () => {
      run({ op: "remove_avatar", avatar }).then(() => notice(`Avatar ${avatar} removed.`), () => {});
    });
    const li = el("li", { dataset: { avatar } }, pick, el("div", { className: "avatar-actions" }, focus, el("span", { className: "control-only" }, remove)));
    return { li, pick, text, focus };
  };

  store.on(["scenes", "selected", "watched", "focus", "viewers"], (s) => {
    if (!s.scenes) return;
    if (!s.scenes.size) root.replaceChildren(el("p", { className: "muted" }, "No scenes."));
    else root.querySelector(":scope > p")?.remove();
    for (const [scene, box] of shown) {
      if (!s.scenes.has(scene)) {
        box.box.remove();
        shown.delete(scene);
      }
    }
    let sceneIndex = 0;
    for (const [scene, avatars] of s.scenes) {
      let box = shown.get(scene);
      if (!box) {
        box = sceneBox(scene);
        shown.set(scene, box);
      }
      place(root, box.box, sceneIndex++);
      box.name.setAttribute("aria-pressed", String(scene === s.watched));
      box.viewers.textContent = watchedBy(s.viewers.get(scene) ?? []);
      box.box.classList.toggle("watched", scene === s.watched);
      for (const [id, item] of box.avatars) {
        if (!avatars.has(id)) {
          item.li.remove();
          box.avatars.delete(id);
        }
      }
      let avatarIndex = 0;
      for (const [id, entry] of avatars) {
        let item = box.avatars.get(id);
        if (!item) {
          item = avatarItem(id);
          box.avatars.set(id, item);
        }
        place(box.list, item.li, avatarIndex++);
        const a = entry.state;
        item.text.textContent = summary(a);
        item.pick.replaceChildren(el("strong", {}, id), ` (${a.asset})`, item.text);
        item.pick.setAttribute("aria-pressed", String(id === s.selected));
        item.focus.setAttribute("aria-pressed", String(id === s.focus));
      }
      box.empty.hidden = avatars.size > 0;
    }
  });

  $("scene-form", HTMLFormElement).addEventListener("submit", (e) => {
    e.preventDefault();
    const input = $("scene-name", HTMLInputElement);
    const scene = input.value.trim();
    if (!scene) return;
    run({ op: "create_scene", scene }).then(() => {
      input.value = "";
      notice(`Scene ${scene} created.`);
      ctx.watch(scene);
    }, () => {});
  });

  mountAddForm(ctx);
}

/** @param {Ctx} ctx */
function mountAddForm(ctx) {
  const { store, run } = ctx;
  const sceneSelect = $("add-scene", HTMLSelectElement);
  const rigSelect = $("add-rig", HTMLSelectElement);
  const clipSelect = $("add-clip", HTMLSelectElement);

  /**
   * Replaces a select's options, keeping the chosen value when it is still offered.
   * @param {HTMLSelectElement} select
   * @param {[string, string][]} options value, label
   * @param {string | null} prefer
   */
  const fill = (select, options, prefer) => {
    const keep = select.value;
    select.replaceChildren(...options.map(([value, label]) => el("option", { value }, label)));
    const values = options.map(([v]) => v);
    if (prefer !== null && values.includes(prefer)) select.value = prefer;
    else if (values.includes(keep)) select.value = keep;
  };
  const fillClips = () => {
    const rig = store.get().assets.find((x) => x.name === rigSelect.value);
    fill(clipSelect, [["", "none (rest pose)"], ...(rig?.clips ?? []).map((c) => /** @type {[string, string]} */ ([c.name, c.name]))], null);
  };
  /** @type {string | null} */
  let watched = null;
  store.on(["scenes", "watched"], (s) => {
    const changed = s.watched !== watched;
    watched = s.watched;
    fill(sceneSelect, [...(s.scenes?.keys() ?? [])].map((k) => [k, k]), changed ? s.watched : null);
  });
  store.on(["assets"], (s) => {
    fill(rigSelect, s.assets.map((a) => [a.name, `${a.name} (${a.joints} joints)`]), null);
    fillClips();
  });
  rigSelect.addEventListener("change", fillClips);

  $("add-form", HTMLFormElement).addEventListener("submit", (e) => {
    e.preventDefault();
    const scene = sceneSelect.value;
    const asset = rigSelect.value;
    if (!scene || !asset) {
      notice("Choose a scene and a rig first (create a scene if there is none).", "error");
      return;
    }
    const id = $("add-id", HTMLInputElement).value.trim();
    const clip = clipSelect.value;
    /** @type {import("./protocol.js").Command} */
    const command = {
      op: "add_avatar",
      scene,
      asset,
      position: [num("add-x", 0), num("add-y", 0), num("add-z", 0)],
      rotation: quatAxisAngle([0, 1, 0], num("add-yaw", 0) * DEG),
    };
    if (id) command.avatar = id;
    if (clip) command.clip = clip;
    run(command).then((result) => {
      const added = /** @type {{avatar: string}} */ (result).avatar;
      $("add-id", HTMLInputElement).value = "";
      notice(`Avatar ${added} added to ${scene}.`);
      ctx.select(added);
    }, () => {});
  });
}
