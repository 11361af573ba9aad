//! Per-image exposure compensation (docs/splatting.md "Exposure"): every photo gets a learned
//! affine colour transform `out = A · rgb + b` (A 3×3, b 3-vector), applied to the render of
//! that photo's camera before the loss, so that the Gaussians need not bend to each photo's
//! exposure and white balance.
//!
//! This follows the reference 3DGS trainer's `train_test_exp` option (Kerbl et al., later
//! versions of the INRIA code): one `3×4` matrix `[A | b]` per image, initialised to the
//! identity (`torch.eye(3, 4)`), all images in one tensor optimised by its own torch Adam
//! (β1 = 0.9, β2 = 0.999, default ε = 1e-8) whose rate decays log-linearly from
//! `exposure_lr_init` to `exposure_lr_final`. Torch updates the whole tensor every step, so
//! the images not seen in a step still move by their decaying first moment; Sylva does the
//! same (on the GPU and in [`ExposureState`]).
//!
//! Held-out views train too: their left halves (columns `x < width / 2`) fit their exposure,
//! their right halves give no gradient and are what the held-out metrics measure
//! ([`crate::splat::eval::EvalRegion::RightHalf`]).
//!
//! Layout: 12 floats per image, row-major `[A | b]`: `[a00, a01, a02, b0, a10, a11, a12, b1,
//! a20, a21, a22, b2]`, so `out_r = Σ_c a_rc · rgb_c + b_r`. (The reference multiplies the
//! pixel as a row vector, `rgb · A`; with A learned from the identity the two are the same
//! family of transforms.)

use crate::splat::config::TrainConfig;

/// Floats per image: `[A | b]`, 3×4.
pub const EXPOSURE_FLOATS: usize = 12;

/// The identity transform (A = I, b = 0), every image's start (reference `torch.eye(3, 4)`).
pub const IDENTITY: [f32; EXPOSURE_FLOATS] =
    [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Adam's denominator ε for the exposures: 1e-8, torch's default (the reference builds its
/// exposure optimiser as `torch.optim.Adam([self._exposure])`, without the Gaussians'
/// ε = 1e-15).
pub const EXPOSURE_EPSILON: f32 = 1e-8;

/// Which learned exposure a training step uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExposureSlot {
    /// The image's transform: training views `0..`, then held-out views (the order of
    /// [`crate::splat::dataset::Dataset::all_views`]).
    pub index: usize,
    /// A held-out view: only its left half (columns `x < width / 2`) trains; the pixels of
    /// the right half are replaced by the photo and give no gradient.
    pub left_half: bool,
}

/// Exposure learning rate at 1-based `step`, per step: the reference `get_expon_lr_func`
/// with `exposure_lr_init`, `exposure_lr_final`, `exposure_lr_delay_steps`,
/// `exposure_lr_delay_mult` and `max_steps = iterations`: log-linear from init to final over
/// `cfg.steps`, times `mult + (1 − mult) · sin(π/2 · min(step / delay, 1))` while a delay is
/// set.
pub fn lr_exposure(cfg: &TrainConfig, step: u32) -> f32 {
    let t = (f64::from(step) / f64::from(cfg.steps.max(1))).clamp(0.0, 1.0);
    let init = f64::from(cfg.lr_exposure_init);
    let last = f64::from(cfg.lr_exposure_final);
    if init <= 0.0 && last <= 0.0 {
        return 0.0;
    }
    let ln = |v: f64| v.max(f64::from(f32::MIN_POSITIVE)).ln();
    let log_lerp = (ln(init) * (1.0 - t) + ln(last) * t).exp();
    let delay = if cfg.lr_exposure_delay_steps > 0 {
        let mult = f64::from(cfg.lr_exposure_delay_mult);
        let f = (f64::from(step) / f64::from(cfg.lr_exposure_delay_steps)).clamp(0.0, 1.0);
        mult + (1.0 - mult) * (0.5 * std::f64::consts::PI * f).sin()
    } else {
        1.0
    };
    (delay * log_lerp) as f32
}

/// The exposures of every image and their Adam state, on the CPU (the twin of
/// [`crate::splat::gpu::exposure::GpuExposure`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ExposureState {
    /// `[A | b]` per image.
    pub params: Vec<[f32; EXPOSURE_FLOATS]>,
    /// First moments, 12 per image.
    pub m: Vec<f32>,
    /// Second moments, 12 per image.
    pub v: Vec<f32>,
    /// Adam steps taken (t of the bias correction).
    pub step: u32,
}

