// @ts-check
// posecast's JavaScript client: one ES module, no build step, no dependencies, served by the
// server at /sdk/posecast.js (its modules beside it under /sdk/), with TypeScript declarations
// at /sdk/posecast.d.ts — the API reference. The dashboard at / is built on it.
//
//   import { Client } from "/sdk/posecast.js";
//   const client = new Client({ token });       // ws(s)://this host/ws, binary frames
//   client.subscribe("default");
//   client.on("frame", () => draw(client.pose("avatar")));
//   client.connect();
//
// - client.js: the connection (hello/welcome, token fallback, subscriptions, commands as
//   promises, ping/pong, reconnect with back-off);
// - webtransport.js: the protocol over WebTransport (frames as datagrams, keyframes
//   acknowledged), tried first when the server offers it (`/api/quic`);
// - frames.js: the binary frame decoder (keyframes, deltas, smallest-three rotations);
// - frames2.js: the wire v2 decoder (protocol version 2: deltas against the previous frame,
//   predicted levels, Rice-coded residuals);
// - jitter.js, clock.js: playout of the stream and the clock offset, as posecast-client does;
// - subset.js: joint subsets (a subscription's `joints`), made whole at rest;
// - fk.js, math.js: forward kinematics and skinning matrices (checked against posecast-proto);
// - tokens.js: minting and revoking tokens for an app's users (its back end, with an admin token);
// - errors.js: PosecastError, with the protocol's error code.

export const SDK_VERSION = "1.14.0";
export { Client, PROTOCOL_VERSION, nowMicros } from "./client.js";
export { PosecastError } from "./errors.js";
export { WebTransportSocket, discoverWebTransport } from "./webtransport.js";
export { mintToken, revokeToken, listTokens, httpBase } from "./tokens.js";
export { FrameDecoder, decodeQuat } from "./frames.js";
export { Frame2Decoder } from "./frames2.js";
export { JitterBuffer } from "./jitter.js";
export { ClockEstimator } from "./clock.js";
export { selectJoints, expandPose } from "./subset.js";
export { forwardKinematics, skinningMatrices, jointPositions } from "./fk.js";
export {
  identity,
  multiply,
  fromTRS,
  perspective,
  lookAt,
  transformPoint,
  quatAxisAngle,
  quatMul,
  quatFromEulerXYZ,
  eulerXYZFromQuat,
  quatSlerp,
  quatAngleDegrees,
  DEG,
} from "./math.js";
