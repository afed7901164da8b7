// Drive an avatar from Node.js with posecast's JavaScript SDK (the npm package in server/sdk):
// take over the built-in avatar, wave its right arm at 60 poses a second for three seconds
// (paced at the server's limit by the SDK), hand it back to its clip.
//
//   cd examples/node && npm install        # installs the SDK from the repository path
//   POSECAST_TOKEN=… node drive.mjs        # Node 22+; Node 20.10+: node --experimental-websocket drive.mjs
//
// POSECAST_URL for a server other than ws://127.0.0.1:8080/ws.

import { Client, quatFromEulerXYZ } from "posecast";

const url = process.env.POSECAST_URL ?? "ws://127.0.0.1:8080/ws";
const token = process.env.POSECAST_TOKEN;
if (!token) throw new Error("set POSECAST_TOKEN to a control token");

const client = new Client({ url, token, reconnect: false });
await new Promise((resolve, reject) => {
  client.on("state", (state) => {
    if (state === "online") resolve(undefined);
    if (state === "closed" || state === "refused") reject(new Error(`cannot connect to ${url}: ${state} ${client.detail}`));
  });
  client.connect();
});

const info = await client.drive("avatar");
console.log(`driving ${info.avatar} (${info.joints.length} joints, at most ${info.max_rate_hz} poses/s)`);
let queued = 0;
for (let i = 0; i < 180; i++) {
  const t = i / 60;
  // The right upper arm raised sideways (about Z; the avatar faces +Z, its right is −X),
  // the forearm up and swinging from side to side.
  const rotations = {
    r_shoulder: quatFromEulerXYZ(0, 0, -1.5),
    r_elbow: quatFromEulerXYZ(0, 0, -1.2 + 0.5 * Math.sin(t * 6)),
  };
  if (client.sendPose("avatar", { rotations }) === "queued") queued++;
  await new Promise((r) => setTimeout(r, 1000 / 60));
}
await client.releaseDrive("avatar");
console.log(`sent 180 poses (${queued} waited for their slot); released avatar`);
client.close();
