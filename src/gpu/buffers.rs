//! Small helpers for storage buffers: creation, upload, zeroing and blocking read-back; and
//! [`wgsl_struct!`], one field list for a parameter struct in Rust and in WGSL.

use wgpu::util::DeviceExt;

use crate::gpu::context::{GpuContext, GpuError};

/// Usage of every storage buffer in this crate: bound in shaders, written from the CPU, copied
/// out for read-back, cleared on the GPU.
pub const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

/// A storage buffer holding `data` (zero-filled 16 bytes when empty: empty bindings are invalid),
/// bound whole: it must fit one storage binding.
pub fn storage_from<T: bytemuck::Pod>(
    ctx: &GpuContext,
    label: &'static str,
    data: &[T],
) -> Result<wgpu::Buffer, GpuError> {
    ctx.check_binding(label, size_of_val(data) as u64)?;
    chunked_from(ctx, label, data)
}

/// As [`storage_from`] for a per-Gaussian buffer that kernels bind in chunks
/// ([`crate::splat::gpu::chunks`]): it must fit the adapter's largest buffer only.
pub fn chunked_from<T: bytemuck::Pod>(
    ctx: &GpuContext,
    label: &'static str,
    data: &[T],
) -> Result<wgpu::Buffer, GpuError> {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    ctx.check_buffer(label, bytes.len() as u64)?;
    if bytes.is_empty() {
        return chunked_zeroed(ctx, label, 4);
    }
    Ok(ctx
        .device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytes,
            usage: STORAGE,
        }))
}

/// The most a model upload ([`chunked_uploaded`]) stages at once, bytes: 8 MiB (Sylva's
/// choice; `crate::splat::plan` counts it).
pub const UPLOAD_SLICE_BYTES: usize = 8 << 20;

/// As [`chunked_from`], uploaded in slices of at most [`UPLOAD_SLICE_BYTES`], each waited for,
/// so the upload never stages more than one slice beside the buffer (wgpu's
/// `create_buffer_init` stages the whole of it until the next submission is done: a model's
/// parameters and moments, uploaded at every refinement, would need their size twice). Blocks
/// until the buffer holds `data`.
pub fn chunked_uploaded<T: bytemuck::Pod>(
    ctx: &GpuContext,
    label: &'static str,
    data: &[T],
) -> Result<wgpu::Buffer, GpuError> {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    let buf = chunked_zeroed(ctx, label, bytes.len() as u64)?;
    for (k, slice) in bytes.chunks(UPLOAD_SLICE_BYTES).enumerate() {
        let offset = (k * UPLOAD_SLICE_BYTES) as u64;
        if slice.len() % 4 == 0 {
            ctx.queue.write_buffer(&buf, offset, slice);
        } else {
            let mut padded = slice.to_vec();
            padded.resize(slice.len().div_ceil(4) * 4, 0);
            ctx.queue.write_buffer(&buf, offset, &padded);
        }
        ctx.queue.submit([]);
        ctx.wait()?;
    }
    Ok(buf)
}

/// A zero-filled storage buffer of `bytes` bytes (rounded up to a multiple of 4, at least 16 so
/// that an empty model still binds `array<vec4<f32>>`), bound whole: it must fit one binding.
pub fn storage_zeroed(
    ctx: &GpuContext,
    label: &'static str,
    bytes: u64,
) -> Result<wgpu::Buffer, GpuError> {
    ctx.check_binding(label, bytes.max(16).div_ceil(4) * 4)?;
    chunked_zeroed(ctx, label, bytes)
}

/// As [`storage_zeroed`] for a per-Gaussian buffer bound in chunks: it must fit the adapter's
/// largest buffer only.
pub fn chunked_zeroed(
    ctx: &GpuContext,
    label: &'static str,
    bytes: u64,
) -> Result<wgpu::Buffer, GpuError> {
    let size = bytes.max(16).div_ceil(4) * 4;
    ctx.check_buffer(label, size)?;
    Ok(ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: STORAGE,
        mapped_at_creation: false,
    }))
}

