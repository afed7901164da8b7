// @ts-check
// Where the selected avatar stands, and moving it (`place_avatar`, at once or over seconds).

import { $, num, notice } from "./ui.js";
import { quatAxisAngle, DEG } from "../sdk/posecast.js";
import { yawDegrees } from "./panel-scenes.js";

/** @typedef {import("./ui.js").Ctx} Ctx */

/** @param {Ctx} ctx */
export function mount(ctx) {
  const { store, run } = ctx;
  /** @type {string | null} */
  let filledFor = null;
  store.on(["scenes", "selected"], () => {
    const entry = store.selectedAvatar();
    if (!entry) {
      $("place-now").textContent = "";
      filledFor = null;
      return;
    }
    const p = entry.state.placement;
    const yaw = yawDegrees(p.rotation);
    $("place-now").textContent =
      `${entry.state.avatar} stands at (${p.position.map((v) => v.toFixed(2)).join(", ")}) m, facing ${yaw.toFixed(0)}°`;
    // The form starts from where a newly selected avatar stands; later pushes leave edits alone.
    if (filledFor !== entry.state.avatar) {
      filledFor = entry.state.avatar;
      ["place-x", "place-y", "place-z"].forEach((id, i) => ($(id, HTMLInputElement).value = String(Number(p.position[i].toFixed(3)))));
      $("place-yaw", HTMLInputElement).value = String(Math.round(yaw));
    }
  });
  $("place-form", HTMLFormElement).addEventListener("submit", (e) => {
    e.preventDefault();
    const entry = store.selectedAvatar();
    if (!entry) return;
    const avatar = entry.state.avatar;
    const duration = Math.max(0, num("place-duration", 0));
    run({
      op: "place_avatar",
      avatar,
      position: [num("place-x", 0), num("place-y", 0), num("place-z", 0)],
      rotation: quatAxisAngle([0, 1, 0], num("place-yaw", 0) * DEG),
      duration,
    }).then(() => notice(`Placing ${avatar}${duration ? ` over ${duration} s` : ""}.`), () => {});
  });
}
