// Type declarations of posecast's JavaScript client, served at /sdk/posecast.d.ts beside the
// module it describes (/sdk/posecast.js). This file is the API reference; proto/PROTOCOL.md is
// the reference of the messages, protocol.d.ts their types (generated from the server's). The
// SDK speaks protocol version 9 (wire v2 binary frames with morph weights, a precision per
// subscription and packed deltas, results tagged with their kind; over WebTransport, wire v2
// frames as datagrams) by default, and 8, 7, 6, 5, 4, 3, 2 or 1 when asked
// (`ClientOptions.version`) or refused by an older server.
//
//   import { Client } from "/sdk/posecast.js";
//   const client = new Client({ token: "…" });          // ws(s)://this host/ws, binary frames
//   client.subscribe("default");
//   client.on("frame", (frame) => { … client.pose("avatar") … });
//   client.connect();
//   await client.command({ op: "play", avatar: "avatar", clip: "walk" });

/** The SDK's version. */
export declare const SDK_VERSION: string;
/** The protocol version the SDK speaks (the `hello`'s `version`). */
export declare const PROTOCOL_VERSION: 9;

export type Vec3 = [number, number, number];
/** The `result` of an `ack`, by the `kind` the server tags it with (protocol.d.ts). */
export type ResultOfKind<K extends CommandResult["kind"]> = Extract<CommandResult, { kind: K }> extends { result: infer R } ? R : null;

/** Which result kind each command answers with (proto/PROTOCOL.md, "Typed results"). */
export interface ResultKinds {
  list_scenes: "scenes";
  list_assets: "assets";
  configure_asset: "assets";
  get_asset: "asset";
  get_avatar: "avatar";
  get_joint: "joint";
  sample_pose: "pose";
  drive: "drive";
  calibrate_trackers: "calibration";
  stop_recording: "recorded";
  record_scene: "take";
  stop_recording_scene: "take";
  get_take: "take";
  list_takes: "takes";
  replay: "replay";
  control_replay: "replay";
  create_scene: "scene_created";
  add_avatar: "avatar_added";
  set_joint_rotation: "rotation";
  rotate_joint_local: "rotation";
  rotate_joint_world: "rotation";
  set_joint_dofs: "dofs";
}

/** What `client.command({op, …})` resolves with: the result of that command's kind, `null` for `done`. */
export type ResultOf<Op extends Command["op"]> = Op extends keyof ResultKinds ? ResultOfKind<ResultKinds[Op]> : null;

/** `[x, y, z, w]`. */
export type Quat = [number, number, number, number];
/** 16 floats, column-major (`p' = M p`). */
export type Mat4 = Float32Array;

// The wire's JSON types, generated from the server's Rust types (protocol.d.ts, served beside
// this file): messages, commands, results, error codes, descriptions.
export type {
  Access,
  AssetDetail,
  AssetInfo,
  AvatarDescription,
  AvatarPoseJson,
  AvatarState,
  CalibrationInfo,
  CalibrationPose,
  ClientMsg,
  ClipInfo,
  Command,
  CommandResult,
  DofInfo,
  DriveInfo,
  Encoding,
  ErrorDetails,
  FadeState,
  JointInfo,
  JointSet,
  Legs,
  LocomotionClip,
  MintRequest,
  MintedToken,
  Placement,
  Precision,
  ProtocolError,
  RecordingInfo,
  Right,
  SceneInfo,
  ServerMsg,
  TokenInfo,
  TrackerTransform,
} from "./protocol";
import type {
  Access,
  AvatarDescription,
  CommandResult,
  DriveInfo,
  AvatarPoseJson,
  Command,
  Encoding,
  ErrorCode as WireErrorCode,
  ErrorDetails,
  JointSet,
  Legs,
  LocomotionClip,
  MintRequest,
  MintedToken,
  Placement,
  Precision,
  ServerMsg,
  TokenInfo,
  TrackerTransform,
} from "./protocol";

/**
 * One avatar's pose in a frame: the JSON frame's shape (`rotations` of every joint — of the
 * subscription's joint set, listed in `joints`, for a JSON frame with one —, `translations` of
 * the description's `translated_joints`, `scales` of its `scaled_joints`, the placement), also
 * for decoded binary frames.
 */
export type FramePose = AvatarPoseJson;

