//! Projection backward kernel (`project_bwd.wgsl`): screen-space gradients → parameters.

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::chunks::bind_ranges;
use crate::splat::gpu::context::GpuContext;
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch_group, groups_for, with_common};
use crate::splat::gpu::raster_bwd::GRADS2D_STRIDE;
use crate::splat::model::SH_FLOATS;

/// SH floats per Gaussian, as the `u32` that sub-range bindings take.
const SH: u32 = SH_FLOATS as u32;
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};

/// The projection backward pipeline.
pub struct ProjectBwd {
    pipeline: wgpu::ComputePipeline,
}

impl ProjectBwd {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        let src = with_common(include_str!("../../../shaders/project_bwd.wgsl"));
        ProjectBwd {
            pipeline: pipeline(ctx, "project_bwd", &src, "main"),
        }
    }

    /// Records the projection backward, one dispatch per chunk of the model's plan: writes
    /// every gradient of `grads` (zero for Gaussians culled in `frame`) and adds this view to
    /// the densification statistic.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        frame: &Frame,
        grads2d: &wgpu::Buffer,
        grads: &GpuGrads,
    ) {
        for chunk in splats.plan.chunks() {
            let cu = chunk.params(ctx);
            let bg = bind_ranges(
                ctx,
                &self.pipeline,
                &[
                    frame.params_buf.as_entire_buffer_binding(),
                    chunk.range(&splats.means, 3),
                    chunk.range(&splats.log_scales, 3),
                    chunk.range(&splats.rotations, 4),
                    chunk.range(&splats.sh, SH),
                    chunk.range(&frame.proj, 12),
                    chunk.range(grads2d, GRADS2D_STRIDE as u32),
                    chunk.range(&grads.means, 3),
                    chunk.range(&grads.log_scales, 3),
                    chunk.range(&grads.rotations, 4),
                    chunk.range(&grads.opacity_logits, 1),
                    chunk.range(&grads.sh, SH),
                    chunk.range(&grads.densify, 3),
                    cu.as_entire_buffer_binding(),
                    chunk.range(&splats.opacity_logits, 1),
                ],
            );
            dispatch_group(enc, &self.pipeline, &bg, groups_for(chunk.len));
        }
    }
}
