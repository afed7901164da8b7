// @ts-check
// The connection (proto/PROTOCOL.md "Exchange"): hello with a token → welcome; subscriptions
// kept across reconnects; descriptions; pose frames (binary by default, or JSON) decoded into
// per-avatar poses and jitter buffers; ping/pong for the clock; commands answered by ack/error
// as promises; reconnects with back-off (250 ms doubling to 5 s by default) and resubscribes.
//
// Tokens: the server welcomes a hello whose token it does not know as anonymous and names the
// token's fault in an `unauthorized` error right after. Anyone may usually watch, so the client
// keeps that connection and watches, remembering why the token was refused (`refusals`); only
// when the welcome allows no viewing does it try the next token (e.g. the view token after a
// control token the server no longer knows), and with none left it stops (`refused`).

import { PosecastError } from "./errors.js";
import { FrameDecoder } from "./frames.js";
import { Frame2Decoder, MAGIC2 } from "./frames2.js";
import { JitterBuffer } from "./jitter.js";
import { ClockEstimator } from "./clock.js";
import { expandPose, selectJoints } from "./subset.js";
import { WebTransportSocket, discoverWebTransport } from "./webtransport.js";

/** @typedef {import("./posecast.js").ClientOptions} ClientOptions */
/** @typedef {import("./posecast.js").SubscribeOptions} SubscribeOptions */
/** @typedef {import("./posecast.js").ConnectionState} ConnectionState */
/** @typedef {import("./posecast.js").Token} Token */
/** @typedef {import("./posecast.js").Refusal} Refusal */
/** @typedef {import("./posecast.js").Access} Access */
/** @typedef {import("./posecast.js").WelcomeMessage} WelcomeMessage */
/** @typedef {import("./posecast.js").ServerMessage} ServerMessage */
/** @typedef {import("./posecast.js").ClientMessage} ClientMessage */
/** @typedef {import("./posecast.js").Command} Command */
/** @typedef {import("./posecast.js").AvatarView} AvatarView */
/** @typedef {import("./posecast.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./posecast.js").Frame} Frame */
/** @typedef {import("./posecast.js").FramePose} FramePose */
/** @typedef {import("./posecast.js").Pose} Pose */
/** @typedef {import("./posecast.js").Stats} Stats */
/** @typedef {import("./posecast.js").ClientEvents} ClientEvents */
/** @typedef {import("./posecast.js").Encoding} Encoding */
/** @typedef {import("./posecast.js").JointSet} JointSet */
/** @typedef {import("./posecast.js").DriveInfo} DriveInfo */
/** @typedef {import("./posecast.js").Quat} Quat */
/** @typedef {import("./posecast.js").Vec3} Vec3 */

/**
 * The protocol version a client asks for unless told otherwise: 9, wire v2 binary frames with
 * morph weights (each pose's `weights`, by channel name), a precision per subscription (coded
 * with coarser steps near an axis, the same bound), deltas packed into one bit stream (frame
 * kind 3, the time a difference from the base frame's), command results tagged with their
 * kind, and over WebTransport wire v2 frames as datagrams (deltas of kind 5 naming the frames
 * they refer to, predicted over the ticks between; every frame decoded is acknowledged). A server that predates it is asked
 * again with the version before.
 */
export const PROTOCOL_VERSION = 9;

/** @returns {number} The wall clock in µs since the Unix epoch. */
export function nowMicros() {
  return Math.round((performance.timeOrigin + performance.now()) * 1000);
}

/** @returns {string} `ws(s)://` + this page's host + `/ws` (or localhost outside a page). */
function defaultUrl() {
  const loc = typeof location !== "undefined" ? location : null;
  if (!loc) return "ws://127.0.0.1:8080/ws";
  return `${loc.protocol === "https:" ? "wss:" : "ws:"}//${loc.host}/ws`;
}

/**
 * @param {ServerMessage} msg
 * @returns {PosecastError}
 */
