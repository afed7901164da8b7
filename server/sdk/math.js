// @ts-check
// Small column-major 4×4 matrix and quaternion helpers (p' = M p, quaternions [x, y, z, w]),
// the same conventions as posecast-proto.

/** @typedef {Float32Array} Mat4 16 floats, column-major. */
/** @typedef {ArrayLike<number>} Mat4Like */
/** @typedef {[number, number, number]} Vec3 */
/** @typedef {[number, number, number, number]} Quat */

/** @returns {Mat4} */
export function identity() {
  const m = new Float32Array(16);
  m[0] = m[5] = m[10] = m[15] = 1;
  return m;
}

/**
 * out = a · b (column-major). `out` may not alias `a` or `b`.
 * @param {Mat4} out
 * @param {Mat4Like} a
 * @param {Mat4Like} b
 * @returns {Mat4}
 */
export function multiply(out, a, b) {
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      out[c * 4 + r] =
        a[r] * b[c * 4] + a[4 + r] * b[c * 4 + 1] + a[8 + r] * b[c * 4 + 2] + a[12 + r] * b[c * 4 + 3];
    }
  }
  return out;
}

/**
 * out = T(t) · R(q) · S(s); `q` is normalised first.
 * @param {Mat4} out
 * @param {ArrayLike<number>} t
 * @param {ArrayLike<number>} q
 * @param {ArrayLike<number>} s
 * @returns {Mat4}
 */
export function fromTRS(out, t, q, s) {
  let x = q[0], y = q[1], z = q[2], w = q[3];
  const n = Math.hypot(x, y, z, w) || 1;
  x /= n; y /= n; z /= n; w /= n;
  const xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z;
  const wx = w * x, wy = w * y, wz = w * z;
  out[0] = (1 - 2 * (yy + zz)) * s[0];
  out[1] = 2 * (xy + wz) * s[0];
  out[2] = 2 * (xz - wy) * s[0];
  out[3] = 0;
  out[4] = 2 * (xy - wz) * s[1];
  out[5] = (1 - 2 * (xx + zz)) * s[1];
  out[6] = 2 * (yz + wx) * s[1];
  out[7] = 0;
  out[8] = 2 * (xz + wy) * s[2];
  out[9] = 2 * (yz - wx) * s[2];
  out[10] = (1 - 2 * (xx + yy)) * s[2];
  out[11] = 0;
  out[12] = t[0];
  out[13] = t[1];
  out[14] = t[2];
  out[15] = 1;
  return out;
}

/**
 * OpenGL-style perspective projection.
 * @param {number} fovy Vertical field of view, radians.
 * @param {number} aspect Width / height.
 * @param {number} near
 * @param {number} far
 * @returns {Mat4}
 */
export function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2);
  const m = new Float32Array(16);
  m[0] = f / aspect;
  m[5] = f;
  m[10] = (far + near) / (near - far);
  m[11] = -1;
  m[14] = (2 * far * near) / (near - far);
  return m;
}

/**
 * The view matrix of a camera at `eye` looking at `target`.
 * @param {ArrayLike<number>} eye
 * @param {ArrayLike<number>} target
 * @param {ArrayLike<number>} up
 * @returns {Mat4}
 */
export function lookAt(eye, target, up) {
  let zx = eye[0] - target[0], zy = eye[1] - target[1], zz = eye[2] - target[2];
  let n = Math.hypot(zx, zy, zz) || 1;
  zx /= n; zy /= n; zz /= n;
  let xx = up[1] * zz - up[2] * zy, xy = up[2] * zx - up[0] * zz, xz = up[0] * zy - up[1] * zx;
  n = Math.hypot(xx, xy, xz) || 1;
  xx /= n; xy /= n; xz /= n;
  const yx = zy * xz - zz * xy, yy = zz * xx - zx * xz, yz = zx * xy - zy * xx;
  const m = new Float32Array(16);
  m[0] = xx; m[4] = xy; m[8] = xz;
  m[1] = yx; m[5] = yy; m[9] = yz;
  m[2] = zx; m[6] = zy; m[10] = zz;
  m[12] = -(xx * eye[0] + xy * eye[1] + xz * eye[2]);
  m[13] = -(yx * eye[0] + yy * eye[1] + yz * eye[2]);
  m[14] = -(zx * eye[0] + zy * eye[1] + zz * eye[2]);
  m[15] = 1;
  return m;
}

/**
 * Applies `m` to point `p`; returns [x, y, z, w] (homogeneous).
 * @param {Mat4Like} m
 * @param {ArrayLike<number>} p
 * @returns {Quat}
 */
