//! Adam on the CPU over the Gaussians' parameter groups, with state that follows densification.
//!
//! One moment pair (m, v) per trained float, stored per parameter group in the model's own
//! layout (stride = floats per Gaussian), so that reordering, cloning and pruning Gaussians is a
//! gather over whole strides. Hyper-parameters are the reference's (torch Adam with
//! β1 = 0.9, β2 = 0.999, ε = 1e-15, Kerbl et al. 2023 `gaussian_model.py`).
//! Like the reference, the step count is shared and survives densification; new Gaussians start
//! with zero moments.

use crate::splat::model::{GaussianGrads, Gaussians, SH_FLOATS};

use crate::splat::config::TrainConfig;

/// First-moment decay. Default 0.9 (reference, torch default).
pub const BETA1: f32 = 0.9;
/// Second-moment decay. Default 0.999 (reference, torch default).
pub const BETA2: f32 = 0.999;
/// Denominator epsilon. Default 1e-15 (reference `eps=1e-15`).
pub const EPSILON: f32 = 1e-15;

/// Position learning rate at `step` (1-based, as the reference `iteration`) in world units: the reference `expon_lr_func`
/// (log-linear from `lr_position_init` to `lr_position_final` over `cfg.steps`), × `scene_extent`
/// (metres).
pub fn lr_position(cfg: &TrainConfig, step: u32, scene_extent: f32) -> f32 {
    let t = (step as f64 / cfg.steps.max(1) as f64).clamp(0.0, 1.0);
    let init = (cfg.lr_position_init.max(f32::MIN_POSITIVE) as f64).ln();
    let last = (cfg.lr_position_final.max(f32::MIN_POSITIVE) as f64).ln();
    ((init * (1.0 - t) + last * t).exp() * scene_extent as f64) as f32
}

/// Learning rates of every parameter group at one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LearningRates {
    /// Means, metres per step (already × scene extent).
    pub position: f32,
    /// SH DC coefficients.
    pub sh_dc: f32,
    /// SH coefficients of degree ≥ 1.
    pub sh_rest: f32,
    /// Opacity logits.
    pub opacity: f32,
    /// Log-scales.
    pub scale: f32,
    /// Rotation quaternions.
    pub rotation: f32,
    /// Per-image exposure transforms ([`crate::splat::exposure::lr_exposure`]); used only by
    /// steps that train an exposure.
    pub exposure: f32,
}

impl LearningRates {
    /// The configured rates at `step`, with the position rate from [`lr_position`].
    pub fn at(cfg: &TrainConfig, step: u32, scene_extent: f32) -> Self {
        LearningRates {
            position: lr_position(cfg, step, scene_extent),
            sh_dc: cfg.lr_sh_dc,
            sh_rest: cfg.lr_sh_rest,
            opacity: cfg.lr_opacity,
            scale: cfg.lr_scale,
            rotation: cfg.lr_rotation,
            exposure: crate::splat::exposure::lr_exposure(cfg, step),
        }
    }
}

/// Adam moments of one parameter group: `stride` floats per Gaussian.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Moments {
    /// Floats per Gaussian in this group.
    pub stride: usize,
    /// First moments, `len() * stride` floats.
    pub m: Vec<f32>,
    /// Second moments, `len() * stride` floats.
    pub v: Vec<f32>,
}

impl Moments {
    fn zeros(stride: usize, n: usize) -> Self {
        Moments {
            stride,
            m: vec![0.0; stride * n],
            v: vec![0.0; stride * n],
        }
    }

    /// Gaussians covered.
    pub fn len(&self) -> usize {
        self.m.len() / self.stride.max(1)
    }

    /// True when no Gaussian is covered.
    pub fn is_empty(&self) -> bool {
        self.m.is_empty()
    }

    /// New state where Gaussian `i` takes the moments of old Gaussian `sources[i]`, or zeros.
    fn remap(&mut self, sources: &[Option<usize>]) {
        let s = self.stride;
        let mut m = vec![0.0; sources.len() * s];
        let mut v = vec![0.0; sources.len() * s];
        for (i, src) in sources.iter().enumerate() {
            if let Some(j) = *src {
                m[i * s..(i + 1) * s].copy_from_slice(&self.m[j * s..(j + 1) * s]);
                v[i * s..(i + 1) * s].copy_from_slice(&self.v[j * s..(j + 1) * s]);
            }
        }
        self.m = m;
        self.v = v;
    }

    /// One Adam update of `params` with `grads` (same flat layout); `lr(k)` gives the learning
    /// rate of float `k` within a stride. `bc1`, `bc2` are the bias corrections 1 − β^t.
    fn update(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        bc1: f32,
        bc2: f32,
        lr: impl Fn(usize) -> f32,
    ) {
        let s = self.stride;
        for (idx, ((p, &g), (m, v))) in params
            .iter_mut()
            .zip(grads)
            .zip(self.m.iter_mut().zip(self.v.iter_mut()))
            .enumerate()
        {
            *m = BETA1 * *m + (1.0 - BETA1) * g;
            *v = BETA2 * *v + (1.0 - BETA2) * g * g;
            let m_hat = *m / bc1;
            let v_hat = *v / bc2;
            *p -= lr(idx % s) * m_hat / (v_hat.sqrt() + EPSILON);
        }
    }
}