/** A decoded pose frame (binary or JSON; both give this shape). */
export interface Frame {
  type: "frame";
  scene: string;
  /** The scene's tick. */
  seq: number;
  /** Server time of the tick, µs since the Unix epoch. */
  server_time_us: number;
  /** A binary keyframe, or a JSON frame (always complete). */
  key: boolean;
  /** Whether it came as a binary frame. */
  binary?: boolean;
  /** Bytes of the message. */
  bytes: number;
  /** When it arrived, µs since the Unix epoch on this machine. */
  received_us: number;
  avatars: FramePose[];
}

/** The newest (or a played-out) pose of an avatar, with the tick it shows. */
export interface Pose extends FramePose {
  seq: number;
  server_time_us: number;
  received_us: number;
}

/** Any message the server sends (proto/PROTOCOL.md); binary frames arrive as {@link Frame}. */
export interface ServerMessage {
  type: string;
  [field: string]: unknown;
}

/** `welcome`: the server's answer to the hello. */
export type WelcomeMessage = Extract<ServerMsg, { type: "welcome" }>;

/** Any message a client sends. */
export interface ClientMessage {
  type: string;
  [field: string]: unknown;
}

/**
 * The protocol's error codes (later servers may add codes), and the SDK's own: `offline` (not
 * connected, or the connection closed before the answer) and `timeout` (no answer in time).
 */
export type ErrorCode = WireErrorCode | "offline" | (string & {});

/** A refused or failed command (or request): the protocol's error code and message. */
export declare class PosecastError extends Error {
  constructor(
    code: ErrorCode,
    message: string,
    options?: { id?: number; retryAfterMs?: number; details?: ErrorDetails },
  );
  /** `"PosecastError"`. */
  readonly name: string;
  readonly code: ErrorCode;
  /** The command's id, when the error answered one. */
  readonly id: number | undefined;
  /** With `rate_limited`: when to try again. */
  readonly retryAfterMs: number | undefined;
  /** What the error is about, as fields (the scene, avatar, rig, clip, joint, expression or
   * take the server could not find; the quota that refused); undefined when the message is
   * all there is. */
  readonly details: ErrorDetails | undefined;
}

export type TokenKind = "control" | "view";
export interface Token {
  kind: TokenKind;
  value: string;
}
/** A token the server refused in a hello, and why. */
export interface Refusal {
  kind: TokenKind;
  code: string;
  message: string;
}

/**
 * - `connecting`: opening, or waiting for the welcome;
 * - `online`: welcomed, with view rights;
 * - `offline`: the connection dropped; reconnecting after the back-off;
 * - `refused`: no token lets this client watch; stopped until {@link Client.restart};
 * - `closed`: {@link Client.close} was called.
 */
export type ConnectionState = "connecting" | "online" | "offline" | "refused" | "closed";

