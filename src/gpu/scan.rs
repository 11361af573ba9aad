//! GPU exclusive prefix sum of `u32` (in place), hierarchical over blocks of 1024 elements.

use crate::gpu::buffers::{bind, grid, params_from, pipeline, storage_zeroed};
use crate::gpu::context::{GpuContext, GpuError};

/// Elements scanned by one workgroup (256 threads × 4).
pub const SCAN_BLOCK: u32 = 1024;

const SOURCE: &str = include_str!("../../shaders/scan.wgsl");

/// Pipelines of the scan; buffers are made per call (block sums are small: n / 1024).
pub struct Scanner {
    scan_blocks: wgpu::ComputePipeline,
    add_offsets: wgpu::ComputePipeline,
}

impl Scanner {
    /// Compiles the scan kernels.
    pub fn new(ctx: &GpuContext) -> Self {
        Scanner {
            scan_blocks: pipeline(ctx, "scan_blocks", SOURCE, "scan_blocks"),
            add_offsets: pipeline(ctx, "add_offsets", SOURCE, "add_offsets"),
        }
    }

    /// Records an exclusive scan of the first `n` elements of `data` into `enc`.
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        n: u32,
    ) -> Result<(), GpuError> {
        if n == 0 {
            return Ok(());
        }
        let blocks = n.div_ceil(SCAN_BLOCK);
        let sums = storage_zeroed(ctx, "scan block sums", blocks as u64 * 4)?;
        let params = params_from(ctx, "scan params", &[n, 0, 0, 0]);
        let (gx, gy) = grid(blocks);
        {
            let bg = bind(ctx, &self.scan_blocks, &[&params, data, &sums]);
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.scan_blocks);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        if blocks > 1 {
            self.encode(ctx, enc, &sums, blocks)?;
            let bg = bind(ctx, &self.add_offsets, &[&params, data, &sums]);
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.add_offsets);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        Ok(())
    }
}
