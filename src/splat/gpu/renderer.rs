//! The rasteriser: forward (projection → tile counts → scan → emit → sort → ranges → raster) and
//! backward (raster backward → projection backward), with optional per-pass CPU timing.
//!
//! When a frame's tile intersections exceed one storage binding (4 bytes each per array), the
//! tiles are split into bands of whole rows ([`plan_bands`], from a read-back of the
//! intersections per row): each band gets its own per-Gaussian tile counts and offsets, emission,
//! sort and ranges, and both rasterisers run once per band. A tile's run lies in one band, so
//! blending and its backward are unchanged.

use crate::splat::camera::{Camera, RenderOptions};

use crate::splat::gpu::buffers::bind_entries;
use crate::splat::gpu::buffers::{
    chunked_zeroed, params_from, read_buffer, read_buffer_at, storage_zeroed,
};
use crate::splat::gpu::chunks::{Chunk, SlotPlan, bind_ranges};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::frame::{Band, Frame};
use crate::splat::gpu::params::RenderParams;
use crate::splat::gpu::project::{ProjectKernels, dispatch_group, groups_for};
use crate::splat::gpu::project_bwd::ProjectBwd;
use crate::splat::gpu::raster_bwd::{GRADS2D_STRIDE, RasterBwd};
use crate::splat::gpu::raster_fwd::RasterFwd;
use crate::splat::gpu::scan::Scanner;
use crate::splat::gpu::sort::{RadixSorter, bits_for};
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};
use crate::splat::gpu::timing::{Clock, PassTimings};
use crate::splat::model::SH_FLOATS;

/// Records one dispatch of `pipeline` per chunk of `splats`, binding the render parameters
/// (0), the chunk's projected records (1) and its chunk uniform (7), and what `more` gives for
/// the chunk.
fn dispatch_projected<'a>(
    ctx: &GpuContext,
    enc: &mut wgpu::CommandEncoder,
    splats: &GpuSplats,
    pipeline: &wgpu::ComputePipeline,
    params_buf: &'a wgpu::Buffer,
    proj: &'a wgpu::Buffer,
    more: impl Fn(&Chunk) -> Vec<(u32, wgpu::BufferBinding<'a>)>,
) {
    for chunk in splats.plan.chunks() {
        let cu = chunk.params(ctx);
        let mut bindings = vec![
            (0, params_buf.as_entire_buffer_binding()),
            (1, chunk.range(proj, 12)),
            (7, cu.as_entire_buffer_binding()),
        ];
        bindings.extend(more(&chunk));
        let bg = bind_entries(ctx, pipeline, &bindings);
        dispatch_group(enc, pipeline, &bg, groups_for(chunk.len));
    }
}

/// All pipelines of the forward and backward rasteriser.
pub struct Renderer {
    project: ProjectKernels,
    scanner: Scanner,
    sorter: RadixSorter,
    raster_fwd: RasterFwd,
    raster_bwd: RasterBwd,
    project_bwd: ProjectBwd,
}

impl Renderer {
    /// Compiles every kernel (atomic flavour from `ctx.atomic_mode`).
    pub fn new(ctx: &GpuContext) -> Self {
        Renderer {
            project: ProjectKernels::new(ctx),
            scanner: Scanner::new(ctx),
            sorter: RadixSorter::new(ctx),
            raster_fwd: RasterFwd::new(ctx),
            raster_bwd: RasterBwd::new(ctx),
            project_bwd: ProjectBwd::new(ctx),
        }
    }

    /// Renders `splats` through `cam` over `background` (RGB) with the default
    /// [`RenderOptions`]. Reads one `u32` (the number of tile intersections) back from the GPU;
    /// everything else stays on the GPU.
    pub fn render(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
    ) -> Result<Frame, GpuError> {
        self.render_with(ctx, splats, cam, background, RenderOptions::default())
    }

    /// [`Renderer::render`] with `options`; the frame's backward uses the same (they travel in
    /// its uniform).
    pub fn render_with(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
        options: RenderOptions,
    ) -> Result<Frame, GpuError> {
        self.render_passes(ctx, splats, cam, background, options, false)
            .map(|(f, _)| f)
    }

    /// [`Renderer::render_with`], and when `timed` waits after each pass to time it (the
    /// timings are zero otherwise).
    pub fn render_passes(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
        options: RenderOptions,
        timed: bool,
    ) -> Result<(Frame, PassTimings), GpuError> {
        self.render_passes_limited(ctx, splats, cam, background, options, timed, None)
    }

