//! Skinning throughput on this machine's adapter: a ~100k-vertex mesh with four influences on a
//! ~60-joint rig, skinned by the compute kernel, by the vertex shader (an offscreen draw), and by
//! the CPU reference `skin_cpu`; morph targets (blend shapes) on the same mesh: the cost per
//! vertex per active target of the compute kernel's `morph()` and of the CPU reference
//! `morph_cpu`; plus the frame time of a full 1280×720 offscreen render.
//!
//! `cargo bench -p posecast-client --bench skinning` (prints figures; no criterion harness).

use glam::{Quat, Vec3};
use posecast_client::render::gpu_types::{
    JointMatrix, SkinnedVertex, pack_matrices, pack_vertices,
};
use posecast_client::render::procedural::{TubeOptions, tube_mesh};
use posecast_client::render::{
    Gpu, GpuMorph, Offscreen, RenderError, Renderer, RendererOptions, SkinningKernel, SkinningPath,
};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::morph::{MorphTarget, morph_cpu};
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::skeleton_bound_at_rest;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use std::time::{Duration, Instant};
use wgpu::util::DeviceExt;

const CHAINS: usize = 5;
const CHAIN_LENGTH: usize = 12;
/// Morph targets of the morph measurement (ARKit's 52 are the most a face streams; a frame of
/// speech moves about ten of them).
const TARGETS: usize = 10;

/// A root with five chains of twelve joints (61 joints, 60 bones), spreading out like a star.
fn rig() -> Skeleton {
    let mut parents = vec![None];
    let mut rest = vec![Transform::IDENTITY];
    for chain in 0..CHAINS {
        let angle = chain as f32 / CHAINS as f32 * std::f32::consts::TAU;
        let dir = Vec3::new(angle.cos(), 0.6, angle.sin()).normalize();
        for link in 0..CHAIN_LENGTH {
            parents.push(Some(if link == 0 { 0 } else { parents.len() - 1 }));
            rest.push(Transform::from_translation(dir * 0.1));
        }
    }
    skeleton_bound_at_rest(parents, rest)
}

fn pose(skeleton: &Skeleton, t: f32) -> Vec<Transform> {
    skeleton
        .rest()
        .iter()
        .enumerate()
        .map(|(j, r)| Transform {
            rotation: Quat::from_rotation_x(0.2 * (t + j as f32).sin())
                * Quat::from_rotation_z(0.15 * (0.7 * t + j as f32).cos()),
            ..*r
        })
        .collect()
}

/// Runs `work` until at least `min_time` and `min_runs` have passed; seconds per run.
fn time(min_runs: u32, min_time: Duration, mut work: impl FnMut()) -> f64 {
    work(); // warm-up: pipelines, caches, allocation
    let start = Instant::now();
    let mut runs = 0;
    let min_runs = if min_time.is_zero() { 1 } else { min_runs };
    while runs < min_runs || start.elapsed() < min_time {
        work();
        runs += 1;
    }
    start.elapsed().as_secs_f64() / f64::from(runs)
}

fn report(what: &str, vertices: usize, seconds: f64) {
    println!(
        "{what:<46} {:>9.3} ms/pass  {:>8.1} M vertices/s",
        seconds * 1e3,
        vertices as f64 / seconds / 1e6
    );
}

