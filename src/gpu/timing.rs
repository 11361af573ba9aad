//! Per-pass timing: CPU wall clock around separately submitted, awaited passes (works on every
//! adapter; timestamp queries are not used).

use std::time::Instant;

use crate::gpu::context::{GpuContext, GpuError};

/// Wall-clock milliseconds per pass, measured on the CPU by submitting each pass separately and
/// waiting for it (so only meaningful from the `*_timed` calls, which serialise the GPU).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PassTimings {
    /// Projection, tile counts, prefix sum and the read-back of the intersection count.
    pub project_ms: f64,
    /// Key emission, radix sort and tile ranges.
    pub sort_ms: f64,
    /// Forward rasterisation.
    pub raster_ms: f64,
    /// Backward rasterisation.
    pub raster_bwd_ms: f64,
    /// Projection backward.
    pub project_bwd_ms: f64,
}

/// Marks wall-clock time between submissions when timing is on.
pub(crate) struct Clock {
    pub(crate) on: bool,
    pub(crate) last: Instant,
}

impl Clock {
    /// A clock marking from now; when `on`, it first waits for the work already submitted so
    /// that it is not counted.
    pub(crate) fn start(ctx: &GpuContext, on: bool) -> Result<Clock, GpuError> {
        if on {
            ctx.wait()?;
        }
        Ok(Clock {
            on,
            last: Instant::now(),
        })
    }

    /// Submits `enc`; when timing, waits and returns the milliseconds since the last mark.
    pub(crate) fn submit(
        &mut self,
        ctx: &GpuContext,
        enc: wgpu::CommandEncoder,
    ) -> Result<f64, GpuError> {
        ctx.queue.submit([enc.finish()]);
        if !self.on {
            return Ok(0.0);
        }
        ctx.wait()?;
        let now = Instant::now();
        let ms = (now - self.last).as_secs_f64() * 1e3;
        self.last = now;
        Ok(ms)
    }
}
