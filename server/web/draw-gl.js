// @ts-check
// The preview's WebGL2 renderer: each rig's mesh uploaded once, morphed and skinned in the
// vertex shader — morph targets (v' = v + Σ w_k Δv_k, normals too, before skinning) from a float
// texture of displacements and the avatar's active weights, then joint matrices
// M_j = W_j · B_j⁻¹ from a float texture; grid and skeletons as lines, the skeletons over every
// mesh.

import { skinningMatrices } from "../sdk/posecast.js";
import { BACKGROUND, JOINT_COLOR, MESH_COLOR, SELECTED_MESH_COLOR, gridLines, boneLines } from "./draw.js";

/** @typedef {import("./draw.js").Line} Line */
/** @typedef {import("./draw.js").Posed} Posed */
/** @typedef {import("./draw.js").Shown} Shown */
/** @typedef {import("./draw.js").Style} Style */
/** @typedef {import("./glb.js").Mesh} Mesh */
/**
 * @typedef {{vao: WebGLVertexArrayObject, indexed: boolean, count: number, vertices: number, targets: string[], morph: WebGLTexture | null}} GpuPrimitive
 * `targets`: the names of the morph targets in `morph` (its slots), none when `morph` is null.
 */

/** Texels per row of a morph displacement texture (WebGL2 guarantees 2048). */
const MORPH_WIDTH = 2048;
/** Most morph targets a draw applies: the heaviest weights when more are set. */
const MAX_ACTIVE_TARGETS = 64;

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
// Morph targets: displacements of target s, vertex v at texels 2(s·V + v) (position) and + 1
// (normal), MORPH_WIDTH to a row; the active targets' slots and weights.
uniform highp sampler2D uMorph;
uniform int uMorphCount;
uniform int uMorphVertices;
uniform int uMorphSlots[${MAX_ACTIVE_TARGETS}];
uniform float uMorphWeights[${MAX_ACTIVE_TARGETS}];
out vec3 vNormal;
vec4 morphTexel(int i) {
  return texelFetch(uMorph, ivec2(i % ${MORPH_WIDTH}, i / ${MORPH_WIDTH}), 0);
}
mat4 jointMatrix(uint j) {
  int x = int(j) * 4;
  return mat4(texelFetch(uJoints, ivec2(x, 0), 0), texelFetch(uJoints, ivec2(x + 1, 0), 0),
              texelFetch(uJoints, ivec2(x + 2, 0), 0), texelFetch(uJoints, ivec2(x + 3, 0), 0));
}
void main() {
  vec3 pos = aPos;
  vec3 normal = aNormal;
  for (int k = 0; k < ${MAX_ACTIVE_TARGETS}; k++) {
    if (k >= uMorphCount) break;
    int base = 2 * (uMorphSlots[k] * uMorphVertices + gl_VertexID);
    pos += uMorphWeights[k] * morphTexel(base).xyz;
    normal += uMorphWeights[k] * morphTexel(base + 1).xyz;
  }
  mat4 m = aWeights.x * jointMatrix(aJoints.x) + aWeights.y * jointMatrix(aJoints.y)
         + aWeights.z * jointMatrix(aJoints.z) + aWeights.w * jointMatrix(aJoints.w);
  vNormal = mat3(m) * normal;
  gl_Position = uViewProj * (m * vec4(pos, 1.0));
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

export class GlRenderer {
  /**
   * Compiles the programs; throws when WebGL2 cannot run them.
   * @param {WebGL2RenderingContext} gl
   * @param {HTMLCanvasElement} canvas
   */
  constructor(gl, canvas) {
    this.gl = gl;
    this.canvas = canvas;
    /** @type {Map<string, {mesh: Mesh, primitives: GpuPrimitive[]}>} Description hash → mesh uploaded once per rig. */
    this.meshGpu = new Map();
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
    this.jointTexture = floatTexture(gl);
    // Bound as the morph texture of a primitive without targets (never read: no active ones).
    this.noMorph = floatTexture(gl);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array(4));
    this.morphSlots = new Int32Array(MAX_ACTIVE_TARGETS);
    this.morphWeights = new Float32Array(MAX_ACTIVE_TARGETS);
    canvas.addEventListener("webglcontextlost", (e) => e.preventDefault());
  }

  clear() {
    const gl = this.gl;
    gl.viewport(0, 0, this.canvas.width, this.canvas.height);
    gl.clearColor(BACKGROUND[0], BACKGROUND[1], BACKGROUND[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  }

  /**
   * Draws the grid, every posed avatar's mesh (when shown and loaded) and skeleton.
   * @param {Float32Array} vp
   * @param {Posed[]} shown
   * @param {Style} style
   */
  render(vp, shown, style) {
    const gl = this.gl;
    this.clear();
    gl.enable(gl.DEPTH_TEST);
    this.drawLines(vp, gridLines(style.distance), gl.LINES);
    for (const { id, a, worlds } of shown) {
      if (style.showMesh && a.mesh) this.drawMesh(vp, a, a.mesh, worlds, id === style.selected);
    }
    // Skeletons over every mesh (no depth test), one draw per kind.
    /** @type {Line[]} */
    const bones = [];
    /** @type {Line[]} */
    const joints = [];
    for (const { id, a, points } of shown) {
      if (!style.showSkeleton && a.mesh) continue;
      bones.push(...boneLines(a.desc, points, id === style.selected));
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
    const gl = this.gl;
    const program = this.lineProgram;
    const data = new Float32Array(lines.length * 12);
    lines.forEach(([a, b, c], i) => data.set([...a, ...c, ...b, ...c], i * 12));
    gl.useProgram(program);
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "uViewProj"), false, vp);
    gl.uniform1f(gl.getUniformLocation(program, "uPointSize"), 6 * Math.min(window.devicePixelRatio || 1, 2));
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuffer);
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
    const gl = this.gl;
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
      const moving = p.targets.filter((t) => t.positions.some((v) => v !== 0) || t.normals?.some((v) => v !== 0));
      return { vao, indexed: !!p.indices, count: indexCount, vertices: count, ...this.uploadTargets(moving, count) };
    });
  }

  /**
   * A primitive's morph targets as one float texture (see SKIN_VS), or none when it has none
   * or they exceed the texture size this WebGL allows (then the face does not move).
   * @param {import("./glb.js").MorphTarget[]} targets
   * @param {number} vertices
   * @returns {{targets: string[], morph: WebGLTexture | null}}
   */
  uploadTargets(targets, vertices) {
    const gl = this.gl;
    const texels = targets.length * vertices * 2;
    const rows = Math.ceil(texels / MORPH_WIDTH);
    if (texels === 0 || rows > gl.getParameter(gl.MAX_TEXTURE_SIZE)) return { targets: [], morph: null };
    const data = new Float32Array(rows * MORPH_WIDTH * 4);
    targets.forEach((t, slot) => {
      for (let v = 0; v < vertices; v++) {
        const at = 8 * (slot * vertices + v);
        data.set(t.positions.subarray(3 * v, 3 * v + 3), at);
        if (t.normals) data.set(t.normals.subarray(3 * v, 3 * v + 3), at + 4);
      }
    });
    const morph = floatTexture(gl);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, MORPH_WIDTH, rows, 0, gl.RGBA, gl.FLOAT, data);
    return { targets: targets.map((t) => t.name), morph };
  }

  /**
   * Sets the morph uniforms of one primitive from the avatar's weights (by channel name): the
   * non-zero ones, heaviest first, at most MAX_ACTIVE_TARGETS.
   * @param {WebGLProgram} program
   * @param {GpuPrimitive} p
   * @param {Record<string, number> | undefined} weights
   */
  bindMorph(program, p, weights) {
    const gl = this.gl;
    /** @type {[number, number][]} slot, weight */
    const active = [];
    if (weights && p.morph) {
      p.targets.forEach((name, slot) => {
        const w = weights[name];
        if (typeof w === "number" && Number.isFinite(w) && w !== 0) active.push([slot, w]);
      });
      active.sort((a, b) => Math.abs(b[1]) - Math.abs(a[1]));
      active.length = Math.min(active.length, MAX_ACTIVE_TARGETS);
    }
    active.forEach(([slot, w], k) => {
      this.morphSlots[k] = slot;
      this.morphWeights[k] = w;
    });
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, p.morph ?? this.noMorph);
    gl.uniform1i(gl.getUniformLocation(program, "uMorph"), 1);
    gl.uniform1i(gl.getUniformLocation(program, "uMorphCount"), active.length);
    gl.uniform1i(gl.getUniformLocation(program, "uMorphVertices"), p.vertices);
    gl.uniform1iv(gl.getUniformLocation(program, "uMorphSlots"), this.morphSlots);
    gl.uniform1fv(gl.getUniformLocation(program, "uMorphWeights"), this.morphWeights);
  }

  /**
   * @param {Float32Array} vp
   * @param {Shown} avatar
   * @param {Mesh} mesh
   * @param {Float32Array} worlds
   * @param {boolean} selected
   */
  drawMesh(vp, avatar, mesh, worlds, selected) {
    const gl = this.gl;
    const program = this.skinProgram;
    const { desc } = avatar;
    const n = desc.joint_names.length;
    if (mesh.jointCount && mesh.jointCount !== n) return; // stale mesh for another rig
    const primitives = this.meshPrimitives(desc.hash, mesh);
    const skin = skinningMatrices(desc, worlds);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.jointTexture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 4 * n, 1, 0, gl.RGBA, gl.FLOAT, skin);
    gl.useProgram(program);
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "uViewProj"), false, vp);
    gl.uniform1i(gl.getUniformLocation(program, "uJoints"), 0);
    gl.uniform3fv(gl.getUniformLocation(program, "uBase"), selected ? SELECTED_MESH_COLOR : MESH_COLOR);
    for (const p of primitives) {
      this.bindMorph(program, p, avatar.pose?.weights);
      gl.bindVertexArray(p.vao);
      if (p.indexed) gl.drawElements(gl.TRIANGLES, p.count, gl.UNSIGNED_INT, 0);
      else gl.drawArrays(gl.TRIANGLES, 0, p.count);
    }
    gl.bindVertexArray(null);
  }}

/**
 * A texture for exact float texels (no filtering), bound on TEXTURE_2D.
 * @param {WebGL2RenderingContext} gl
 * @returns {WebGLTexture}
 */
function floatTexture(gl) {
  const t = gl.createTexture();
  if (!t) throw new Error("no WebGL texture");
  gl.bindTexture(gl.TEXTURE_2D, t);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  return t;
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

