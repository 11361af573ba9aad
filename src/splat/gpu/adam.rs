//! Adam on the GPU (`adam.wgsl`), one dispatch per parameter buffer and chunk, with a CPU twin.
//!
//! Hyper-parameters are the reference's (Kerbl et al. 2023 `train.py`, torch Adam):
//! β1 = 0.9, β2 = 0.999, ε = 1e-15. Moments start at zero; the step count is shared.

use crate::splat::model::SH_FLOATS;

use crate::splat::gpu::buffers::{
    chunked_uploaded, chunked_zeroed, params_from, read_buffer, wgsl_struct,
};
use crate::splat::gpu::chunks::bind_ranges;
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::project::{dispatch_group, groups_for};
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};

/// First-moment decay (reference / torch default).
pub const BETA1: f32 = 0.9;
/// Second-moment decay (reference / torch default).
pub const BETA2: f32 = 0.999;
/// Denominator epsilon (reference `eps=1e-15`).
pub const EPSILON: f32 = 1e-15;

/// Learning rates of one step, per parameter group (units: parameter units per step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamRates {
    /// Means, metres (already × scene extent).
    pub means: f32,
    pub log_scales: f32,
    pub rotations: f32,
    pub opacity: f32,
    /// SH DC coefficients (the first 3 floats of each Gaussian's 48).
    pub sh_dc: f32,
    /// SH coefficients of degree ≥ 1.
    pub sh_rest: f32,
}

impl AdamRates {
    /// Per parameter buffer, in [`GpuSplats::buffers`]' order: the rate of the first `n_first`
    /// floats of each Gaussian, the rate of the others, and `n_first`.
    pub fn per_buffer(&self) -> [(f32, f32, u32); 5] {
        [
            (self.means, self.means, 3),
            (self.log_scales, self.log_scales, 3),
            (self.rotations, self.rotations, 4),
            (self.opacity, self.opacity, 1),
            (self.sh_dc, self.sh_rest, 3),
        ]
    }
}

wgsl_struct! {
    /// The parameter buffer of `adam.wgsl`.
    struct AdamParams {
        n_floats: u32,
        stride: u32,
        n_first: u32,
        _pad: u32,
        lr_first: f32,
        lr_rest: f32,
        bc1: f32,
        bc2: f32,
        beta1: f32,
        beta2: f32,
        eps: f32,
        _pad2: f32,
    }
}

/// Bias corrections (1 − β1^t, 1 − β2^t) at 1-based step `t`, computed in f64.
pub fn bias_corrections(step: u32) -> (f32, f32) {
    let t = step as i32;
    (
        (1.0 - (BETA1 as f64).powi(t)) as f32,
        (1.0 - (BETA2 as f64).powi(t)) as f32,
    )
}

/// The CPU twin of `adam.wgsl` for one buffer at 1-based step `step`: floats whose index within
/// a stride of `stride` is below `n_first` use `lr_first`, the others `lr_rest`; `eps` is the
/// denominator ε ([`EPSILON`] for the model, torch's default
/// [`crate::splat::exposure::EXPOSURE_EPSILON`] for the exposures).
#[allow(clippy::too_many_arguments)]
pub fn adam_cpu(
    params: &mut [f32],
    grads: &[f32],
    m: &mut [f32],
    v: &mut [f32],
    stride: usize,
    n_first: usize,
    lr_first: f32,
    lr_rest: f32,
    step: u32,
    eps: f32,
) {
    let (bc1, bc2) = bias_corrections(step);
    for (i, p) in params.iter_mut().enumerate() {
        let g = grads[i];
        m[i] = BETA1 * m[i] + (1.0 - BETA1) * g;
        v[i] = BETA2 * v[i] + (1.0 - BETA2) * g * g;
        let lr = if i % stride.max(1) < n_first {
            lr_first
        } else {
            lr_rest
        };
        *p -= lr * (m[i] / bc1) / ((v[i] / bc2).sqrt() + eps);
    }
}

/// The Adam pipeline of `adam.wgsl`, for flat buffers outside the model
/// ([`encode_adam_flat`]).
pub fn adam_pipeline(ctx: &GpuContext) -> wgpu::ComputePipeline {
    let src = format!(
        "{}\n{}",
        AdamParams::wgsl(),
        include_str!("../../../shaders/adam.wgsl")
    );
    crate::splat::gpu::buffers::pipeline(ctx, "adam", &src, "main")
}

/// Records one Adam step of the first `n_floats` floats of `param` (one rate `lr`, gradient
/// `grad`, moments `m` and `v`, all whole storage buffers) at 1-based step `step` with
/// denominator `eps`; `pipeline` from [`adam_pipeline`]. The CPU twin is [`adam_cpu`].
#[allow(clippy::too_many_arguments)]
pub fn encode_adam_flat(
    ctx: &GpuContext,
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    [param, grad, m, v]: [&wgpu::Buffer; 4],
    n_floats: u32,
    lr: f32,
    step: u32,
    eps: f32,
) {
    let (bc1, bc2) = bias_corrections(step);
    let ap = AdamParams {
        n_floats,
        stride: 1,
        n_first: 1,
        _pad: 0,
        lr_first: lr,
        lr_rest: lr,
        bc1,
        bc2,
        beta1: BETA1,
        beta2: BETA2,
        eps,
        _pad2: 0.0,
    };
    let u = params_from(ctx, "adam params", &ap);
    let bg = crate::splat::gpu::buffers::bind(ctx, pipeline, &[&u, param, grad, m, v]);
    dispatch_group(enc, pipeline, &bg, groups_for(n_floats));
}

