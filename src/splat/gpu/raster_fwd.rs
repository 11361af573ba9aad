//! Forward rasterisation kernel (`raster_fwd.wgsl`): one workgroup per 16×16 tile,
//! [`GpuContext::raster_pixels`] pixels per thread.

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::context::GpuContext;
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, with_common};

/// The forward raster pipeline.
pub struct RasterFwd {
    pipeline: wgpu::ComputePipeline,
}

impl RasterFwd {
    /// Compiles the kernel for the context's pixels per thread.
    pub fn new(ctx: &GpuContext) -> Self {
        let pix = ctx.raster_pixels.clamp(1, 16).next_power_of_two();
        let src = with_common(&format!(
            "const PIX: u32 = {pix}u;\nconst THREADS: u32 = {}u;\n{}",
            256 / pix,
            include_str!("../../../shaders/raster_fwd.wgsl")
        ));
        RasterFwd {
            pipeline: pipeline(ctx, "raster_fwd", &src, "main"),
        }
    }

    /// Records the rasterisation of `frame` (sorted, with tile ranges) into its image,
    /// final transmittance and contributor buffers.
    pub fn encode(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, frame: &Frame) {
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
                &frame.image,
                &frame.final_t,
                &frame.n_contrib,
            ],
            (tx, ty),
        );
    }
}
