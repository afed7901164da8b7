// An app's back end hands each joining user a token of their own (issue 39): mint one that may
// only drive the avatar `avatar` for ten minutes, connect as that user with it, show that it
// drives but cannot pause the clip, then revoke it — the user's connection is closed.
//
//   cd examples/node && npm install
//   POSECAST_ADMIN_TOKEN=… node --experimental-websocket mint.mjs   # Node 22+: no flag
//
// POSECAST_URL for a server other than ws://127.0.0.1:8080/ws. The admin token is an unlimited
// control token from the server's configuration (the one `posecast` prints at start): keep it
// on the back end, never send it to a browser.

import { Client, mintToken, revokeToken, quatFromEulerXYZ } from "posecast";

const url = process.env.POSECAST_URL ?? "ws://127.0.0.1:8080/ws";
const admin = process.env.POSECAST_ADMIN_TOKEN;
if (!admin) throw new Error("set POSECAST_ADMIN_TOKEN to the server's control token");

// 1. The back end mints alice's token.
const { token, info } = await mintToken(url, admin, {
  name: "alice",
  rights: ["view", "drive"],
  avatars: ["avatar"],
  ttl_s: 600,
});
console.log(`minted ${info.id} for ${info.name}: ${info.rights.join(", ")} until ${new Date(info.expires_at * 1000).toISOString()}`);

// 2. Alice's app connects with it.
const alice = new Client({ url, token, reconnect: false });
const closed = new Promise((resolve) => alice.on("state", (s) => s === "closed" && resolve(alice.detail)));
await new Promise((resolve, reject) => {
  alice.on("state", (s) => {
    if (s === "online") resolve(undefined);
    if (s === "refused") reject(new Error(`refused: ${alice.detail}`));
  });
  alice.connect();
});
console.log(`alice is online: may ${alice.access?.rights?.join(", ")}`);
await alice.drive("avatar");
alice.sendPose("avatar", { rotations: { r_shoulder: quatFromEulerXYZ(0, 0, -1.5) } });
try {
  await alice.command({ op: "pause", avatar: "avatar" });
  throw new Error("pause was allowed");
} catch (e) {
  console.log(`pause refused: ${e.code}`);
}
await alice.releaseDrive("avatar");

// 3. The back end revokes it; the server closes alice's connection.
await revokeToken(url, admin, info.id);
console.log(`revoked; alice's connection closed: ${await closed}`);
