//! Forward rasterisation kernel (`raster_fwd.wgsl`): one workgroup per 16×16 tile.

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::context::GpuContext;
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, with_common};

/// The forward raster pipeline.
pub struct RasterFwd {
    pipeline: wgpu::ComputePipeline,
}

impl RasterFwd {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        let src = with_common(include_str!("../../../shaders/raster_fwd.wgsl"));
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
