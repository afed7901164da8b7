// @ts-check
// The page's tokens, kept in sessionStorage (gone when the tab closes). A link like
// `/#control=TOKEN` (the server prints one when it generates its control token) hands the
// page a token: it is stored and taken out of the address bar and history — at load and
// whenever the hash changes in an open tab.

/** @typedef {import("../sdk/posecast.js").Token} Token */
/** @typedef {import("../sdk/posecast.js").TokenKind} TokenKind */

/** @type {Record<TokenKind, string>} */
const KEYS = { view: "posecast.token.view", control: "posecast.token.control" };

/**
 * @param {TokenKind} kind
 * @returns {string} The stored token, or "".
 */
export function token(kind) {
  return sessionStorage.getItem(KEYS[kind]) || "";
}

/**
 * Stores (or, empty, forgets) a token.
 * @param {TokenKind} kind
 * @param {string} value
 */
export function setToken(kind, value) {
  if (value) sessionStorage.setItem(KEYS[kind], value);
  else sessionStorage.removeItem(KEYS[kind]);
}

/** @returns {Token[]} The tokens to present in the hello, in order: control (it may view too), then view. */
export function forHello() {
  /** @type {Token[]} */
  const out = [];
  for (const kind of /** @type {TokenKind[]} */ (["control", "view"])) {
    const value = token(kind);
    if (value && !out.some((t) => t.value === value)) out.push({ kind, value });
  }
  return out;
}

/**
 * The token for REST reads (mesh) or writes (upload), or null.
 * @param {boolean} write
 * @returns {string | null}
 */
export function forRest(write) {
  return (write ? token("control") || token("view") : token("view") || token("control")) || null;
}

/**
 * Takes tokens out of the address's hash (`#control=…`, `#view=…`) into storage.
 * @returns {boolean} Whether the hash held one.
 */
export function takeFromHash() {
  const hash = new URLSearchParams(location.hash.slice(1));
  let found = false;
  for (const kind of /** @type {TokenKind[]} */ (["view", "control"])) {
    const v = hash.get(kind);
    if (v) {
      setToken(kind, v);
      found = true;
    }
  }
  if (found) history.replaceState(null, "", location.pathname + location.search);
  return found;
}

/**
 * Calls `changed` whenever a `#control=…` / `#view=…` link is opened in this tab.
 * @param {() => void} changed
 */
export function watchHash(changed) {
  window.addEventListener("hashchange", () => {
    if (takeFromHash()) changed();
  });
}
