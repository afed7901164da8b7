// The ground: one quad at y = 0 around the scene, with grid lines drawn per pixel (anti-aliased
// by the screen-space derivative of the grid coordinate) rather than as line primitives, whose
// rasterisation differs between GPUs far more than triangles' does. Fades into the background
// towards its edge. Built after camera.wgsl (`camera`, group 0).

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) xz: vec2<f32>,
}

@vertex
fn vs_ground(@builtin(vertex_index) index: u32) -> VertexOut {
    // Two triangles, counter-clockwise seen from above.
    var corners = array<vec2<f32>, 6>(
        vec2<f32>(-1.0, 1.0), vec2<f32>(1.0, 1.0), vec2<f32>(1.0, -1.0),
        vec2<f32>(-1.0, 1.0), vec2<f32>(1.0, -1.0), vec2<f32>(-1.0, -1.0),
    );
    let xz = camera.grid.xy + corners[index] * camera.grid.z;
    var out: VertexOut;
    out.clip = camera.view_proj * vec4<f32>(xz.x, 0.0, xz.y, 1.0);
    out.xz = xz;
    return out;
}

fn line_coverage(coord: vec2<f32>) -> f32 {
    let width = max(fwidth(coord), vec2<f32>(1e-6));
    let distance = abs(fract(coord - 0.5) - 0.5) / width;
    return 1.0 - min(min(distance.x, distance.y), 1.0);
}

@fragment
fn fs_ground(in: VertexOut) -> @location(0) vec4<f32> {
    let cell = camera.grid.w;
    let minor = line_coverage(in.xz / cell);
    let major = line_coverage(in.xz / (cell * 5.0));
    let floor_color = vec3<f32>(0.16, 0.17, 0.19);
    var color = mix(floor_color, vec3<f32>(0.30, 0.31, 0.34), minor);
    color = mix(color, vec3<f32>(0.45, 0.46, 0.50), major);
    let r = length(in.xz - camera.grid.xy) / camera.grid.z;
    let fade = 1.0 - smoothstep(0.6, 1.0, r);
    return vec4<f32>(mix(camera.background.rgb, color, fade), 1.0);
}