/// A small parameter buffer holding one `T`, which kernels read as `var<storage, read>`.
///
/// Not a uniform buffer, for a measured reason: Mesa's lavapipe (22.3, Debian 12) inlines the
/// values of a uniform buffer that steer a kernel's branches and loops into a freshly compiled
/// shader variant, so every step whose counts changed (intersections, sort passes, Adam's step)
/// recompiled several kernels with LLVM and kept every variant: the resident memory of a
/// Brighton run grew by 0.73 MiB a step (700 MiB at 500 steps, 1.9 GiB at 2000), nearly all of
/// it allocated on lavapipe's queue thread (heaptrack, 2026-11-27). A read-only storage buffer
/// is never inlined. On real GPUs the difference was not measured (no GPU was lent); docs/
/// splatting.md "Parameter buffers".
pub fn params_from<T: bytemuck::Pod>(ctx: &GpuContext, label: &'static str, v: &T) -> wgpu::Buffer {
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(label),
            contents: bytemuck::bytes_of(v),
            usage: STORAGE,
        })
}

/// Copies the first `count` elements of `buffer` back to the CPU (blocking).
pub fn read_buffer<T: bytemuck::Pod>(
    ctx: &GpuContext,
    buffer: &wgpu::Buffer,
    count: usize,
) -> Result<Vec<T>, GpuError> {
    read_buffer_at(ctx, buffer, 0, count)
}

/// Copies `count` elements of `buffer` from element `first` on back to the CPU (blocking).
pub fn read_buffer_at<T: bytemuck::Pod>(
    ctx: &GpuContext,
    buffer: &wgpu::Buffer,
    first: usize,
    count: usize,
) -> Result<Vec<T>, GpuError> {
    let bytes = (count * size_of::<T>()) as u64;
    let start = (first * size_of::<T>()) as u64;
    if bytes == 0 {
        return Ok(Vec::new());
    }
    if !start.is_multiple_of(4) || start + bytes.div_ceil(4) * 4 > buffer.size() {
        return Err(GpuError::Invalid(format!(
            "read of {bytes} bytes at {start} from a buffer of {} bytes",
            buffer.size()
        )));
    }
    let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("staging"),
        size: bytes.div_ceil(4) * 4,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    enc.copy_buffer_to_buffer(buffer, start, &staging, 0, staging.size());
    ctx.queue.submit([enc.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    staging.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    ctx.wait()?;
    rx.recv()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let out = {
        let view = staging
            .get_mapped_range(..)
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        bytemuck::cast_slice::<u8, T>(&view[..bytes as usize]).to_vec()
    };
    staging.unmap();
    Ok(out)
}

/// Number of workgroups along x and y covering `groups` workgroups (x ≤ 65535, the WebGPU
/// default `max_compute_workgroups_per_dimension`); kernels count them back with `flat_group`
/// of `shaders/grid.wgsl`.
pub fn grid(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, 65535);
    (x, groups.div_ceil(x).max(1))
}

/// Binds `buffers` in order to binding 0.. of a fresh bind group for `pipeline`'s group 0.
pub fn bind(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    buffers: &[&wgpu::Buffer],
) -> wgpu::BindGroup {
    let indexed: Vec<(u32, &wgpu::Buffer)> = buffers
        .iter()
        .enumerate()
        .map(|(i, b)| (i as u32, *b))
        .collect();
    bind_indexed(ctx, pipeline, &indexed)
}

/// Binds each `(binding, buffer)` of `pipeline`'s group 0 (for entry points that use a subset).
pub fn bind_indexed(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    buffers: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let whole: Vec<(u32, wgpu::BufferBinding)> = buffers
        .iter()
        .map(|(i, b)| (*i, b.as_entire_buffer_binding()))
        .collect();
    bind_entries(ctx, pipeline, &whole)
}

/// Binds each `(binding, range)` of `pipeline`'s group 0 (for entry points that use a subset).
pub fn bind_entries(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    bindings: &[(u32, wgpu::BufferBinding)],
) -> wgpu::BindGroup {
    let layout = pipeline.get_bind_group_layout(0);
    let entries: Vec<wgpu::BindGroupEntry> = bindings
        .iter()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: *i,
            resource: wgpu::BindingResource::Buffer(b.clone()),
        })
        .collect();
    ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &layout,
        entries: &entries,
    })
}

