// Linear blend skinning (seed 001), shared verbatim by the compute kernel (compute.wgsl) and the
// vertex shader (mesh.wgsl): both modules are built as this file followed by their own source,
// so the two GPU paths cannot drift apart. Callers fetch the four joint matrices from their own
// bindings; this function only does the maths, mirroring proto's `skin_cpu`.

struct SkinVertex {
    position: vec3<f32>,
    normal: vec3<f32>,
    joints: vec4<u32>,
    weights: vec4<f32>,
}

struct Skinned {
    position: vec3<f32>,
    normal: vec3<f32>,
}

// v' = Σ_k w_k M_{j_k} v, and n' = normalize(C n) with C the cofactor matrix of the blended 3×3.
//
// Normals need the inverse-transpose of the blended linear part (DESIGN.md): under non-uniform
// joint scale, or where several joints blend, the blend is no rotation and transforming n by it
// would tilt the normal off the surface. The cofactor matrix cof(A) = det(A) · A⁻ᵀ is the same
// up to that scalar, so after normalising it gives the inverse-transpose's direction, while
// costing three cross products instead of an inverse and staying finite where the blend is
// singular (joints blended at opposite rotations). Multiplying by sign(det) keeps the direction
// the inverse-transpose would give where a blend mirrors (det < 0). A singular blend has no
// defined normal: it returns zero, like `skin_cpu`.
fn skin(
    v: SkinVertex,
    m0: mat4x4<f32>,
    m1: mat4x4<f32>,
    m2: mat4x4<f32>,
    m3: mat4x4<f32>,
) -> Skinned {
    let w = v.weights;
    let m = m0 * w.x + m1 * w.y + m2 * w.z + m3 * w.w;
    var out: Skinned;
    out.position = (m * vec4<f32>(v.position, 1.0)).xyz;
    let a = m[0].xyz;
    let b = m[1].xyz;
    let c = m[2].xyz;
    let cofactor = mat3x3<f32>(cross(b, c), cross(c, a), cross(a, b));
    let det = dot(a, cross(b, c));
    let n = cofactor * v.normal * sign(det);
    let len = length(n);
    out.normal = select(vec3<f32>(0.0), n / len, len > 1e-30);
    return out;
}