    /// [`Renderer::render_passes`] that fails with [`GpuError::OverPlan`], before allocating
    /// anything for them, when the frame's tile intersections exceed `max_intersections`.
    #[allow(clippy::too_many_arguments)]
    pub fn render_passes_limited(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
        options: RenderOptions,
        timed: bool,
        max_intersections: Option<u64>,
    ) -> Result<(Frame, PassTimings), GpuError> {
        if cam.width == 0 || cam.height == 0 || !(cam.fx > 0.0 && cam.fy > 0.0) {
            return Err(GpuError::Invalid(format!(
                "camera {}x{} px with fx {} fy {}",
                cam.width, cam.height, cam.fx, cam.fy
            )));
        }
        if ctx.device.limits().max_storage_buffers_per_shader_stage < 14 {
            return Err(GpuError::Invalid(
                "the adapter allows fewer than 14 storage buffers per shader stage".into(),
            ));
        }
        let mut times = PassTimings::default();
        let mut clock = Clock::start(ctx, timed)?;
        let n = splats.count;
        let slots = SlotPlan::new(ctx, n)?;
        let mut params = RenderParams::new(cam, background, n, splats.sh_degree, options);
        let params_buf = params_from(ctx, "render params", &params);
        let proj = chunked_zeroed(ctx, "projected", n as u64 * 48)?;
        let offsets = storage_zeroed(ctx, "tile offsets", (n as u64 + 1) * 4)?;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.encode_project(ctx, &mut enc, splats, &params_buf, &proj, &offsets);
        self.scanner.encode(ctx, &mut enc, &offsets, n + 1)?;
        ctx.queue.submit([enc.finish()]);
        // The one read-back of the forward pass: the total number of intersections.
        let isect = read_buffer_at::<u32>(ctx, &offsets, n as usize, 1)?
            .first()
            .copied()
            .unwrap_or(0);
        if let Some(limit) = max_intersections.filter(|&l| u64::from(isect) > l) {
            return Err(GpuError::OverPlan {
                intersections: u64::from(isect),
                limit,
            });
        }
        times.project_ms =
            clock.submit(ctx, ctx.device.create_command_encoder(&Default::default()))?;

        params.counts[2] = isect;
        ctx.queue
            .write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
        let (tx, ty) = params.tiles();
        let tiles = tx * ty;
        // Intersections per band: one binding of each intersection array.
        let cap = (ctx.chunk_binding_bytes() / 4).max(1);
        let spans = if u64::from(isect) <= cap {
            vec![BandSpan {
                row0: 0,
                rows: ty,
                count: isect,
            }]
        } else {
            plan_bands(&self.row_counts(ctx, splats, &params_buf, &proj, ty)?, cap)?
        };
        let ranges = storage_zeroed(ctx, "tile ranges", tiles as u64 * 8)?;
        let pixels = cam.width as u64 * cam.height as u64;
        let image = storage_zeroed(ctx, "image", pixels * 12)?;
        let final_t = storage_zeroed(ctx, "final T", pixels * 4)?;
        let n_contrib = storage_zeroed(ctx, "n contrib", pixels * 4)?;
        let depth = storage_zeroed(ctx, "depth", pixels * 4)?;
        let depth_grad = storage_zeroed(ctx, "dL/ddepth", pixels * 4)?;
        // Several bands: per-band tile counts and offsets, one band after the other.
        let band_offsets = if spans.len() > 1 {
            Some(storage_zeroed(
                ctx,
                "band tile offsets",
                (n as u64 + 1) * 4,
            )?)
        } else {
            None
        };
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        let mut bands = Vec::with_capacity(spans.len());
        for span in spans {
            bands.push(self.encode_band(
                ctx,
                &mut enc,
                splats,
                (&params_buf, &proj, &offsets),
                (span, tx, slots.per_slot),
                band_offsets.as_ref(),
                &ranges,
            )?);
        }
        times.sort_ms = clock.submit(ctx, enc)?;

        let dummy = storage_zeroed(ctx, "empty slot", 16)?;
        let frame = Frame {
            params,
            params_buf,
            proj,
            slots,
            dummy,
            offsets,
            bands,
            ranges,
            image,
            final_t,
            n_contrib,
            depth,
            depth_grad,
            count: n,
            intersections: isect,
        };
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.raster_fwd.encode(ctx, &mut enc, &frame);
        times.raster_ms = clock.submit(ctx, enc)?;
        Ok((frame, times))
    }

