// @ts-check
// The live 3D preview of every avatar of the watched scene, each where it stands: forward
// kinematics (fk.js) from the avatar description's rest transforms, the streamed local
// rotations and the frame's placement (W_root = P · D_root), then either WebGL2 (skinned mesh
// in the vertex shader with joint matrices M_j = W_j · B_j⁻¹ from a float texture, skeleton on
// top) or, when WebGL2 is unavailable, a 2D-canvas skeleton. Orbit with the mouse (drag,
// wheel) or the keyboard (arrows, +/-, Home) while the canvas has focus; a click on an avatar
// picks it. The camera frames the whole scene, or follows one avatar (`focusOn`).

import { multiply, perspective, lookAt, transformPoint } from "./math.js";
import { forwardKinematics, jointPositions } from "./fk.js";

/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./protocol.js").AvatarPose} AvatarPose */
/** @typedef {import("./protocol.js").Vec3} Vec3 */
/** @typedef {import("./glb.js").Mesh} Mesh */
/** @typedef {{vao: WebGLVertexArrayObject, indexed: boolean, count: number}} GpuPrimitive */
/** @typedef {{desc: AvatarDescription, pose: AvatarPose | null, mesh: Mesh | null}} Shown */
/** @typedef {{id: string, a: Shown, worlds: Float32Array, points: Vec3[]}} Posed */
/** @typedef {[Vec3, Vec3, Vec3]} Line from, to, colour */

/**
 * Per avatar drawn: its root joint in world space and on the canvas (device pixels).
 * @typedef {object} Drawn
 * @property {string} avatar
 * @property {Vec3} root
 * @property {[number, number] | null} screen
 */

export const BACKGROUND = [0.106, 0.118, 0.141];
/** @type {Vec3} */
const GRID_COLOR = [0.2, 0.22, 0.26];
/** @type {Vec3} */
const BONE_COLOR = [1.0, 0.62, 0.11];
/** @type {Vec3} */
const JOINT_COLOR = [1.0, 0.85, 0.4];
/** @type {Vec3} */
const SELECTED_BONE_COLOR = [0.35, 0.85, 1.0];
/** @type {Vec3} */
const MESH_COLOR = [0.62, 0.7, 0.8];
/** @type {Vec3} */
const SELECTED_MESH_COLOR = [0.7, 0.8, 0.62];
/** A click moving less than this (CSS px) picks rather than orbits. */
const CLICK_SLOP = 5;
/** Farthest a click may be from an avatar's nearest joint to pick it (CSS px). */
const PICK_RADIUS = 40;

const LINE_VS = `#version 300 es
layout(location = 0) in vec3 aPos;
layout(location = 1) in vec3 aColor;
uniform mat4 uViewProj;
uniform float uPointSize;
out vec3 vColor;
void main() {
  vColor = aColor;
  gl_Position = uViewProj * vec4(aPos, 1.0);
  gl_PointSize = uPointSize;
}`;
const LINE_FS = `#version 300 es
precision mediump float;
in vec3 vColor;
out vec4 color;
void main() { color = vec4(vColor, 1.0); }`;
const SKIN_VS = `#version 300 es
layout(location = 0) in vec3 aPos;
layout(location = 1) in vec3 aNormal;
layout(location = 2) in uvec4 aJoints;
layout(location = 3) in vec4 aWeights;
uniform mat4 uViewProj;
uniform highp sampler2D uJoints;
out vec3 vNormal;
mat4 jointMatrix(uint j) {
  int x = int(j) * 4;
  return mat4(texelFetch(uJoints, ivec2(x, 0), 0), texelFetch(uJoints, ivec2(x + 1, 0), 0),
              texelFetch(uJoints, ivec2(x + 2, 0), 0), texelFetch(uJoints, ivec2(x + 3, 0), 0));
}
void main() {
  mat4 m = aWeights.x * jointMatrix(aJoints.x) + aWeights.y * jointMatrix(aJoints.y)
         + aWeights.z * jointMatrix(aJoints.z) + aWeights.w * jointMatrix(aJoints.w);
  vNormal = mat3(m) * aNormal;
  gl_Position = uViewProj * (m * vec4(aPos, 1.0));
}`;
const SKIN_FS = `#version 300 es
precision mediump float;
in vec3 vNormal;
uniform vec3 uBase;
out vec4 color;
void main() {
  vec3 n = normalize(vNormal);
  float d = max(dot(n, normalize(vec3(0.4, 0.8, 0.6))), 0.0);
  float back = max(dot(n, normalize(vec3(-0.5, 0.2, -0.7))), 0.0);
  vec3 base = uBase;
  color = vec4(base * (0.35 + 0.65 * d) + vec3(0.10, 0.12, 0.16) * back, 1.0);
}`;

