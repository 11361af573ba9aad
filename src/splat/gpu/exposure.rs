//! Per-image exposure compensation on the GPU (`shaders/exposure.wgsl`; docs/splatting.md
//! "Exposure"). The transforms of every image and their Adam moments stay on the GPU; a step
//! records four dispatches into the step's encoder — apply the image's transform to the
//! render, then (after the loss) the backward with its per-workgroup sums, one workgroup
//! reducing those into the gradient of every image's 12 floats (zero but for the stepped
//! image), and Adam (`adam.wgsl`) over all of them. The image index travels in a parameter buffer
//! written with the dispatch: nothing is read back.
//!
//! CPU twins: [`crate::splat::cpu::exposure`] (apply, backward) and
//! [`crate::splat::exposure::ExposureState`] (Adam).

use crate::splat::exposure::{EXPOSURE_EPSILON, EXPOSURE_FLOATS, ExposureSlot, ExposureState};
use crate::splat::gpu::adam::{adam_pipeline, encode_adam_flat};
use crate::splat::gpu::buffers::{
    bind_indexed, grid, params_from, pipeline, read_buffer, storage_from, storage_zeroed,
    wgsl_struct,
};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::project::dispatch_group;

/// Threads per workgroup of the per-pixel passes (one pixel each).
const GROUP: u32 = 256;

wgsl_struct! {
    /// The parameter buffer of `exposure.wgsl`.
    struct Params {
        width: u32,
        height: u32,
        /// The image whose transform applies.
        index: u32,
        /// 1 on a held-out view's training step: pixels with x ≥ width / 2 take the photo and
        /// give no gradient.
        left_half: u32,
        /// Workgroups of `backward` (12-float partial sums).
        n_partials: u32,
        /// Images (the gradient buffer holds 12 floats per image).
        n_images: u32,
        _pad0: u32,
        _pad1: u32,
    }
}

/// The per-step buffers of one image size: the exposed render, dL/d(exposed render) and the
/// per-workgroup partial sums.
pub struct ExposureScratch {
    /// Pixels these buffers hold.
    pub pixels: usize,
    /// The exposed render, RGB f32 interleaved (the loss reads it).
    pub exposed: wgpu::Buffer,
    /// dL/d(exposed render), RGB f32 interleaved (the loss writes it).
    pub dl_out: wgpu::Buffer,
    partials: wgpu::Buffer,
}

impl ExposureScratch {
    /// Buffers for images of `pixels` pixels.
    pub fn new(ctx: &GpuContext, pixels: usize) -> Result<Self, GpuError> {
        let groups = (pixels as u64).div_ceil(u64::from(GROUP));
        Ok(ExposureScratch {
            pixels,
            exposed: storage_zeroed(ctx, "exposed image", pixels as u64 * 12)?,
            dl_out: storage_zeroed(ctx, "dL/dexposed", pixels as u64 * 12)?,
            partials: storage_zeroed(ctx, "exposure partials", groups * 48)?,
        })
    }
}

/// See the module documentation.
pub struct GpuExposure {
    apply: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    reduce: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    count: u32,
    /// `[A | b]` per image, 12 f32 each.
    pub params: wgpu::Buffer,
    /// dL/d`[A | b]` of the latest step, per image.
    pub grads: wgpu::Buffer,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    /// Bound as the photo where none is read (renders for evaluation).
    dummy: wgpu::Buffer,
    /// Adam steps taken (t of the bias correction).
    pub step: u32,
}

impl GpuExposure {
    /// Identity transforms with zero moments for `count` images.
    pub fn new(ctx: &GpuContext, count: usize) -> Result<Self, GpuError> {
        Self::from_state(ctx, &ExposureState::new(count))
    }

    /// The transforms, moments and step count of `state`.
    pub fn from_state(ctx: &GpuContext, state: &ExposureState) -> Result<Self, GpuError> {
        let n = state.len();
        let floats = n * EXPOSURE_FLOATS;
        if state.m.len() != floats || state.v.len() != floats {
            return Err(GpuError::Invalid(format!(
                "exposure moments hold {} and {} floats, {floats} expected",
                state.m.len(),
                state.v.len()
            )));
        }
        let count = u32::try_from(n)
            .map_err(|_| GpuError::Invalid(format!("{n} exposures are too many")))?;
        let shader = format!(
            "{}\n{}",
            Params::wgsl(),
            include_str!("../../../shaders/exposure.wgsl")
        );
        Ok(GpuExposure {
            apply: pipeline(ctx, "exposure apply", &shader, "apply"),
            backward: pipeline(ctx, "exposure backward", &shader, "backward"),
            reduce: pipeline(ctx, "exposure reduce", &shader, "reduce"),
            adam: adam_pipeline(ctx),
            count,
            params: storage_from(ctx, "exposures", state.params.as_flattened())?,
            grads: storage_zeroed(ctx, "exposure grads", floats as u64 * 4)?,
            m: storage_from(ctx, "exposure adam m", &state.m)?,
            v: storage_from(ctx, "exposure adam v", &state.v)?,
            dummy: storage_zeroed(ctx, "exposure dummy", 16)?,
            step: state.step,
        })
    }

    /// Number of images.
    pub fn count(&self) -> usize {
        self.count as usize
    }

