// The live 3D preview of every avatar of the watched scene, each where it stands: forward
// kinematics from the avatar description's rest transforms, the streamed local rotations and
// the frame's placement (W_root = P · D_root), then either WebGL2 (skinned mesh in the vertex
// shader with joint matrices M_j = W_j · B_j⁻¹ from a float texture, skeleton on top) or, when
// WebGL2 is unavailable, a 2D-canvas skeleton. Orbit with the mouse (drag, wheel) or the
// keyboard (arrows, +/-, Home) while the canvas has focus.

import { multiply, fromTRS, perspective, lookAt, transformPoint } from "./math.js";

export const BACKGROUND = [0.106, 0.118, 0.141];
const GRID_COLOR = [0.2, 0.22, 0.26];
const BONE_COLOR = [1.0, 0.62, 0.11];
const JOINT_COLOR = [1.0, 0.85, 0.4];

/**
 * World matrices of every joint: W_j = W_parent(j) · T(t_j) R_j S_j, and for roots
 * W_root = P · D_root with P = T(position) · R(rotation) the pose's `placement` (the frame's;
 * identity when absent), so the avatar is drawn where it stands in the scene.
 */
export function forwardKinematics(desc, pose) {
  const n = desc.joint_names.length;
  const worlds = new Float32Array(16 * n);
  const local = new Float32Array(16);
  const tmp = new Float32Array(16);
  const placement = pose?.placement;
  const place = placement
    ? fromTRS(new Float32Array(16), placement.position, placement.rotation, [1, 1, 1])
    : null;
  const translated = new Map(desc.translated_joints.map((j, i) => [j, i]));
  const scaled = new Map(desc.scaled_joints.map((j, i) => [j, i]));
  for (let j = 0; j < n; j++) {
    const q = pose?.rotations?.[j] ?? desc.rest_rotations[j];
    const ti = translated.get(j);
    const t = ti !== undefined && pose?.translations?.[ti] ? pose.translations[ti] : desc.rest_translations[j];
    const si = scaled.get(j);
    const s = si !== undefined && pose?.scales?.[si] ? pose.scales[si] : desc.rest_scales[j];
    fromTRS(local, t, q, s);
    const p = desc.parents[j];
    if (p >= 0) {
      multiply(tmp, worlds.subarray(16 * p, 16 * p + 16), local);
      worlds.set(tmp, 16 * j);
    } else if (place) {
      multiply(tmp, place, local);
      worlds.set(tmp, 16 * j);
    } else {
      worlds.set(local, 16 * j);
    }
  }
  return worlds;
}

