// @ts-check
// A small binary glTF (.glb) reader for the server's skinned mesh
// (GET /api/assets/{name}/mesh.glb, see rigs/src/export/): every primitive of the first
// skinned mesh, with POSITION, NORMAL, JOINTS_0, WEIGHTS_0, indices and morph targets
// (POSITION and NORMAL displacements, named by `mesh.extras.targetNames`, else `target<k>`;
// dense or sparse accessors).

/**
 * @typedef {object} Primitive
 * @property {Float32Array} positions
 * @property {Float32Array | null} normals
 * @property {Uint16Array} joints
 * @property {Float32Array} weights
 * @property {Uint32Array | null} indices
 * @property {MorphTarget[]} targets Morph targets, in the file's order.
 */

/**
 * @typedef {object} MorphTarget
 * @property {string} name
 * @property {Float32Array} positions Position displacement per vertex (xyz).
 * @property {Float32Array | null} normals Normal displacement per vertex (xyz), or none.
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
  const binEnd = bin.start + bin.length;

  /**
   * `count` elements of a component type from a buffer view.
   * @param {number} bufferView
   * @param {number} byteOffset Within the view.
   * @param {number} componentType
   * @param {number} count Components to read.
   * @param {number} components Per element (for the stride check).
   * @param {number} index The accessor, for errors.
   * @returns {TypedArray}
   */
  const read = (bufferView, byteOffset, componentType, count, components, index) => {
    const v = json.bufferViews[bufferView];
    // Every typed array constructor takes (buffer, offset, length): one of them stands for all.
    const Ctor = /** @type {Float32ArrayConstructor | undefined} */ (ARRAYS[componentType]);
    if (!v || !Ctor) throw new Error(`unsupported accessor ${index}`);
    if (v.byteStride && v.byteStride !== components * Ctor.BYTES_PER_ELEMENT) {
      throw new Error(`interleaved accessor ${index} not supported`);
    }
    const start = binStart + (v.byteOffset || 0) + byteOffset;
    if (start + count * Ctor.BYTES_PER_ELEMENT > binEnd) throw new Error(`accessor ${index} past the buffer`);
    if (start % Ctor.BYTES_PER_ELEMENT !== 0) {
      // Misaligned: copy.
      const bytes = new Uint8Array(buffer, start, count * Ctor.BYTES_PER_ELEMENT).slice();
      return new Ctor(bytes.buffer);
    }
    return new Ctor(buffer, start, count);
  };

  /**
   * An accessor's elements; a sparse one (or one without a buffer view: zeros) with its
   * substitutions applied.
   * @param {number} index
   * @returns {TypedArray}
   */
  const accessor = (index) => {
    const a = json.accessors[index];
    const n = COMPONENTS[a?.type];
    if (!a || !n) throw new Error(`unsupported accessor ${index}`);
    const dense =
      a.bufferView === undefined
        ? new Float32Array(a.count * n)
        : read(a.bufferView, a.byteOffset || 0, a.componentType, a.count * n, n, index);
    const s = a.sparse;
    if (!s) return dense;
    const out = Float32Array.from(dense);
    const at = read(s.indices.bufferView, s.indices.byteOffset || 0, s.indices.componentType, s.count, 1, index);
    const values = read(s.values.bufferView, s.values.byteOffset || 0, a.componentType, s.count * n, n, index);
    for (let i = 0; i < s.count; i++) {
      if (at[i] >= a.count) throw new Error(`sparse index ${at[i]} past accessor ${index}`);
      for (let c = 0; c < n; c++) out[at[i] * n + c] = values[i * n + c];
    }
    return out;
  };

  const mesh = (json.meshes || [])[0];
  if (!mesh) throw new Error(".glb without a mesh");
  /** @type {Primitive[]} */
  const primitives = [];
  const names = Array.isArray(mesh.extras?.targetNames) ? mesh.extras.targetNames : [];
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
      targets: (p.targets || []).map((/** @type {any} */ t, /** @type {number} */ k) => {
        const target = {
          name: typeof names[k] === "string" && names[k] !== "" ? names[k] : `target${k}`,
          positions: t.POSITION !== undefined ? f32(accessor(t.POSITION)) : new Float32Array(positions.length),
          normals: t.NORMAL !== undefined ? f32(accessor(t.NORMAL)) : null,
        };
        for (const list of [target.positions, target.normals]) {
          if (list && list.length !== positions.length) throw new Error(`morph target ${k} has ${list.length / 3} entries for ${positions.length / 3} vertices`);
        }
        return target;
      }),
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