    /// Reads the transforms, moments and step count back (blocking).
    pub fn download(&self, ctx: &GpuContext) -> Result<ExposureState, GpuError> {
        let floats = self.count() * EXPOSURE_FLOATS;
        let flat: Vec<f32> = read_buffer(ctx, &self.params, floats)?;
        Ok(ExposureState {
            params: flat
                .chunks_exact(EXPOSURE_FLOATS)
                .map(|c| std::array::from_fn(|k| c[k]))
                .collect(),
            m: read_buffer(ctx, &self.m, floats)?,
            v: read_buffer(ctx, &self.v, floats)?,
            step: self.step,
        })
    }

    fn params(
        &self,
        ctx: &GpuContext,
        width: u32,
        height: u32,
        slot: ExposureSlot,
    ) -> wgpu::Buffer {
        let pixels = u64::from(width) * u64::from(height);
        params_from(
            ctx,
            "exposure params",
            &Params {
                width,
                height,
                index: slot.index as u32,
                left_half: u32::from(slot.left_half),
                n_partials: pixels.div_ceil(u64::from(GROUP)) as u32,
                n_images: self.count,
                _pad0: 0,
                _pad1: 0,
            },
        )
    }

    fn check(
        &self,
        scratch: &ExposureScratch,
        width: u32,
        height: u32,
        slot: ExposureSlot,
    ) -> Result<(), GpuError> {
        if slot.index >= self.count() {
            return Err(GpuError::Invalid(format!(
                "exposure of image {} asked for, but {} are on the GPU",
                slot.index, self.count
            )));
        }
        let pixels = width as usize * height as usize;
        if pixels == 0 || scratch.pixels != pixels {
            return Err(GpuError::Invalid(format!(
                "exposure scratch for {} pixels, image {width}×{height}",
                scratch.pixels
            )));
        }
        Ok(())
    }

    /// Records `scratch.exposed = A · rendered + b` of image `slot.index` (`rendered`: RGB f32,
    /// `width × height`); with `slot.left_half` the pixels of columns `x ≥ width / 2` take the
    /// photo `target` (RGBA8 per pixel) instead, which must then be given.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_apply(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        rendered: &wgpu::Buffer,
        target: Option<&wgpu::Buffer>,
        scratch: &ExposureScratch,
        width: u32,
        height: u32,
        slot: ExposureSlot,
    ) -> Result<(), GpuError> {
        self.check(scratch, width, height, slot)?;
        if slot.left_half && target.is_none() {
            return Err(GpuError::Invalid(
                "a held-out view's exposure step needs its photo".into(),
            ));
        }
        let u = self.params(ctx, width, height, slot);
        let buffers = [
            (0, &u),
            (1, rendered),
            (2, target.unwrap_or(&self.dummy)),
            (3, &self.params),
            (4, &scratch.exposed),
        ];
        dispatch_pixels(ctx, enc, &self.apply, &buffers, width * height);
        Ok(())
    }

    /// Records the backward of [`GpuExposure::encode_apply`]: from `scratch.dl_out`
    /// (dL/d(exposed render)) writes `dl_drgb = Aᵀ · dL/dout` (zero on the photo's pixels of a
    /// left-half step) and [`GpuExposure::grads`]: dL/d`[A | b]` of image `slot.index` summed
    /// over the pixels, zero for every other image.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        rendered: &wgpu::Buffer,
        scratch: &ExposureScratch,
        dl_drgb: &wgpu::Buffer,
        width: u32,
        height: u32,
        slot: ExposureSlot,
    ) -> Result<(), GpuError> {
        self.check(scratch, width, height, slot)?;
        let u = self.params(ctx, width, height, slot);
        let buffers = [
            (0, &u),
            (1, rendered),
            (3, &self.params),
            (5, &scratch.dl_out),
            (6, dl_drgb),
            (7, &scratch.partials),
        ];
        dispatch_pixels(ctx, enc, &self.backward, &buffers, width * height);
        let bg = bind_indexed(
            ctx,
            &self.reduce,
            &[(0, &u), (7, &scratch.partials), (8, &self.grads)],
        );
        dispatch_group(enc, &self.reduce, &bg, (1, 1));
        Ok(())
    }

    /// Records one Adam step of every image's transform with [`GpuExposure::grads`] at rate
    /// `lr` (ε = [`EXPOSURE_EPSILON`]).
    pub fn encode_adam(&mut self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, lr: f32) {
        if self.count == 0 {
            return;
        }
        self.step += 1;
        encode_adam_flat(
            ctx,
            enc,
            &self.adam,
            [&self.params, &self.grads, &self.m, &self.v],
            self.count * EXPOSURE_FLOATS as u32,
            lr,
            self.step,
            EXPOSURE_EPSILON,
        );
    }
}

/// Records `pipeline` with `buffers` bound (group 0), one thread per pixel of `pixels`.
fn dispatch_pixels(
    ctx: &GpuContext,
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    buffers: &[(u32, &wgpu::Buffer)],
    pixels: u32,
) {
    let bg = bind_indexed(ctx, pipeline, buffers);
    dispatch_group(enc, pipeline, &bg, grid(pixels.div_ceil(GROUP)));
}
