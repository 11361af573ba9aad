//! The GPU device: instance, adapter and device creation with the optional features this crate
//! can use (float atomics, timestamp queries), plus the crate's error type.

use std::sync::Arc;

/// Everything that can go wrong on the GPU side.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter was found (no Vulkan driver, or `WGPU_BACKEND` points at a missing backend).
    #[error(
        "no GPU adapter found: install a Vulkan driver (e.g. mesa-vulkan-drivers) or set WGPU_BACKEND ({0})"
    )]
    NoAdapter(String),
    /// The adapter refused to create a device.
    #[error("could not create the GPU device: {0}")]
    Device(String),
    /// A buffer would exceed what one storage binding may hold on this adapter.
    #[error(
        "{what} needs {bytes} bytes but at most {limit} bytes can be bound for it on this adapter \
         (storage binding limits); render fewer Gaussians or a smaller image"
    )]
    BufferTooLarge {
        what: &'static str,
        bytes: u64,
        limit: u64,
    },
    /// A buffer would exceed the adapter's largest buffer (`max_buffer_size`), or per-Gaussian
    /// chunks cannot be planned under the binding cap.
    #[error("{what} needs {bytes} bytes but the largest buffer on this adapter is {limit} bytes")]
    BufferBeyondDevice {
        what: &'static str,
        bytes: u64,
        limit: u64,
    },
    /// A frame's tile intersections exceed the room a memory plan left for them
    /// ([`crate::splat::plan`]); nothing was allocated for them.
    #[error("{intersections} tile intersections exceed the {limit} the memory plan has room for")]
    OverPlan { intersections: u64, limit: u64 },
    /// Inputs disagree with each other (lengths, counts).
    #[error("invalid input: {0}")]
    Invalid(String),
    /// Mapping a buffer for reading failed, or polling the device failed.
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}

/// How per-Gaussian gradients are accumulated across pixels in the raster backward pass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AtomicMode {
    /// Native `atomicAdd` on `atomic<f32>` (feature `SHADER_FLOAT32_ATOMIC`).
    Float,
    /// A compare-and-swap loop on the bit pattern in `atomic<u32>` (always available).
    CompareSwap,
}

/// Raster pixels per thread on CPU adapters: in the backward raster each thread sums 8 pixels'
/// contributions before one atomic add per Gaussian, and both rasters read each staged Gaussian
/// once per 8 pixels (measured on lavapipe, 2 cores: docs/results/splatting.md, speed table).
pub const RASTER_PIXELS_CPU: u32 = 8;

/// The rasters' pixels per thread for `device_type`: [`RASTER_PIXELS_CPU`] on CPU adapters, 1
/// on GPUs. A caller may set [`GpuContext::raster_pixels`] itself before building a renderer
/// (`sylva bench train --raster-pixels`, the GPU tests); nothing reads the environment.
fn raster_pixels_for(device_type: wgpu::DeviceType) -> u32 {
    if device_type == wgpu::DeviceType::Cpu {
        RASTER_PIXELS_CPU
    } else {
        1
    }
}

/// Adapter, device and queue, plus what the adapter can do.
#[derive(Clone)]
pub struct GpuContext {
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// Float-atomic strategy used by the raster backward pass.
    pub atomic_mode: AtomicMode,
    /// The largest storage binding, bytes (`max_storage_buffer_binding_size`; 128 MiB on lavapipe).
    pub max_binding_bytes: u64,
    /// The largest buffer, bytes (`max_buffer_size`). Per-Gaussian buffers may be larger than
    /// one binding: kernels bind them in whole-Gaussian chunks (see [`crate::splat::gpu::chunks`]).
    pub max_buffer_bytes: u64,
    /// Alignment of a bound sub-range's offset, bytes (`min_storage_buffer_offset_alignment`;
    /// 256 by the WebGPU default).
    pub offset_alignment: u64,
    /// Caps the binding size used to plan per-Gaussian chunks, the rasterisers' projected-record
    /// slots and the bands of intersections, bytes (`None`: the adapter's `max_binding_bytes`).
    /// Only for tests and experiments: a small cap splits even a small model into many chunks,
    /// slots and bands.
    pub chunk_cap_bytes: Option<u64>,
    /// Pixels per thread of both rasters (1, 2, 4, 8 or 16; see `raster_bwd.wgsl`):
    /// [`RASTER_PIXELS_CPU`] on CPU adapters (lavapipe), 1 on GPUs, unless the caller sets it.
    /// Read when a [`crate::splat::gpu::Renderer`] is built.
    pub raster_pixels: u32,
    /// Adapter name and backend, for logs.
    pub description: Arc<str>,
}

