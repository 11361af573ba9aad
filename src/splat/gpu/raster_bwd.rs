//! Backward rasterisation kernel (`raster_bwd.wgsl`), built with native float atomics or with
//! the compare-and-swap fallback (`atomic_float.wgsl` / `atomic_cas.wgsl`).

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::context::{AtomicMode, GpuContext};
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, with_common};

/// Screen-space gradient floats per Gaussian: mean2d (2), conic (3), rgb (3), opacity (1).
pub const GRADS2D_STRIDE: u64 = 9;

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
        let pix = ctx.raster_pixels.clamp(1, 16).next_power_of_two();
        let src = with_common(&format!(
            "const PIX: u32 = {pix}u;\nconst THREADS: u32 = {}u;\n{atomics}\n{}",
            256 / pix,
            include_str!("../../../shaders/raster_bwd.wgsl")
        ));
        RasterBwd {
            pipeline: pipeline(ctx, "raster_bwd", &src, "main"),
        }
    }

    /// Records the raster backward of `frame` given dL/dimage (w·h·3 f32, interleaved RGB),
    /// accumulating into `grads2d` (which must be zero beforehand, 9 floats per Gaussian).
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads2d: &wgpu::Buffer,
    ) {
        let (tx, ty) = frame.params.tiles();
        dispatch(
            ctx,
            enc,
            &self.pipeline,
            &[
                &frame.params_buf,
                &frame.proj,
                &frame.values,
                &frame.ranges,
                &frame.final_t,
                &frame.n_contrib,
                dl_dimage,
                grads2d,
            ],
            (tx, ty),
        );
    }
}