export function transformPoint(m, p) {
  const x = p[0], y = p[1], z = p[2];
  return [
    m[0] * x + m[4] * y + m[8] * z + m[12],
    m[1] * x + m[5] * y + m[9] * z + m[13],
    m[2] * x + m[6] * y + m[10] * z + m[14],
    m[3] * x + m[7] * y + m[11] * z + m[15],
  ];
}

/**
 * Rotation by `angle` radians about the unit `axis`.
 * @param {ArrayLike<number>} axis
 * @param {number} angle
 * @returns {Quat}
 */
export function quatAxisAngle(axis, angle) {
  const s = Math.sin(angle / 2);
  return [axis[0] * s, axis[1] * s, axis[2] * s, Math.cos(angle / 2)];
}

/**
 * The rotation `a · b` (b first, then a).
 * @param {Quat} a
 * @param {Quat} b
 * @returns {Quat}
 */
export function quatMul(a, b) {
  const [ax, ay, az, aw] = a;
  const [bx, by, bz, bw] = b;
  return [
    aw * bx + ax * bw + ay * bz - az * by,
    aw * by - ax * bz + ay * bw + az * bx,
    aw * bz + ax * by - ay * bx + az * bw,
    aw * bw - ax * bx - ay * by - az * bz,
  ];
}

/**
 * R = R_z(z) · R_y(y) · R_x(x): Euler angles applied x, then y, then z (radians).
 * @param {number} x
 * @param {number} y
 * @param {number} z
 * @returns {Quat}
 */
export function quatFromEulerXYZ(x, y, z) {
  const qx = quatAxisAngle([1, 0, 0], x);
  const qy = quatAxisAngle([0, 1, 0], y);
  const qz = quatAxisAngle([0, 0, 1], z);
  return quatMul(qz, quatMul(qy, qx));
}

/**
 * The inverse of `quatFromEulerXYZ`: [x, y, z] radians.
 * @param {Quat} q
 * @returns {Vec3}
 */
export function eulerXYZFromQuat(q) {
  const [x, y, z, w] = q;
  // Rotation matrix entries of R = Rz Ry Rx.
  const r20 = 2 * (x * z - w * y);
  const r21 = 2 * (y * z + w * x);
  const r22 = 1 - 2 * (x * x + y * y);
  const r10 = 2 * (x * y + w * z);
  const r00 = 1 - 2 * (y * y + z * z);
  const ey = Math.asin(Math.max(-1, Math.min(1, -r20)));
  const ex = Math.atan2(r21, r22);
  const ez = Math.atan2(r10, r00);
  return [ex, ey, ez];
}

/** Above this dot product slerp is linear (glam's threshold, `1 − f32::EPSILON`). */
const SLERP_LINEAR_DOT = 1 - 2 ** -23;

/**
 * Shortest-arc spherical interpolation from `a` (w = 0) to `b` (w = 1), normalised — as
 * posecast-proto's `Transform::blend` does it (glam's `Quat::slerp`).
 * @param {ArrayLike<number>} a
 * @param {ArrayLike<number>} b
 * @param {number} w
 * @returns {Quat}
 */
export function quatSlerp(a, b, w) {
  let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
  const s = dot < 0 ? -1 : 1;
  dot *= s;
  let k0 = 1 - w;
  let k1 = s * w;
  if (dot <= SLERP_LINEAR_DOT) {
    // Not (nearly) the same rotation: there, linear then normalised (sin θ would vanish).
    const theta = Math.acos(dot);
    k0 = Math.sin((1 - w) * theta) / Math.sin(theta);
    k1 = (s * Math.sin(w * theta)) / Math.sin(theta);
  }
  const q = [0, 1, 2, 3].map((i) => a[i] * k0 + b[i] * k1);
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
}

/**
 * The angle between two rotations, degrees (`q` and `−q` are the same rotation).
 * @param {ArrayLike<number>} a
 * @param {ArrayLike<number>} b
 * @returns {number}
 */
export function quatAngleDegrees(a, b) {
  const na = Math.hypot(a[0], a[1], a[2], a[3]) || 1;
  const nb = Math.hypot(b[0], b[1], b[2], b[3]) || 1;
  let dot = 0;
  let diff = 0;
  let sum = 0;
  for (let i = 0; i < 4; i++) dot += (a[i] / na) * (b[i] / nb);
  const s = dot < 0 ? -1 : 1;
  for (let i = 0; i < 4; i++) {
    diff += (a[i] / na - (s * b[i]) / nb) ** 2;
    sum += (a[i] / na + (s * b[i]) / nb) ** 2;
  }
  return (4 * Math.atan2(Math.sqrt(diff), Math.sqrt(sum)) * 180) / Math.PI;
}

export const DEG = Math.PI / 180;
