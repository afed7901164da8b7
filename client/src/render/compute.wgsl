// Compute skinning: one invocation per vertex, appended to skinning.wgsl (which defines
// SkinVertex, Skinned and skin()) and morph.wgsl (morph(), reading the two morph bindings
// below). Bindings match `SkinningKernel` in compute.rs.

@group(0) @binding(0) var<storage, read> vertices: array<SkinVertex>;
@group(0) @binding(1) var<storage, read> joint_matrices: array<mat4x4<f32>>;
@group(0) @binding(2) var<storage, read_write> skinned: array<Skinned>;
@group(0) @binding(3) var<storage, read> morph_deltas: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> morph_state: MorphState;

@compute @workgroup_size(64)
fn skin_vertices(@builtin(global_invocation_id) id: vec3<u32>) {
    let i = id.x;
    if i >= arrayLength(&vertices) {
        return;
    }
    let v = morph(vertices[i], i);
    // Joint indices were checked against the joint buffer on upload; WGSL's bounds checks
    // (clamping) would still keep a bad index inside the buffer.
    skinned[i] = skin(
        v,
        joint_matrices[v.joints.x],
        joint_matrices[v.joints.y],
        joint_matrices[v.joints.z],
        joint_matrices[v.joints.w],
    );
}
