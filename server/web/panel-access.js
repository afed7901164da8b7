// @ts-check
// The token form: the tokens this tab presents (sessionStorage), applied by reconnecting.

import { $, notice } from "./ui.js";
import { token, setToken } from "./tokens.js";

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
}
