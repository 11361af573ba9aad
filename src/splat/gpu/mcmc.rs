//! The MCMC strategy's per-step terms on the GPU ([`crate::splat::mcmc`]): the regularisers'
//! gradients (`mcmc.wgsl`'s `regularise`, after the backward passes) and the position noise
//! (its `noise`, after Adam), one thread per Gaussian of each chunk, no read-back. The CPU
//! twins are `mcmc::regularise_grads` and `mcmc::add_noise`.

use crate::splat::gpu::buffers::bind_entries;
use crate::splat::gpu::buffers::{chunked_from, params_from, pipeline, wgsl_struct};
use crate::splat::gpu::chunks::Chunk;
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::project::{dispatch_group, groups_for};
use crate::splat::gpu::splats::{GpuGrads, GpuSplats};
use crate::splat::mcmc::{self, StepTerms};

wgsl_struct! {
    /// The parameter buffer of both kernels.
    struct McmcParams {
        /// Gaussians in the whole model (the regularisers are means over all of them).
        n_total: u32,
        /// Optimiser step (1-based) and seed of the noise.
        step: u32,
        seed: u32,
        _p0: u32,
        /// λ_o / N and λ_s / (3 N).
        opacity_coef: f32,
        scale_coef: f32,
        /// Position learning rate × noise_lr.
        scaler: f32,
        _p1: f32,
    }
}

/// The two kernels, the terms and the per-Gaussian flags of the installed model.
pub struct GpuMcmc {
    regularise: wgpu::ComputePipeline,
    noise: wgpu::ComputePipeline,
    terms: StepTerms,
    /// [`mcmc::FLAG_BOUND`] / [`mcmc::FLAG_BACKGROUND`] per Gaussian.
    flags: wgpu::Buffer,
    count: u32,
}

impl GpuMcmc {
    /// Compiles the kernels for `terms` and uploads the flags of the Gaussians with trunk
    /// probabilities `trunk_prob`.
    pub fn new(ctx: &GpuContext, terms: StepTerms, trunk_prob: &[f32]) -> Result<Self, GpuError> {
        let src = format!(
            "{}\n{}",
            McmcParams::wgsl(),
            include_str!("../../../shaders/mcmc.wgsl")
        );
        let regularise = pipeline(ctx, "mcmc regularise", &src, "regularise");
        let noise = pipeline(ctx, "mcmc noise", &src, "noise");
        let mut s = GpuMcmc {
            regularise,
            noise,
            terms,
            flags: chunked_from(ctx, "mcmc flags", &[0u32])?,
            count: 0,
        };
        s.set_model(ctx, trunk_prob)?;
        Ok(s)
    }

    /// The flags of a new model (after every refinement).
    pub fn set_model(&mut self, ctx: &GpuContext, trunk_prob: &[f32]) -> Result<(), GpuError> {
        let flags = mcmc::flags(trunk_prob, &self.terms);
        self.flags = chunked_from(ctx, "mcmc flags", &flags)?;
        self.count = u32::try_from(flags.len())
            .map_err(|_| GpuError::Invalid("too many Gaussians for the MCMC flags".into()))?;
        Ok(())
    }

    fn params(&self, step: u32, lr_position: f32) -> McmcParams {
        let n = self.count.max(1) as f32;
        McmcParams {
            n_total: self.count,
            step,
            seed: self.terms.seed,
            _p0: 0,
            opacity_coef: self.terms.opacity_reg / n,
            scale_coef: self.terms.scale_reg / (3.0 * n),
            scaler: lr_position * self.terms.noise_lr,
            _p1: 0.0,
        }
    }

    fn check(&self, splats: &GpuSplats) -> Result<(), GpuError> {
        if splats.count != self.count {
            return Err(GpuError::Invalid(format!(
                "MCMC flags for {} Gaussians, model {}",
                self.count, splats.count
            )));
        }
        Ok(())
    }

    /// Bindings 0-4 of both kernels for `chunk`: the parameters `u`, the chunk uniform `cu`,
    /// the chunk's opacity logits, log-scales and flags.
    fn shared_bindings<'a>(
        &'a self,
        u: &'a wgpu::Buffer,
        cu: &'a wgpu::Buffer,
        chunk: &Chunk,
        splats: &'a GpuSplats,
    ) -> Vec<(u32, wgpu::BufferBinding<'a>)> {
        vec![
            (0, u.as_entire_buffer_binding()),
            (1, cu.as_entire_buffer_binding()),
            (2, chunk.range(&splats.opacity_logits, 1)),
            (3, chunk.range(&splats.log_scales, 3)),
            (4, chunk.range(&self.flags, 1)),
        ]
    }

    /// Records the regularisers' gradients (before Adam).
    pub fn encode_regularise(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        grads: &GpuGrads,
    ) -> Result<(), GpuError> {
        let extra = [(5, &grads.opacity_logits, 1), (6, &grads.log_scales, 3)];
        self.encode_pass(ctx, enc, splats, &self.regularise, (0, 0.0), extra)
    }

    /// Records the position noise of optimiser step `step` (after Adam) with the step's
    /// position learning rate, metres.
    pub fn encode_noise(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        step: u32,
        lr_position: f32,
    ) -> Result<(), GpuError> {
        let extra = [(7, &splats.means, 3), (8, &splats.rotations, 4)];
        self.encode_pass(ctx, enc, splats, &self.noise, (step, lr_position), extra)
    }

    /// Records `pipeline` (either kernel) once per chunk with the parameters of optimiser step
    /// `step` at position learning rate `lr`: the shared bindings plus the chunk's range of each
    /// `(binding, buffer, floats per Gaussian)` of `extra`.
    fn encode_pass(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        splats: &GpuSplats,
        pipeline: &wgpu::ComputePipeline,
        (step, lr): (u32, f32),
        extra: [(u32, &wgpu::Buffer, u32); 2],
    ) -> Result<(), GpuError> {
        self.check(splats)?;
        let u = params_from(ctx, "mcmc params", &self.params(step, lr));
        for chunk in splats.plan.chunks() {
            let cu = chunk.params(ctx);
            let mut b = self.shared_bindings(&u, &cu, &chunk, splats);
            b.extend(extra.map(|(slot, buffer, floats)| (slot, chunk.range(buffer, floats))));
            let bg = bind_entries(ctx, pipeline, &b);
            dispatch_group(enc, pipeline, &bg, groups_for(chunk.len));
        }
        Ok(())
    }
}
