// @ts-check
// The token form: the tokens this tab presents (sessionStorage), applied by reconnecting; and
// links for others: a token minted for one person (`POST /api/tokens`, needs the admin token),
// limited to the watched scene and an hour.

import { $, el, notice } from "./ui.js";
import { token, setToken, forRest } from "./tokens.js";
import { errorMessage } from "./rest.js";

/** @typedef {import("./ui.js").Ctx} Ctx */

/** Shows the stored tokens in the form (at start, and after a `#control=…` link). */
export function showTokens() {
  $("token-view", HTMLInputElement).value = token("view");
  $("token-control", HTMLInputElement).value = token("control");
}

/** @param {Ctx} ctx */
export function mount(ctx) {
  showTokens();
  $("token-form", HTMLFormElement).addEventListener("submit", (e) => {
    e.preventDefault();
    setToken("view", $("token-view", HTMLInputElement).value.trim());
    setToken("control", $("token-control", HTMLInputElement).value.trim());
    notice("Tokens changed: reconnecting.");
    ctx.conn.restart();
  });
  $("token-forget").addEventListener("click", () => {
    $("token-view", HTMLInputElement).value = "";
    $("token-control", HTMLInputElement).value = "";
    $("token-form", HTMLFormElement).requestSubmit();
  });
  $("share-form", HTMLFormElement).addEventListener("submit", async (e) => {
    e.preventDefault();
    const scene = ctx.store.get().watched;
    const name = $("share-name", HTMLInputElement).value.trim();
    const right = $("share-rights", HTMLSelectElement).value;
    if (!scene || !name) return;
    const rights = right === "view" ? ["view"] : ["view", right];
    const admin = forRest(true);
    const r = await fetch("/api/tokens", {
      method: "POST",
      headers: { "content-type": "application/json", ...(admin ? { Authorization: `Bearer ${admin}` } : {}) },
      body: JSON.stringify({ name, rights, scenes: [scene], ttl_s: 3600 }),
    });
    if (!r.ok) {
      notice(`No link made — ${await errorMessage(r)}`, "error");
      return;
    }
    const minted = await r.json();
    const kind = right === "view" ? "view" : "control";
    const url = `${location.origin}${location.pathname}#${kind}=${encodeURIComponent(minted.token)}`;
    const out = $("share-link");
    out.replaceChildren(
      `For ${name}, until ${new Date(minted.info.expires_at * 1000).toLocaleTimeString()}: `,
      el("a", { href: url, dataset: { share: minted.info.id } }, "link"),
      ` (token ${minted.info.id}; revoke with DELETE /api/tokens/${minted.info.id})`,
    );
    out.hidden = false;
  });
}
