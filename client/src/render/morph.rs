//! Morph targets on the GPU (`morph.wgsl`'s `morph()`, run by both skinning paths before
//! `skin()`): every target that displaces anything is uploaded once, target-major, as one
//! position and one normal displacement per vertex; each frame uploads only the list of targets
//! with a non-zero weight, so a face at rest costs nothing and a talking one costs two loads per
//! vertex per active target. The CPU reference is `posecast_proto::morph::morph_cpu`.

use super::error::RenderError;
use bytemuck::{Pod, Zeroable};
use posecast_proto::SkinnedMesh;
use wgpu::util::DeviceExt;

/// Header of the per-frame morph state (`MorphState` in `morph.wgsl`), followed by
/// [`ActiveTarget`]s.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct MorphHeader {
    /// Number of [`ActiveTarget`]s that follow and are in use.
    pub count: u32,
    /// Vertices of the mesh: the stride between two targets' blocks of displacements.
    pub vertices: u32,
    /// Padding to the 16-byte alignment of WGSL's runtime array after a header.
    pub _pad: [u32; 2],
}

/// One target with a non-zero weight this frame (`ActiveTarget` in `morph.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct ActiveTarget {
    /// The target's slot among the uploaded ones.
    pub slot: u32,
    /// Its weight.
    pub weight: f32,
}

/// Bytes of one vertex's displacements in one target: a position and a normal `vec4`.
const BYTES_PER_VERTEX_TARGET: u64 = 32;

/// A mesh's morph targets on the GPU and the per-frame list of active ones.
#[derive(Debug)]
pub struct GpuMorph {
    deltas: wgpu::Buffer,
    state: wgpu::Buffer,
    /// For each of the mesh's targets, its slot among the uploaded ones; `None` for a target
    /// that displaces nothing (not uploaded, its weight has no effect).
    slots: Vec<Option<u32>>,
    vertices: u32,
    staging: Vec<ActiveTarget>,
    /// Whether the last upload had active targets (an all-zero frame after an all-zero frame
    /// uploads nothing).
    any_active: bool,
}

impl GpuMorph {
    /// Uploads `mesh`'s targets. A mesh without targets gets one-element placeholder buffers
    /// (wgpu binds no empty buffer) and never reads them.
    ///
    /// # Errors
    /// [`RenderError::MorphTooLarge`] when the displacements exceed one storage binding of
    /// this device.
    pub fn new(
        device: &wgpu::Device,
        label: &str,
        mesh: &SkinnedMesh,
    ) -> Result<Self, RenderError> {
        let vertices = mesh.vertex_count();
        let mut slots = Vec::with_capacity(mesh.targets().len());
        let mut uploaded = 0u32;
        for target in mesh.targets() {
            if target.is_empty() {
                slots.push(None);
            } else {
                slots.push(Some(uploaded));
                uploaded += 1;
            }
        }
        let bytes = u64::from(uploaded) * vertices as u64 * BYTES_PER_VERTEX_TARGET;
        let limits = device.limits();
        let limit = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if bytes > limit {
            return Err(RenderError::MorphTooLarge {
                targets: uploaded as usize,
                vertices,
                bytes,
                limit,
            });
        }
        let mut packed: Vec<[f32; 4]> = Vec::with_capacity((bytes / 16) as usize);
        for target in mesh.targets().iter().filter(|t| !t.is_empty()) {
            for (v, dp) in target.positions.iter().enumerate() {
                let dn = target.normals.get(v).copied().unwrap_or_default();
                packed.push(dp.extend(0.0).to_array());
                packed.push(dn.extend(0.0).to_array());
            }
        }
        if packed.is_empty() {
            packed.push([0.0; 4]);
        }
        let vertices = u32::try_from(vertices).unwrap_or(u32::MAX);
        let capacity = uploaded.max(1) as usize;
        let (deltas, state) = buffers(device, label, &packed, vertices, capacity);
        Ok(Self {
            deltas,
            state,
            slots,
            vertices,
            staging: Vec::with_capacity(capacity),
            any_active: false,
        })
    }

    /// Placeholder buffers for `mesh`'s targets when they cannot be uploaded
    /// ([`RenderError::MorphTooLarge`]): weights for them are accepted and change nothing.
    #[must_use]
    pub fn ignoring(device: &wgpu::Device, label: &str, mesh: &SkinnedMesh) -> Self {
        let vertices = u32::try_from(mesh.vertex_count()).unwrap_or(u32::MAX);
        let (deltas, state) = buffers(device, label, &[[0.0; 4]], vertices, 1);
        Self {
            deltas,
            state,
            slots: vec![None; mesh.targets().len()],
            vertices,
            staging: Vec::new(),
            any_active: false,
        }
    }

    /// The mesh's targets, uploaded or not: the length [`GpuMorph::set_weights`] accepts.
    #[must_use]
    pub fn targets(&self) -> usize {
        self.slots.len()
    }

    /// Sets the weights of the mesh's targets (in the mesh's order; missing entries are 0,
    /// like `morph_cpu`). Zero weights cost nothing on the GPU; a weight that is not finite
    /// counts as 0, so no vertex can become NaN.
    ///
    /// # Errors
    /// [`RenderError::Length`] when more weights than targets are given.
    pub fn set_weights(&mut self, queue: &wgpu::Queue, weights: &[f32]) -> Result<(), RenderError> {
        if weights.len() > self.slots.len() {
            return Err(RenderError::Length {
                what: "morph weights",
                expected: self.slots.len(),
                actual: weights.len(),
            });
        }
        self.staging.clear();
        for (slot, &weight) in self.slots.iter().zip(weights) {
            if let Some(slot) = *slot
                && weight != 0.0
                && weight.is_finite()
            {
                self.staging.push(ActiveTarget { slot, weight });
            }
        }
        if self.staging.is_empty() && !self.any_active {
            return Ok(());
        }
        self.any_active = !self.staging.is_empty();
        let header = MorphHeader {
            count: self.staging.len() as u32,
            vertices: self.vertices,
            _pad: [0; 2],
        };
        queue.write_buffer(&self.state, 0, bytemuck::bytes_of(&header));
        if !self.staging.is_empty() {
            queue.write_buffer(
                &self.state,
                std::mem::size_of::<MorphHeader>() as u64,
                bytemuck::cast_slice(&self.staging),
            );
        }
        Ok(())
    }

    /// The displacements (`morph_deltas` in `morph.wgsl`).
    #[must_use]
    pub fn deltas(&self) -> &wgpu::Buffer {
        &self.deltas
    }

    /// The active targets (`morph_state` in `morph.wgsl`).
    #[must_use]
    pub fn state(&self) -> &wgpu::Buffer {
        &self.state
    }
}

/// The displacement buffer holding `packed` and the active-target buffer (a header with no
/// active target, room for `capacity` entries).
fn buffers(
    device: &wgpu::Device,
    label: &str,
    packed: &[[f32; 4]],
    vertices: u32,
    capacity: usize,
) -> (wgpu::Buffer, wgpu::Buffer) {
    let deltas = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(&format!("{label} morph displacements")),
        contents: bytemuck::cast_slice(packed),
        usage: wgpu::BufferUsages::STORAGE,
    });
    let header = MorphHeader {
        count: 0,
        vertices,
        _pad: [0; 2],
    };
    let mut initial = bytemuck::bytes_of(&header).to_vec();
    initial.resize(
        initial.len() + capacity.max(1) * std::mem::size_of::<ActiveTarget>(),
        0,
    );
    let state = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(&format!("{label} morph weights")),
        contents: &initial,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
    });
    (deltas, state)
}
