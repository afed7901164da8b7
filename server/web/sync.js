// @ts-check
// Keeps the store in step with the server. On every welcome the page asks for the scene list
// once (`watch_scenes`); from then on the server pushes each change (`scene_created`,
// `scene_deleted`, `avatar_changed`, `avatar_removed`) — nothing polls. The watched scene's
// descriptions and frames feed the preview; rigs' meshes are fetched once per description hash.

import { fetchMesh } from "./rest.js";
import { notice, describeError } from "./ui.js";

/** @typedef {import("./protocol.js").ServerMsg} ServerMsg */
/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./protocol.js").AssetInfo} AssetInfo */
/** @typedef {import("./store.js").Store} Store */
/** @typedef {import("./store.js").AvatarEntry} AvatarEntry */
/** @typedef {import("../sdk/posecast.js").Client} Connection */
/** @typedef {import("./viewer.js").Viewer} Viewer */

export class Sync {
  /**
   * @param {Store} store
   * @param {Connection} conn
   * @param {Viewer} viewer
   */
  constructor(store, conn, viewer) {
    this.store = store;
    this.conn = conn;
    this.viewer = viewer;
    /** @type {Map<string, Promise<import("./glb.js").Mesh>>} Description hash → its mesh. */
    this.meshes = new Map();
    /** @type {Promise<void> | null} */
    this.listing = null;
    /** @type {import("./protocol.js").WelcomeMsg | null} */
    this.welcomed = null;
    /** @type {ServerMsg[] | null} Changes that came before the answer to `watch_scenes`. */
    this.early = null;
    conn.on("state", () => this.onState());
    // The client's messages are the protocol's (frames decoded into the JSON frame's shape).
    conn.on("message", (msg) => this.onMessage(/** @type {ServerMsg} */ (/** @type {unknown} */ (msg))));
    viewer.onPick = (avatar) => this.select(avatar);
  }

  onState() {
    const c = this.conn;
    this.store.set({
      conn: c.state,
      connDetail: c.detail,
      transport: c.transport,
      transportNote: c.webtransportFailure,
      access: c.access,
      refusals: [...c.refusals],
      tickRate: c.welcome?.tick_rate ?? this.store.get().tickRate,
    });
    if (c.state === "online" && c.welcome && c.welcome !== this.welcomed) {
      // A new connection (first, or after a reconnect): the list once, then changes.
      this.welcomed = c.welcome;
      this.early = [];
      c.send({ type: "watch_scenes" });
      this.refreshAssets();
    }
  }

  /** Lists the rigs again (at connect, after an upload, or when a change names one unknown). */
  refreshAssets() {
    if (this.listing) return this.listing;
    this.listing = this.conn
      .command({ op: "list_assets" })
      .then((assets) => this.store.set({ assets: /** @type {AssetInfo[]} */ (assets ?? []) }))
      .catch((e) => {
        if (e.code !== "offline") notice(`Listing the rigs failed — ${describeError(e)}`, "error");
      })
      .finally(() => (this.listing = null));
    return this.listing;
  }