function jointPositions(worlds) {
  const n = worlds.length / 16;
  const out = [];
  for (let j = 0; j < n; j++) out.push([worlds[16 * j + 12], worlds[16 * j + 13], worlds[16 * j + 14]]);
  return out;
}

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
out vec4 color;
void main() {
  vec3 n = normalize(vNormal);
  float d = max(dot(n, normalize(vec3(0.4, 0.8, 0.6))), 0.0);
  float back = max(dot(n, normalize(vec3(-0.5, 0.2, -0.7))), 0.0);
  vec3 base = vec3(0.62, 0.70, 0.80);
  color = vec4(base * (0.35 + 0.65 * d) + vec3(0.10, 0.12, 0.16) * back, 1.0);
}`;

function compile(gl, vs, fs) {
  const program = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(program, s);
  }
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  return program;
}

export class Viewer {
  constructor(canvas, { prefer2d = false } = {}) {
    this.canvas = canvas;
    this.scene = null; // the scene whose avatars are shown
    this.selected = null; // the avatar the page edits
    this.avatars = new Map(); // avatar id → { desc, pose, mesh }
    this.meshGpu = new Map(); // description hash → { mesh, primitives } uploaded once per rig
    this.drawn = []; // per avatar drawn last: { avatar, root (world), screen (canvas px) }
    this.showSkeleton = true;
    this.showMesh = true;
    this.framed = false;
    this.resetCamera();
    this.renderedFrames = 0;
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
    // Draw only when something changed: a new pose, mesh, avatar, camera move or resize.
    this.dirty = true;
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
    let drag = null;
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
      c.setPointerCapture(e.pointerId);
      c.focus();
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.pan) {
        this.target[1] += dy * this.distance * 0.002;
        this.dirty = true;
      } else {
        this.orbit(-dx * 0.01, dy * 0.01);
      }
    });
    const end = () => (drag = null);
    c.addEventListener("pointerup", end);
    c.addEventListener("pointercancel", end);
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom(Math.exp(e.deltaY * 0.001));
    }, { passive: false });
    c.addEventListener("keydown", (e) => {
      const step = e.shiftKey ? 0.3 : 0.1;
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
        Home: () => this.resetCamera(),
        "0": () => this.resetCamera(),
      };
      const f = keys[e.key];
      if (f) {
        e.preventDefault();
        f();
      }
    });
  }

  orbit(dyaw, dpitch) {
    this.dirty = true;
    this.yaw += dyaw;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dpitch));
  }

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

  /** Shows the avatars of `scene` (the watched one) from now on; forgets every other's. */
  setScene(scene) {
    if (this.scene === scene) return;
    this.scene = scene;
    this.avatars.clear();
    this.resetCamera();
  }

  /** The avatar the page edits (its description and mesh are `desc` and `mesh`). */
  select(id) {
    this.selected = id;
    this.dirty = true;
  }

  get desc() {
    return this.avatars.get(this.selected)?.desc ?? null;
  }

  get mesh() {
    return this.avatars.get(this.selected)?.mesh ?? null;
  }

  /** An avatar of the scene (or a new rig for it): a new rig drops pose and mesh. */
  setAvatar(desc) {
    const old = this.avatars.get(desc.id);
    const same = old?.desc.hash === desc.hash;
    this.avatars.set(desc.id, { desc, pose: same ? old.pose : null, mesh: same ? old.mesh : null });
    this.dirty = true;
  }

  removeAvatar(id) {
    if (this.avatars.delete(id)) this.dirty = true;
  }

  /** A streamed pose (with its placement); ignored when it is of another rig than described. */
  setPose(id, pose) {
    const a = this.avatars.get(id);
    if (!a || pose.hash !== a.desc.hash) return;
    a.pose = pose;
    this.dirty = true;
  }

  /** The mesh of every avatar of the rig whose description hash is `hash`. */
  setMesh(hash, mesh) {
    for (const a of this.avatars.values()) if (a.desc.hash === hash) a.mesh = mesh;
    this.dirty = true;
  }

  /** Frames the camera on the scene's skeletons the first time poses are shown. */
  frame(points) {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const p of points) for (let i = 0; i < 3; i++) {
      lo[i] = Math.min(lo[i], p[i]);
      hi[i] = Math.max(hi[i], p[i]);
    }
    if (!Number.isFinite(lo[0])) return;
    this.target = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.2);
    this.distance = size * 1.9;
    this.framed = true;
  }

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
    const shown = [];
    for (const [id, a] of this.avatars) {
      if (!a.pose) continue;
      const worlds = forwardKinematics(a.desc, a.pose);
      shown.push({ id, a, worlds, points: jointPositions(worlds) });
    }
    if (!shown.length) {
      this.clear();
      this.drawn = [];
      return;
    }
    if (!this.framed) this.frame(shown.flatMap((s) => s.points));
    const vp = this.viewProj();
    if (this.gl) this.renderGl(vp, shown);
    else this.render2d(vp, shown);
    this.drawn = shown.map(({ id, a, points }) => {
      const root = points[Math.max(0, a.desc.parents.findIndex((p) => p < 0))];
      return { avatar: id, root, screen: this.project(vp, root) };
    });
    this.renderedFrames++;
  }

  /** Canvas pixel of world point `p`, or null behind the camera. */
  project(vp, p) {
    const [x, y, , w] = transformPoint(vp, p);
    if (w <= 1e-6) return null;
    return [(x / w * 0.5 + 0.5) * this.canvas.width, (1 - (y / w * 0.5 + 0.5)) * this.canvas.height];
  }

  clear() {
    if (this.gl) {
      const gl = this.gl;
      gl.viewport(0, 0, this.canvas.width, this.canvas.height);
      gl.clearColor(...BACKGROUND, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    } else {
      this.ctx.fillStyle = rgb(BACKGROUND);
      this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    }
  }

  gridLines() {
    const lines = [];
    const half = Math.max(2, Math.ceil(this.distance));
    const y = 0;
    for (let i = -half; i <= half; i++) {
      lines.push([[i * 0.5, y, -half * 0.5], [i * 0.5, y, half * 0.5], GRID_COLOR]);
      lines.push([[-half * 0.5, y, i * 0.5], [half * 0.5, y, i * 0.5], GRID_COLOR]);
    }
    return lines;
  }

  boneLines(desc, points) {
    const lines = [];
    desc.parents.forEach((p, j) => {
      if (p >= 0) lines.push([points[p], points[j], BONE_COLOR]);
    });
    return lines;
  }

  renderGl(vp, shown) {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(...BACKGROUND, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    this.drawLines(vp, this.gridLines(), gl.LINES);
    for (const { a, worlds } of shown) if (this.showMesh && a.mesh) this.drawMesh(vp, a, worlds);
    // Skeletons over every mesh (no depth test), one draw per kind.
    const bones = [], joints = [];
    for (const { a, points } of shown) {
      if (!this.showSkeleton && a.mesh) continue;
      bones.push(...this.boneLines(a.desc, points));
      for (const p of points) joints.push([p, p, JOINT_COLOR]);
    }
    if (bones.length || joints.length) {
      gl.disable(gl.DEPTH_TEST);
      this.drawLines(vp, bones, gl.LINES);
      this.drawLines(vp, joints, gl.POINTS);
      gl.enable(gl.DEPTH_TEST);
    }
  }

  drawLines(vp, lines, mode) {
    const gl = this.gl;
    const data = new Float32Array(lines.length * 12);
    lines.forEach(([a, b, c], i) => data.set([...a, ...c, ...b, ...c], i * 12));
    gl.useProgram(this.lineProgram);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.lineProgram, "uViewProj"), false, vp);
    gl.uniform1f(gl.getUniformLocation(this.lineProgram, "uPointSize"), 6 * Math.min(window.devicePixelRatio || 1, 2));
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
    gl.drawArrays(mode, 0, lines.length * 2);
    gl.bindVertexArray(null);
  }

  /** The rig's mesh on the GPU, uploaded once and shared by every avatar of the rig. */
  meshPrimitives(hash, mesh) {
    const held = this.meshGpu.get(hash);
    if (held?.mesh === mesh) return held.primitives;
    const primitives = this.uploadMesh(mesh);
    this.meshGpu.set(hash, { mesh, primitives });
    return primitives;
  }

  uploadMesh(mesh) {
    const gl = this.gl;
    return mesh.primitives.map((p) => {
      const vao = gl.createVertexArray();
      gl.bindVertexArray(vao);
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

  drawMesh(vp, avatar, worlds) {
    const gl = this.gl;
    const { desc, mesh } = avatar;
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
    gl.bindTexture(gl.TEXTURE_2D, this.jointTexture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 4 * n, 1, 0, gl.RGBA, gl.FLOAT, skin);
    gl.useProgram(this.skinProgram);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.skinProgram, "uViewProj"), false, vp);
    gl.uniform1i(gl.getUniformLocation(this.skinProgram, "uJoints"), 0);
    for (const p of primitives) {
      gl.bindVertexArray(p.vao);
      if (p.indexed) gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, 0);
      else gl.drawArrays(gl.TRIANGLES, 0, p.count);
    }
    gl.bindVertexArray(null);
  }

  render2d(vp, shown) {
    const ctx = this.ctx;
    const w = this.canvas.width, h = this.canvas.height;
    ctx.fillStyle = rgb(BACKGROUND);
    ctx.fillRect(0, 0, w, h);
    const project = (p) => this.project(vp, p);
    const stroke = (lines, width) => {
      ctx.lineWidth = width;
      for (const [a, b, c] of lines) {
        const pa = project(a), pb = project(b);
        if (!pa || !pb) continue;
        ctx.strokeStyle = rgb(c);
        ctx.beginPath();
        ctx.moveTo(...pa);
        ctx.lineTo(...pb);
        ctx.stroke();
      }
    };
    stroke(this.gridLines(), 1);
    for (const { a, points } of shown) stroke(this.boneLines(a.desc, points), 3);
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

function upNormals(count) {
  const n = new Float32Array(count * 3);
  for (let i = 0; i < count; i++) n[3 * i + 1] = 1;
  return n;
}

function rgb(c) {
  return `rgb(${c.map((v) => Math.round(v * 255)).join(",")})`;
}