/// Adam state for a [`Gaussians`] model: one [`Moments`] per trained parameter.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AdamState {
    /// Steps taken so far (t of the bias correction).
    pub step: u32,
    pub means: Moments,
    pub log_scales: Moments,
    pub rotations: Moments,
    pub opacity_logits: Moments,
    pub sh: Moments,
}

/// Why an optimiser step was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AdamError {
    #[error(
        "model, gradients and optimiser state disagree on the number of Gaussians \
         (model {model}, gradients {grads}, state {state}); reindex the state after densifying"
    )]
    LengthMismatch {
        model: usize,
        grads: usize,
        state: usize,
    },
}

impl AdamState {
    /// Zero state for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        AdamState {
            step: 0,
            means: Moments::zeros(3, n),
            log_scales: Moments::zeros(3, n),
            rotations: Moments::zeros(4, n),
            opacity_logits: Moments::zeros(1, n),
            sh: Moments::zeros(SH_FLOATS, n),
        }
    }

    /// Gaussians covered.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// True when no Gaussian is covered.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    fn groups_mut(&mut self) -> [&mut Moments; 5] {
        [
            &mut self.means,
            &mut self.log_scales,
            &mut self.rotations,
            &mut self.opacity_logits,
            &mut self.sh,
        ]
    }

    /// Reindexes the state: new Gaussian `i` takes the moments of old Gaussian `sources[i]`;
    /// `None` (a new Gaussian) starts at zero. Every index must be `< self.len()`.
    pub fn remap(&mut self, sources: &[Option<usize>]) {
        for g in self.groups_mut() {
            g.remap(sources);
        }
    }

    /// Keeps the Gaussians listed in `indices`, in that order (a gather).
    pub fn gather(&mut self, indices: &[usize]) {
        let sources: Vec<Option<usize>> = indices.iter().map(|&i| Some(i)).collect();
        self.remap(&sources);
    }

    /// Appends zero state for `count` new Gaussians.
    pub fn extend_zeros(&mut self, count: usize) {
        for g in self.groups_mut() {
            let add = count * g.stride;
            g.m.resize(g.m.len() + add, 0.0);
            g.v.resize(g.v.len() + add, 0.0);
        }
    }

    /// Keeps the Gaussians with `keep[i]` true, in order (same semantics as
    /// [`Gaussians::retain_mask`]).
    pub fn retain_mask(&mut self, keep: &[bool]) {
        let idx: Vec<usize> = (0..self.len())
            .filter(|&i| keep.get(i).copied().unwrap_or(false))
            .collect();
        self.gather(&idx);
    }

    /// Zeros the opacity moments, as the reference does when it resets opacities.
    pub fn reset_opacity_moments(&mut self) {
        self.opacity_logits.m.fill(0.0);
        self.opacity_logits.v.fill(0.0);
    }

    /// One Adam step on every parameter group. SH floats `0..3` (the DC coefficient) use
    /// `lr.sh_dc`, the rest `lr.sh_rest`.
    pub fn step(
        &mut self,
        model: &mut Gaussians,
        grads: &GaussianGrads,
        lr: &LearningRates,
    ) -> Result<(), AdamError> {
        let n = model.len();
        let grads_n = grads.means.len();
        let ok = model.is_consistent()
            && self.len() == n
            && grads_n == n
            && grads.log_scales.len() == n
            && grads.rotations.len() == n
            && grads.opacity_logits.len() == n
            && grads.sh.len() == n;
        if !ok {
            return Err(AdamError::LengthMismatch {
                model: n,
                grads: grads_n,
                state: self.len(),
            });
        }
        self.step += 1;
        let bc1 = 1.0 - BETA1.powi(self.step as i32);
        let bc2 = 1.0 - BETA2.powi(self.step as i32);
        // Per group, in the order of `groups_mut`: parameters, gradients, and the learning
        // rates of the first three floats of a stride and of the rest (they differ for SH only).
        let groups = [
            (
                model.means.as_flattened_mut(),
                grads.means.as_flattened(),
                (lr.position, lr.position),
            ),
            (
                model.log_scales.as_flattened_mut(),
                grads.log_scales.as_flattened(),
                (lr.scale, lr.scale),
            ),
            (
                model.rotations.as_flattened_mut(),
                grads.rotations.as_flattened(),
                (lr.rotation, lr.rotation),
            ),
            (
                &mut model.opacity_logits[..],
                &grads.opacity_logits[..],
                (lr.opacity, lr.opacity),
            ),
            (
                model.sh.as_flattened_mut(),
                grads.sh.as_flattened(),
                (lr.sh_dc, lr.sh_rest),
            ),
        ];
        for (moments, (params, grads, (first, rest))) in self.groups_mut().into_iter().zip(groups) {
            moments.update(
                params,
                grads,
                bc1,
                bc2,
                |k| if k < 3 { first } else { rest },
            );
        }
        Ok(())
    }
}

#[cfg(test)]
#[path = "adam_tests.rs"]
mod tests;
