//! The LiDAR depth loss on the GPU (`depth_loss.wgsl`): per pixel, the gradient of
//! [`crate::splat::depth::loss_and_grad`] written into the frame's depth gradient before the
//! backward pass. The LiDAR maps are uploaded once per view and stay on the GPU; no read-back.

use crate::splat::gpu::buffers::{pipeline, uniform_from};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, groups_for};

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct DepthParams {
    pixels: u32,
    _p: [u32; 3],
    coef: f32,
    _f: [f32; 3],
}

/// The depth-loss pipeline.
pub struct DepthLoss {
    pipeline: wgpu::ComputePipeline,
}

impl DepthLoss {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        DepthLoss {
            pipeline: pipeline(
                ctx,
                "depth loss",
                include_str!("../../../shaders/depth_loss.wgsl"),
                "main",
            ),
        }
    }

    /// Records dL/d(depth) of `frame` against `lidar` (one f32 per pixel, 0 = no return) with
    /// weight `weight` over `valid` LiDAR pixels into `frame.depth_grad`.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &Frame,
        lidar: &wgpu::Buffer,
        weight: f32,
        valid: usize,
    ) -> Result<(), GpuError> {
        let pixels = frame.pixels();
        if lidar.size() < pixels as u64 * 4 {
            return Err(GpuError::Invalid(format!(
                "the LiDAR depth map holds {} bytes, the image needs {}",
                lidar.size(),
                pixels * 4
            )));
        }
        let pixels = u32::try_from(pixels)
            .map_err(|_| GpuError::Invalid("too many pixels for the depth loss".into()))?;
        let u = uniform_from(
            ctx,
            "depth params",
            &DepthParams {
                pixels,
                _p: [0; 3],
                coef: if valid > 0 {
                    weight / valid as f32
                } else {
                    0.0
                },
                _f: [0.0; 3],
            },
        );
        dispatch(
            ctx,
            enc,
            &self.pipeline,
            &[&u, &frame.depth, lidar, &frame.depth_grad],
            groups_for(pixels),
        );
        Ok(())
    }
}
