// Morph targets (blend shapes), shared verbatim by the compute kernel (compute.wgsl) and the
// vertex shader (mesh.wgsl), like skin(): both modules are built as skinning.wgsl, this file,
// then their own source, which declares the two bindings read here:
//   morph_deltas: array<vec4<f32>>  every uploaded target's displacements, target-major,
//                                   two entries a vertex (position, then normal; w unused);
//   morph_state:  MorphState        the targets with a non-zero weight this frame.
// Mirrors proto's `morph_cpu`: v' = v + Σ_k w_k Δv_k for positions and normals, before skinning
// (glTF 2.0 §3.7.2.2). The normal is left unnormalised: skin() normalises its result, and the
// direction of C·(n + Σ w Δn) does not depend on the length of n + Σ w Δn.

struct ActiveTarget {
    // Index of the target among the uploaded ones (block of `vertices` × 2 entries).
    slot: u32,
    weight: f32,
}

struct MorphState {
    // Entries of `targets` in use: only targets with a non-zero weight are looped over.
    count: u32,
    // Vertices of the mesh: the stride between two targets' blocks.
    vertices: u32,
    _pad0: u32,
    _pad1: u32,
    targets: array<ActiveTarget>,
}

fn morph(v: SkinVertex, vertex: u32) -> SkinVertex {
    var out = v;
    let stride = morph_state.vertices;
    if vertex >= stride {
        return out;
    }
    let count = min(morph_state.count, arrayLength(&morph_state.targets));
    for (var i = 0u; i < count; i++) {
        let a = morph_state.targets[i];
        let base = 2u * (a.slot * stride + vertex);
        out.position += a.weight * morph_deltas[base].xyz;
        out.normal += a.weight * morph_deltas[base + 1u].xyz;
    }
    return out;
}
