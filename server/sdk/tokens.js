// @ts-check
// Minted tokens, for an app's back end (Node.js 18+ or any runtime with `fetch`): when a user
// joins, mint a token limited to what that user may do — drive *their* avatar, watch *this*
// scene, for an hour — and hand it to their browser or headset. Minting needs an admin token
// (an unlimited control token from the server's configuration); never send that to a browser.
//
//   import { mintToken } from "posecast";
//   const { token, info } = await mintToken("http://127.0.0.1:8080", adminToken, {
//     name: "alice", rights: ["view", "drive"], avatars: ["alice"], ttl_s: 3600,
//   });
//   // … later, when alice leaves or misbehaves:
//   await revokeToken("http://127.0.0.1:8080", adminToken, info.id);

import { PosecastError } from "./errors.js";

/** @typedef {import("./posecast.js").MintRequest} MintRequest */
/** @typedef {import("./posecast.js").MintedToken} MintedToken */
/** @typedef {import("./posecast.js").TokenInfo} TokenInfo */

/**
 * An HTTP base URL from a server URL of any scheme: `ws://h:p/ws` → `http://h:p`.
 * @param {string} server
 */
export function httpBase(server) {
  const url = new URL(server);
  if (url.protocol === "ws:") url.protocol = "http:";
  if (url.protocol === "wss:") url.protocol = "https:";
  return url.origin;
}

/**
 * One REST call with the admin token; the server's typed error becomes a PosecastError.
 * @param {string} server
 * @param {string} adminToken
 * @param {string} method
 * @param {string} path
 * @param {unknown} [body]
 */
async function call(server, adminToken, method, path, body) {
  /** @type {Record<string, string>} */
  const headers = { authorization: `Bearer ${adminToken}` };
  if (body !== undefined) headers["content-type"] = "application/json";
  let response;
  try {
    response = await fetch(httpBase(server) + path, {
      method,
      headers,
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (e) {
    throw new PosecastError("offline", `cannot reach ${httpBase(server)}: ${e}`);
  }
  if (response.status === 204) return undefined;
  const text = await response.text();
  let value;
  try {
    value = JSON.parse(text);
  } catch {
    throw new PosecastError("internal", `HTTP ${response.status}: ${text.slice(0, 200)}`);
  }
  if (!response.ok) throw new PosecastError(value.code ?? "internal", value.message ?? `HTTP ${response.status}`);
  return value;
}

/**
 * Mints a token (`POST /api/tokens`).
 * @param {string} server the server's URL (http(s):// or ws(s)://)
 * @param {string} adminToken
 * @param {MintRequest} request
 * @returns {Promise<MintedToken>}
 */
export async function mintToken(server, adminToken, request) {
  return call(server, adminToken, "POST", "/api/tokens", request);
}

/**
 * Revokes a token by its id (`DELETE /api/tokens/{id}`): refused from now on, and the
 * connections holding it are closed.
 * @param {string} server
 * @param {string} adminToken
 * @param {string} id
 * @returns {Promise<void>}
 */
export async function revokeToken(server, adminToken, id) {
  await call(server, adminToken, "DELETE", `/api/tokens/${encodeURIComponent(id)}`);
}

/**
 * The tokens the server minted that are neither expired nor revoked (`GET /api/tokens`).
 * @param {string} server
 * @param {string} adminToken
 * @returns {Promise<TokenInfo[]>}
 */
export async function listTokens(server, adminToken) {
  return call(server, adminToken, "GET", "/api/tokens");
}