    /// Records the projection of every chunk of `splats` into `proj`, with each Gaussian's
    /// tile count in `offsets` (scanned into offsets after).
    fn encode_project(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: &GpuSplats,
        params_buf: &wgpu::Buffer,
        proj: &wgpu::Buffer,
        offsets: &wgpu::Buffer,
    ) {
        let p = &self.project;
        for chunk in s.plan.chunks() {
            let cu = chunk.params(ctx);
            let bg = bind_ranges(
                ctx,
                &p.project,
                &[
                    params_buf.as_entire_buffer_binding(),
                    chunk.range(&s.means, 3),
                    chunk.range(&s.log_scales, 3),
                    chunk.range(&s.rotations, 4),
                    chunk.range(&s.opacity_logits, 1),
                    chunk.range(&s.sh, SH_FLOATS as u32),
                    chunk.range(proj, 12),
                    chunk.range(offsets, 1),
                    cu.as_entire_buffer_binding(),
                ],
            );
            dispatch_group(enc, &p.project, &bg, groups_for(chunk.len));
        }
    }

    /// Records one band's intersection keys (tile, depth), their sort and the tile ranges of
    /// its rows. `projected` is (render parameters, projected records, scanned tile offsets
    /// of the whole frame); `layout` is (the band, tiles per row, Gaussians per chunk slot).
    /// With several bands, `band_offsets` receives this band's own counts and offsets.
    #[allow(clippy::too_many_arguments)]
    fn encode_band(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: &GpuSplats,
        (params_buf, proj, offsets): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        (span, tx, per_slot): (BandSpan, u32, u32),
        band_offsets: Option<&wgpu::Buffer>,
        ranges: &wgpu::Buffer,
    ) -> Result<Band, GpuError> {
        let p = &self.project;
        let n = s.count;
        let params = params_from(
            ctx,
            "band",
            &[span.row0, span.row0 + span.rows, per_slot, span.count],
        );
        let m = span.count as u64 * 4;
        let keys_hi = storage_zeroed(ctx, "keys hi (tile)", m)?;
        let keys_lo = storage_zeroed(ctx, "keys lo (depth)", m)?;
        let values = storage_zeroed(ctx, "sorted ids", m)?;
        let offs = match band_offsets {
            Some(b) => {
                dispatch_projected(ctx, enc, s, &p.band_counts, params_buf, proj, |chunk| {
                    vec![
                        (8, params.as_entire_buffer_binding()),
                        (10, chunk.range(b, 1)),
                    ]
                });
                self.scanner.encode(ctx, enc, b, n + 1)?;
                b
            }
            None => offsets,
        };
        dispatch_projected(ctx, enc, s, &p.emit, params_buf, proj, |chunk| {
            vec![
                (2, chunk.range(offs, 1)),
                (3, keys_hi.as_entire_buffer_binding()),
                (4, keys_lo.as_entire_buffer_binding()),
                (5, values.as_entire_buffer_binding()),
                (8, params.as_entire_buffer_binding()),
            ]
        });
        self.sorter.encode(
            ctx,
            enc,
            &keys_hi,
            &keys_lo,
            &values,
            span.count,
            bits_for((span.rows * tx).max(1) - 1),
        )?;
        let rbg = bind_entries(
            ctx,
            &p.ranges,
            &[
                (0, params_buf.as_entire_buffer_binding()),
                (3, keys_hi.as_entire_buffer_binding()),
                (6, ranges.as_entire_buffer_binding()),
                (8, params.as_entire_buffer_binding()),
            ],
        );
        dispatch_group(enc, &p.ranges, &rbg, groups_for(span.count));
        Ok(Band {
            row0: span.row0,
            rows: span.rows,
            count: span.count,
            keys_hi,
            keys_lo,
            values,
            params,
        })
    }

    /// Intersections per tile row (`ty` rows), read back: the plan of the bands.
    fn row_counts(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        params_buf: &wgpu::Buffer,
        proj: &wgpu::Buffer,
        ty: u32,
    ) -> Result<Vec<u32>, GpuError> {
        let rows = storage_zeroed(ctx, "intersections per tile row", ty as u64 * 4)?;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        let p = &self.project;
        dispatch_projected(
            ctx,
            &mut enc,
            splats,
            &p.row_counts,
            params_buf,
            proj,
            |_| vec![(9, rows.as_entire_buffer_binding())],
        );
        ctx.queue.submit([enc.finish()]);
        read_buffer(ctx, &rows, ty as usize)
    }

