//! Projection backward kernel (`project_bwd.wgsl`): screen-space gradients → parameters.

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::context::GpuContext;
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, groups_for, with_common};
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

    /// Records the projection backward: writes every gradient of `grads` (zero for Gaussians
    /// culled in `frame`) and adds this view to the densification statistic.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        frame: &Frame,
        grads2d: &wgpu::Buffer,
        grads: &GpuGrads,
    ) {
        dispatch(
            ctx,
            enc,
            &self.pipeline,
            &[
                &frame.params_buf,
                &splats.means,
                &splats.log_scales,
                &splats.rotations,
                &splats.sh,
                &frame.proj,
                grads2d,
                &grads.means,
                &grads.log_scales,
                &grads.rotations,
                &grads.opacity_logits,
                &grads.sh,
                &grads.densify,
            ],
            groups_for(frame.count),
        );
    }
}
