//! Stable GPU radix sort of 64-bit keys held as two `u32` words (`hi`, `lo`) with a `u32` value,
//! 4 bits per pass, least significant digit first (8 passes for `lo`, then as many as `hi` needs).

use crate::gpu::buffers::{bind, grid, params_from, pipeline, storage_zeroed};
use crate::gpu::context::{GpuContext, GpuError};
use crate::gpu::scan::Scanner;

/// Elements per sort block (128 threads × 8).
const BLOCK: u32 = 1024;
/// Digit width, bits.
const RADIX_BITS: u32 = 4;
/// Digit values per pass.
const BINS: u32 = 1 << RADIX_BITS;

const SOURCE: &str = include_str!("../../shaders/sort.wgsl");

/// Radix sort pipelines.
pub struct RadixSorter {
    count: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
    scanner: Scanner,
}

/// Number of significant bits of `max_value` (0 for 0).
pub fn bits_for(max_value: u32) -> u32 {
    32 - max_value.leading_zeros()
}

impl RadixSorter {
    /// Compiles the sort kernels.
    pub fn new(ctx: &GpuContext) -> Self {
        RadixSorter {
            count: pipeline(ctx, "sort count", SOURCE, "count"),
            scatter: pipeline(ctx, "sort scatter", SOURCE, "scatter"),
            scanner: Scanner::new(ctx),
        }
    }

    /// Records a stable sort of the first `n` triples of (`hi`, `lo`, `val`) by (hi, lo) into
    /// `enc`; only the low `hi_bits` bits of `hi` are considered. The result replaces the input.
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        hi: &wgpu::Buffer,
        lo: &wgpu::Buffer,
        val: &wgpu::Buffer,
        n: u32,
        hi_bits: u32,
    ) -> Result<(), GpuError> {
        if n <= 1 {
            return Ok(());
        }
        let bytes = n as u64 * 4;
        let alt = [
            storage_zeroed(ctx, "sort hi alt", bytes)?,
            storage_zeroed(ctx, "sort lo alt", bytes)?,
            storage_zeroed(ctx, "sort val alt", bytes)?,
        ];
        let num_blocks = n.div_ceil(BLOCK);
        let hist_len = num_blocks * BINS;
        let hist = storage_zeroed(ctx, "sort histogram", hist_len as u64 * 4)?;
        let (gx, gy) = grid(num_blocks);
        let mut passes: Vec<(u32, u32)> =
            (0..32 / RADIX_BITS).map(|p| (0, p * RADIX_BITS)).collect();
        passes.extend((0..hi_bits.min(32).div_ceil(RADIX_BITS)).map(|p| (1, p * RADIX_BITS)));
        let main = [hi, lo, val];
        for (p, &(use_hi, shift)) in passes.iter().enumerate() {
            let (src, dst): ([&wgpu::Buffer; 3], [&wgpu::Buffer; 3]) = if p % 2 == 0 {
                (main, [&alt[0], &alt[1], &alt[2]])
            } else {
                ([&alt[0], &alt[1], &alt[2]], main)
            };
            let params = params_from(ctx, "sort params", &[n, shift, use_hi, num_blocks]);
            let count_bg = bind(ctx, &self.count, &[&params, src[0], src[1], &hist]);
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.count);
                pass.set_bind_group(0, &count_bg, &[]);
                pass.dispatch_workgroups(gx, gy, 1);
            }
            self.scanner.encode(ctx, enc, &hist, hist_len)?;
            let scatter_bg = bind(
                ctx,
                &self.scatter,
                &[
                    &params, src[0], src[1], &hist, src[2], dst[0], dst[1], dst[2],
                ],
            );
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.scatter);
            pass.set_bind_group(0, &scatter_bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        if passes.len() % 2 == 1 {
            for (a, m) in alt.iter().zip(main) {
                enc.copy_buffer_to_buffer(a, 0, m, 0, bytes);
            }
        }
        Ok(())
    }
}