/// The WGSL side of [`grid`]: the `Invocation` an entry point takes and its `flat_group` and
/// `flat_index`, prepended to every kernel by [`pipeline`].
const GRID_WGSL: &str = include_str!("../../shaders/grid.wgsl");

/// A compute pipeline with an automatic layout from WGSL `source` (after [`GRID_WGSL`]), entry
/// point `entry`.
pub fn pipeline(ctx: &GpuContext, label: &str, source: &str, entry: &str) -> wgpu::ComputePipeline {
    let module = ctx
        .device
        .create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(format!("{GRID_WGSL}{source}").into()),
        });
    ctx.device
        .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(label),
            layout: None,
            module: &module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        })
}

/// The WGSL spelling of a parameter field's Rust type ([`wgsl_struct!`]).
pub trait WgslType {
    const WGSL: &'static str;
}

impl WgslType for u32 {
    const WGSL: &'static str = "u32";
}
impl WgslType for f32 {
    const WGSL: &'static str = "f32";
}
impl WgslType for [u32; 3] {
    const WGSL: &'static str = "vec3<u32>";
}
impl WgslType for [f32; 3] {
    const WGSL: &'static str = "vec3<f32>";
}

/// `struct name { field: type, ... }` in WGSL, fields `(name, WGSL type)` in order.
pub fn wgsl_struct_decl(name: &str, fields: &[(&str, &str)]) -> String {
    let mut s = format!("struct {name} {{\n");
    for (field, ty) in fields {
        s.push_str(&format!("    {field}: {ty},\n"));
    }
    s.push_str("}\n");
    s
}

/// Declares a `#[repr(C)]`, `Pod` parameter struct and, from the same field list, its WGSL
/// declaration `Name::wgsl()`, which the kernel's source is prefixed with: the shader's struct
/// cannot drift from the Rust one. Every field's type must be a [`WgslType`]; the layout must
/// follow WGSL's uniform-buffer rules by itself, the stricter ones, which storage buffers also
/// accept (a `[f32; 3]` is a `vec3`, 16-byte aligned: pad by hand).
macro_rules! wgsl_struct {
    (
        $(#[$m:meta])*
        struct $name:ident {
            $($(#[$fm:meta])* $f:ident: $t:ty,)*
        }
    ) => {
        $(#[$m])*
        #[repr(C)]
        #[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
        struct $name {
            $($(#[$fm])* $f: $t,)*
        }

        impl $name {
            /// This struct's WGSL declaration: the same fields, in order.
            fn wgsl() -> String {
                $crate::gpu::buffers::wgsl_struct_decl(
                    stringify!($name),
                    &[$((stringify!($f), <$t as $crate::gpu::buffers::WgslType>::WGSL)),*],
                )
            }
        }
    };
}
pub(crate) use wgsl_struct;

#[cfg(test)]
mod tests {
    /// Guard for [`params_from`]: no kernel declares a uniform buffer, which lavapipe would
    /// recompile for every new value (docs/splatting.md "Parameter buffers").
    #[test]
    fn no_kernel_reads_a_uniform_buffer() {
        fn walk(dir: &std::path::Path, found: &mut Vec<String>, files: &mut usize) {
            let Ok(entries) = std::fs::read_dir(dir) else {
                return;
            };
            for e in entries.flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, found, files);
                } else if p.extension().is_some_and(|x| x == "wgsl") {
                    *files += 1;
                    let text = std::fs::read_to_string(&p).unwrap_or_default();
                    for (i, line) in text.lines().enumerate() {
                        if line.contains("var<uniform") {
                            found.push(format!("{}:{}", p.display(), i + 1));
                        }
                    }
                }
            }
        }
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders");
        let (mut found, mut files) = (Vec::new(), 0);
        walk(&root, &mut found, &mut files);
        assert!(
            files > 10,
            "only {files} WGSL files under {}",
            root.display()
        );
        assert!(found.is_empty(), "uniform buffers in kernels: {found:?}");
    }
}
