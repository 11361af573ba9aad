//! Backward rasterisation kernel (`raster_bwd.wgsl`), built with native float atomics or with
//! the compare-and-swap fallback (`atomic_float.wgsl` / `atomic_cas.wgsl`).

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::chunks::{SLOTS, bind_ranges};
use crate::splat::gpu::context::{AtomicMode, GpuContext};
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::dispatch_group;
use crate::splat::gpu::raster_fwd::{band_bindings, raster_source};

/// Binding of the first screen-space gradient slot (`raster_bwd.wgsl`).
const GRADS2D_BINDING: u32 = 11;

/// Screen-space gradient floats per Gaussian: mean2d (2), conic (3), rgb (3), opacity (1),
/// camera depth (1).
pub const GRADS2D_STRIDE: u64 = 10;

/// The backward raster pipeline.
pub struct RasterBwd {
    pipeline: wgpu::ComputePipeline,
}

impl RasterBwd {
    /// Compiles the kernel for the context's atomic mode and pixels per thread.
    pub fn new(ctx: &GpuContext) -> Self {
        let atomics = match ctx.atomic_mode {
            AtomicMode::Float => include_str!("../../../shaders/atomic_float.wgsl"),
            AtomicMode::CompareSwap => include_str!("../../../shaders/atomic_cas.wgsl"),
        };
        let atomics: String = (0..SLOTS)
            .map(|s| {
                atomics
                    .replace("SLOT", &s.to_string())
                    .replace("BINDING", &(GRADS2D_BINDING + s).to_string())
            })
            .collect::<Vec<_>>()
            .join("\n");
        let src = raster_source(
            ctx,
            &format!("{atomics}\n"),
            include_str!("../../../shaders/raster_bwd.wgsl"),
        );
        RasterBwd {
            pipeline: pipeline(ctx, "raster_bwd", &src, "main"),
        }
    }

    /// Records the raster backward of `frame` given dL/dimage (w·h·3 f32, interleaved RGB) and
    /// the frame's dL/d(depth) (`Frame::depth_grad`, zero unless a depth loss wrote it),
    /// accumulating into `grads2d` (which must be zero beforehand, [`GRADS2D_STRIDE`] floats per
    /// Gaussian, bound in the frame's slots), one dispatch per band of tile rows.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads2d: &wgpu::Buffer,
    ) {
        let (tx, _) = frame.params.tiles();
        // Empty gradient slots bind their own dummy each: writable bindings must not alias.
        let dummies: Vec<wgpu::Buffer> = (0..SLOTS)
            .map(|_| {
                ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("empty gradient slot"),
                    size: 16,
                    usage: wgpu::BufferUsages::STORAGE,
                    mapped_at_creation: false,
                })
            })
            .collect();
        let g2d: Vec<wgpu::BufferBinding> = frame
            .slots
            .bindings(grads2d, GRADS2D_STRIDE as u32, &frame.dummy)
            .into_iter()
            .zip(&dummies)
            .enumerate()
            .map(|(s, (b, d))| {
                if (s as u32) < frame.slots.used() {
                    b
                } else {
                    d.as_entire_buffer_binding()
                }
            })
            .collect();
        for band in &frame.bands {
            let mut b = band_bindings(frame, band);
            b.extend([
                frame.final_t.as_entire_buffer_binding(),
                frame.n_contrib.as_entire_buffer_binding(),
                dl_dimage.as_entire_buffer_binding(),
            ]);
            b.extend(g2d.iter().cloned());
            b.push(frame.depth_grad.as_entire_buffer_binding());
            let bg = bind_ranges(ctx, &self.pipeline, &b);
            dispatch_group(enc, &self.pipeline, &bg, (tx, band.rows));
        }
    }
}
