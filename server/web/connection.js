// @ts-check
// The websocket side of the dashboard (proto/PROTOCOL.md): hello with the JSON encoding and a
// token → welcome; subscribe; descriptions, JSON frames and pushed scene changes; ping/pong for
// the round trip; commands answered by ack/error. Reconnects with back-off (250 ms doubling to
// 5 s) and resubscribes.
//
// Tokens: the server welcomes a hello whose token it does not know as anonymous and reports
// the token right after (`unauthorized`). Anyone may usually watch, so the page then keeps
// the connection and watches, remembering why control was refused; only when the welcome
// allows no viewing does it try the next token (e.g. the view token after a control token the
// server no longer knows — it restarted and generated a new one), and with none left it stops
// ("refused") until the tokens change.

/** @typedef {import("./protocol.js").ServerMsg} ServerMsg */
/** @typedef {import("./protocol.js").ClientMsg} ClientMsg */
/** @typedef {import("./protocol.js").Command} Command */
/** @typedef {import("./protocol.js").Access} Access */
/** @typedef {import("./protocol.js").WelcomeMsg} WelcomeMsg */

/** @typedef {"control" | "view"} TokenKind */
/** @typedef {{kind: TokenKind, value: string}} Token */
/** @typedef {"connecting" | "online" | "offline" | "refused"} ConnState */

/**
 * A token the server refused in a hello.
 * @typedef {object} Refusal
 * @property {TokenKind} kind
 * @property {string} code
 * @property {string} message
 */

const PROTOCOL_VERSION = 1;
const COMMAND_TIMEOUT_MS = 8000;

/** @returns {number} The wall clock in µs since the Unix epoch. */
export function nowMicros() {
  return Math.round((performance.timeOrigin + performance.now()) * 1000);
}

/** A refusal or failure: `code` is the protocol's error code ("unauthorized", "forbidden", …). */
export class ServerError extends Error {
  /**
   * @param {string} code
   * @param {string} message
   */
  constructor(code, message) {
    super(message);
    this.code = code;
  }
}

export class Connection {
  /**
   * @param {string} url The websocket URL.
   * @param {() => Token[]} tokens The tokens to try in order (control first, then view).
   */
  constructor(url, tokens) {
    this.url = url;
    this.tokens = tokens;
    /** @type {ConnState} */
    this.state = "connecting";
    /** @type {string} */
    this.detail = "";
    /** @type {WelcomeMsg | null} */
    this.welcome = null;
    /** @type {Access | null} */
    this.access = null;
    /** @type {Token | null} The token the current connection presented. */
    this.token = null;
    /** @type {Refusal[]} Tokens refused since the last (re)start, in the order tried. */
    this.refusals = [];
    /** @type {Set<string>} Scenes kept subscribed across reconnects. */
    this.scenes = new Set();
    /** @type {Map<number, {resolve: (v: unknown) => void, reject: (e: ServerError) => void, timer: ReturnType<typeof setTimeout>}>} */
    this.pending = new Map();
    this.nextId = 1;
    this.nextPing = 1;
    this.backoff = 250;
    /** @type {number | null} Round trip of the last ping, ms. */
    this.rtt = null;
    this.frames = 0;
    /** Commands sent, by op (the tests check that nothing polls). */
    /** @type {Record<string, number>} */
    this.sent = {};
    this.tokenIndex = 0;
    this.stopped = true;
    /** @type {ReturnType<typeof setTimeout> | undefined} */
    this.timer = undefined;
    /** @type {WebSocket | null} */
    this.ws = null;
    /** Set between a welcome that ignored our token and the `unauthorized` error naming it. */
    this.awaitingTokenError = false;
    /** Why the current token does not let this page watch (it moves on to the next). */
    this.blockedWhy = "";
    /** @type {(msg: ServerMsg) => void} Every message after the welcome. */
    this.onMessage = () => {};
    /** @type {() => void} The state, access or refusals changed. */
    this.onState = () => {};
    setInterval(() => this.ping(), 1000);
  }

  /** Connects (again), trying every token from the first. */
  start() {
    this.stopped = false;
    this.tokenIndex = 0;
    this.refusals = [];
    this.backoff = 250;
    this.open();
  }

  /** Closes and reconnects at once (e.g. after the tokens changed). */
  restart() {
    this.drop();
    this.failPending(new ServerError("offline", "reconnecting"));
    this.start();
  }

