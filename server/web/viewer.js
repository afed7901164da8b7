// @ts-check
// The live 3D preview of every avatar of the watched scene, each where it stands: forward
// kinematics (fk.js) from the avatar description's rest transforms, the streamed local
// rotations and the frame's placement (W_root = P · D_root), then either WebGL2 (skinned mesh
// in the vertex shader with joint matrices M_j = W_j · B_j⁻¹ from a float texture, skeleton on
// top) or, when WebGL2 is unavailable, a 2D-canvas skeleton. Orbit with the mouse (drag,
// wheel) or the keyboard (arrows, +/-, Home) while the canvas has focus; a click on an avatar
// picks it. The camera frames the whole scene, or follows one avatar (`focusOn`).

import { multiply, perspective, lookAt, transformPoint } from "../sdk/posecast.js";
import { forwardKinematics, jointPositions } from "../sdk/posecast.js";
import { BACKGROUND, render2d, rgb } from "./draw.js";
import { GlRenderer } from "./draw-gl.js";

/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./protocol.js").AvatarPose} AvatarPose */
/** @typedef {import("./protocol.js").Vec3} Vec3 */
/** @typedef {import("./glb.js").Mesh} Mesh */
/** @typedef {import("./draw.js").Shown} Shown */
/** @typedef {import("./draw.js").Posed} Posed */

/**
 * Per avatar drawn: its root joint in world space and on the canvas (device pixels).
 * @typedef {object} Drawn
 * @property {string} avatar
 * @property {Vec3} root
 * @property {[number, number] | null} screen
 */

/** A click moving less than this (CSS px) picks rather than orbits. */
const CLICK_SLOP = 5;
/** Farthest a click may be from an avatar's nearest joint to pick it (CSS px). */
const PICK_RADIUS = 40;