fn main() -> Result<(), RenderError> {
    let skeleton = rig();
    let mesh: SkinnedMesh = tube_mesh(
        &skeleton,
        &TubeOptions {
            sides: 32,
            rings: 52,
            radius: 0.25,
        },
    )
    .map_err(|e| RenderError::Gpu {
        during: "building the mesh",
        reason: e.to_string(),
    })?;
    let n = mesh.vertex_count();
    let real4 = mesh
        .weights()
        .chunks_exact(4)
        .filter(|w| w.iter().all(|&x| x > 0.0))
        .count();
    let gpu = Gpu::headless()?;
    println!("adapter: {}", gpu.describe());
    println!(
        "mesh: {n} vertices, {} triangles, {} joints, 4 influences ({:.0}% of vertices with 4 non-zero)",
        mesh.indices().len() / 3,
        skeleton.len(),
        100.0 * real4 as f64 / n as f64
    );
    // `cargo bench` passes `--bench`; `cargo test --all-targets` runs this binary without it,
    // and then one pass of each path is enough to check it still works.
    let measuring = std::env::args().any(|a| a == "--bench");
    let min_time = if measuring {
        Duration::from_secs(2)
    } else {
        Duration::ZERO
    };
    let mut buffers = PoseBuffers::new(&skeleton);
    buffers.update(&skeleton, &pose(&skeleton, 0.3));
    let skinning = buffers.skinning.clone();

    // CPU reference, single thread.
    let mut p = vec![Vec3::ZERO; n];
    let mut nn = vec![Vec3::ZERO; n];
    let cpu = time(5, min_time, || skin_cpu(&mesh, &skinning, &mut p, &mut nn));
    report("CPU skin_cpu (1 thread)", n, cpu);

    // Compute kernel: upload matrices + dispatch + wait, no read-back.
    let device = &gpu.device;
    let vertices = pack_vertices(&mesh);
    let vertex_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("bench vertices"),
        contents: bytemuck::cast_slice(&vertices),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let mut matrices: Vec<JointMatrix> = Vec::new();
    pack_matrices(&skinning, &mut matrices);
    let joint_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("bench joints"),
        contents: bytemuck::cast_slice(&matrices),
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
    });
    let output = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("bench skinned"),
        size: (n * std::mem::size_of::<SkinnedVertex>()) as u64,
        usage: wgpu::BufferUsages::STORAGE,
        mapped_at_creation: false,
    });
    let kernel = SkinningKernel::new(device);
    let targets: Vec<MorphTarget> = (0..TARGETS)
        .map(|k| MorphTarget {
            name: format!("target{k}"),
            positions: (0..n)
                .map(|v| Vec3::splat(0.001 * ((v * (k + 1)) as f32).sin()))
                .collect(),
            normals: (0..n)
                .map(|v| Vec3::splat(0.01 * ((v + k) as f32).cos()))
                .collect(),
        })
        .collect();
    let morph_mesh = mesh
        .clone()
        .with_targets(targets)
        .map_err(|e| RenderError::Gpu {
            during: "building the morph targets",
            reason: e.to_string(),
        })?;
    let mut morph = GpuMorph::new(device, "bench", &morph_mesh)?;
    let bind_group = kernel.bind_group(
        device,
        "bench bind group",
        &vertex_buffer,
        &joint_buffer,
        &output,
        &morph,
    );
    let dispatch_time = |min_runs| {
        let mut failure = None;
        let seconds = time(min_runs, min_time, || {
            gpu.queue
                .write_buffer(&joint_buffer, 0, bytemuck::cast_slice(&matrices));
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("bench compute encoder"),
            });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("bench compute pass"),
                    timestamp_writes: None,
                });
                kernel.encode(&mut pass, &bind_group, n);
            }
            gpu.queue.submit([encoder.finish()]);
            if let Err(e) = gpu.wait_idle() {
                failure = Some(e);
            }
        });
        failure.map_or(Ok(seconds), Err)
    };
    let dispatch = dispatch_time(10)?;
    report("GPU compute (dispatch + wait)", n, dispatch);
    morph.set_weights(&gpu.queue, &[0.5; TARGETS])?;
    let morphed = dispatch_time(10)?;
    report(
        &format!("GPU compute, {TARGETS} morph targets active"),
        n,
        morphed,
    );
    println!(
        "GPU morph: {:.2} ns per vertex per active target (compute kernel, {} vertices)",
        (morphed - dispatch) / (n * TARGETS) as f64 * 1e9,
        n
    );
    let mut mp = vec![Vec3::ZERO; n];
    let mut mn = vec![Vec3::ZERO; n];
    let weights = [0.5; TARGETS];
    let cpu_morph = time(5, min_time, || {
        morph_cpu(&morph_mesh, &weights, &mut mp, &mut mn);
    });
    println!(
        "CPU morph: {:.2} ns per vertex per active target (morph_cpu, 1 thread, copy and \
         renormalise included)",
        cpu_morph / (n * TARGETS) as f64 * 1e9
    );

    // Compute with read-back to the CPU, as the tests use it.
    let mut failure = None;
    let mut skinner = posecast_client::render::ComputeSkinner::new(&gpu, &mesh)?;
    let readback = time(5, min_time, || {
        if let Err(e) = skinner.skin(&skinning) {
            failure = Some(e);
        }
    });
    if let Some(e) = failure.take() {
        return Err(e);
    }
    report("GPU compute + read-back", n, readback);

    // Vertex shader: draws of the mesh into a small target, so vertex work dominates.
    let draw =
        |skinning: SkinningPath, width: u32, height: u32, grid: bool| -> Result<f64, RenderError> {
            let target = Offscreen::new(&gpu, width, height)?;
            let mut renderer = Renderer::new(
                &gpu,
                Offscreen::FORMAT,
                width,
                height,
                RendererOptions {
                    skinning,
                    grid,
                    auto_frame: false,
                    ..RendererOptions::default()
                },
            )?;
            let handle = renderer.add_avatar(&skeleton, &mesh)?;
            let locals = pose(&skeleton, 0.3);
            renderer.set_pose(handle, &locals)?;
            renderer.frame_all();
            let mut error = None;
            let mut t = 0.0f32;
            let seconds = time(10, min_time, || {
                t += 0.016;
                let result = renderer
                    .set_pose(handle, &pose(&skeleton, t))
                    .and_then(|()| target.draw(&mut renderer))
                    .and_then(|_| gpu.wait_idle());
                if let Err(e) = result {
                    error = Some(e);
                }
            });
            error.map_or(Ok(seconds), Err)
        };
    let vertex_small = draw(SkinningPath::VertexShader, 64, 64, false)?;
    report(
        "GPU vertex shader (FK + upload + draw 64×64)",
        n,
        vertex_small,
    );
    let compute_small = draw(SkinningPath::Compute, 64, 64, false)?;
    report("GPU compute path drawn (64×64)", n, compute_small);
    let frame = draw(SkinningPath::VertexShader, 1280, 720, true)?;
    println!(
        "{:<46} {:>9.3} ms/frame ({:.1} frames/s)",
        "offscreen frame 1280×720 (grid, vertex path)",
        frame * 1e3,
        1.0 / frame
    );
    let frame_compute = draw(SkinningPath::Compute, 1280, 720, true)?;
    println!(
        "{:<46} {:>9.3} ms/frame ({:.1} frames/s)",
        "offscreen frame 1280×720 (grid, compute path)",
        frame_compute * 1e3,
        1.0 / frame_compute
    );
    Ok(())
}