/**
 * @param {WebGL2RenderingContext} gl
 * @param {string} vs
 * @param {string} fs
 * @returns {WebGLProgram}
 */
function compile(gl, vs, fs) {
  const program = gl.createProgram();
  if (!program) throw new Error("no WebGL program");
  for (const [type, src] of /** @type {[number, string][]} */ ([[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]])) {
    const s = gl.createShader(type);
    if (!s) throw new Error("no WebGL shader");
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s) ?? "shader did not compile");
    gl.attachShader(program, s);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program) ?? "program did not link");
  return program;
}

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
    /** @type {Map<string, {mesh: Mesh, primitives: GpuPrimitive[]}>} Description hash → mesh uploaded once per rig. */
    this.meshGpu = new Map();
    /** @type {Drawn[]} Per avatar drawn last. */
    this.drawn = [];
    /** @type {{id: string, points: [number, number][]}[]} Projected joints of the last render, for picking. */
    this.picks = [];
    /** @type {(avatar: string) => void} Called when a click picks an avatar. */
    this.onPick = () => {};
    this.showSkeleton = true;
    this.showMesh = true;
    this.framed = false;
    this.yaw = 0.5;
    this.pitch = 0.2;
    this.distance = 3;
    /** @type {Vec3} */
    this.target = [0, 0.9, 0];
    this.renderedFrames = 0;
    /** Draw only when something changed: a new pose, mesh, avatar, camera move or resize. */
    this.dirty = true;
    /** @type {WebGL2RenderingContext | null} */
    this.gl = null;
    /** @type {CanvasRenderingContext2D | null} */
    this.ctx = null;
    /** @type {"webgl2" | "2d"} */
    this.mode = "2d";
    this.resetCamera();
    const gl = prefer2d ? null : canvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true });
    if (gl) {
      try {
        this.initGl(gl);
        this.mode = "webgl2";
      } catch (e) {
        console.warn("WebGL2 set-up failed, using the 2D preview:", e);
        this.gl = null;
      }
    }
    if (!this.gl) {
      this.ctx = canvas.getContext("2d");
      this.mode = "2d";
    }
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
  }

  /** @param {WebGL2RenderingContext} gl */
  initGl(gl) {
    this.gl = gl;
    this.lineProgram = compile(gl, LINE_VS, LINE_FS);
    this.skinProgram = compile(gl, SKIN_VS, SKIN_FS);
    this.lineVao = gl.createVertexArray();
    this.lineBuffer = gl.createBuffer();
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuffer);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 24, 0);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribPointer(1, 3, gl.FLOAT, false, 24, 12);
    gl.bindVertexArray(null);
    this.jointTexture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.jointTexture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.canvas.addEventListener("webglcontextlost", (e) => e.preventDefault());
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
    this.yaw += dyaw;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dpitch));
  }

  /** @param {number} factor */
  zoom(factor) {
    this.dirty = true;
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
    this.target = b.center;
    this.distance = b.size * 1.9;
    this.framed = true;
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
    if (this.gl) this.renderGl(vp, shown);
    else this.render2d(vp, shown);
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
    if (this.gl) {
      const gl = this.gl;
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.clearColor(BACKGROUND[0], BACKGROUND[1], BACKGROUND[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    } else if (this.ctx) {
      this.ctx.fillStyle = rgb(BACKGROUND);
      this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    }
  }

  /** @returns {Line[]} */
  gridLines() {
    /** @type {Line[]} */
    const lines = [];
    const half = Math.max(2, Math.ceil(this.distance));
    const y = 0;
    for (let i = -half; i <= half; i++) {
      lines.push([[i * 0.5, y, -half * 0.5], [i * 0.5, y, half * 0.5], GRID_COLOR]);
      lines.push([[-half * 0.5, y, i * 0.5], [half * 0.5, y, i * 0.5], GRID_COLOR]);
    }
    return lines;
  }

  /**
   * @param {string} id
   * @param {AvatarDescription} desc
   * @param {Vec3[]} points
   * @returns {Line[]}
   */
  boneLines(id, desc, points) {
    const color = id === this.selected ? SELECTED_BONE_COLOR : BONE_COLOR;
    /** @type {Line[]} */
    const lines = [];
    desc.parents.forEach((p, j) => {
      if (p >= 0) lines.push([points[p], points[j], color]);
    });
    return lines;
  }

  /**
   * @param {Float32Array} vp
   * @param {Posed[]} shown
   */
  renderGl(vp, shown) {
    const gl = /** @type {WebGL2RenderingContext} */ (this.gl);
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(BACKGROUND[0], BACKGROUND[1], BACKGROUND[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    this.drawLines(vp, this.gridLines(), gl.LINES);
    for (const { id, a, worlds } of shown) if (this.showMesh && a.mesh) this.drawMesh(vp, id, a, a.mesh, worlds);
    // Skeletons over every mesh (no depth test), one draw per kind.
    /** @type {Line[]} */
    const bones = [];
    /** @type {Line[]} */
    const joints = [];
    for (const { id, a, points } of shown) {
      if (!this.showSkeleton && a.mesh) continue;
      bones.push(...this.boneLines(id, a.desc, points));
      for (const p of points) joints.push([p, p, JOINT_COLOR]);
    }
    if (bones.length || joints.length) {
      gl.disable(gl.DEPTH_TEST);
      this.drawLines(vp, bones, gl.LINES);
      this.drawLines(vp, joints, gl.POINTS);
      gl.enable(gl.DEPTH_TEST);
    }
  }

  /**
   * @param {Float32Array} vp
   * @param {Line[]} lines
   * @param {number} mode
   */
  drawLines(vp, lines, mode) {
    const gl = /** @type {WebGL2RenderingContext} */ (this.gl);
    const program = /** @type {WebGLProgram} */ (this.lineProgram);
    const data = new Float32Array(lines.length * 12);
    lines.forEach(([a, b, c], i) => data.set([...a, ...c, ...b, ...c], i * 12));
    gl.useProgram(program);
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "uViewProj"), false, vp);
    gl.uniform1f(gl.getUniformLocation(program, "uPointSize"), 6 * Math.min(window.devicePixelRatio || 1, 2));
    gl.bindVertexArray(this.lineVao ?? null);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuffer ?? null);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
    gl.drawArrays(mode, 0, lines.length * 2);
    gl.bindVertexArray(null);
  }

  /**
   * The rig's mesh on the GPU, uploaded once and shared by every avatar of the rig.
   * @param {string} hash
   * @param {Mesh} mesh
   * @returns {GpuPrimitive[]}
   */
  meshPrimitives(hash, mesh) {
    const held = this.meshGpu.get(hash);
    if (held?.mesh === mesh) return held.primitives;
    const primitives = this.uploadMesh(mesh);
    this.meshGpu.set(hash, { mesh, primitives });
    return primitives;
  }

  /**
   * @param {Mesh} mesh
   * @returns {GpuPrimitive[]}
   */
  uploadMesh(mesh) {
    const gl = /** @type {WebGL2RenderingContext} */ (this.gl);
    return mesh.primitives.map((p) => {
      const vao = gl.createVertexArray();
      gl.bindVertexArray(vao);
      /**
       * @param {number} loc
       * @param {BufferSource} data
       * @param {number} size
       * @param {boolean} integer
       */
      const attrib = (loc, data, size, integer) => {
        const b = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, b);
        gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
        gl.enableVertexAttribArray(loc);
        if (integer) gl.vertexAttribIPointer(loc, size, gl.UNSIGNED_SHORT, 0, 0);
        else gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
      };
      const count = p.positions.length / 3;
      attrib(0, p.positions, 3, false);
      attrib(1, p.normals ?? upNormals(count), 3, false);
      attrib(2, p.joints, 4, true);
      attrib(3, p.weights, 4, false);
      let indexCount = count;
      if (p.indices) {
        const ib = gl.createBuffer();
        gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
        gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, p.indices, gl.STATIC_DRAW);
        indexCount = p.indices.length;
      }
      gl.bindVertexArray(null);
      return { vao, indexed: !!p.indices, count: indexCount };
    });
  }

  /**
   * @param {Float32Array} vp
   * @param {string} id
   * @param {Shown} avatar
   * @param {Mesh} mesh
   * @param {Float32Array} worlds
   */
  drawMesh(vp, id, avatar, mesh, worlds) {
    const gl = /** @type {WebGL2RenderingContext} */ (this.gl);
    const program = /** @type {WebGLProgram} */ (this.skinProgram);
    const { desc } = avatar;
    const n = desc.joint_names.length;
    if (mesh.jointCount && mesh.jointCount !== n) return; // stale mesh for another rig
    const primitives = this.meshPrimitives(desc.hash, mesh);
    const skin = new Float32Array(16 * n);
    const m = new Float32Array(16);
    for (let j = 0; j < n; j++) {
      multiply(m, worlds.subarray(16 * j, 16 * j + 16), desc.inverse_binds[j]);
      skin.set(m, 16 * j);
    }
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.jointTexture ?? null);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 4 * n, 1, 0, gl.RGBA, gl.FLOAT, skin);
    gl.useProgram(program);
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "uViewProj"), false, vp);
    gl.uniform1i(gl.getUniformLocation(program, "uJoints"), 0);
    gl.uniform3fv(gl.getUniformLocation(program, "uBase"), id === this.selected ? SELECTED_MESH_COLOR : MESH_COLOR);
    for (const p of primitives) {
      gl.bindVertexArray(p.vao);
      if (p.indexed) gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, 0);
      else gl.drawArrays(gl.TRIANGLES, 0, p.count);
    }
    gl.bindVertexArray(null);
  }

  /**
   * @param {Float32Array} vp
   * @param {Posed[]} shown
   */
  render2d(vp, shown) {
    const ctx = /** @type {CanvasRenderingContext2D} */ (this.ctx);
    const w = this.canvas.width, h = this.canvas.height;
    ctx.fillStyle = rgb(BACKGROUND);
    ctx.fillRect(0, 0, w, h);
    /** @param {Vec3} p */
    const project = (p) => this.project(vp, p);
    /**
     * @param {Line[]} lines
     * @param {number} width
     */
    const stroke = (lines, width) => {
      ctx.lineWidth = width;
      for (const [a, b, c] of lines) {
        const pa = project(a), pb = project(b);
        if (!pa || !pb) continue;
        ctx.strokeStyle = rgb(c);
        ctx.beginPath();
        ctx.moveTo(pa[0], pa[1]);
        ctx.lineTo(pb[0], pb[1]);
        ctx.stroke();
      }
    };
    stroke(this.gridLines(), 1);
    for (const { id, a, points } of shown) stroke(this.boneLines(id, a.desc, points), 3);
    ctx.fillStyle = rgb(JOINT_COLOR);
    for (const { points } of shown) {
      for (const p of points) {
        const q = project(p);
        if (!q) continue;
        ctx.beginPath();
        ctx.arc(q[0], q[1], 3.5, 0, Math.PI * 2);
        ctx.fill();
      }
    }
  }
}

/**
 * @param {number} count
 * @returns {Float32Array} Normals pointing up, for a mesh without any.
 */
function upNormals(count) {
  const n = new Float32Array(count * 3);
  for (let i = 0; i < count; i++) n[3 * i + 1] = 1;
  return n;
}

/**
 * @param {number[]} c
 * @returns {string}
 */
function rgb(c) {
  return `rgb(${c.map((v) => Math.round(v * 255)).join(",")})`;
}