function errorOf(msg) {
  const code = typeof msg.code === "string" ? msg.code : "internal";
  const message = typeof msg.message === "string" ? msg.message : code;
  return new PosecastError(code, message, {
    id: typeof msg.id === "number" ? msg.id : undefined,
    retryAfterMs: typeof msg.retry_after_ms === "number" ? msg.retry_after_ms : undefined,
    details:
      msg.details !== null && typeof msg.details === "object"
        ? /** @type {import("./protocol").ErrorDetails} */ (msg.details)
        : undefined,
  });
}

export class Client {
  /** @param {ClientOptions} [options] */
  constructor(options = {}) {
    this.url = options.url ?? defaultUrl();
    /** @type {Encoding} */
    this.encoding = options.encoding ?? "binary";
    /** The protocol version asked for in the hello: 9 (8 with datagram deltas predicted over the ticks between), 8 (7 with wire v2 frames as datagrams over WebTransport), 7 (6 with packed deltas), 6 (5 with near-axis steps in a precision's frames), 5 (wire v2 frames with morph weights and a precision per subscription), 4 (with morph weights), 3 or 2 (wire v2 frames) or 1 (v1 frames). */
    this.version = options.version ?? PROTOCOL_VERSION;
    const tokens = options.tokens ?? (options.token ? [{ kind: /** @type {const} */ ("control"), value: options.token }] : []);
    /** @type {() => Token[]} */
    this.tokens = typeof tokens === "function" ? tokens : () => tokens;
    this.name = options.name ?? "posecast-js";
    this.reconnect = options.reconnect ?? true;
    this.initialBackoffMs = options.initialBackoffMs ?? 250;
    this.maxBackoffMs = options.maxBackoffMs ?? 5000;
    this.commandTimeoutMs = options.commandTimeoutMs ?? 8000;
    this.pingIntervalMs = options.pingIntervalMs ?? 1000;
    /** @type {"auto" | "websocket" | "webtransport"} Which transport to try: WebTransport first when the server offers it (`auto`), or one only. */
    this.transportChoice = options.transport ?? "auto";
    /** How long asking for the WebTransport endpoint, and then its handshake, may each take before the websocket is used instead. */
    this.quicTimeoutMs = options.quicTimeoutMs ?? 5000;
    /** @type {"websocket" | "webtransport" | null} The transport of the connection (the newest one while reconnecting). */
    this.transport = null;
    /** @type {string | null} Why the newest connection did not use the WebTransport the server offered (UDP blocked on the way?). */
    this.webtransportFailure = null;

    /** @type {ConnectionState} */
    this.state = "closed";
    this.detail = "";
    /** @type {WelcomeMessage | null} */
    this.welcome = null;
    /** @type {Access | null} */
    this.access = null;
    /** @type {Token | null} */
    this.token = null;
    /** @type {Refusal[]} */
    this.refusals = [];
    this.tickRate = 60;
    /** @type {number | null} */
    this.rttMs = null;
    this.clock = new ClockEstimator();
    /** @type {Stats} */
    this.stats = { frames: 0, keyframes: 0, frameBytes: 0, undecodable: 0, stale: 0, connects: 0, commands: {} };
    /** @type {Map<string, SubscribeOptions>} */
    this.subscriptions = new Map();
    /** @type {Map<string, AvatarView & {num: number}>} */
    this.avatars = new Map();

    /** @type {Map<number, string>} Scene number (from `subscribed`) → scene. */
    /** @type {Map<string, JointSet>} Each subscribed scene's joint set (from `subscribed`). */
    this.jointSets = new Map();
    this.sceneNames = new Map();
    this.decoder = new FrameDecoder();
    this.decoder2 = new Frame2Decoder();
    /** @type {Map<number, {resolve: (v: unknown) => void, reject: (e: PosecastError) => void, timer: ReturnType<typeof setTimeout>}>} */
    this.pending = new Map();
    /** @type {Map<number, number>} Ping id → its send time, µs. */
    this.pings = new Map();
    this.nextId = 1;
    this.nextPing = 1;
    this.backoff = this.initialBackoffMs;
    this.tokenIndex = 0;
    this.stopped = true;
    /** @type {ReturnType<typeof setTimeout> | undefined} */
    this.timer = undefined;
    /** @type {ReturnType<typeof setInterval> | undefined} */
    this.pinger = undefined;
    /** @type {WebSocket | WebTransportSocket | null} */
    this.ws = null;
    /** Counts connection attempts: a socket that opens after a newer attempt began is closed. */
    this.attempt = 0;
    /** Set between a welcome that ignored the token and the `unauthorized` error naming it. */
    this.awaitingTokenError = false;
    /** @type {Map<string, Set<(value: any) => void>>} */
    this.listeners = new Map();
    /** @type {Map<string, {spacingMs: number, lastMs: number, pending: ClientMessage | null, timer: ReturnType<typeof setTimeout> | undefined}>} Paced drives, by avatar. */
    this.drives = new Map();
  }

