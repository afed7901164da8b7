// @ts-check
// A small binary glTF (.glb) reader for the server's skinned mesh
// (GET /api/assets/{name}/mesh.glb, see rigs/src/export/): every primitive of the first
// skinned mesh, with POSITION, NORMAL, JOINTS_0, WEIGHTS_0 and indices.

/**
 * @typedef {object} Primitive
 * @property {Float32Array} positions
 * @property {Float32Array | null} normals
 * @property {Uint16Array} joints
 * @property {Float32Array} weights
 * @property {Uint32Array | null} indices
 */

/**
 * @typedef {object} Mesh
 * @property {Primitive[]} primitives
 * @property {number} jointCount Joints of the skin (0 when unknown).
 */

/** @typedef {Int8Array | Uint8Array | Int16Array | Uint16Array | Uint32Array | Float32Array} TypedArray */

/** @type {Record<string, number>} */
const COMPONENTS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4, MAT4: 16 };
/** @type {Record<number, Int8ArrayConstructor | Uint8ArrayConstructor | Int16ArrayConstructor | Uint16ArrayConstructor | Uint32ArrayConstructor | Float32ArrayConstructor>} */
const ARRAYS = {
  5120: Int8Array,
  5121: Uint8Array,
  5122: Int16Array,
  5123: Uint16Array,
  5125: Uint32Array,
  5126: Float32Array,
};

/**
 * Parses .glb bytes.
 * @param {ArrayBuffer} buffer
 * @returns {Mesh}
 */
export function parseGlb(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength < 20 || view.getUint32(0, true) !== 0x46546c67) {
    throw new Error("not a .glb file");
  }
  let offset = 12;
  /** @type {any} */
  let json = null;
  /** @type {{start: number, length: number} | null} */
  let bin = null;
  while (offset + 8 <= buffer.byteLength) {
    const length = view.getUint32(offset, true);
    const type = view.getUint32(offset + 4, true);
    const start = offset + 8;
    if (start + length > buffer.byteLength) throw new Error("truncated .glb chunk");
    if (type === 0x4e4f534a) {
      json = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, start, length)));
    } else if (type === 0x004e4942) {
      bin = { start, length };
    }
    offset = start + length;
  }
  if (!json || !bin) throw new Error(".glb without JSON or BIN chunk");
  const binStart = bin.start;

  /**
   * @param {number} index
   * @returns {TypedArray}
   */
  const accessor = (index) => {
    const a = json.accessors[index];
    const v = json.bufferViews[a.bufferView];
    // Every typed array constructor takes (buffer, offset, length): one of them stands for all.
    const Ctor = /** @type {Float32ArrayConstructor | undefined} */ (ARRAYS[a.componentType]);
    const n = COMPONENTS[a.type];
    if (!Ctor || !n) throw new Error(`unsupported accessor ${index}`);
    if (v.byteStride && v.byteStride !== n * Ctor.BYTES_PER_ELEMENT) {
      throw new Error(`interleaved accessor ${index} not supported`);
    }
    const byteOffset = binStart + (v.byteOffset || 0) + (a.byteOffset || 0);
    if (byteOffset % Ctor.BYTES_PER_ELEMENT !== 0) {
      // Misaligned: copy.
      const bytes = new Uint8Array(buffer, byteOffset, a.count * n * Ctor.BYTES_PER_ELEMENT).slice();
      return new Ctor(bytes.buffer);
    }
    return new Ctor(buffer, byteOffset, a.count * n);
  };

  const mesh = (json.meshes || [])[0];
  if (!mesh) throw new Error(".glb without a mesh");
  /** @type {Primitive[]} */
  const primitives = [];
  for (const p of mesh.primitives) {
    const at = p.attributes;
    if (at.POSITION === undefined || at.JOINTS_0 === undefined || at.WEIGHTS_0 === undefined) {
      continue;
    }
    const positions = accessor(at.POSITION);
    const joints = accessor(at.JOINTS_0);
    primitives.push({
      positions: f32(positions),
      normals: at.NORMAL !== undefined ? f32(accessor(at.NORMAL)) : null,
      joints: joints instanceof Uint16Array ? joints : Uint16Array.from(joints),
      weights: f32(accessor(at.WEIGHTS_0)),
      indices: p.indices !== undefined ? Uint32Array.from(accessor(p.indices)) : null,
    });
  }
  return { primitives, jointCount: json.skins?.[0]?.joints?.length ?? 0 };
}

/**
 * `a` as floats (the server writes float positions, normals and weights: no copy then).
 * @param {TypedArray} a
 * @returns {Float32Array}
 */
function f32(a) {
  return a instanceof Float32Array ? a : Float32Array.from(a);
}