    /// Records the backward pass of `frame` into `enc`: `dl_dimage` is dL/d(image), w·h·3 f32
    /// interleaved RGB; overwrites every gradient in `grads` and adds to its densification
    /// statistic. Put it in the same command buffer as the loss and the optimiser step.
    pub fn encode_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads: &GpuGrads,
    ) -> Result<(), GpuError> {
        self.backward_impl(ctx, Some(enc), splats, frame, dl_dimage, grads, false)
            .map(|_| ())
    }

    /// Runs the backward pass of `frame` (see [`Renderer::encode_backward`]) and submits it;
    /// when `timed` waits after each pass to time it (the timings are zero otherwise).
    pub fn backward(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads: &GpuGrads,
        timed: bool,
    ) -> Result<PassTimings, GpuError> {
        self.backward_impl(ctx, None, splats, frame, dl_dimage, grads, timed)
    }

    #[allow(clippy::too_many_arguments)]
    fn backward_impl(
        &self,
        ctx: &GpuContext,
        enc_in: Option<&mut wgpu::CommandEncoder>,
        splats: &GpuSplats,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads: &GpuGrads,
        timed: bool,
    ) -> Result<PassTimings, GpuError> {
        if splats.count != frame.count || grads.count != frame.count {
            return Err(GpuError::Invalid(format!(
                "backward over {} Gaussians with a model of {} and gradients of {}",
                frame.count, splats.count, grads.count
            )));
        }
        if dl_dimage.size() < frame.pixels() as u64 * 12 {
            return Err(GpuError::Invalid(format!(
                "dL/dimage holds {} bytes, the image needs {}",
                dl_dimage.size(),
                frame.pixels() * 12
            )));
        }
        let grads2d = chunked_zeroed(ctx, "grads 2d", frame.count as u64 * GRADS2D_STRIDE * 4)?;
        let mut times = PassTimings::default();
        if let Some(enc) = enc_in {
            self.raster_bwd.encode(ctx, enc, frame, dl_dimage, &grads2d);
            self.project_bwd
                .encode(ctx, enc, splats, frame, &grads2d, grads);
            return Ok(times);
        }
        let mut clock = Clock::start(ctx, timed)?;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.raster_bwd
            .encode(ctx, &mut enc, frame, dl_dimage, &grads2d);
        if timed {
            times.raster_bwd_ms = clock.submit(ctx, enc)?;
            enc = ctx.device.create_command_encoder(&Default::default());
        }
        self.project_bwd
            .encode(ctx, &mut enc, splats, frame, &grads2d, grads);
        times.project_bwd_ms = clock.submit(ctx, enc)?;
        Ok(times)
    }
}

/// Tile rows and intersections of one band.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BandSpan {
    /// First tile row.
    pub row0: u32,
    /// Tile rows.
    pub rows: u32,
    /// Intersections in those rows.
    pub count: u32,
}

/// Splits tile rows with `row_counts` intersections each into consecutive bands of at most `cap`
/// intersections (greedy, top to bottom; every row in exactly one band). Fails with
/// [`GpuError::BufferTooLarge`] when one row alone exceeds `cap`.
pub fn plan_bands(row_counts: &[u32], cap: u64) -> Result<Vec<BandSpan>, GpuError> {
    let mut out: Vec<BandSpan> = Vec::new();
    let mut cur: Option<BandSpan> = None;
    for (y, &c) in row_counts.iter().enumerate() {
        let y = u32::try_from(y).unwrap_or(u32::MAX);
        if u64::from(c) > cap {
            return Err(GpuError::BufferTooLarge {
                what: "the tile intersections of one row of 16-pixel tiles",
                bytes: u64::from(c) * 4,
                limit: cap * 4,
            });
        }
        cur = match cur {
            Some(b) if u64::from(b.count) + u64::from(c) <= cap => Some(BandSpan {
                rows: b.rows + 1,
                count: b.count + c,
                ..b
            }),
            Some(b) => {
                out.push(b);
                Some(BandSpan {
                    row0: y,
                    rows: 1,
                    count: c,
                })
            }
            None => Some(BandSpan {
                row0: y,
                rows: 1,
                count: c,
            }),
        };
    }
    out.extend(cur);
    Ok(out)
}