export interface ClientOptions {
  /** The websocket URL; default `ws(s)://` + this page's host + `/ws`. */
  url?: string;
  /** One token (control or view). */
  token?: string;
  /**
   * Tokens to try in order (control first, then view), read at each (re)connect. A token the
   * server does not know leaves the connection watching (anonymously) when the server lets
   * anyone watch; otherwise the next token is tried.
   */
  tokens?: Token[] | (() => Token[]);
  /** Frame encoding; default `"binary"` (several times smaller than JSON). */
  encoding?: Encoding;
  /**
   * Protocol version asked for in the hello: 9 (default: 8 with datagram deltas of kind 5,
   * predicted over the ticks between the frames they name and their own), 8 (7 with wire v2
   * frames as datagrams over WebTransport — deltas of kind 4 naming the frames they refer to,
   * every frame decoded acknowledged; on a websocket, 9 and 8 are 7), 7 (6 with deltas packed into one bit stream, frame
   * kind 3; over WebTransport, wire v1 frames), 6 (5 with a precision's frames coded on coarser steps near an
   * axis, the same bound), 5 (4 with a `precision` per
   * subscription), 4 (3 with each pose's morph `weights` in binary frames too), 3 or 2 — binary frames in wire v2,
   * deltas against the previous frame, about half the bytes of v1; 3 also tags every `ack`'s
   * result with its `kind` and serves a subscription with `joints` v2 frames cut to them (2
   * gets those as v1 frames) — or 1 (v1 frames); the client decodes both. A server that refuses the version (`unsupported_version`:
   * one that predates it) gets a hello with the version before, and `Client.version` follows.
   */
  version?: 1 | 2 | 3 | 4 | 5 | 6 | 7 | 8 | 9;
  /** The `client` name in the hello; default `"posecast-js"`. */
  name?: string;
  /** Reconnect when the connection drops (default true), resubscribing. */
  reconnect?: boolean;
  /** First reconnect delay, ms (default 250), doubled after every failure up to `maxBackoffMs`. */
  initialBackoffMs?: number;
  /** Longest reconnect delay, ms (default 5000). */
  maxBackoffMs?: number;
  /** How long a command waits for its answer, ms (default 8000). */
  commandTimeoutMs?: number;
  /** Ping interval for the clock offset and round trip, ms (default 1000; 0: never). */
  pingIntervalMs?: number;
  /**
   * The transport: `"auto"` (default) asks the server's `/api/quic` and connects over
   * WebTransport when it is offered and the browser has it — frames then come as datagrams, so a
   * lost packet costs its own tick and never stalls the ones after it — and over the websocket
   * otherwise, or when the QUIC handshake does not complete (UDP blocked on the way);
   * `"websocket"` or `"webtransport"` use that one only.
   */
  transport?: Transport;
  /** How long asking for the WebTransport endpoint, and then its handshake, may each take before the websocket is used, ms (default 5000). */
  quicTimeoutMs?: number;
}

/** A client's transport choice (`ClientOptions.transport`). */
export type Transport = "auto" | "websocket" | "webtransport";

export interface SubscribeOptions {
  /** Only these avatars of the scene. */
  avatars?: string[];
  /** Frames per second wanted (the server sends every `round(tick_rate / rate)`-th tick). */
  rate?: number;
  /** Only these joints of every avatar (fewer bytes for distant or small avatars). */
  joints?: JointSet;
  /** `false`: no morph weights in the frames (a view that draws no faces); default true. */
  morphWeights?: boolean;
  /**
   * How finely binary frames code each joint (protocol version 5): `degrees` (worst angle per
   * joint), `millimetres` at `shell` metres from each joint (a world-space bound: joints far
   * down a chain are coded more coarsely), `translation` (metres). Default: the finest
   * (≈ 0.0087°). A distant view, a crowd or a thin link pays less: about 1.7 B a joint at
   * 0.05° against 2.6 at the finest for motion capture. Not sent on JSON connections or to a
   * server that predates version 5.
   */
  precision?: Precision;
}

/** What the client knows of one subscribed avatar. */
export interface AvatarView {
  scene: string;
  description: AvatarDescription;
  /** The joints its binary frames carry, when the subscription has a joint set selecting fewer than all. */
  joints?: number[] | null;
  /** The newest decoded pose. */
  latest: Pose | null;
  /** Its recent poses, for playout. */
  jitter: JitterBuffer;
}

export interface Stats {
  /** Frames decoded. */
  frames: number;
  /** Binary keyframes among them (JSON frames count as keyframes). */
  keyframes: number;
  /** Bytes of frame messages received. */
  frameBytes: number;
  /** Binary frames that could not be decoded (a delta without its keyframe, malformed bytes). */
  undecodable: number;
  /** Poses for a rig other than the described one (skipped). */
  stale: number;
  /** Connections welcomed. */
  connects: number;
  /** Commands sent, by op. */
  commands: Record<string, number>;
}

export interface ClientEvents {
  /** The state, access or refusals changed. */
  state: ConnectionState;
  /** Every server message after the welcome, frames decoded into {@link Frame}. */
  message: ServerMessage | Frame;
  /** A pose frame of a subscribed scene. */
  frame: Frame;
  /** An avatar's description (new, or its rig changed). */
  description: AvatarDescription;
  /** An avatar left a subscribed scene. */
  removed: { scene: string; avatar: string };
  /** An error that answered no command (e.g. subscribing to an unknown scene). */
  error: PosecastError;
}

