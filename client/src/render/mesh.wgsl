// Avatar meshes: vertex-shader morphing and skinning (vs_skinned, appended to skinning.wgsl and
// morph.wgsl so it runs the same morph() and skin() as the compute kernel), already-skinned vertices (vs_preskinned, for the compute
// path), and one lit fragment shader. Built after camera.wgsl (`camera`, group 0) and
// skinning.wgsl. Bindings match `Pipelines` in renderer.rs.

struct Avatar {
    color: vec4<f32>,
}

@group(1) @binding(0) var<storage, read> joint_matrices: array<mat4x4<f32>>;
@group(1) @binding(1) var<uniform> avatar: Avatar;
@group(1) @binding(2) var<storage, read> morph_deltas: array<vec4<f32>>;
@group(1) @binding(3) var<storage, read> morph_state: MorphState;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) normal: vec3<f32>,
}

fn to_clip(s: Skinned) -> VertexOut {
    var out: VertexOut;
    out.clip = camera.view_proj * vec4<f32>(s.position, 1.0);
    out.world = s.position;
    out.normal = s.normal;
    return out;
}

@vertex
fn vs_skinned(
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) joints: vec4<u32>,
    @location(3) weights: vec4<f32>,
    // With an index buffer this is the index read, i.e. the mesh's own vertex number.
    @builtin(vertex_index) vertex: u32,
) -> VertexOut {
    let v = morph(SkinVertex(position, normal, joints, weights), vertex);
    return to_clip(skin(
        v,
        joint_matrices[joints.x],
        joint_matrices[joints.y],
        joint_matrices[joints.z],
        joint_matrices[joints.w],
    ));
}

@vertex
fn vs_preskinned(@location(0) position: vec3<f32>, @location(1) normal: vec3<f32>) -> VertexOut {
    return to_clip(Skinned(position, normal));
}

// Hemispheric ambient (sky above, ground bounce below) plus one directional light: cheap,
// shows the shape from any side, and needs no shadow maps.
@fragment
fn fs_lit(in: VertexOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    let len = length(in.normal);
    var n = select(vec3<f32>(0.0, 1.0, 0.0), in.normal / len, len > 1e-6);
    // Open tubes and cut meshes show their inside: light it as the surface facing the viewer.
    n = select(-n, n, front);
    let sky = vec3<f32>(0.55, 0.60, 0.70);
    let ground = vec3<f32>(0.22, 0.19, 0.16);
    let ambient = mix(ground, sky, 0.5 * n.y + 0.5);
    let diffuse = max(dot(n, camera.light.xyz), 0.0) * camera.light.w;
    let view = normalize(camera.eye.xyz - in.world);
    let half_vector = normalize(view + camera.light.xyz);
    let specular = 0.15 * pow(max(dot(n, half_vector), 0.0), 32.0) * camera.light.w;
    let color = avatar.color.rgb * (ambient + vec3<f32>(diffuse)) + vec3<f32>(specular);
    return vec4<f32>(color, 1.0);
}
