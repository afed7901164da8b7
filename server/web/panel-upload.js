// @ts-check
// Uploads through the REST API (POST /api/assets/{name}, multipart, field "file").

import { $ } from "./ui.js";
import { upload } from "./rest.js";

/** @typedef {import("./ui.js").Ctx} Ctx */

/** @param {Ctx} ctx */
export function mount(ctx) {
  $("upload-form", HTMLFormElement).addEventListener("submit", async (e) => {
    e.preventDefault();
    const files = [...($("upload-files", HTMLInputElement).files ?? [])];
    const out = $("upload-result");
    out.className = "small";
    if (!files.length) {
      out.textContent = "Choose the files first.";
      return;
    }
    // Only .anim files: clips for the existing (.skel) rig named in the form.
    const clipsOnly = files.every((f) => /\.anim$/i.test(f.name));
    const name = $("upload-name", HTMLInputElement).value.trim() ||
      (clipsOnly ? "" : files[0].name.replace(/\.[^.]*$/, "").replace(/[^A-Za-z0-9_-]/g, "_"));
    if (!name) {
      out.textContent = "Name the .skel rig the clips are for.";
      return;
    }
    const names = files.map((f) => f.name).join(", ");
    out.textContent = clipsOnly ? `Adding ${names} to ${name}…` : `Uploading ${names} as ${name}…`;
    try {
      const r = await upload(name, files, clipsOnly);
      if (r.ok) {
        const list = r.assets.map((x) => {
          const kind = x.humanoid ? `humanoid, ${x.mapped} mapped` : `not humanoid, ${x.mapped} mapped`;
          return `${x.name} (${x.joints} joints; ${kind}; clips: ${x.clips.map((c) => c.name).join(", ") || "none"})`;
        });
        // What the importer skipped or approximated (materials, renamed joints, short clips, …).
        const notes = r.assets.flatMap((x) => (x.notes ?? []).map((n) => `${x.name}: ${n}`));
        out.className = "small ok";
        out.textContent = `Imported ${list.join("; ")}${notes.length ? `. Notes: ${notes.join("; ")}` : ""}`;
        ctx.refreshAssets();
      } else {
        out.className = "small error";
        out.textContent = `Upload refused (${r.status}): ${r.message}`;
      }
    } catch (err) {
      out.className = "small error";
      out.textContent = `Upload failed: ${err instanceof Error ? err.message : String(err)}`;
    }
  });
}