/** A connection to a posecast server (proto/PROTOCOL.md) that keeps itself connected. */
export declare class Client {
  constructor(options?: ClientOptions);
  readonly url: string;
  readonly encoding: Encoding;
  /** The protocol version said in the hello (lower after a server refused one; `welcome.version` says the one in use). */
  readonly version: 1 | 2 | 3 | 4 | 5 | 6 | 7 | 8 | 9;
  readonly state: ConnectionState;
  /** Why the state is what it is ("connection lost", a refusal's reason…). */
  readonly detail: string;
  /** The current connection's welcome (null until welcomed). */
  readonly welcome: WelcomeMessage | null;
  readonly access: Access | null;
  /** The token the current connection presented. */
  readonly token: Token | null;
  /** Tokens refused since the last (re)start, in the order tried. */
  readonly refusals: Refusal[];
  /** Ticks per second (from the welcome; 60 before). */
  readonly tickRate: number;
  /** Round trip of the newest ping, ms (null before the first pong). */
  readonly rttMs: number | null;
  /** The transport of the connection (the newest one while reconnecting); null before the first. */
  readonly transport: "websocket" | "webtransport" | null;
  /** Why the newest connection did not use the WebTransport the server offered (the handshake failed or timed out: UDP blocked?); null when it did, or none was offered. */
  readonly webtransportFailure: string | null;
  readonly clock: ClockEstimator;
  readonly stats: Stats;
  /** Subscriptions kept across reconnects. */
  readonly subscriptions: ReadonlyMap<string, SubscribeOptions>;
  /** Every described avatar of the subscribed scenes, by id. */
  readonly avatars: ReadonlyMap<string, AvatarView>;

  /** Connects (again), trying the tokens from the first. */
  connect(): void;
  /** Closes and connects at once (e.g. after the tokens changed); pending commands fail `offline`. */
  restart(): void;
  /** Closes for good (no reconnect); pending commands fail `offline`. */
  close(): void;
  /** Subscribes to a scene now (when online) and after every reconnect. */
  subscribe(scene: string, options?: SubscribeOptions): void;
  /** Ends a subscription. */
  unsubscribe(scene: string): void;
  /** Stops renewing a subscription the server ended (its scene was deleted), without a message. */
  forget(scene: string): void;
  /** Sends a message when online; whether it was sent. */
  send(message: ClientMessage): boolean;
  /**
   * Runs a command: resolves with its `ack`'s result, typed by the command's `op`
   * ({@link ResultOf}), rejects with a {@link PosecastError}.
   */
  command<C extends Command>(command: C): Promise<ResultOf<C["op"]>>;
  /**
   * Takes over an avatar as its live driver (`drive`); poses then go with {@link sendPose},
   * paced at the answer's `max_rate_hz`. With `trackers` the poses carry tracker transforms
   * and the server solves the body from them.
   */
  drive(
    avatar: string,
    options?: {
      source?: string;
      on_release?: "clip" | "hold";
      trackers?: string[];
      legs?: Legs;
      locomotion?: LocomotionClip[];
    },
  ): Promise<DriveInfo>;
  /**
   * Sends a live pose of a driven avatar (local rotations of the source's joints by name, the
   * root's translation, the capture time in µs; or, for a tracker drive, tracker transforms in
   * the scene's space by name). Paced at the drive's `max_rate_hz`: a pose before its slot
   * waits for it ("queued"), a newer one replaces a waiting one.
   */
  sendPose(
    avatar: string,
    pose: {
      rotations?: Record<string, Quat>;
      root_position?: Vec3;
      time_us?: number;
      trackers?: Record<string, TrackerTransform>;
    },
  ): "sent" | "queued" | "offline";
  /** Ends a drive this connection holds (`release_drive`). */
  releaseDrive(avatar: string): Promise<unknown>;
  /**
   * Forgets the pacing of an avatar's poses, dropping a pose waiting for its slot: for a drive
   * that ended elsewhere (released by another client, timed out), so no refused pose follows.
   */
  endPacing(avatar: string): void;
  /** An avatar's description and poses. */
  avatar(id: string): AvatarView | undefined;
  /** An avatar's newest decoded pose. */
  latest(id: string): Pose | null;
  /**
   * The pose to show now (or at client time `nowUs`, µs since the Unix epoch): the avatar's
   * jitter buffer played out ({@link JitterBuffer.playout}).
   */
  pose(id: string, nowUs?: number): FramePose | null;
  /** Calls `listener` on every `event`; returns a function that stops it. */
  on<K extends keyof ClientEvents>(event: K, listener: (value: ClientEvents[K]) => void): () => void;
}