/// First and second moments of one parameter group, flat in the model's layout.
pub type MomentPair = (Vec<f32>, Vec<f32>);

/// Adam state on the GPU: (m, v) per parameter buffer, in [`GpuSplats::buffers`] order.
pub struct GpuAdam {
    pipeline: wgpu::ComputePipeline,
    moments: Vec<(wgpu::Buffer, wgpu::Buffer)>,
    /// Steps taken (t of the bias correction).
    pub step: u32,
    /// Number of Gaussians covered.
    pub count: u32,
}

impl GpuAdam {
    /// Zero moments for `count` Gaussians.
    pub fn new(ctx: &GpuContext, count: u32) -> Result<Self, GpuError> {
        let strides = [3u64, 3, 4, 1, SH_FLOATS as u64];
        let moments = strides
            .iter()
            .map(|s| {
                let bytes = s * count as u64 * 4;
                Ok((
                    chunked_zeroed(ctx, "adam m", bytes)?,
                    chunked_zeroed(ctx, "adam v", bytes)?,
                ))
            })
            .collect::<Result<_, GpuError>>()?;
        Ok(GpuAdam {
            pipeline: adam_pipeline(ctx),
            moments,
            step: 0,
            count,
        })
    }

    /// State from CPU moments (after densification remapped them): `moments[k]` = (m, v) of
    /// parameter group k in [`GpuSplats::buffers`] order, flat.
    pub fn from_moments(
        ctx: &GpuContext,
        count: u32,
        step: u32,
        moments: &[MomentPair; 5],
    ) -> Result<Self, GpuError> {
        let strides = [3usize, 3, 4, 1, SH_FLOATS];
        for (k, ((m, v), st)) in moments.iter().zip(strides).enumerate() {
            let want = st * count as usize;
            if m.len() != want || v.len() != want {
                return Err(GpuError::Invalid(format!(
                    "Adam moments of group {k} hold {} and {} floats, {want} expected",
                    m.len(),
                    v.len()
                )));
            }
        }
        // Uploaded directly: no zeroed moments beside them, even for a moment.
        let moments = moments
            .iter()
            .map(|(m, v)| {
                Ok((
                    chunked_uploaded(ctx, "adam m", m)?,
                    chunked_uploaded(ctx, "adam v", v)?,
                ))
            })
            .collect::<Result<_, GpuError>>()?;
        Ok(GpuAdam {
            pipeline: adam_pipeline(ctx),
            moments,
            step,
            count,
        })
    }

    /// Reads the moments back (blocking), in [`GpuSplats::buffers`] order.
    pub fn download_moments(&self, ctx: &GpuContext) -> Result<Vec<MomentPair>, GpuError> {
        let strides = [3usize, 3, 4, 1, SH_FLOATS];
        self.moments
            .iter()
            .zip(strides)
            .map(|((m, v), s)| {
                let n = s * self.count as usize;
                Ok((read_buffer(ctx, m, n)?, read_buffer(ctx, v, n)?))
            })
            .collect()
    }

    /// Records one Adam step of every parameter of `splats` with `grads` into `enc`.
    pub fn encode_step(
        &mut self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        grads: &GpuGrads,
        rates: &AdamRates,
    ) -> Result<(), GpuError> {
        if splats.count != self.count || grads.count != self.count {
            return Err(GpuError::Invalid(format!(
                "Adam state for {} Gaussians, model {}, gradients {}",
                self.count, splats.count, grads.count
            )));
        }
        self.step += 1;
        let (bc1, bc2) = bias_corrections(self.step);
        let grad_bufs = grads.buffers();
        let lrs = rates.per_buffer();
        for (k, ((param, stride), (m, v))) in
            splats.buffers().into_iter().zip(&self.moments).enumerate()
        {
            let (lr_first, lr_rest, n_first) = lrs[k];
            let floats = stride as u32;
            // A chunk starts at a whole Gaussian, so `i % stride` in the kernel is unchanged.
            for chunk in splats.plan.chunks() {
                let n_floats = floats * chunk.len;
                let ap = AdamParams {
                    n_floats,
                    stride: floats,
                    n_first,
                    _pad: 0,
                    lr_first,
                    lr_rest,
                    bc1,
                    bc2,
                    beta1: BETA1,
                    beta2: BETA2,
                    eps: EPSILON,
                    _pad2: 0.0,
                };
                let u = params_from(ctx, "adam params", &ap);
                let bg = bind_ranges(
                    ctx,
                    &self.pipeline,
                    &[
                        u.as_entire_buffer_binding(),
                        chunk.range(param, floats),
                        chunk.range(grad_bufs[k], floats),
                        chunk.range(m, floats),
                        chunk.range(v, floats),
                    ],
                );
                dispatch_group(enc, &self.pipeline, &bg, groups_for(n_floats));
            }
        }
        Ok(())
    }

    /// One Adam step, submitted.
    pub fn step(
        &mut self,
        ctx: &GpuContext,
        splats: &GpuSplats,
        grads: &GpuGrads,
        rates: &AdamRates,
    ) -> Result<(), GpuError> {
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        self.encode_step(ctx, &mut enc, splats, grads, rates)?;
        ctx.queue.submit([enc.finish()]);
        Ok(())
    }
}
