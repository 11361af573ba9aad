//! The LiDAR depth loss on the GPU (`depth_loss.wgsl`): per pixel, the gradient of
//! [`crate::splat::depth::loss_and_grad`] written into the frame's depth gradient before the
//! backward pass. The LiDAR maps are uploaded once per view and stay on the GPU; no read-back.

use crate::splat::gpu::buffers::{params_from, pipeline, wgsl_struct};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::project::{dispatch, groups_for};

wgsl_struct! {
    /// The parameter buffer of `depth_loss.wgsl`.
    struct DepthParams {
        pixels: u32,
        _p0: u32,
        _p1: u32,
        _p2: u32,
        coef: f32,
        _f0: f32,
        _f1: f32,
        _f2: f32,
    }
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
                &format!(
                    "{}\n{}",
                    DepthParams::wgsl(),
                    include_str!("../../../shaders/depth_loss.wgsl")
                ),
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
        let u = params_from(
            ctx,
            "depth params",
            &DepthParams {
                pixels,
                _p0: 0,
                _p1: 0,
                _p2: 0,
                coef: if valid > 0 {
                    weight / valid as f32
                } else {
                    0.0
                },
                _f0: 0.0,
                _f1: 0.0,
                _f2: 0.0,
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
