// @ts-check
// What the preview draws, whatever draws it: colours, the ground grid and skeleton lines, and
// the 2D-canvas fallback used when WebGL2 is unavailable (draw-gl.js draws the rest).

/** @typedef {import("./protocol.js").AvatarDescription} AvatarDescription */
/** @typedef {import("./protocol.js").AvatarPose} AvatarPose */
/** @typedef {import("./protocol.js").Vec3} Vec3 */
/** @typedef {import("./glb.js").Mesh} Mesh */
/** @typedef {{desc: AvatarDescription, pose: AvatarPose | null, mesh: Mesh | null}} Shown An avatar of the watched scene. */
/** @typedef {{id: string, a: Shown, worlds: Float32Array, points: Vec3[]}} Posed A shown avatar posed for this frame. */
/** @typedef {[Vec3, Vec3, Vec3]} Line from, to, colour */
/** @typedef {{selected: string | null, showMesh: boolean, showSkeleton: boolean, distance: number}} Style */

export const BACKGROUND = [0.106, 0.118, 0.141];
/** @type {Vec3} */
const GRID_COLOR = [0.2, 0.22, 0.26];
/** @type {Vec3} */
const BONE_COLOR = [1.0, 0.62, 0.11];
/** @type {Vec3} */
export const JOINT_COLOR = [1.0, 0.85, 0.4];
/** @type {Vec3} */
const SELECTED_BONE_COLOR = [0.35, 0.85, 1.0];
/** @type {Vec3} */
export const MESH_COLOR = [0.62, 0.7, 0.8];
/** @type {Vec3} */
export const SELECTED_MESH_COLOR = [0.7, 0.8, 0.62];

/**
 * The ground grid (half-metre squares), wider for a farther camera.
 * @param {number} distance The camera's distance from its target, metres.
 * @returns {Line[]}
 */
export function gridLines(distance) {
  /** @type {Line[]} */
  const lines = [];
  const half = Math.max(2, Math.ceil(distance));
  const y = 0;
  for (let i = -half; i <= half; i++) {
    lines.push([[i * 0.5, y, -half * 0.5], [i * 0.5, y, half * 0.5], GRID_COLOR]);
    lines.push([[-half * 0.5, y, i * 0.5], [half * 0.5, y, i * 0.5], GRID_COLOR]);
  }
  return lines;
}

/**
 * A skeleton's bones, joint to parent.
 * @param {AvatarDescription} desc
 * @param {Vec3[]} points The joints' world positions.
 * @param {boolean} selected The avatar under control, drawn in another colour.
 * @returns {Line[]}
 */
export function boneLines(desc, points, selected) {
  const color = selected ? SELECTED_BONE_COLOR : BONE_COLOR;
  /** @type {Line[]} */
  const lines = [];
  desc.parents.forEach((p, j) => {
    if (p >= 0) lines.push([points[p], points[j], color]);
  });
  return lines;
}

/**
 * @param {number[]} c
 * @returns {string}
 */
export function rgb(c) {
  return `rgb(${c.map((v) => Math.round(v * 255)).join(",")})`;
}

/**
 * The 2D fallback: grid and skeletons projected by `project` (canvas pixels, null behind the
 * camera).
 * @param {CanvasRenderingContext2D} ctx
 * @param {Posed[]} shown
 * @param {Style} style
 * @param {(p: Vec3) => [number, number] | null} project
 */
export function render2d(ctx, shown, style, project) {
  ctx.fillStyle = rgb(BACKGROUND);
  ctx.fillRect(0, 0, ctx.canvas.width, ctx.canvas.height);
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
  stroke(gridLines(style.distance), 1);
  for (const { id, a, points } of shown) stroke(boneLines(a.desc, points, id === style.selected), 3);
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
