// The websocket side of the dashboard (proto/PROTOCOL.md): hello with the JSON encoding and
// an optional token → welcome; subscribe; descriptions and JSON frames; ping/pong for the
// round trip; commands answered by ack/error. Reconnects with back-off (250 ms doubling to
// 5 s) and resubscribes; a hello refused for its token is not retried with the same token.

const PROTOCOL_VERSION = 1;
const COMMAND_TIMEOUT_MS = 8000;

export function nowMicros() {
  return Math.round((performance.timeOrigin + performance.now()) * 1000);
}

/** A refusal or failure: `code` is the protocol's error code ("unauthorized", "forbidden", …). */
export class ServerError extends Error {
  constructor(code, message) {
    super(message);
    this.code = code;
  }
}

export class Connection extends EventTarget {
  /** `tokens()` returns the list of tokens to try in order (e.g. control, then view). */
  constructor(url, tokens) {
    super();
    this.url = url;
    this.tokens = tokens;
    this.state = "connecting";
    this.access = null;
    this.welcome = null;
    this.refusal = null;
    this.scenes = new Set();
    this.pending = new Map();
    this.nextId = 1;
    this.nextPing = 1;
    this.backoff = 250;
    this.rtt = null;
    this.frames = 0;
    this.tokenIndex = 0;
    this.stopped = false;
    this.timer = null;
    this.pingTimer = setInterval(() => this.ping(), 1000);
  }

  start() {
    this.stopped = false;
    this.tokenIndex = 0;
    this.refusal = null;
    this.backoff = 250;
    this.open();
  }

  /** Closes and reconnects at once (e.g. after the tokens changed). */
  restart() {
    this.stopped = true;
    clearTimeout(this.timer);
    if (this.ws) {
      this.ws.onclose = null;
      this.ws.close();
      this.ws = null;
    }
    this.failPending(new ServerError("offline", "reconnecting"));
    this.start();
  }

  setState(state, detail = "") {
    this.state = state;
    this.dispatchEvent(new CustomEvent("state", { detail: { state, detail } }));
  }

  open() {
    clearTimeout(this.timer);
    const tokens = this.tokens();
    const token = tokens[this.tokenIndex] ?? null;
    this.usedToken = token;
    this.setState("connecting");
    let ws;
    try {
      ws = new WebSocket(this.url);
    } catch (e) {
      this.scheduleReconnect(String(e));
      return;
    }
    this.ws = ws;
    let welcomed = false;
    ws.onopen = () => {
      const hello = { type: "hello", version: PROTOCOL_VERSION, encoding: "json", client: "posecast-dashboard" };
      if (token) hello.token = token;
      ws.send(JSON.stringify(hello));
    };
    ws.onmessage = (e) => {
      if (typeof e.data !== "string") return;
      let msg;
      try {
        msg = JSON.parse(e.data);
      } catch {
        return;
      }
      if (!welcomed) {
        if (msg.type === "welcome") {
          welcomed = true;
          this.welcome = msg;
          this.access = msg.access ?? null;
          this.backoff = 250;
          this.setState("online");
          for (const scene of this.scenes) this.send({ type: "subscribe", scene });
          this.dispatchEvent(new CustomEvent("welcome", { detail: msg }));
          this.ping();
        } else if (msg.type === "error") {
          this.onRefused(msg);
        }
        return;
      }
      this.handle(msg);
    };
    ws.onclose = () => {
      if (this.ws !== ws) return;
      this.ws = null;
      this.failPending(new ServerError("offline", "the connection closed"));
      if (this.stopped) return;
      this.scheduleReconnect("connection lost");
    };
    ws.onerror = () => {};
  }

  onRefused(msg) {
    const refusal = { code: msg.code, message: msg.message, token: this.usedToken };
    if (msg.code === "unauthorized" || msg.code === "forbidden") {
      this.dispatchEvent(new CustomEvent("refused", { detail: refusal }));
      const tokens = this.tokens();
      if (this.tokenIndex + 1 < tokens.length) {
        // Try the next token (e.g. the view token after a refused control token).
        this.tokenIndex++;
        this.ws.onclose = null;
        this.ws.close();
        this.ws = null;
        this.open();
        return;
      }
      this.refusal = refusal;
      this.stopped = true;
      this.ws.onclose = null;
      this.ws.close();
      this.ws = null;
      this.setState("refused", `${msg.code}: ${msg.message}`);
      return;
    }
    this.dispatchEvent(new CustomEvent("refused", { detail: refusal }));
  }

  scheduleReconnect(reason) {
    this.setState("offline", reason);
    const delay = this.backoff;
    this.backoff = Math.min(this.backoff * 2, 5000);
    this.timer = setTimeout(() => this.open(), delay);
  }

  failPending(error) {
    for (const { reject, timer } of this.pending.values()) {
      clearTimeout(timer);
      reject(error);
    }
    this.pending.clear();
  }

  send(msg) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN && this.state === "online") {
      this.ws.send(JSON.stringify(msg));
      return true;
    }
    return false;
  }

  handle(msg) {
    switch (msg.type) {
      case "frame":
        this.frames++;
        this.dispatchEvent(new CustomEvent("frame", { detail: msg }));
        break;
      case "description":
        this.dispatchEvent(new CustomEvent("description", { detail: msg }));
        break;
      case "pong":
        this.rtt = (nowMicros() - msg.client_time_us) / 1000;
        this.dispatchEvent(new CustomEvent("pong", { detail: this.rtt }));
        break;
      case "ack":
      case "error": {
        const p = msg.id !== undefined ? this.pending.get(msg.id) : undefined;
        if (p) {
          this.pending.delete(msg.id);
          clearTimeout(p.timer);
          if (msg.type === "ack") p.resolve(msg.result ?? null);
          else p.reject(new ServerError(msg.code, msg.message));
        } else if (msg.type === "error" && this.usedToken && !this.access?.name && msg.code === "unauthorized") {
          // The server welcomes a hello with an unknown token as anonymous and then reports
          // the token: treat it as the token's refusal.
          this.onRefused(msg);
        } else if (msg.type === "error") {
          this.dispatchEvent(new CustomEvent("servererror", { detail: msg }));
        }
        break;
      }
      default:
        this.dispatchEvent(new CustomEvent(msg.type, { detail: msg }));
    }
  }

  /** Sends a command; resolves with its result or rejects with a ServerError. */
  command(command) {
    return new Promise((resolve, reject) => {
      const id = this.nextId++;
      if (!this.send({ type: "command", id, command })) {
        reject(new ServerError("offline", "not connected"));
        return;
      }
      const timer = setTimeout(() => {
        this.pending.delete(id);
        reject(new ServerError("timeout", `no answer to ${command.op} within ${COMMAND_TIMEOUT_MS / 1000} s`));
      }, COMMAND_TIMEOUT_MS);
      this.pending.set(id, { resolve, reject, timer });
    });
  }

  /** Keeps `scene` subscribed (across reconnects) — and only it. */
  subscribeOnly(scene) {
    for (const s of this.scenes) {
      if (s !== scene) this.send({ type: "unsubscribe", scene: s });
    }
    const had = this.scenes.has(scene);
    this.scenes = new Set(scene ? [scene] : []);
    if (scene && !had) this.send({ type: "subscribe", scene });
  }

  ping() {
    if (document.hidden) return;
    this.send({ type: "ping", id: this.nextPing++ & 0xffffffff, client_time_us: nowMicros() });
  }
}