impl GpuContext {
    /// Creates a context on the high-performance adapter selected by the environment
    /// (`WGPU_BACKEND`, `WGPU_ADAPTER_NAME`, ...), with float atomics when available.
    pub fn new() -> Result<Self, GpuError> {
        Self::with_atomic_mode(None)
    }

    /// As [`GpuContext::new`], but `force` picks the float-atomic strategy (`CompareSwap` always
    /// works; `Float` falls back to `CompareSwap` when the adapter lacks the feature).
    pub fn with_atomic_mode(force: Option<AtomicMode>) -> Result<Self, GpuError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let available = adapter.features();
        let has_float_atomic = available.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC);
        let atomic_mode = match force {
            Some(AtomicMode::CompareSwap) => AtomicMode::CompareSwap,
            _ if has_float_atomic => AtomicMode::Float,
            _ => AtomicMode::CompareSwap,
        };
        let mut features = wgpu::Features::empty();
        if atomic_mode == AtomicMode::Float {
            features |= wgpu::Features::SHADER_FLOAT32_ATOMIC;
        }
        // Default (WebGPU) limits, raised to the adapter's storage sizes so that large models fit.
        let al = adapter.limits();
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: al.max_storage_buffer_binding_size,
            max_buffer_size: al.max_buffer_size,
            max_storage_buffers_per_shader_stage: al.max_storage_buffers_per_shader_stage.min(16),
            ..wgpu::Limits::default()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("splat-gpu"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let info = adapter.get_info();
        let description = format!("{} ({:?})", info.name, info.backend).into();
        Ok(GpuContext {
            adapter,
            device,
            queue,
            atomic_mode,
            max_binding_bytes: limits
                .max_storage_buffer_binding_size
                .min(limits.max_buffer_size),
            max_buffer_bytes: limits.max_buffer_size,
            offset_alignment: u64::from(limits.min_storage_buffer_offset_alignment.max(4)),
            chunk_cap_bytes: None,
            raster_pixels: raster_pixels_for(info.device_type),
            description,
        })
    }

    /// Fails with [`GpuError::BufferTooLarge`] when `bytes` exceed one storage binding.
    pub fn check_binding(&self, what: &'static str, bytes: u64) -> Result<(), GpuError> {
        if bytes > self.max_binding_bytes {
            return Err(GpuError::BufferTooLarge {
                what,
                bytes,
                limit: self.max_binding_bytes,
            });
        }
        Ok(())
    }

    /// Fails with [`GpuError::BufferBeyondDevice`] when `bytes` exceed the largest buffer.
    pub fn check_buffer(&self, what: &'static str, bytes: u64) -> Result<(), GpuError> {
        if bytes > self.max_buffer_bytes {
            return Err(GpuError::BufferBeyondDevice {
                what,
                bytes,
                limit: self.max_buffer_bytes,
            });
        }
        Ok(())
    }

    /// The binding size per-Gaussian chunks are planned for, bytes: the adapter's binding limit,
    /// or [`GpuContext::chunk_cap_bytes`] when smaller.
    pub fn chunk_binding_bytes(&self) -> u64 {
        self.chunk_cap_bytes
            .map_or(self.max_binding_bytes, |c| c.min(self.max_binding_bytes))
    }

    /// The GPU's own memory, bytes: the largest device-local heap the Vulkan driver reports
    /// (`VkPhysicalDeviceMemoryProperties`; on a discrete card its VRAM, on lavapipe and
    /// integrated GPUs the share of system memory the driver offers). `None` on a backend that
    /// does not say.
    pub fn device_memory_bytes(&self) -> Option<u64> {
        // SAFETY: the hal adapter is only read (the physical device's memory properties), and
        // the guard is dropped before the function returns.
        let hal = unsafe { self.adapter.as_hal::<wgpu::hal::api::Vulkan>() }?;
        let instance = hal.shared_instance().raw_instance();
        // SAFETY: the physical device belongs to this instance and outlives the call.
        let props =
            unsafe { instance.get_physical_device_memory_properties(hal.raw_physical_device()) };
        let count = (props.memory_heap_count as usize).min(props.memory_heaps.len());
        // VK_MEMORY_HEAP_DEVICE_LOCAL_BIT = 0x1.
        props.memory_heaps[..count]
            .iter()
            .filter(|h| h.flags.as_raw() & 1 != 0)
            .map(|h| h.size)
            .max()
    }

    /// What the device's memory allocator holds now, bytes: (allocated to live buffers,
    /// reserved in its memory blocks), from wgpu's allocator report; `None` where the backend
    /// gives none. Buffers dropped while the GPU still uses them count until it is done.
    pub fn allocated_bytes(&self) -> Option<(u64, u64)> {
        self.device
            .generate_allocator_report()
            .map(|r| (r.total_allocated_bytes, r.total_reserved_bytes))
    }

    /// Blocks until all submitted work has finished.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Readback(e.to_string()))
    }
}
