// @ts-check
// Small DOM helpers and what every panel is given (`Ctx`).

import { PosecastError } from "../sdk/posecast.js";

/**
 * What a panel works with.
 * @typedef {object} Ctx
 * @property {import("./store.js").Store} store
 * @property {import("../sdk/posecast.js").Client} conn
 * @property {import("./viewer.js").Viewer} viewer
 * @property {import("./drive.js").PageDrive} drive The page as a live driver of one avatar.
 * @property {(avatar: string | null) => void} select Picks the avatar the page controls (and watches its scene).
 * @property {(scene: string | null) => void} watch Shows a scene in the preview (its first avatar picked).
 * @property {(command: import("./protocol.js").Command) => Promise<unknown>} run Runs a command that changes something; failures are reported, then rethrown.
 * @property {() => Promise<void>} refreshAssets Lists the rigs again (after an upload).
 */

/**
 * The element with this id, checked to be of `type` (a page out of step with its script fails
 * at once, not with a null later).
 * @template {HTMLElement} T
 * @param {string} id
 * @param {{new (): T, prototype: T}} [type]
 * @returns {T}
 */
export function $(id, type) {
  const e = document.getElementById(id);
  const t = type ?? HTMLElement;
  if (!(e instanceof t)) throw new Error(`no ${t.name} #${id} on the page`);
  return /** @type {T} */ (e);
}

/**
 * A new element: `props` are set as properties (or attributes when the element has no such
 * property; `dataset` entries go to `data-*`), then `children` appended.
 * @template {keyof HTMLElementTagNameMap} K
 * @param {K} tag
 * @param {Record<string, unknown>} [props]
 * @param {...(Node | string)} children
 * @returns {HTMLElementTagNameMap[K]}
 */
export function el(tag, props = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(props)) {
    if (k === "dataset") Object.assign(e.dataset, v);
    else if (k in e) /** @type {Record<string, unknown>} */ (/** @type {unknown} */ (e))[k] = v;
    else e.setAttribute(k, String(v));
  }
  e.append(...children);
  return e;
}

/**
 * Adds a line to the page's message log (newest first, six kept).
 * @param {string} text
 * @param {"info" | "error"} [kind]
 */
export function notice(text, kind = "info") {
  const list = $("notice");
  list.prepend(el("li", { className: kind }, `${new Date().toLocaleTimeString()} — ${text}`));
  while (list.children.length > 6) list.lastElementChild?.remove();
}

/**
 * A failure in words, with what to do about refusals.
 * @param {unknown} e
 * @returns {string}
 */
export function describeError(e) {
  if (e instanceof PosecastError) {
    if (e.code === "unauthorized") return `Refused (unauthorized): ${e.message}. Check the control token.`;
    if (e.code === "forbidden") return `Refused (forbidden): ${e.message}. This token may not do that.`;
    return `${e.code}: ${e.message}`;
  }
  return e instanceof Error ? e.message : String(e);
}

/**
 * The number in an input, or `fallback` when it holds none.
 * @param {string} id
 * @param {number} fallback
 * @returns {number}
 */
export function num(id, fallback) {
  const raw = $(id, HTMLInputElement).value.trim();
  const v = Number(raw);
  return raw !== "" && Number.isFinite(v) ? v : fallback;
}
