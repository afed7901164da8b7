//! Headless GPU device creation: no window, no surface, so it works in tests and on servers
//! with a software adapter (Mesa lavapipe).

use super::error::RenderError;

/// An adapter, its device and queue. Cheap to clone: wgpu handles are reference counted.
#[derive(Clone, Debug)]
pub struct Gpu {
    /// The wgpu instance the adapter came from (windows make their surfaces with it).
    pub instance: wgpu::Instance,
    /// The adapter (physical or software GPU) in use.
    pub adapter: wgpu::Adapter,
    /// The logical device every resource is created on.
    pub device: wgpu::Device,
    /// The device's queue, for uploads and submissions.
    pub queue: wgpu::Queue,
}

impl Gpu {
    /// Requests any adapter (the `WGPU_BACKEND` / `WGPU_ADAPTER_NAME` environment variables are
    /// honoured) and a device with the default WebGPU limits.
    ///
    /// Returns [`RenderError::NoAdapter`] when the machine has no usable adapter at all, e.g.
    /// no Vulkan driver installed (`apt-get install mesa-vulkan-drivers libvulkan1` gives the
    /// lavapipe software adapter).
    pub fn headless() -> Result<Self, RenderError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        pollster::block_on(Self::with_instance(instance, None))
    }

    /// Requests an adapter from `instance` that can present to `surface`, when given, and its
    /// device. The windowed viewer uses this; [`Gpu::headless`] passes no surface.
    pub async fn with_instance(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Self, RenderError> {
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                compatible_surface: surface,
                ..Default::default()
            })
            .await
            .map_err(|source| RenderError::NoAdapter {
                reason: source.to_string(),
            })?;
        let info = adapter.get_info();
        tracing::info!(name = %info.name, backend = ?info.backend, "GPU adapter");
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("posecast device"),
                required_features: wgpu::Features::empty(),
                required_limits: wgpu::Limits::default(),
                ..Default::default()
            })
            .await
            .map_err(|source| RenderError::NoDevice {
                adapter: info.name.clone(),
                reason: source.to_string(),
            })?;
        Ok(Self {
            instance,
            adapter,
            device,
            queue,
        })
    }

    /// The adapter's name and backend, e.g. `"llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)"`.
    #[must_use]
    pub fn describe(&self) -> String {
        let info = self.adapter.get_info();
        format!("{} ({:?})", info.name, info.backend)
    }

    /// Blocks until all submitted work has finished.
    pub fn wait_idle(&self) -> Result<(), RenderError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|source| RenderError::Poll {
                reason: source.to_string(),
            })
    }

    /// Copies a `MAP_READ` buffer's whole contents to the CPU, waiting for the GPU.
    pub fn read_buffer(
        &self,
        buffer: &wgpu::Buffer,
        what: &'static str,
    ) -> Result<Vec<u8>, RenderError> {
        let (sender, receiver) = std::sync::mpsc::sync_channel(1);
        buffer.map_async(wgpu::MapMode::Read, .., move |result| {
            // The receiver lives until after the poll below, so the send cannot fail unless the
            // reader already gave up; nothing is left to tell then.
            sender.send(result).ok();
        });
        self.wait_idle()?;
        let mapped = receiver
            .recv()
            .map_err(|_| RenderError::Readback {
                what,
                reason: "the map callback never ran".into(),
            })?
            .map_err(|source| RenderError::Readback {
                what,
                reason: source.to_string(),
            });
        mapped?;
        let bytes = buffer
            .get_mapped_range(..)
            .map_err(|source| RenderError::Readback {
                what,
                reason: source.to_string(),
            })?
            .to_vec();
        buffer.unmap();
        Ok(bytes)
    }

    /// Runs `work` inside a validation + out-of-memory error scope and turns a captured wgpu
    /// error into [`RenderError::Gpu`] instead of wgpu's default of panicking.
    pub fn scoped<T>(
        &self,
        during: &'static str,
        work: impl FnOnce() -> Result<T, RenderError>,
    ) -> Result<T, RenderError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = work();
        let validation = pollster::block_on(validation.pop());
        let oom = pollster::block_on(oom.pop());
        if let Some(error) = validation.or(oom) {
            return Err(RenderError::Gpu {
                during,
                reason: error.to_string(),
            });
        }
        result
    }
}
