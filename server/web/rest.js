// @ts-check
// The REST side of the dashboard: the rig's mesh (`mesh_url`), uploads, JSON reads (the takes).

import { parseGlb } from "./glb.js";
import { forRest } from "./tokens.js";

/**
 * The readable part of an error response: the typed `{code, message}` body, or its text.
 * @param {Response} response
 * @returns {Promise<string>}
 */
export async function errorMessage(response) {
  const text = await response.text();
  try {
    const body = JSON.parse(text);
    if (body && body.message) return `${body.code ? `${body.code}: ` : ""}${body.message}`;
  } catch {
    /* not JSON */
  }
  return text || response.statusText;
}

/**
 * Fetches and parses a rig's skinned mesh (.glb).
 * @param {string} url
 * @returns {Promise<import("./glb.js").Mesh>}
 */
export async function fetchMesh(url) {
  const token = forRest(false);
  let r = await fetch(url, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
  // A stale or mistyped token is refused (401) even where anyone may watch: read without it
  // then (the connection already says why control is refused).
  if (r.status === 401 && token) r = await fetch(url);
  if (!r.ok) throw new Error(`${r.status} ${await errorMessage(r)}`);
  return parseGlb(await r.arrayBuffer());
}

/**
 * Reads a JSON answer of the REST API (`GET /api/takes`: the `list_takes` result), with the
 * view token — without it when that is refused, as for meshes.
 * @param {string} path
 * @returns {Promise<unknown>}
 */
export async function getJson(path) {
  const token = forRest(false);
  let r = await fetch(path, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
  if (r.status === 401 && token) r = await fetch(path);
  if (!r.ok) throw new Error(`${r.status} ${await errorMessage(r)}`);
  return r.json();
}

/**
 * Uploads files as asset `name` (`POST /api/assets/{name}`), or — `clipsOnly` — adds .anim
 * clips to it (`/clips`).
 * @param {string} name
 * @param {File[]} files
 * @param {boolean} clipsOnly
 * @returns {Promise<{ok: true, assets: import("./protocol.js").AssetInfo[]} | {ok: false, status: number, message: string}>}
 */
export async function upload(name, files, clipsOnly) {
  const form = new FormData();
  for (const f of files) form.append("file", f, f.name);
  const token = forRest(true);
  const r = await fetch(`/api/assets/${encodeURIComponent(name)}${clipsOnly ? "/clips" : ""}`, {
    method: "POST",
    body: form,
    headers: token ? { Authorization: `Bearer ${token}` } : {},
  });
  if (r.ok) {
    const body = await r.json();
    const result = Array.isArray(body.result) ? body.result : [body.result];
    return { ok: true, assets: result.filter(Boolean) };
  }
  const message =
    r.status === 404 && !(r.headers.get("content-type") ?? "").includes("json")
      ? "this server has no upload endpoint"
      : await errorMessage(r);
  return { ok: false, status: r.status, message };
}
