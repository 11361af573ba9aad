//! Forward rasterisation kernel (`raster_fwd.wgsl`): one workgroup per 16×16 tile,
//! [`GpuContext::raster_pixels`] pixels per thread, one dispatch per band of tile rows.

use crate::splat::gpu::buffers::pipeline;
use crate::splat::gpu::chunks::bind_ranges;
use crate::splat::gpu::context::GpuContext;
use crate::splat::gpu::frame::{Band, Frame};
use crate::splat::gpu::project::{dispatch_group, with_common};

/// `slots.wgsl`: the projected-record slots and the band uniform of both rasterisers.
const SLOTS_WGSL: &str = include_str!("../../../shaders/slots.wgsl");

/// The source of a rasteriser: `common.wgsl`, the context's pixels per thread (`PIX`,
/// `THREADS`), [`SLOTS_WGSL`], then `extra` and `body`.
pub(crate) fn raster_source(ctx: &GpuContext, extra: &str, body: &str) -> String {
    let pix = ctx.raster_pixels.clamp(1, 16).next_power_of_two();
    with_common(&format!(
        "const PIX: u32 = {pix}u;\nconst THREADS: u32 = {}u;\n{SLOTS_WGSL}\n{extra}{body}",
        256 / pix
    ))
}

/// Bindings 0-7 of both rasterisers for `band` of `frame`: the frame's parameters, the
/// projected-record slots and band uniform (`slots.wgsl`), the band's sorted intersections and
/// the frame's tile ranges.
pub(crate) fn band_bindings<'a>(frame: &'a Frame, band: &'a Band) -> Vec<wgpu::BufferBinding<'a>> {
    let mut b = vec![frame.params_buf.as_entire_buffer_binding()];
    b.extend(frame.slots.bindings(&frame.proj, 12, &frame.dummy));
    b.extend([
        band.params.as_entire_buffer_binding(),
        band.values.as_entire_buffer_binding(),
        frame.ranges.as_entire_buffer_binding(),
    ]);
    b
}

/// The forward raster pipeline.
pub struct RasterFwd {
    pipeline: wgpu::ComputePipeline,
}

impl RasterFwd {
    /// Compiles the kernel for the context's pixels per thread.
    pub fn new(ctx: &GpuContext) -> Self {
        let src = raster_source(ctx, "", include_str!("../../../shaders/raster_fwd.wgsl"));
        RasterFwd {
            pipeline: pipeline(ctx, "raster_fwd", &src, "main"),
        }
    }

    /// Records the rasterisation of `frame` (sorted, with tile ranges) into its image,
    /// final transmittance, contributor and depth buffers.
    pub fn encode(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, frame: &Frame) {
        let (tx, _) = frame.params.tiles();
        for band in &frame.bands {
            let mut b = band_bindings(frame, band);
            b.extend([
                frame.image.as_entire_buffer_binding(),
                frame.final_t.as_entire_buffer_binding(),
                frame.n_contrib.as_entire_buffer_binding(),
                frame.depth.as_entire_buffer_binding(),
            ]);
            let bg = bind_ranges(ctx, &self.pipeline, &b);
            dispatch_group(enc, &self.pipeline, &bg, (tx, band.rows));
        }
    }
}