  /**
   * @template {keyof ClientEvents} K
   * @param {K} event
   * @param {(value: ClientEvents[K]) => void} listener
   * @returns {() => void}
   */
  on(event, listener) {
    let set = this.listeners.get(event);
    if (!set) this.listeners.set(event, (set = new Set()));
    set.add(listener);
    return () => set.delete(listener);
  }

  /**
   * @template {keyof ClientEvents} K
   * @param {K} event
   * @param {ClientEvents[K]} value
   */
  emit(event, value) {
    for (const l of this.listeners.get(event) ?? []) {
      try {
        l(value);
      } catch (e) {
        // A listener's bug must not break the connection; it still shows in the console.
        console.error(e);
      }
    }
  }

  connect() {
    this.stopped = false;
    this.tokenIndex = 0;
    this.refusals = [];
    this.backoff = this.initialBackoffMs;
    if (this.pinger === undefined && this.pingIntervalMs > 0) {
      this.pinger = setInterval(() => this.ping(), this.pingIntervalMs);
    }
    this.open();
  }

  restart() {
    this.drop();
    this.failPending(new PosecastError("offline", "reconnecting"));
    this.connect();
  }

  close() {
    this.stopped = true;
    this.drop();
    clearInterval(this.pinger);
    this.pinger = undefined;
    this.failPending(new PosecastError("offline", "the client was closed"));
    this.setState("closed");
  }

  /** Forgets the current socket without reconnecting from its close. */
  drop() {
    clearTimeout(this.timer);
    this.attempt++;
    const ws = this.ws;
    this.ws = null;
    if (ws) {
      ws.onclose = null;
      ws.onmessage = null;
      ws.close();
    }
  }

  /**
   * @param {ConnectionState} state
   * @param {string} [detail]
   */
  setState(state, detail = "") {
    this.state = state;
    this.detail = detail;
    this.emit("state", state);
  }

  open() {
    clearTimeout(this.timer);
    const token = this.tokens()[this.tokenIndex] ?? null;
    this.token = token;
    this.welcome = null;
    this.access = null;
    this.awaitingTokenError = false;
    this.setState("connecting");
    const attempt = ++this.attempt;
    this.openSocket().then(
      (ws) => {
        if (attempt !== this.attempt) ws.close();
        else this.attach(ws, token);
      },
      (e) => {
        if (attempt === this.attempt) this.scheduleReconnect(String(e?.message ?? e));
      },
    );
  }

  /**
   * A socket to the server: over WebTransport when the transport choice allows it, the browser
   * has it and the server offers it (`/api/quic`), and its handshake completes in time; a
   * websocket otherwise. `transport` and `webtransportFailure` say which, and why.
   * @returns {Promise<WebSocket | WebTransportSocket>}
   */
  async openSocket() {
    let failure = null;
    if (this.transportChoice !== "websocket" && typeof WebTransport !== "undefined") {
      /** @type {{url: string, certSha256: Uint8Array | null} | null} */
      let offer = null;
      try {
        offer = await discoverWebTransport(this.url, this.quicTimeoutMs);
      } catch {
        // A server that cannot be asked: the websocket says why.
      }
      if (offer) {
        try {
          const socket = await WebTransportSocket.open(offer.url, offer.certSha256, this.quicTimeoutMs);
          this.transport = "webtransport";
          this.webtransportFailure = null;
          return socket;
        } catch (e) {
          failure = `${offer.url}: ${/** @type {Error} */ (e)?.message ?? e}`;
        }
      }
    }
    if (this.transportChoice === "webtransport") throw new Error(failure ?? "WebTransport is not offered (or this browser has none)");
    const ws = new WebSocket(this.url);
    this.transport = "websocket";
    this.webtransportFailure = failure;
    return ws;
  }