/** How a played-out pose was made. */
export type Sampled = "interpolated" | "extrapolated" | "held";

/**
 * An avatar's recent poses by server time, played out a little in the past: at client time
 * `now` it shows server time `now − D`, `D` = the 99.5th percentile of the recent raw transits
 * (arrival − stamp) + one tick; between two frames it interpolates (slerp, lerp); past the
 * newest it extrapolates from the last two for at most 100 ms, then holds.
 */
export declare class JitterBuffer {
  constructor(tickRate: number);
  /** Adds a pose stamped `serverTimeUs`, received at `arrivalUs` (any epoch); older stamps are ignored. */
  push(serverTimeUs: number, arrivalUs: number, pose: FramePose): void;
  /** The playout delay, µs (includes the clock offset: only `now − delay` is meaningful). */
  delayUs(): number;
  /** Arrival jitter (RFC 3550), µs. */
  jitterUs(): number;
  /** Frames held. */
  readonly length: number;
  /** The pose at server time `timeUs`, and how it was made. */
  sample(timeUs: number): { pose: FramePose; kind: Sampled } | null;
  /** The server time shown at client time `nowUs`. */
  playoutTime(nowUs: number): number;
  /** The pose to show at client time `nowUs`. */
  playout(nowUs: number): FramePose | null;
}

/**
 * Clock offset and round trip from ping/pong: `rtt = t1 − t0`, `offset = server − (t0 + t1)/2`,
 * from the fastest of the last 16 exchanges.
 */
export declare class ClockEstimator {
  constructor();
  add(t0Us: number, serverUs: number, t1Us: number): void;
  /** `server − client`, µs (0 before any sample). */
  offsetUs(): number;
  /** The smallest recent round trip, µs. */
  rttUs(): number | null;
}

/** The binary frame decoder (proto/PROTOCOL.md "Pose frames"); keeps keyframes for deltas. */
export declare class FrameDecoder {
  constructor();
  /** Decodes one binary frame; throws a {@link PosecastError} `bad_message` on malformed bytes or a missing keyframe (and changes nothing). */
  decode(bytes: ArrayBuffer | Uint8Array): BinaryFrame;
}
export interface BinaryFrame {
  key: boolean;
  scene_num: number;
  seq: number;
  server_time_us: number;
  base_seq: number;
  /** `weights`: morph weight per channel of the avatar's `morph_targets`, in [0, 1] (level / 1023; protocol version 4; empty when the chunk carries none). */
  avatars: { num: number; hash: string; rotations: Quat[]; translations: Vec3[]; scales: Vec3[]; placement: Placement; weights: number[] }[];
}
/**
 * Decodes wire v2 frames (first byte 0x51; proto/PROTOCOL.md "Pose frames, wire v2"), keeping
 * each (scene, avatar)'s last 8 decoded frames for the deltas that refer to them, and each
 * scene's last (seq, server time) for the packed deltas (protocol version 7, frame kind 3) whose
 * time is a difference from it — the twin of posecast-proto's `Frame2Decoder`. One decoder per
 * connection.
 */
export declare class Frame2Decoder {
  /** `datagrams`: as {@link Frame2Decoder.forDatagrams}. */
  constructor(options?: { datagrams?: boolean });
  /**
   * A decoder of frames that come as datagrams (protocol version 8 over WebTransport), any of
   * which may be lost or come out of order: it keeps each avatar's last 64 frames in the order
   * they came for the deltas of kind 4, which name the frames they refer to, and a keyframe of
   * the rig an avatar has does not drop them (`Frame2Decoder::for_datagrams`).
   */
  static forDatagrams(): Frame2Decoder;
  /**
   * Decodes one v2 frame (a keyframe, a delta, a packed delta or a delta naming its frames);
   * throws a {@link PosecastError} `bad_message` on malformed bytes, a delta whose base frames
   * are not held or a packed delta whose base is not the scene's last decoded frame (and
   * changes nothing). A delta naming its frames has `base_seq` the newest it names.
   */
  decode(bytes: ArrayBuffer | Uint8Array): BinaryFrame;
  /** Forgets a scene's frames and its last (seq, time) (the client left it). */
  forgetScene(sceneNum: number): void;
  /** Forgets one avatar's frames (it left the scene). */
  forgetAvatar(sceneNum: number, avatarNum: number): void;
}
/** Decodes a 48-bit smallest-three rotation. */
export declare function decodeQuat(bits: number): Quat;