  /** @param {ServerMsg} msg */
  onMessage(msg) {
    const change = ["scene_created", "scene_deleted", "avatar_changed", "avatar_removed"].includes(msg.type);
    if (change && this.early) {
      // Made while the list was being made: applied after it (each carries whole states).
      this.early.push(msg);
      return;
    }
    const store = this.store;
    const scenes = store.get().scenes ?? new Map();
    switch (msg.type) {
      case "scenes": {
        /** @type {Map<string, Map<string, AvatarEntry>>} */
        const all = new Map();
        // The list does not say its tick: its clip times hold at the scene's next frame.
        for (const s of msg.scenes) {
          all.set(s.scene, new Map(s.avatars.map((a) => [a.avatar, { state: a, seq: null }])));
        }
        store.set({ scenes: all, viewers: new Map(msg.scenes.map((s) => [s.scene, s.viewers ?? []])) });
        const watched = store.get().watched;
        if (watched && !all.has(watched)) {
          // Gone while the page was away (a restart without it).
          this.conn.forget(watched);
          this.watch(null);
        }
        /** @type {ServerMsg[]} */
        const early = this.early ?? [];
        this.early = null;
        for (const m of early) this.onMessage(m);
        this.keepSelection();
        break;
      }
      case "viewers": {
        const viewers = store.get().viewers;
        viewers.set(msg.scene, msg.viewers);
        store.set({ viewers });
        break;
      }
      case "scene_created":
        if (!scenes.has(msg.scene)) scenes.set(msg.scene, new Map());
        store.set({ scenes });
        break;
      case "scene_deleted":
        scenes.delete(msg.scene);
        this.conn.forget(msg.scene);
        store.set({ scenes });
        if (store.get().watched === msg.scene) this.watch(null);
        this.keepSelection();
        break;
      case "avatar_changed": {
        let avatars = scenes.get(msg.scene);
        if (!avatars) scenes.set(msg.scene, (avatars = new Map()));
        avatars.set(msg.avatar.avatar, { state: msg.avatar, seq: msg.seq });
        store.set({ scenes });
        const known = store.get().assets.find((x) => x.name === (msg.avatar.clip_asset ?? msg.avatar.asset));
        if (!known || (msg.avatar.clip && !known.clips.some((c) => c.name === msg.avatar.clip))) {
          this.refreshAssets(); // a rig or clip added since (an upload, a recording)
        }
        this.keepSelection();
        break;
      }
      case "avatar_removed": {
        scenes.get(msg.scene)?.delete(msg.avatar);
        store.get().descriptions.delete(msg.avatar);
        store.get().poses.delete(msg.avatar);
        this.viewer.removeAvatar(msg.avatar);
        if (store.get().focus === msg.avatar) store.set({ focus: null });
        store.set({ scenes });
        store.touch("descriptions");
        this.keepSelection();
        break;
      }
      case "description":
        if (msg.scene !== store.get().watched) break;
        store.get().descriptions.set(msg.avatar.id, msg.avatar);
        store.touch("descriptions");
        this.show(msg.avatar);
        break;
      case "frame": {
        const poses = store.get().poses;
        const shown = msg.scene === this.viewer.scene;
        for (const pose of msg.avatars) {
          poses.set(pose.avatar, pose);
          if (shown) this.viewer.setPose(pose.avatar, pose);
        }
        for (const entry of scenes.get(msg.scene)?.values() ?? []) entry.seq ??= msg.seq;
        if (shown) store.set({ frame: { scene: msg.scene, seq: msg.seq } });
        break;
      }
      case "unsubscribed":
        // Deleted (`scene_deleted` follows) or the server shutting down: a reconnect renews it.
        break;
      case "error":
        notice(`${msg.code}: ${msg.message}`, "error");
        break;
    }
  }

  /**
   * Shows a described avatar in the preview and fetches its rig's mesh (once per rig).
   * @param {AvatarDescription} desc
   */
  show(desc) {
    this.viewer.setAvatar(desc);
    if (!desc.mesh_url) return;
    let mesh = this.meshes.get(desc.hash);
    if (!mesh) {
      mesh = fetchMesh(desc.mesh_url);
      this.meshes.set(desc.hash, mesh);
      mesh.catch(() => this.meshes.delete(desc.hash));
    }
    mesh.then(
      (m) => this.viewer.setMesh(desc.hash, m),
      (e) => notice(`Mesh of ${desc.id} not shown (skeleton only): ${e.message}`, "error"),
    );
  }

  /**
   * Watches a scene: the preview shows its avatars (and the page subscribes to it).
   * @param {string | null} scene
   */
  watch(scene) {
    const store = this.store;
    if (store.get().watched === scene) return;
    store.get().descriptions.clear();
    store.set({ watched: scene, frame: null, focus: null });
    store.touch("descriptions");
    this.subscribeOnly(scene);
    this.viewer.setScene(scene);
  }

  /**
   * Keeps `scene` subscribed (across reconnects) — and only it.
   * @param {string | null} scene
   */
  subscribeOnly(scene) {
    for (const s of [...this.conn.subscriptions.keys()]) if (s !== scene) this.conn.unsubscribe(s);
    if (scene && !this.conn.subscriptions.has(scene)) this.conn.subscribe(scene);
  }

  /**
   * Picks the avatar the page controls, and watches its scene.
   * @param {string | null} avatar
   */
  select(avatar) {
    const entry = this.store.avatar(avatar);
    if (entry) this.watch(entry.state.scene);
    if (this.store.get().selected !== avatar) this.store.set({ selected: entry ? avatar : null, joint: null });
    this.viewer.select(entry ? avatar : null);
  }

  /** After a change: the selected avatar still exists, or another is picked — of the watched scene first. */
  keepSelection() {
    const { scenes, selected, watched } = this.store.get();
    if (!scenes || this.store.avatar(selected)) return;
    /** @param {Map<string, unknown> | undefined} m */
    const first = (m) => m?.keys().next().value ?? null;
    const here = watched ? first(scenes.get(watched)) : null;
    if (here || (watched && scenes.has(watched))) {
      // An empty watched scene stays watched: avatars are about to be added to it.
      this.select(here);
      return;
    }
    for (const avatars of scenes.values()) {
      const a = first(avatars);
      if (a) {
        this.select(a);
        return;
      }
    }
    this.select(null);
    this.watch(first(scenes));
  }
}