  /**
   * Speaks the protocol on a socket just made.
   * @param {WebSocket | WebTransportSocket} ws
   * @param {Token | null} token
   */
  attach(ws, token) {
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      /** @type {ClientMessage} */
      const hello = { type: "hello", version: this.version, encoding: this.encoding, client: this.name };
      if (token) hello.token = token.value;
      ws.send(JSON.stringify(hello));
    };
    // A WebTransport socket is open when it is made.
    if (ws instanceof WebTransportSocket) queueMicrotask(() => ws.onopen?.());
    ws.onmessage = (/** @type {{data: string | ArrayBuffer}} */ e) => {
      const received = nowMicros();
      if (typeof e.data !== "string") {
        if (this.welcome) this.onBinary(/** @type {ArrayBuffer} */ (e.data), received);
        return;
      }
      /** @type {ServerMessage} */
      let msg;
      try {
        msg = JSON.parse(e.data);
      } catch {
        return;
      }
      if (!msg || typeof msg.type !== "string") return;
      if (this.welcome) this.handle(msg, received, e.data.length);
      else if (msg.type === "welcome") this.onWelcome(/** @type {WelcomeMessage} */ (/** @type {unknown} */ (msg)));
      else if (msg.type === "error" && this.awaitingTokenError && msg.code === "unauthorized") {
        // Why the token that did not let this client watch was refused: now the next one.
        this.tokenRefused(String(msg.message));
        this.nextToken(this.detail || "no token lets this client watch");
      } else if (msg.type === "error" && msg.code === "unsupported_version" && this.version > 1) {
        // A server that predates this version: say hello again with the one before.
        this.version -= 1;
        this.drop();
        this.open();
      } else if (msg.type === "error") this.refuseHello(String(msg.code), String(msg.message));
    };
    ws.onclose = (/** @type {{code: number, reason: string}} */ e) => {
      if (this.ws !== ws) return;
      this.ws = null;
      // The server's reason when it gave one (e.g. "token no longer valid": revoked, expired).
      const why = e.reason || "connection lost";
      this.failPending(new PosecastError("offline", `the connection closed: ${why}`));
      if (this.stopped) return;
      if (this.reconnect) this.scheduleReconnect(why);
      else {
        // Nothing more will happen on this client (until connect()): no timer keeps a Node
        // process alive.
        clearInterval(this.pinger);
        this.pinger = undefined;
        this.setState("closed", why);
      }
    };
    ws.onerror = () => {};
  }

  /** @param {WelcomeMessage} msg */
  onWelcome(msg) {
    const access = msg.access ?? { view: true, control: false };
    if (this.token && !access.name) {
      // The server did not know the token; its `unauthorized` error (with the reason) follows.
      this.refusals.push({ kind: this.token.kind, code: "unauthorized", message: "the server does not know this token" });
      this.awaitingTokenError = true;
    }
    if (!access.view) {
      const why = this.token ? "no token lets this client watch" : "watching this server needs a view token";
      this.detail = why;
      // With a refused token, its reason follows at once; move on then (or after a second).
      if (this.awaitingTokenError) this.timer = setTimeout(() => this.nextToken(why), 1000);
      else this.nextToken(why);
      return;
    }
    this.welcome = msg;
    this.access = access;
    this.tickRate = msg.tick_rate > 0 ? msg.tick_rate : 60;
    this.backoff = this.initialBackoffMs;
    // A new connection: its own scene numbers and keyframes. Over WebTransport v2 frames come
    // as datagrams (protocol version 8): lost, out of order, their deltas naming the frames
    // they refer to.
    this.decoder = new FrameDecoder();
    this.decoder2 = this.ws instanceof WebTransportSocket ? Frame2Decoder.forDatagrams() : new Frame2Decoder();
    this.sceneNames.clear();
    this.stats.connects++;
    this.setState("online");
    for (const [scene, options] of this.subscriptions) this.sendSubscribe(scene, options);
    this.ping();
  }

  /** @param {string} message */
  tokenRefused(message) {
    this.awaitingTokenError = false;
    const last = this.refusals[this.refusals.length - 1];
    if (last) last.message = message;
  }

  /**
   * The hello itself was refused (an error before any welcome): the next token, or stop.
   * @param {string} code
   * @param {string} message
   */
  refuseHello(code, message) {
    if (this.token) this.refusals.push({ kind: this.token.kind, code, message });
    this.nextToken(`${code}: ${message}`);
  }

  /** @param {string} why */
  nextToken(why) {
    this.drop();
    if (this.tokenIndex + 1 < this.tokens().length) {
      this.tokenIndex++;
      this.open();
      return;
    }
    this.stopped = true;
    this.setState("refused", why);
  }

  /** @param {string} reason */
  scheduleReconnect(reason) {
    this.setState("offline", reason);
    const delay = this.backoff;
    this.backoff = Math.min(this.backoff * 2, this.maxBackoffMs);
    this.tokenIndex = 0;
    this.timer = setTimeout(() => {
      this.refusals = [];
      this.open();
    }, delay);
  }

  /** @param {PosecastError} error */
  failPending(error) {
    for (const { reject, timer } of this.pending.values()) {
      clearTimeout(timer);
      reject(error);
    }
    this.pending.clear();
  }

  /**
   * @param {ClientMessage} msg
   * @returns {boolean}
   */
  send(msg) {
    if (this.ws && this.ws.readyState === 1 && this.state === "online") {
      this.ws.send(JSON.stringify(msg));
      return true;
    }
    return false;
  }

  /**
   * @param {Command} command
   * @returns {Promise<unknown>}
   */
  command(command) {
    return new Promise((resolve, reject) => {
      const id = this.nextId++;
      if (!this.send({ type: "command", id, command })) {
        reject(new PosecastError("offline", "not connected"));
        return;
      }
      this.stats.commands[command.op] = (this.stats.commands[command.op] ?? 0) + 1;
      const timer = setTimeout(() => {
        this.pending.delete(id);
        reject(new PosecastError("timeout", `no answer to ${command.op} within ${this.commandTimeoutMs / 1000} s`, { id }));
      }, this.commandTimeoutMs);
      this.pending.set(id, { resolve, reject, timer });
    });
  }

  /**
   * Takes over an avatar as its live driver (the `drive` command); its poses then go with
   * `sendPose`, paced at the answer's `max_rate_hz`. The drive ends with `releaseDrive`, the
   * connection's end, or `timeout` seconds without a pose. With `trackers` (`head`, `l_hand`,
   * `r_hand`, optionally `hips`, `l_foot`, `r_foot` or joint names) its poses carry tracker
   * transforms in the scene's space and the server solves the body from them.
   * @param {string} avatar
   * @param {{ source?: string, on_release?: "clip" | "hold", trackers?: string[], legs?: "planted" | "animated" | "locomotion", locomotion?: { clip: string, speed: number }[] }} [options]
   * @returns {Promise<DriveInfo>}
   */
  async drive(avatar, options = {}) {
    /** @type {Command} */
    const command = { op: "drive", avatar };
    if (options.source !== undefined) command.source = options.source;
    if (options.on_release !== undefined) command.on_release = options.on_release;
    if (options.trackers !== undefined) command.trackers = options.trackers;
    if (options.legs !== undefined) command.legs = options.legs;
    if (options.locomotion !== undefined) command.locomotion = options.locomotion;
    const info = /** @type {DriveInfo} */ (await this.command(command));
    this.endPacing(avatar);
    const rate = Number.isFinite(info.max_rate_hz) && info.max_rate_hz > 0 ? info.max_rate_hz : 1 / 60;
    // At most a minute between poses, whatever rate a server announces.
    this.drives.set(avatar, { spacingMs: Math.min(1000 / rate, 60000), lastMs: -Infinity, pending: null, timer: undefined });
    return info;
  }

  /**
   * Sends a live pose of a driven avatar: local rotations of the drive's source joints by
   * name, optionally the source root's translation (metres) and the capture time (µs; now by
   * default) — or, for a tracker drive, tracker transforms in the scene's space by name. Poses are paced at the drive's `max_rate_hz`: one sent before its slot waits for
   * it, and a newer pose replaces a waiting one (poses supersede each other), so a driver
   * sending faster than the server takes is never refused `rate_limited`.
   * @param {string} avatar
   * @param {{ rotations?: Record<string, Quat>, root_position?: Vec3, time_us?: number, trackers?: Record<string, { position: Vec3, rotation: Quat }> }} pose
   * @returns {"sent" | "queued" | "offline"}
   */
  sendPose(avatar, pose) {
    /** @type {ClientMessage} */
    const msg = { type: "pose", avatar, time_us: pose.time_us ?? nowMicros() };
    if (pose.rotations) msg.rotations = pose.rotations;
    if (pose.root_position) msg.root_position = pose.root_position;
    if (pose.trackers) msg.trackers = pose.trackers;
    const pacing = this.drives.get(avatar);
    if (!pacing) return this.send(msg) ? "sent" : "offline";
    const now = performance.now();
    const wait = pacing.lastMs + pacing.spacingMs - now;
    if (wait <= 0 && pacing.timer === undefined) {
      pacing.lastMs = now;
      return this.send(msg) ? "sent" : "offline";
    }
    pacing.pending = msg;
    if (pacing.timer === undefined) {
      pacing.timer = setTimeout(() => {
        pacing.timer = undefined;
        const next = pacing.pending;
        pacing.pending = null;
        if (next) {
          pacing.lastMs = performance.now();
          this.send(next);
        }
      }, Math.max(wait, 0));
    }
    return "queued";
  }

  /**
   * Ends a drive this connection holds (`release_drive`); the avatar plays its clip again.
   * @param {string} avatar
   * @returns {Promise<unknown>}
   */
  releaseDrive(avatar) {
    this.endPacing(avatar);
    return this.command({ op: "release_drive", avatar });
  }

  /**
   * Forgets the pacing of an avatar's poses, dropping a pose waiting for its slot: for a drive
   * that ended elsewhere (released by another client, timed out), so no refused pose follows.
   * @param {string} avatar
   */
  endPacing(avatar) {
    const pacing = this.drives.get(avatar);
    if (pacing?.timer !== undefined) clearTimeout(pacing.timer);
    this.drives.delete(avatar);
  }

  /**
   * @param {string} scene
   * @param {SubscribeOptions} [options]
   */
  subscribe(scene, options = {}) {
    this.subscriptions.set(scene, options);
    this.sendSubscribe(scene, options);
  }

  /**
   * @param {string} scene
   * @param {SubscribeOptions} options
   */
  sendSubscribe(scene, options) {
    /** @type {ClientMessage} */
    const msg = { type: "subscribe", scene };
    if (options.avatars) msg.avatars = options.avatars;
    if (options.rate !== undefined) msg.rate = options.rate;
    if (options.joints !== undefined) msg.joints = options.joints;
    if (options.morphWeights === false) msg.morph_weights = false;
    // A precision is for binary frames of protocol version 5 (a server that predates it, or
    // JSON frames, get the finest).
    if (options.precision && this.version >= 5 && this.encoding === "binary") msg.precision = options.precision;
    this.send(msg);
  }

  /** @param {string} scene */
  unsubscribe(scene) {
    if (this.subscriptions.delete(scene)) this.send({ type: "unsubscribe", scene });
    this.dropScene(scene);
  }

  /** @param {string} scene */
  forget(scene) {
    this.subscriptions.delete(scene);
    this.dropScene(scene);
  }

  /** @param {string} scene */
  dropScene(scene) {
    for (const [id, view] of this.avatars) if (view.scene === scene) this.avatars.delete(id);
    // Its v2 frames are of no use any more (a new subscription starts with a keyframe).
    for (const [num, name] of this.sceneNames) if (name === scene) this.decoder2.forgetScene(num);
  }

  /**
   * @param {string} id
   * @returns {AvatarView | undefined}
   */
  avatar(id) {
    return this.avatars.get(id);
  }

  /**
   * @param {string} id
   * @returns {Pose | null}
   */
  latest(id) {
    return this.avatars.get(id)?.latest ?? null;
  }

  /**
   * @param {string} id
   * @param {number} [nowUs]
   * @returns {FramePose | null}
   */
  pose(id, nowUs) {
    return this.avatars.get(id)?.jitter.playout(nowUs ?? nowMicros()) ?? null;
  }

  ping() {
    if (typeof document !== "undefined" && document.hidden) return;
    const id = this.nextPing++ & 0xffffffff;
    const t0 = nowMicros();
    if (this.send({ type: "ping", id, client_time_us: t0 })) {
      this.pings.set(id, t0);
      // Pongs that never came are not kept for ever.
      if (this.pings.size > 64) this.pings.delete(this.pings.keys().next().value ?? id);
    }
  }

  /**
   * @param {ServerMessage} msg
   * @param {number} received
   * @param {number} bytes
   */
  handle(msg, received, bytes) {
    switch (msg.type) {
      case "frame": {
        const f = /** @type {Omit<Frame, "key" | "bytes" | "received_us">} */ (/** @type {unknown} */ (msg));
        this.onFrame({ type: "frame", scene: f.scene, seq: f.seq, server_time_us: f.server_time_us, key: true, bytes, received_us: received, avatars: f.avatars });
        return;
      }
      case "pong": {
        const t0 = typeof msg.client_time_us === "number" ? msg.client_time_us : NaN;
        this.rttMs = (received - t0) / 1000;
        this.clock.add(t0, Number(msg.server_time_us), received);
        this.pings.delete(Number(msg.id));
        break;
      }
      case "subscribed":
        this.sceneNames.set(Number(msg.scene_num), String(msg.scene));
        if (msg.joints) this.jointSets.set(String(msg.scene), /** @type {JointSet} */ (msg.joints));
        else this.jointSets.delete(String(msg.scene));
        break;
      case "unsubscribed":
        // Deleted, or the server going away: a reconnect renews it unless it was forgotten.
        this.dropScene(String(msg.scene));
        break;
      case "scene_deleted":
        this.forget(String(msg.scene));
        break;
      case "description": {
        const desc = /** @type {AvatarDescription} */ (msg.avatar);
        const scene = String(msg.scene);
        const old = this.avatars.get(desc.id);
        const set = this.jointSets.get(scene);
        const joints = set ? selectJoints(set, desc) : null;
        this.avatars.set(desc.id, {
          scene,
          num: desc.num,
          description: desc,
          joints: joints && joints.length < desc.parents.length ? joints : null,
          latest: old && old.description.hash === desc.hash ? old.latest : null,
          jitter: old && old.description.hash === desc.hash ? old.jitter : new JitterBuffer(this.tickRate),
        });
        this.emit("description", desc);
        break;
      }
      case "avatar_removed": {
        const avatar = String(msg.avatar);
        const view = this.avatars.get(avatar);
        // Its v2 frames too (a decoder for datagrams keeps 64 an avatar).
        for (const [num, name] of this.sceneNames) if (view && name === view.scene) this.decoder2.forgetAvatar(num, view.num);
        this.avatars.delete(avatar);
        this.emit("removed", { scene: String(msg.scene), avatar });
        break;
      }
      case "ack":
      case "error": {
        const id = typeof msg.id === "number" ? msg.id : undefined;
        const p = id !== undefined ? this.pending.get(id) : undefined;
        if (p && id !== undefined) {
          this.pending.delete(id);
          clearTimeout(p.timer);
          if (msg.type === "ack") p.resolve(msg.result ?? null);
          else p.reject(errorOf(msg));
          return;
        }
        if (msg.type === "error" && this.awaitingTokenError && msg.code === "unauthorized") {
          // The reason the hello's token was refused: kept, it is not a failure now.
          this.tokenRefused(String(msg.message));
          this.emit("state", this.state);
          return;
        }
        if (msg.type === "error") this.emit("error", errorOf(msg));
        break;
      }
    }
    this.emit("message", msg);
  }

  /**
   * @param {ArrayBuffer} data
   * @param {number} received
   */
  onBinary(data, received) {
    let decoded;
    // The first byte says which wire a frame is (a server of before version 3 sends a v2
    // connection v1 frames for a subscription with a joint subset).
    const v2 = data.byteLength > 0 && new Uint8Array(data, 0, 1)[0] === MAGIC2;
    try {
      decoded = v2 ? this.decoder2.decode(data) : this.decoder.decode(data);
    } catch {
      this.stats.undecodable++;
      return;
    }
    // Over WebTransport, the server codes deltas only against frames acknowledged: every v2
    // frame (or part) decoded (protocol version 8), a v1 keyframe (versions 1 to 7).
    if (this.ws instanceof WebTransportSocket && (v2 || decoded.key)) {
      const avatars = decoded.avatars.map((a) => a.num);
      if (v2) this.ws.ackFrame(decoded.scene_num, decoded.seq, avatars);
      else this.ws.ackKey(decoded.scene_num, decoded.seq, avatars);
    }
    const scene = this.sceneNames.get(decoded.scene_num);
    if (scene === undefined) {
      this.stats.undecodable++;
      return;
    }
    /** @type {Map<number, string>} */
    const ids = new Map();
    for (const [id, view] of this.avatars) if (view.scene === scene) ids.set(view.num, id);
    /** @type {FramePose[]} */
    const avatars = [];
    for (const a of decoded.avatars) {
      const avatar = ids.get(a.num);
      if (avatar === undefined) continue; // not described (yet): nothing to pose
      /** @type {FramePose} */
      const pose = { avatar, hash: a.hash, rotations: a.rotations, translations: a.translations, scales: a.scales, placement: a.placement };
      // Morph weights (protocol version 4) by channel name, as a JSON frame gives them.
      const channels = this.avatars.get(avatar)?.description.morph_targets ?? [];
      if (a.weights.length > 0 && a.weights.length === channels.length) {
        pose.weights = Object.fromEntries(channels.map((name, c) => [name, a.weights[c]]));
      }
      avatars.push(pose);
    }
    this.onFrame({
      type: "frame",
      scene,
      seq: decoded.seq,
      server_time_us: decoded.server_time_us,
      key: decoded.key,
      binary: true,
      bytes: data.byteLength,
      received_us: received,
      avatars,
    });
  }

  /** @param {Frame} frame */
  onFrame(frame) {
    this.stats.frames++;
    if (frame.key) this.stats.keyframes++;
    this.stats.frameBytes += frame.bytes;
    const fresh = [];
    for (let pose of frame.avatars) {
      const view = this.avatars.get(pose.avatar);
      if (!view) continue;
      if (view.description.hash !== pose.hash) {
        this.stats.stale++;
        continue;
      }
      // A subset (a JSON frame lists its joints; a binary one has the subscription's): made
      // whole, every joint not sent at rest.
      const joints = pose.joints ?? (frame.binary ? view.joints : null);
      if (joints) {
        const whole = expandPose(pose, view.description, joints);
        if (!whole) {
          this.stats.undecodable++;
          continue;
        }
        /** @type {FramePose} */
        const expanded = { avatar: pose.avatar, hash: pose.hash, placement: pose.placement, ...whole };
        // No `weights` key at all when there are none (not one holding undefined).
        if (pose.weights) expanded.weights = pose.weights;
        pose = expanded;
      }
      // Not older than the newest pose (within 120 ticks: a restarted server counts from 0):
      // over WebTransport a keyframe comes again before each delta until acknowledged, and
      // datagrams may be overtaken.
      const newest = view.latest?.seq;
      if (newest !== undefined && frame.seq <= newest && newest - frame.seq <= 120) continue;
      view.latest = { ...pose, seq: frame.seq, server_time_us: frame.server_time_us, received_us: frame.received_us };
      view.jitter.push(frame.server_time_us, frame.received_us, pose);
      fresh.push(pose);
    }
    frame.avatars = fresh;
    this.emit("frame", frame);
    this.emit("message", frame);
  }
}
