// @ts-check
// The dashboard's one store: what the page knows of the server and what the user picked.
// Panels read it and subscribe to the keys they show; only sync.js (server messages) and the
// panels' own actions write it. Notifications are batched per task: a listener runs once
// however many of its keys changed together.

/** @typedef {import("./protocol.js").AvatarState} AvatarState */
/** @typedef {import("./protocol.js").AssetInfo} AssetInfo */
/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./protocol.js").AvatarPose} AvatarPose */
/** @typedef {import("./protocol.js").Access} Access */
/** @typedef {import("./protocol.js").Viewer} Viewer */
/** @typedef {import("../sdk/posecast.js").ConnectionState} ConnState */
/** @typedef {import("../sdk/posecast.js").Refusal} Refusal */

/**
 * An avatar as last pushed: its state holds at the scene's tick `seq` (null: listed, not
 * pushed — at the scene's next frame).
 * @typedef {object} AvatarEntry
 * @property {AvatarState} state
 * @property {number | null} seq
 */

/**
 * @typedef {object} State
 * @property {ConnState} conn
 * @property {string} connDetail
 * @property {"websocket" | "webtransport" | null} transport The connection's transport.
 * @property {string | null} transportNote Why WebTransport was not used although offered.
 * @property {Access | null} access What the connection may do (null before a welcome).
 * @property {Refusal[]} refusals Tokens the server refused, and why.
 * @property {number} tickRate Ticks per second (from the welcome).
 * @property {Map<string, Map<string, AvatarEntry>> | null} scenes Scene → avatar → entry (null until listed).
 * @property {Map<string, Viewer[]>} viewers Scene → who watches it (presence), by token name.
 * @property {AssetInfo[]} assets
 * @property {Map<string, AvatarDescription>} descriptions Avatar → rig, for the watched scene.
 * @property {Map<string, AvatarPose>} poses Avatar → newest pose (updated without notifying).
 * @property {{scene: string, seq: number} | null} frame The newest frame of the watched scene.
 * @property {string | null} watched The scene the preview shows (and the page subscribes to).
 * @property {string | null} selected The avatar the page controls (in the watched scene).
 * @property {string | null} joint The selected joint.
 * @property {string | null} focus The avatar the camera follows (null: the whole scene).
 * @property {string | null} driving The avatar this page drives live (drive.js).
 */

/** @typedef {keyof State} Key */

export class Store {
  constructor() {
    /** @type {State} */
    this.state = {
      conn: "connecting",
      connDetail: "",
      transport: null,
      transportNote: null,
      access: null,
      refusals: [],
      tickRate: 60,
      scenes: null,
      viewers: new Map(),
      assets: [],
      descriptions: new Map(),
      poses: new Map(),
      frame: null,
      watched: null,
      selected: null,
      joint: null,
      focus: null,
      driving: null,
    };
    /** @type {{keys: Set<Key>, fn: (s: State) => void}[]} */
    this.listeners = [];
    /** @type {Set<Key>} */
    this.changed = new Set();
  }

  /** @returns {Readonly<State>} */
  get() {
    return this.state;
  }

  /**
   * Sets some keys and notifies their listeners.
   * @param {Partial<State>} patch
   */
  set(patch) {
    Object.assign(this.state, patch);
    this.touch(.../** @type {Key[]} */ (Object.keys(patch)));
  }

  /**
   * Notifies the listeners of keys whose value was changed in place (a Map).
   * @param {...Key} keys
   */
  touch(...keys) {
    const first = this.changed.size === 0;
    for (const k of keys) this.changed.add(k);
    if (first && keys.length) queueMicrotask(() => this.flush());
  }

  flush() {
    const changed = this.changed;
    this.changed = new Set();
    for (const l of this.listeners) {
      for (const k of changed) {
        if (l.keys.has(k)) {
          l.fn(this.state);
          break;
        }
      }
    }
  }

  /**
   * Calls `fn` now and whenever one of `keys` changes.
   * @param {Key[]} keys
   * @param {(s: State) => void} fn
   */
  on(keys, fn) {
    this.listeners.push({ keys: new Set(keys), fn });
    fn(this.state);
  }

  /**
   * An avatar's entry, wherever it is.
   * @param {string | null} id
   * @returns {AvatarEntry | null}
   */
  avatar(id) {
    if (id === null) return null;
    for (const avatars of this.state.scenes?.values() ?? []) {
      const a = avatars.get(id);
      if (a) return a;
    }
    return null;
  }

  /** @returns {AvatarEntry | null} The selected avatar's entry. */
  selectedAvatar() {
    return this.avatar(this.state.selected);
  }

  /**
   * The duration of the clip an avatar plays (seconds), from the listed assets; 0 when unknown.
   * @param {AvatarState} a
   * @returns {number}
   */
  clipDuration(a) {
    if (!a.clip) return 0;
    const asset = this.state.assets.find((x) => x.name === (a.clip_asset ?? a.asset));
    return asset?.clips.find((c) => c.name === a.clip)?.duration ?? 0;
  }
}

/**
 * An avatar's clip time at scene tick `seq` (seconds): its state's time advanced by the ticks
 * since the state's own tick at its speed, wrapped (looping) or clamped to the clip — the
 * server's own clock rule (proto/PROTOCOL.md, "Scene and avatar changes").
 * @param {AvatarEntry} entry
 * @param {number} seq
 * @param {number} tickRate
 * @param {number} duration The clip's length (0: unknown, no wrapping).
 * @returns {number}
 */
export function clipTimeAt(entry, seq, tickRate, duration) {
  const a = entry.state;
  if (!a.clip) return 0;
  const t = a.paused || entry.seq === null ? a.time : a.time + ((seq - entry.seq) / tickRate) * a.speed;
  if (!(duration > 0)) return Math.max(0, t);
  if (a.looping) return ((t % duration) + duration) % duration;
  return Math.min(duration, Math.max(0, t));
}

/**
 * How far a cross-fade is at scene tick `seq`, 0–1, or null when none is running.
 * @param {AvatarEntry} entry
 * @param {number} seq
 * @param {number} tickRate
 * @returns {number | null}
 */
export function fadeAt(entry, seq, tickRate) {
  const f = entry.state.fade;
  if (!f || !(f.duration > 0)) return null;
  const w = (f.elapsed + (seq - (entry.seq ?? seq)) / tickRate) / f.duration;
  return w >= 1 ? null : Math.max(0, w);
}