impl ExposureState {
    /// `n` identity transforms with zero moments.
    pub fn new(n: usize) -> Self {
        ExposureState {
            params: vec![IDENTITY; n],
            m: vec![0.0; n * EXPOSURE_FLOATS],
            v: vec![0.0; n * EXPOSURE_FLOATS],
            step: 0,
        }
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.params.len()
    }

    /// True without images.
    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    /// One Adam step of every image's transform at rate `lr`: image `index` with gradient
    /// `grad`, the others with a zero gradient (as torch does for the one exposure tensor).
    pub fn adam_step(&mut self, index: usize, grad: &[f32; EXPOSURE_FLOATS], lr: f32) {
        let n = self.params.len();
        if index >= n {
            return;
        }
        self.step += 1;
        let mut g = vec![0.0f32; n * EXPOSURE_FLOATS];
        g[index * EXPOSURE_FLOATS..(index + 1) * EXPOSURE_FLOATS].copy_from_slice(grad);
        crate::splat::gpu::adam::adam_cpu(
            self.params.as_flattened_mut(),
            &g,
            &mut self.m,
            &mut self.v,
            EXPOSURE_FLOATS,
            EXPOSURE_FLOATS,
            lr,
            lr,
            self.step,
            EXPOSURE_EPSILON,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rate_decays_log_linearly_and_the_delay_ramps_it_in() {
        let cfg = TrainConfig {
            steps: 1000,
            ..TrainConfig::default()
        };
        assert!((lr_exposure(&cfg, 0) - 0.01).abs() < 1e-9);
        assert!((lr_exposure(&cfg, 1000) - 0.001).abs() < 1e-9);
        // Halfway is the geometric mean.
        assert!((lr_exposure(&cfg, 500) - 0.01f32 * 0.1f32.sqrt()).abs() < 1e-7);
        // The README setting of the reference: 0.001 → 0.0001 with a 5000-step delay at 0.001.
        let readme = TrainConfig {
            steps: 30_000,
            lr_exposure_init: 0.001,
            lr_exposure_final: 0.0001,
            lr_exposure_delay_steps: 5000,
            lr_exposure_delay_mult: 0.001,
            ..TrainConfig::default()
        };
        assert!((lr_exposure(&readme, 0) - 1e-6).abs() < 1e-10);
        let full = 0.001 * (0.1f64).powf(5000.0 / 30_000.0);
        assert!((f64::from(lr_exposure(&readme, 5000)) - full).abs() < 1e-9);
        assert!(lr_exposure(&readme, 2500) < lr_exposure(&readme, 5000));
    }

    #[test]
    fn adam_moves_the_stepped_image_and_lets_the_others_coast() {
        let mut s = ExposureState::new(3);
        let mut g = [0.0f32; EXPOSURE_FLOATS];
        g[0] = 2.0;
        g[7] = -0.5;
        s.adam_step(1, &g, 0.01);
        // The first Adam step is lr · sign(g) (up to ε); the other images have no moments yet.
        assert!((s.params[1][0] - (1.0 - 0.01)).abs() < 1e-6);
        assert!((s.params[1][7] - 0.01).abs() < 1e-6);
        assert_eq!(s.params[0], IDENTITY);
        assert_eq!(s.params[2], IDENTITY);
        // A step on another image: image 1 still moves along its decaying first moment.
        let before = s.params[1][0];
        s.adam_step(0, &[0.0; EXPOSURE_FLOATS], 0.01);
        assert!(s.params[1][0] < before);
        assert_eq!(s.step, 2);
    }
}