export class Viewer {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {{prefer2d?: boolean}} [options]
   */
  constructor(canvas, { prefer2d = false } = {}) {
    this.canvas = canvas;
    /** @type {string | null} The scene whose avatars are shown. */
    this.scene = null;
    /** @type {string | null} The avatar the page edits (drawn highlighted). */
    this.selected = null;
    /** @type {string | null} The avatar the camera follows (null: the whole scene). */
    this.focus = null;
    /** @type {Map<string, Shown>} */
    this.avatars = new Map();
    /** @type {Drawn[]} Per avatar drawn last. */
    this.drawn = [];
    /** @type {{id: string, points: [number, number][]}[]} Projected joints of the last render, for picking. */
    this.picks = [];
    /** @type {(avatar: string) => void} Called when a click picks an avatar. */
    this.onPick = () => {};
    this.showSkeleton = true;
    this.showMesh = true;
    this.framed = false;
    /** Whether the user aimed the camera (orbit, zoom, pan) since it was last framed. */
    this.moved = false;
    this.yaw = 0.5;
    this.pitch = 0.2;
    this.distance = 3;
    /** @type {Vec3} */
    this.target = [0, 0.9, 0];
    this.renderedFrames = 0;
    /** Draw only when something changed: a new pose, mesh, avatar, camera move or resize. */
    this.dirty = true;
    /** @type {GlRenderer | null} */
    this.webgl = null;
    /** @type {CanvasRenderingContext2D | null} */
    this.ctx = null;
    /** @type {"webgl2" | "2d"} */
    this.mode = "2d";
    this.resetCamera();
    const gl = prefer2d ? null : canvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true });
    if (gl) {
      try {
        this.webgl = new GlRenderer(gl, canvas);
        this.mode = "webgl2";
      } catch (e) {
        console.warn("WebGL2 set-up failed, using the 2D preview:", e);
      }
    }
    if (!this.webgl) this.ctx = canvas.getContext("2d");
    this.installControls();
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
    const loop = () => {
      if (this.dirty) {
        this.dirty = false;
        this.render();
      }
      requestAnimationFrame(loop);
    };
    requestAnimationFrame(loop);
  }

  resetCamera() {
    this.dirty = true;
    this.yaw = 0.5;
    this.pitch = 0.2;
    this.distance = 3;
    this.target = [0, 0.9, 0];
    this.framed = false;
    this.moved = false;
  }


  installControls() {
    const c = this.canvas;
    /** @type {{x: number, y: number, startX: number, startY: number, pan: boolean} | null} */
    let drag = null;
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, startX: e.clientX, startY: e.clientY, pan: e.button === 2 || e.shiftKey };
      c.setPointerCapture(e.pointerId);
      c.focus();
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (Math.hypot(e.clientX - drag.startX, e.clientY - drag.startY) < CLICK_SLOP) return;
      if (drag.pan) {
        this.target[1] += dy * this.distance * 0.002;
        this.moved = true;
        this.dirty = true;
      } else {
        this.orbit(-dx * 0.01, dy * 0.01);
      }
    });
    c.addEventListener("pointerup", (e) => {
      if (drag && Math.hypot(e.clientX - drag.startX, e.clientY - drag.startY) < CLICK_SLOP) {
        const r = c.getBoundingClientRect();
        const picked = this.pick(e.clientX - r.left, e.clientY - r.top);
        if (picked) this.onPick(picked);
      }
      drag = null;
    });
    c.addEventListener("pointercancel", () => (drag = null));
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom(Math.exp(e.deltaY * 0.001));
    }, { passive: false });
    c.addEventListener("keydown", (e) => {
      const step = e.shiftKey ? 0.3 : 0.1;
      /** @type {Record<string, () => void>} */
      const keys = {
        ArrowLeft: () => this.orbit(step, 0),
        ArrowRight: () => this.orbit(-step, 0),
        ArrowUp: () => this.orbit(0, step),
        ArrowDown: () => this.orbit(0, -step),
        "+": () => this.zoom(0.9),
        "=": () => this.zoom(0.9),
        PageUp: () => this.zoom(0.9),
        "-": () => this.zoom(1.1),
        PageDown: () => this.zoom(1.1),
        Home: () => this.focusOn(null),
        "0": () => this.focusOn(null),
      };
      const f = keys[e.key];
      if (f) {
        e.preventDefault();
        f();
      }
    });
  }

  /**
   * The avatar whose drawn joint is nearest the canvas point (CSS px), within PICK_RADIUS.
   * @param {number} x
   * @param {number} y
   * @returns {string | null}
   */
  pick(x, y) {
    const scale = this.canvas.width / Math.max(1, this.canvas.clientWidth);
    let best = null, bestD = PICK_RADIUS * scale;
    for (const { id, points } of this.picks) {
      for (const [px, py] of points) {
        const d = Math.hypot(px - x * scale, py - y * scale);
        if (d < bestD) {
          bestD = d;
          best = id;
        }
      }
    }
    return best;
  }

  /**
   * @param {number} dyaw
   * @param {number} dpitch
   */
  orbit(dyaw, dpitch) {
    this.dirty = true;
    this.moved = true;
    this.yaw += dyaw;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dpitch));
  }

  /** @param {number} factor */
  zoom(factor) {
    this.dirty = true;
    this.moved = true;
    this.distance = Math.max(0.2, Math.min(100, this.distance * factor));
  }

  resize() {
    const dpr = Math.min(window.devicePixelRatio || 1, 2);
    const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
    const h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
      this.dirty = true;
    }
  }

  /**
   * Shows the avatars of `scene` (the watched one) from now on; forgets every other's.
   * @param {string | null} scene
   */
  setScene(scene) {
    if (this.scene === scene) return;
    this.scene = scene;
    this.avatars.clear();
    this.focus = null;
    this.resetCamera();
  }

  /**
   * The avatar the page edits: drawn highlighted.
   * @param {string | null} id
   */
  select(id) {
    this.selected = id;
    this.dirty = true;
  }

  /**
   * Points the camera at one avatar and follows it as it moves (null: frames the whole scene
   * once, then stays).
   * @param {string | null} id
   */
  focusOn(id) {
    this.focus = id;
    this.framed = false;
    this.moved = false;
    this.dirty = true;
  }

  /** @returns {AvatarDescription | null} The selected avatar's rig. */
  get desc() {
    return this.avatars.get(this.selected ?? "")?.desc ?? null;
  }

  /** @returns {Mesh | null} The selected avatar's mesh, once loaded. */
  get mesh() {
    return this.avatars.get(this.selected ?? "")?.mesh ?? null;
  }

  /**
   * An avatar of the scene (or a new rig for it): a new rig drops pose and mesh.
   * @param {AvatarDescription} desc
   */
  setAvatar(desc) {
    const old = this.avatars.get(desc.id);
    const same = old?.desc.hash === desc.hash;
    this.avatars.set(desc.id, { desc, pose: same ? old.pose : null, mesh: same ? old.mesh : null });
    // An avatar added while the page watches the whole scene: frame the scene again with it,
    // unless the user has aimed the camera since it was last framed.
    if (!old && this.focus === null && !this.moved) this.framed = false;
    this.dirty = true;
  }

  /** @param {string} id */
  removeAvatar(id) {
    if (this.avatars.delete(id)) this.dirty = true;
    if (this.focus === id) this.focusOn(null);
  }

  /**
   * A streamed pose (with its placement); ignored when it is of another rig than described.
   * @param {string} id
   * @param {AvatarPose} pose
   */
  setPose(id, pose) {
    const a = this.avatars.get(id);
    if (!a || pose.hash !== a.desc.hash) return;
    a.pose = pose;
    this.dirty = true;
  }

  /**
   * The mesh of every avatar of the rig whose description hash is `hash`.
   * @param {string} hash
   * @param {Mesh} mesh
   */
  setMesh(hash, mesh) {
    for (const a of this.avatars.values()) if (a.desc.hash === hash) a.mesh = mesh;
    this.dirty = true;
  }

  /**
   * The box around `points`, or null when empty.
   * @param {Vec3[]} points
   * @returns {{center: Vec3, size: number} | null}
   */
  static bounds(points) {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const p of points) for (let i = 0; i < 3; i++) {
      lo[i] = Math.min(lo[i], p[i]);
      hi[i] = Math.max(hi[i], p[i]);
    }
    if (!Number.isFinite(lo[0])) return null;
    return {
      center: [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2],
      size: Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.2),
    };
  }

  /**
   * Aims the camera: at the focused avatar every render (it may walk away), or once at the
   * whole scene.
   * @param {Posed[]} shown
   */
  aim(shown) {
    const followed = this.focus !== null ? shown.find((s) => s.id === this.focus) : undefined;
    if (followed) {
      const b = Viewer.bounds(followed.points);
      if (!b) return;
      this.target = b.center;
      if (!this.framed) this.distance = b.size * 1.9;
      this.framed = true;
      return;
    }
    if (this.framed) return;
    const b = Viewer.bounds(shown.flatMap((s) => s.points));
    if (!b) return;
    if (!this.moved) {
      this.target = b.center;
      this.distance = b.size * 1.9;
    }
    // Framed for good once every avatar is posed: one whose first frame has not come yet (it
    // was just added) is framed with the others when it comes.
    this.framed = this.moved || shown.length >= this.avatars.size;
  }

  /** @returns {{target: Vec3, distance: number, focus: string | null}} The camera, for the tests. */
  get camera() {
    return { target: [...this.target], distance: this.distance, focus: this.focus };
  }

  /** @returns {Float32Array} */
  viewProj() {
    const aspect = this.canvas.width / this.canvas.height;
    const cp = Math.cos(this.pitch);
    const eye = [
      this.target[0] + this.distance * cp * Math.sin(this.yaw),
      this.target[1] + this.distance * Math.sin(this.pitch),
      this.target[2] + this.distance * cp * Math.cos(this.yaw),
    ];
    const proj = perspective(0.8, aspect, this.distance * 0.02, this.distance * 20 + 10);
    return multiply(new Float32Array(16), proj, lookAt(eye, this.target, [0, 1, 0]));
  }

  render() {
    // Only posed avatars: before its first frame an avatar's placement is unknown.
    /** @type {Posed[]} */
    const shown = [];
    for (const [id, a] of this.avatars) {
      if (!a.pose) continue;
      const worlds = forwardKinematics(a.desc, a.pose);
      shown.push({ id, a, worlds, points: jointPositions(worlds) });
    }
    if (!shown.length) {
      this.clear();
      this.drawn = [];
      this.picks = [];
      return;
    }
    this.aim(shown);
    const vp = this.viewProj();
    const style = { selected: this.selected, showMesh: this.showMesh, showSkeleton: this.showSkeleton, distance: this.distance };
    if (this.webgl) this.webgl.render(vp, shown, style);
    else if (this.ctx) render2d(this.ctx, shown, style, (p) => this.project(vp, p));
    this.drawn = shown.map(({ id, a, points }) => {
      const root = points[Math.max(0, a.desc.parents.findIndex((p) => p < 0))];
      return { avatar: id, root, screen: this.project(vp, root) };
    });
    this.picks = shown.map(({ id, points }) => ({
      id,
      points: /** @type {[number, number][]} */ (points.map((p) => this.project(vp, p)).filter((p) => p !== null)),
    }));
    this.renderedFrames++;
  }

  /**
   * Canvas pixel of world point `p`, or null behind the camera.
   * @param {Float32Array} vp
   * @param {Vec3} p
   * @returns {[number, number] | null}
   */
  project(vp, p) {
    const [x, y, , w] = transformPoint(vp, p);
    if (w <= 1e-6) return null;
    return [(x / w * 0.5 + 0.5) * this.canvas.width, (1 - (y / w * 0.5 + 0.5)) * this.canvas.height];
  }

  clear() {
    if (this.webgl) {
      this.webgl.clear();
    } else if (this.ctx) {
      this.ctx.fillStyle = rgb(BACKGROUND);
      this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    }
  }








}