  /** Forgets the current socket without reconnecting from its close. */
  drop() {
    clearTimeout(this.timer);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.onmessage = null;
      this.ws.close();
      this.ws = null;
    }
  }

  /**
   * @param {ConnState} state
   * @param {string} [detail]
   */
  setState(state, detail = "") {
    this.state = state;
    this.detail = detail;
    this.onState();
  }

  open() {
    clearTimeout(this.timer);
    const token = this.tokens()[this.tokenIndex] ?? null;
    this.token = token;
    this.welcome = null;
    this.access = null;
    this.awaitingTokenError = false;
    this.setState("connecting");
    /** @type {WebSocket} */
    let ws;
    try {
      ws = new WebSocket(this.url);
    } catch (e) {
      this.scheduleReconnect(String(e));
      return;
    }
    this.ws = ws;
    ws.onopen = () => {
      /** @type {ClientMsg} */
      const hello = { type: "hello", version: PROTOCOL_VERSION, encoding: "json", client: "posecast-dashboard" };
      if (token) hello.token = token.value;
      ws.send(JSON.stringify(hello));
    };
    ws.onmessage = (e) => {
      if (typeof e.data !== "string") return;
      /** @type {ServerMsg} */
      let msg;
      try {
        msg = JSON.parse(e.data);
      } catch {
        return;
      }
      if (this.welcome) this.handle(msg);
      else if (msg.type === "welcome") this.onWelcome(msg);
      else if (msg.type === "error" && this.awaitingTokenError && msg.code === "unauthorized") {
        // Why the token that did not let this page watch was refused: now the next one.
        this.tokenRefused(msg.message);
        this.nextToken(this.blockedWhy);
      } else if (msg.type === "error") this.refuseHello(msg.code, msg.message);
    };
    ws.onclose = () => {
      if (this.ws !== ws) return;
      this.ws = null;
      this.failPending(new ServerError("offline", "the connection closed"));
      if (!this.stopped) this.scheduleReconnect("connection lost");
    };
    ws.onerror = () => {};
  }

  /** @param {WelcomeMsg} msg */
  onWelcome(msg) {
    const access = msg.access ?? { view: true, control: false };
    if (this.token && !access.name) {
      // The server did not know the token; its `unauthorized` error (with the reason) follows.
      this.refusals.push({ kind: this.token.kind, code: "unauthorized", message: "the server does not know this token" });
      this.awaitingTokenError = true;
    }
    if (!access.view) {
      this.blockedWhy = this.token ? "no token lets this page watch" : "watching this server needs a view token";
      // With a refused token, its reason follows at once; move on then (or after a second).
      if (this.awaitingTokenError) this.timer = setTimeout(() => this.nextToken(this.blockedWhy), 1000);
      else this.nextToken(this.blockedWhy);
      return;
    }
    this.welcome = msg;
    this.access = access;
    this.backoff = 250;
    this.setState("online");
    for (const scene of this.scenes) this.send({ type: "subscribe", scene });
    this.ping();
  }

  /**
   * The server's reason for refusing the hello's token (the error after the welcome).
   * @param {string} message
   */
  tokenRefused(message) {
    this.awaitingTokenError = false;
    const last = this.refusals[this.refusals.length - 1];
    if (last) last.message = message;
  }

  /**
   * The hello itself was refused (an error before any welcome): try the next token, or stop.
   * @param {string} code
   * @param {string} message
   */
  refuseHello(code, message) {
    if (this.token) this.refusals.push({ kind: this.token.kind, code, message });
    this.nextToken(`${code}: ${message}`);
  }

  /**
   * Reconnects with the next token; with none left, stops until the tokens change.
   * @param {string} why
   */
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
    this.backoff = Math.min(this.backoff * 2, 5000);
    this.tokenIndex = 0;
    this.timer = setTimeout(() => {
      this.refusals = [];
      this.open();
    }, delay);
  }

  /** @param {ServerError} error */
  failPending(error) {
    for (const { reject, timer } of this.pending.values()) {
      clearTimeout(timer);
      reject(error);
    }
    this.pending.clear();
  }

  /**
   * Sends a message if the connection is up.
   * @param {ClientMsg} msg
   * @returns {boolean} Whether it was sent.
   */
  send(msg) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN && this.state === "online") {
      this.ws.send(JSON.stringify(msg));
      return true;
    }
    return false;
  }

  /** @param {ServerMsg} msg */
  handle(msg) {
    switch (msg.type) {
      case "frame":
        this.frames++;
        break;
      case "pong":
        this.rtt = (nowMicros() - msg.client_time_us) / 1000;
        break;
      case "ack":
      case "error": {
        const p = msg.id !== undefined ? this.pending.get(msg.id) : undefined;
        if (p && msg.id !== undefined) {
          this.pending.delete(msg.id);
          clearTimeout(p.timer);
          if (msg.type === "ack") p.resolve(msg.result ?? null);
          else p.reject(new ServerError(msg.code, msg.message));
          return;
        }
        if (msg.type === "error" && this.awaitingTokenError && msg.code === "unauthorized") {
          // The reason the hello's token was refused: keep it, it is not a failure now.
          this.tokenRefused(msg.message);
          this.onState();
          return;
        }
        break;
      }
    }
    this.onMessage(msg);
  }

  /**
   * Sends a command; resolves with its result or rejects with a ServerError.
   * @param {Command} command
   * @returns {Promise<unknown>}
   */
  command(command) {
    return new Promise((resolve, reject) => {
      const id = this.nextId++;
      if (!this.send({ type: "command", id, command })) {
        reject(new ServerError("offline", "not connected"));
        return;
      }
      this.sent[command.op] = (this.sent[command.op] ?? 0) + 1;
      const timer = setTimeout(() => {
        this.pending.delete(id);
        reject(new ServerError("timeout", `no answer to ${command.op} within ${COMMAND_TIMEOUT_MS / 1000} s`));
      }, COMMAND_TIMEOUT_MS);
      this.pending.set(id, { resolve, reject, timer });
    });
  }

  /**
   * Keeps `scene` subscribed (across reconnects) — and only it.
   * @param {string | null} scene
   */
  subscribeOnly(scene) {
    for (const s of this.scenes) {
      if (s !== scene) this.send({ type: "unsubscribe", scene: s });
    }
    const had = scene !== null && this.scenes.has(scene);
    this.scenes = new Set(scene ? [scene] : []);
    if (scene && !had) this.send({ type: "subscribe", scene });
  }

  /**
   * The server ended the subscription to `scene` (it was deleted): do not renew it.
   * @param {string} scene
   */
  forget(scene) {
    this.scenes.delete(scene);
  }

  ping() {
    if (document.hidden) return;
    this.send({ type: "ping", id: this.nextPing++ & 0xffffffff, client_time_us: nowMicros() });
  }
}
