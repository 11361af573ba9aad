//! The rasteriser: forward (projection → tile counts → scan → emit → sort → ranges → raster) and
//! backward (raster backward → projection backward), with optional per-pass CPU timing.

use std::time::Instant;

use crate::splat::camera::Camera;

use crate::splat::gpu::buffers::{read_buffer, storage_zeroed, uniform_from};
use crate::splat::gpu::chunks::bind_ranges;
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::frame::Frame;
use crate::splat::gpu::params::RenderParams;
use crate::splat::gpu::project::{ProjectKernels, dispatch, dispatch_group, groups_for};
use crate::splat::gpu::project_bwd::ProjectBwd;
use crate::splat::gpu::raster_bwd::{GRADS2D_STRIDE, RasterBwd};
use crate::splat::gpu::raster_fwd::RasterFwd;
use crate::splat::gpu::scan::Scanner;
use crate::splat::gpu::sort::{RadixSorter, bits_for};
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};
use crate::splat::gpu::timing::{Clock, PassTimings};
use crate::splat::model::SH_FLOATS;

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

    /// Renders `splats` through `cam` over `background` (RGB). Reads one `u32` (the number of
    /// tile intersections) back from the GPU; everything else stays on the GPU.
    pub fn render(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
    ) -> Result<Frame, GpuError> {
        self.render_impl(ctx, splats, cam, background, false)
            .map(|(f, _)| f)
    }

    /// As [`Renderer::render`], waiting after each pass to time it.
    pub fn render_timed(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
    ) -> Result<(Frame, PassTimings), GpuError> {
        self.render_impl(ctx, splats, cam, background, true)
    }

    fn render_impl(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        cam: &Camera,
        background: [f32; 3],
        timed: bool,
    ) -> Result<(Frame, PassTimings), GpuError> {
        if cam.width == 0 || cam.height == 0 || !(cam.fx > 0.0 && cam.fy > 0.0) {
            return Err(GpuError::Invalid(format!(
                "camera {}x{} px with fx {} fy {}",
                cam.width, cam.height, cam.fx, cam.fy
            )));
        }
        if ctx.device.limits().max_storage_buffers_per_shader_stage < 12 {
            return Err(GpuError::Invalid(
                "the adapter allows fewer than 12 storage buffers per shader stage".into(),
            ));
        }
        let mut times = PassTimings::default();
        let mut clock = Clock {
            on: timed,
            last: Instant::now(),
        };
        if timed {
            ctx.wait()?;
            clock.last = Instant::now();
        }
        let n = splats.count;
        let mut params = RenderParams::new(cam, background, n, splats.sh_degree);
        let params_buf = uniform_from(ctx, "render params", &params);
        let proj = storage_zeroed(ctx, "projected", n as u64 * 48)?;
        let offsets = storage_zeroed(ctx, "tile offsets", (n as u64 + 1) * 4)?;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        let p = &self.project;
        let s = splats;
        for chunk in s.plan.chunks() {
            let cu = chunk.uniform(ctx);
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
                    proj.as_entire_buffer_binding(),
                    offsets.as_entire_buffer_binding(),
                    cu.as_entire_buffer_binding(),
                ],
            );
            dispatch_group(&mut enc, &p.project, &bg, groups_for(chunk.len));
        }
        self.scanner.encode(ctx, &mut enc, &offsets, n + 1)?;
        ctx.queue.submit([enc.finish()]);
        // The one read-back of the forward pass: the total number of intersections.
        let total = read_buffer::<u32>(ctx, &offsets, n as usize + 1)?;
        let isect = total.last().copied().unwrap_or(0);
        times.project_ms =
            clock.submit(ctx, ctx.device.create_command_encoder(&Default::default()))?;

        params.counts[2] = isect;
        ctx.queue
            .write_buffer(&params_buf, 0, bytemuck::bytes_of(&params));
        let (tx, ty) = params.tiles();
        let tiles = tx * ty;
        let m = isect as u64 * 4;
        let keys_hi = storage_zeroed(ctx, "keys hi (tile)", m)?;
        let keys_lo = storage_zeroed(ctx, "keys lo (depth)", m)?;
        let values = storage_zeroed(ctx, "sorted ids", m)?;
        let ranges = storage_zeroed(ctx, "tile ranges", tiles as u64 * 8)?;
        let pixels = cam.width as u64 * cam.height as u64;
        let image = storage_zeroed(ctx, "image", pixels * 12)?;
        let final_t = storage_zeroed(ctx, "final T", pixels * 4)?;
        let n_contrib = storage_zeroed(ctx, "n contrib", pixels * 4)?;
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        let emit_bufs = [&params_buf, &proj, &offsets, &keys_hi, &keys_lo, &values];
        dispatch(ctx, &mut enc, &p.emit, &emit_bufs, groups_for(n));
        self.sorter.encode(
            ctx,
            &mut enc,
            &keys_hi,
            &keys_lo,
            &values,
            isect,
            bits_for(tiles - 1),
        )?;
        let rbg = crate::splat::gpu::buffers::bind_indexed(
            ctx,
            &p.ranges,
            &[(0, &params_buf), (3, &keys_hi), (6, &ranges)],
        );
        dispatch_group(&mut enc, &p.ranges, &rbg, groups_for(isect));
        times.sort_ms = clock.submit(ctx, enc)?;

        let frame = Frame {
            params,
            params_buf,
            proj,
            offsets,
            keys_hi,
            keys_lo,
            values,
            ranges,
            image,
            final_t,
            n_contrib,
            count: n,
            intersections: isect,
        };
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.raster_fwd.encode(ctx, &mut enc, &frame);
        times.raster_ms = clock.submit(ctx, enc)?;
        Ok((frame, times))
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

    /// Runs the backward pass of `frame` (see [`Renderer::encode_backward`]) and submits it.
    pub fn backward(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads: &GpuGrads,
    ) -> Result<(), GpuError> {
        self.backward_impl(ctx, None, splats, frame, dl_dimage, grads, false)
            .map(|_| ())
    }

    /// As [`Renderer::backward`], waiting after each pass; fills the backward timings.
    pub fn backward_timed(
        &self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        frame: &Frame,
        dl_dimage: &wgpu::Buffer,
        grads: &GpuGrads,
    ) -> Result<PassTimings, GpuError> {
        self.backward_impl(ctx, None, splats, frame, dl_dimage, grads, true)
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
        let grads2d = storage_zeroed(ctx, "grads 2d", frame.count as u64 * GRADS2D_STRIDE * 4)?;
        let mut times = PassTimings::default();
        if let Some(enc) = enc_in {
            self.raster_bwd.encode(ctx, enc, frame, dl_dimage, &grads2d);
            self.project_bwd
                .encode(ctx, enc, splats, frame, &grads2d, grads);
            return Ok(times);
        }
        let mut clock = Clock {
            on: timed,
            last: Instant::now(),
        };
        if timed {
            ctx.wait()?;
            clock.last = Instant::now();
        }
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
