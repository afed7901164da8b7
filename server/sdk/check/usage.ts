// What a TypeScript user of /sdk/posecast.js writes, type-checked against posecast.d.ts alone
// (`tsc --noEmit -p server/sdk/check`, run by scripts/check-web and tests/web/). The
// `@ts-expect-error` lines must stay errors: they guard that the declarations are not too loose.

import {
  Client,
  PosecastError,
  FrameDecoder,
  Frame2Decoder,
  JitterBuffer,
  ClockEstimator,
  forwardKinematics,
  skinningMatrices,
  jointPositions,
  quatSlerp,
  SDK_VERSION,
  PROTOCOL_VERSION,
  type AvatarDescription,
  type ConnectionState,
  type Frame,
  type FramePose,
  type Vec3,
} from "../posecast.js";

const client = new Client({ url: "ws://localhost:8080/ws", token: "secret", encoding: "binary", maxBackoffMs: 2000 });
const tokens = new Client({ tokens: () => [{ kind: "control", value: "a" }, { kind: "view", value: "b" }] });
client.subscribe("default", { avatars: ["avatar"], rate: 20 });
client.connect();
const state: ConnectionState = client.state;
const version: string = `${SDK_VERSION} speaks protocol ${PROTOCOL_VERSION}`;

const stop: () => void = client.on("frame", (frame: Frame) => {
  const seq: number = frame.seq;
  const key: boolean = frame.key;
  for (const pose of frame.avatars) {
    const view = client.avatar(pose.avatar);
    if (!view) continue;
    const desc: AvatarDescription = view.description;
    const worlds: Float32Array = forwardKinematics(desc, pose);
    const skin: Float32Array = skinningMatrices(desc, worlds);
    const joints: Vec3[] = jointPositions(worlds);
    const latest = client.latest(pose.avatar);
    const when: number | undefined = latest?.server_time_us;
    const shown: FramePose | null = client.pose(pose.avatar);
    void [seq, key, skin, joints, when, shown];
  }
});
client.on("state", (s) => console.log(s satisfies ConnectionState, client.detail, client.refusals));
client.on("error", (e) => console.log(e.code, e.message));
client.on("removed", ({ scene, avatar }) => console.log(scene, avatar));

async function wave(): Promise<void> {
  try {
    // Results are typed by the command's op.
    const done: null = await client.command({ op: "play", avatar: "avatar", clip: "wave", fade: 0.3 });
    const scenes = await client.command({ op: "list_scenes" });
    const watchers: number = scenes[0].viewers?.length ?? 0;
    const state = await client.command({ op: "get_avatar", avatar: "avatar" });
    const drivenBy: string | undefined = state.driver?.name;
    const drive = await client.command({ op: "drive", avatar: "avatar" });
    const rate: number = drive.max_rate_hz;
    const take = await client.command({ op: "stop_recording", avatar: "avatar" });
    const clip: string = take.clip;
    void [done, watchers, drivenBy, rate, clip];
  } catch (e) {
    if (e instanceof PosecastError) {
      const code: string = e.code;
      const retry: number | undefined = e.retryAfterMs;
      void [code, retry];
    }
  }
}

const jitter = new JitterBuffer(60);
const sampled = jitter.sample(1_000_000);
if (sampled) console.log(sampled.kind satisfies "interpolated" | "extrapolated" | "held", sampled.pose.rotations);
const clock = new ClockEstimator();
clock.add(0, 5_000, 200);
const offset: number = clock.offsetUs();
const frame = new FrameDecoder().decode(new Uint8Array(32));
const frame2 = new Frame2Decoder().decode(new Uint8Array([0x51, 1, 0, 0, 1, 0]));
const v1 = new Client({ version: 1 });
const asked: 1 | 2 | 3 | 4 | 5 | 6 | 7 | 8 | 9 = v1.version;
client.subscribe("crowd", { precision: { degrees: 0.1 } });
client.subscribe("stage", { precision: { millimetres: 2, shell: 0.03, translation: 0.001 } });
const q = quatSlerp([0, 0, 0, 1], [0, 1, 0, 0], 0.5);

// @ts-expect-error — a command needs its `op`.
void client.command({ avatar: "avatar" });
async function wrongResult(): Promise<void> {
  // @ts-expect-error — get_avatar answers an avatar state, not a list.
  const list: unknown[] = await client.command({ op: "get_avatar", avatar: "avatar" });
  void list;
}
void wrongResult;
// @ts-expect-error — no such event.
client.on("frames", () => {});
// @ts-expect-error — encodings are "binary" or "json".
void new Client({ encoding: "msgpack" });
// @ts-expect-error — protocol versions are 1 to 9.
void new Client({ version: 10 });
// @ts-expect-error — a precision names its bounds (degrees, millimetres, shell, translation).
client.subscribe("crowd", { precision: { degree: 0.1 } });
// @ts-expect-error — subscribe takes a scene name.
client.subscribe(42);

void [tokens, state, version, stop, wave, offset, frame, frame2, asked, q];
client.close();

// Live driving, paced at the drive's rate.
async function driveWave(): Promise<void> {
  const info = await client.drive("avatar", { on_release: "clip" });
  const rate: number = info.max_rate_hz;
  const sent: "sent" | "queued" | "offline" = client.sendPose("avatar", {
    rotations: { l_shoulder: [0, 0, 0.38, 0.92] },
    root_position: [0, 0.9, 0],
  });
  // @ts-expect-error rotations are quaternions by joint name, not a list
  client.sendPose("avatar", { rotations: [[0, 0, 0, 1]] });
  await client.releaseDrive("avatar");
  void rate;
  void sent;
}
void driveWave;

// Tracker driving: a headset and two controllers, then a calibration.
async function driveTrackers(): Promise<void> {
  const info = await client.drive("avatar", { trackers: ["head", "l_hand", "r_hand"], legs: "planted" });
  const order: string[] = info.trackers ?? [];
  client.sendPose("avatar", {
    trackers: {
      head: { position: [0, 1.6, 0], rotation: [0, 0, 0, 1] },
      l_hand: { position: [0.3, 1.1, 0.2], rotation: [0, 0, 0, 1] },
    },
  });
  const measured = await client.command({ op: "calibrate_trackers", avatar: "avatar", pose: "t_pose" });
  const scale: number = measured.scale;
  // @ts-expect-error legs are "planted" or "animated"
  await client.drive("avatar", { trackers: ["head"], legs: "running" });
  void order;
  void scale;
}
void driveTrackers;