/**
 * World matrices of every joint (16 floats each): `W_j = W_parent(j) · T(t_j) R_j S_j`, roots
 * `W_root = P · D_root` with `P` the pose's placement. Rotations from the pose (rest when absent);
 * translations and scales for the description's translated / scaled joints, rest otherwise.
 */
/** The joints of `description` a joint set selects, ascending (as the server selects them). */
export declare function selectJoints(set: JointSet, description: AvatarDescription): number[];
/** A pose of only `joints` made whole, every other joint at rest; `null` when it does not fit. */
export declare function expandPose(
  pose: { rotations: Quat[]; translations: Vec3[]; scales: Vec3[] },
  description: AvatarDescription,
  joints: number[],
): { rotations: Quat[]; translations: Vec3[]; scales: Vec3[] } | null;

export declare function forwardKinematics(
  desc: AvatarDescription,
  pose: Partial<Pick<FramePose, "rotations" | "translations" | "scales" | "placement">> | null,
): Float32Array;
/** Skinning matrices `M_j = W_j · B_j⁻¹` (16 floats each) from {@link forwardKinematics}' world matrices. */
export declare function skinningMatrices(desc: AvatarDescription, worlds: Float32Array): Float32Array;
/** Joint positions in world space (the translation column of each world matrix). */
export declare function jointPositions(worlds: Float32Array): Vec3[];

export declare function identity(): Mat4;
/** `out = a · b`; `out` may not alias `a` or `b`. */
export declare function multiply(out: Mat4, a: ArrayLike<number>, b: ArrayLike<number>): Mat4;
/** `out = T(t) · R(q) · S(s)`. */
export declare function fromTRS(out: Mat4, t: ArrayLike<number>, q: ArrayLike<number>, s: ArrayLike<number>): Mat4;
export declare function perspective(fovy: number, aspect: number, near: number, far: number): Mat4;
export declare function lookAt(eye: ArrayLike<number>, target: ArrayLike<number>, up: ArrayLike<number>): Mat4;
/** `m · [p, 1]`, homogeneous. */
export declare function transformPoint(m: ArrayLike<number>, p: ArrayLike<number>): Quat;
export declare function quatAxisAngle(axis: ArrayLike<number>, angle: number): Quat;
/** `a · b` (b first). */
export declare function quatMul(a: Quat, b: Quat): Quat;
export declare function quatFromEulerXYZ(x: number, y: number, z: number): Quat;
export declare function eulerXYZFromQuat(q: Quat): Vec3;
/** Shortest-arc slerp, normalised. */
export declare function quatSlerp(a: ArrayLike<number>, b: ArrayLike<number>, w: number): Quat;
/** The angle between two rotations, degrees (`q ≡ −q`). */
export declare function quatAngleDegrees(a: ArrayLike<number>, b: ArrayLike<number>): number;
export declare const DEG: number;
/** µs since the Unix epoch. */
export declare function nowMicros(): number;

// Minted tokens (tokens.js), for an app's back end: a token per user, limited to rights,
// scenes, avatars and a lifetime. `server` is the server's URL, http(s):// or ws(s)://;
// `adminToken` an unlimited control token from the server's configuration (keep it on the
// back end). Refusals reject with a PosecastError (`unauthorized`, `forbidden`,
// `invalid_value`; `offline` when the server cannot be reached).

/** Mints a token (`POST /api/tokens`); hand `token` to the user, keep `info.id` to revoke it. */
export declare function mintToken(server: string, adminToken: string, request: MintRequest): Promise<MintedToken>;
/** Revokes a token: refused from now on, and the connections holding it are closed. */
export declare function revokeToken(server: string, adminToken: string, id: string): Promise<void>;
/** The tokens the server minted that are neither expired nor revoked. */
export declare function listTokens(server: string, adminToken: string): Promise<TokenInfo[]>;
/** The HTTP origin of a server URL of any scheme (`ws://h:p/ws` → `http://h:p`). */
export declare function httpBase(server: string): string;
