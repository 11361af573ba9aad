//! The training configuration: one struct, every knob documented with its unit and the source of
//! its default.
//!
//! Defaults follow the reference 3DGS trainer (Kerbl et al. 2023, `arguments/__init__.py` of the
//! INRIA code) and docs/method.md Stage 4. The struct (de)serialises with serde; missing fields take
//! their defaults, so a JSON file only needs the values it changes.

use serde::{Deserialize, Serialize};

/// Number of steps the reference schedule is written for (Kerbl et al. 2023: 30 000 iterations).
pub const REFERENCE_STEPS: u32 = 30_000;

/// Default exposure learning rate at step 0 (reference `exposure_lr_init`); the one source of
/// this default, which `params.train.exposure_lr_init` takes too.
pub const DEFAULT_LR_EXPOSURE_INIT: f64 = 0.01;
/// Default exposure learning rate at the last step (reference `exposure_lr_final`).
pub const DEFAULT_LR_EXPOSURE_FINAL: f64 = 0.001;
/// Default exposure ramp, steps (reference `exposure_lr_delay_steps`).
pub const DEFAULT_LR_EXPOSURE_DELAY_STEPS: u32 = 0;
/// Default exposure ramp multiplier (reference `exposure_lr_delay_mult`).
pub const DEFAULT_LR_EXPOSURE_DELAY_MULT: f64 = 0.0;

/// Everything the trainer needs to know besides the data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Optimisation steps, one view each. Default 30 000 (reference; docs/method.md Stage 4).
    pub steps: u32,

    /// Position learning rate at step 0, in units of the scene extent (multiplied by it).
    /// Default 1.6e-4 (reference `position_lr_init`).
    pub lr_position_init: f32,
    /// Position learning rate at the last step, × scene extent; the rate decays exponentially
    /// (log-linear) from `lr_position_init` over `steps` (reference `expon_lr_func`).
    /// Default 1.6e-6 (reference `position_lr_final`).
    pub lr_position_final: f32,
    /// Learning rate of the SH DC coefficients. Default 2.5e-3 (reference `feature_lr`).
    pub lr_sh_dc: f32,
    /// Learning rate of the SH coefficients of degree ≥ 1. Default 2.5e-3 / 20 = 1.25e-4
    /// (reference: `feature_lr / 20.0` for `f_rest`).
    pub lr_sh_rest: f32,
    /// Learning rate of the opacity logits. Default 0.025 (reference `opacity_lr`; docs/method.md
    /// allows 0.025–0.05).
    pub lr_opacity: f32,
    /// Learning rate of the log-scales. Default 5e-3 (reference `scaling_lr`).
    pub lr_scale: f32,
    /// Learning rate of the (unnormalised) rotation quaternions. Default 1e-3
    /// (reference `rotation_lr`).
    pub lr_rotation: f32,

    /// Weight λ of the D-SSIM term, L = (1 − λ) L1 + λ (1 − SSIM), [0, 1].
    /// Default 0.2 (reference `lambda_dssim`; docs/splatting.md "Loss").
    pub lambda_ssim: f32,

    /// First step at which densification runs (exclusive, as the reference). Default 500
    /// (reference `densify_from_iter`).
    pub densify_from: u32,
    /// Step after which neither densification nor opacity reset run. Default 15 000
    /// (reference `densify_until_iter`).
    pub densify_until: u32,
    /// Steps between densifications. Default 100 (reference `densification_interval`).
    pub densify_interval: u32,
    /// Threshold on the mean view-space positional gradient (NDC units, see docs/splatting.md
    /// "Backward") above which a Gaussian is cloned or split. Default 0.0002
    /// (reference `densify_grad_threshold`).
    pub densify_grad_threshold: f32,
    /// Gaussians whose largest axis is ≤ `percent_dense` × scene extent are cloned, larger ones
    /// split; fraction of the extent. Default 0.01 (reference `percent_dense`).
    pub percent_dense: f32,
    /// Steps between opacity resets (opacity ← min(opacity, 0.01)). Default 3000
    /// (reference `opacity_reset_interval`).
    pub opacity_reset_interval: u32,
    /// Gaussians with opacity below this are pruned at each densification, [0, 1].
    /// Default 0.005 (reference `densify_and_prune(..., 0.005, ...)`).
    pub prune_opacity: f32,
    /// After the first opacity reset, Gaussians whose largest screen radius since the last
    /// densification exceeds this are pruned; pixels. Default 20 (reference `size_threshold`).
    pub prune_screen_radius_px: f32,
    /// After the first opacity reset, Gaussians whose largest axis exceeds this fraction of the
    /// scene extent are pruned. Default 0.1 (reference `prune`: `0.1 * extent`).
    pub prune_world_size: f32,
    /// Optional cap on the number of Gaussians; densification stops growing the model at the
    /// cap, taking the highest gradients first. Default none (reference has no cap).
    pub max_gaussians: Option<usize>,

    /// The active SH degree grows by one every this many steps. Default 1000 (reference
    /// `oneupSHdegree` every 1000 iterations; docs/method.md Stage 4).
    pub sh_degree_interval: u32,
    /// Highest SH degree, 0..=3. Default 3 (reference `sh_degree`).
    pub max_sh_degree: u32,

    /// Background colour composited behind the Gaussians, linear RGB in [0, 1].
    /// Default black (reference `white_background = False`).
    pub background: [f32; 3],
    /// Every `test_every`-th image (sorted by name, index % test_every == 0) is held out for
    /// evaluation; 0 holds out nothing. Default 8 (reference `llffhold`; docs/method.md evaluation).
    pub test_every: usize,
    /// Long side of the training images in pixels after downscaling (area averaging); none keeps
    /// the native resolution. Default none (the reference rescales only above 1600 px).
    pub resolution: Option<u32>,
    /// Host memory the decoded photos may take before the dataset keeps them compressed, MiB
    /// (default [`crate::splat::photo::DEFAULT_HOST_PHOTO_MB`]).
    pub host_photo_mb: u64,
    /// Seed of the random numbers used by densification (split sampling). Default 0.
    pub seed: u64,
    /// Rasterise with Mip-Splatting's 2-D filter (Yu et al. 2024; gsplat
    /// `rasterize_mode="antialiased"`): the 0.3 px² screen-space blur with its opacity
    /// compensation `ρ = sqrt(det Σ2D / det(Σ2D + 0.3 · I))` (unitless), so sub-pixel Gaussians
    /// keep their total light at every resolution (docs/splatting.md "Forward", step 4). Used
    /// for every training step and the held-out renders alike. Default false (the reference
    /// 3DGS dilation without compensation, Kerbl et al. 2023).
    pub antialias: bool,
    /// The semantic trunk term L_geo (docs/method.md Stage 4); off by default (vanilla 3DGS). Its
    /// anchors are installed on the backend by the caller ([`crate::splat::backend::Backend::set_semantic`]).
    pub semantic: crate::splat::semantic::SemanticConfig,
    /// Sylva's trunk binding (docs/method.md Stage 4, "Sylva's binding"); off by default here. Its
    /// anchors are installed on the backend by the caller ([`crate::splat::backend::Backend::set_bind`]).
    pub bind: crate::splat::bind::BindConfig,
    /// How the set of Gaussians changes: the reference adaptive density control (default,
    /// Kerbl et al. 2023) or MCMC relocation under the `max_gaussians` budget.
    pub strategy: StrategyKind,
    /// The MCMC strategy's knobs ([`crate::splat::mcmc`]), used when `strategy` is `Mcmc`.
    pub mcmc: crate::splat::mcmc::McmcConfig,

    /// Per-image exposure compensation (docs/splatting.md "Exposure"; the reference trainer's
    /// `train_test_exp`): a learned affine colour transform per photo applied to its render
    /// before the loss; the held-out views' left halves train too, and the held-out metrics
    /// are measured on their right halves. Default false here (the reference's default, which
    /// the trainer's tests and `sylva bench method` compare with); jobs, `sylva run` and
    /// `sylva train` turn it on (`crate::pipeline::params::TrainParams::exposure`).
    pub exposure: bool,
    /// Exposure learning rate at step 0, parameter units ([A | b], dimensionless) per step.
    /// Default 0.01 (reference `exposure_lr_init`, `arguments/__init__.py`).
    pub lr_exposure_init: f32,
    /// Exposure learning rate at the last step; the rate decays log-linearly from
    /// `lr_exposure_init` over `steps` (reference `get_expon_lr_func`). Default 0.001
    /// (reference `exposure_lr_final`).
    pub lr_exposure_final: f32,
    /// Steps over which the exposure rate ramps in from `lr_exposure_delay_mult` times its
    /// value (a quarter sine); 0 = no ramp. Default 0 (reference `exposure_lr_delay_steps`;
    /// the reference README suggests 5000 of 30 000, with rates 0.001 → 0.0001 and a
    /// multiplier of 0.001, for captures with strong exposure changes).
    pub lr_exposure_delay_steps: u32,
    /// Multiplier of the exposure rate at step 0 while a ramp is set, [0, 1]. Default 0
    /// (reference `exposure_lr_delay_mult`).
    pub lr_exposure_delay_mult: f32,
}

/// Which densification strategy trains the model.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StrategyKind {
    /// Clone, split and prune by gradient (Kerbl et al. 2023; [`crate::splat::strategy`]).
    #[default]
    Default,
    /// Relocate dead Gaussians and grow to a fixed budget (Kheradmand et al. 2024;
    /// [`crate::splat::mcmc`]).
    Mcmc,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: REFERENCE_STEPS,
            lr_position_init: 1.6e-4,
            lr_position_final: 1.6e-6,
            lr_sh_dc: 2.5e-3,
            lr_sh_rest: 2.5e-3 / 20.0,
            lr_opacity: 0.025,
            lr_scale: 5e-3,
            lr_rotation: 1e-3,
            lambda_ssim: 0.2,
            densify_from: 500,
            densify_until: 15_000,
            densify_interval: 100,
            densify_grad_threshold: 2e-4,
            percent_dense: 0.01,
            opacity_reset_interval: 3000,
            prune_opacity: 0.005,
            prune_screen_radius_px: 20.0,
            prune_world_size: 0.1,
            max_gaussians: None,
            sh_degree_interval: 1000,
            max_sh_degree: 3,
            background: [0.0; 3],
            test_every: 8,
            resolution: None,
            host_photo_mb: crate::splat::photo::DEFAULT_HOST_PHOTO_MB,
            seed: 0,
            antialias: false,
            semantic: Default::default(),
            bind: Default::default(),
            strategy: StrategyKind::Default,
            mcmc: Default::default(),
            exposure: false,
            lr_exposure_init: DEFAULT_LR_EXPOSURE_INIT as f32,
            lr_exposure_final: DEFAULT_LR_EXPOSURE_FINAL as f32,
            lr_exposure_delay_steps: DEFAULT_LR_EXPOSURE_DELAY_STEPS,
            lr_exposure_delay_mult: DEFAULT_LR_EXPOSURE_DELAY_MULT as f32,
        }
    }
}

impl TrainConfig {
    /// This configuration trained for `steps` steps instead.
    ///
    /// When `steps` is below [`REFERENCE_STEPS`], every step count of the schedule
    /// (densification start, end and interval, opacity-reset interval, SH-degree interval) is
    /// multiplied by `steps / 30 000` and rounded, with intervals kept ≥ 1 — so a short run goes
    /// through the same phases in the same proportions (e.g. 3000 steps: densify from 50 to 1500,
    /// SH degree up every 100) — except the densification interval, which stays
    /// the reference 100 steps (at most a tenth of the run): new Gaussians need that long to
    /// settle before their gradients mean anything, and densifying every few steps grows the
    /// model geometrically (measured: 1.5 k → 76 k Gaussians in 200 steps). Thresholds and
    /// learning rates are
    /// unchanged; the position rate still decays over the (new) `steps`. At 30 000 steps or more
    /// only `steps` changes and the schedule stays the reference one.
    pub fn scaled_to(&self, steps: u32) -> TrainConfig {
        let mut c = self.clone();
        c.steps = steps;
        if steps >= REFERENCE_STEPS {
            return c;
        }
        let f = steps as f64 / REFERENCE_STEPS as f64;
        let scale = |s: u32| (s as f64 * f).round() as u32;
        c.densify_from = scale(self.densify_from);
        c.densify_until = scale(self.densify_until);
        c.densify_interval = self.densify_interval.min(steps / 10).max(1);
        // Opacity resets keep the reference period: the model needs thousands of steps to recover
        // from one, so a short run is better without (measured: 1000 steps, +5.2 dB with a reset
        // every 100 steps).
        c.opacity_reset_interval = self.opacity_reset_interval;
        c.sh_degree_interval = scale(self.sh_degree_interval).max(1);
        c.semantic = self.semantic.scaled_to(steps);
        c.lr_exposure_delay_steps = scale(self.lr_exposure_delay_steps);
        c
    }

    /// How the trainer's backend rasterises, for training and the held-out renders.
    pub fn render_options(&self) -> crate::splat::camera::RenderOptions {
        crate::splat::camera::RenderOptions {
            antialias: self.antialias,
        }
    }

    /// Checks the exposure settings a user can set (docs/splatting.md "Exposure").
    pub fn validate_exposure(&self) -> Result<(), String> {
        let rate = |v: f32| v >= 0.0 && v.is_finite();
        if !rate(self.lr_exposure_init) || !rate(self.lr_exposure_final) {
            return Err(format!(
                "exposure learning rates must be finite and ≥ 0, got {} and {}",
                self.lr_exposure_init, self.lr_exposure_final
            ));
        }
        if !(0.0..=1.0).contains(&self.lr_exposure_delay_mult) {
            return Err(format!(
                "exposure_lr_delay_mult must be in [0, 1], got {}",
                self.lr_exposure_delay_mult
            ));
        }
        Ok(())
    }

    /// Active SH degree at `step` (1-based): one more every `sh_degree_interval` steps, capped
    /// at `max_sh_degree` (reference: degree up at iterations 1000, 2000, 3000).
    pub fn sh_degree_at(&self, step: u32) -> u32 {
        let up = step / self.sh_degree_interval.max(1);
        up.min(self.max_sh_degree.min(crate::splat::model::MAX_SH_DEGREE))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_match_the_reference_trainer() {
        let c = TrainConfig::default();
        assert_eq!(c.steps, 30_000);
        assert!((c.lr_sh_rest - 1.25e-4).abs() < 1e-9);
        assert_eq!(
            (c.densify_from, c.densify_until, c.densify_interval),
            (500, 15_000, 100)
        );
        assert_eq!(c.test_every, 8);
        assert!(!c.exposure);
        assert_eq!((c.lr_exposure_init, c.lr_exposure_final), (0.01, 0.001));
        assert_eq!(c.lr_exposure_delay_steps, 0);
        assert!(c.validate_exposure().is_ok());
        let bad = TrainConfig {
            lr_exposure_final: f32::NAN,
            ..TrainConfig::default()
        };
        assert!(bad.validate_exposure().is_err());
        let bad = TrainConfig {
            lr_exposure_delay_mult: 1.5,
            ..TrainConfig::default()
        };
        assert!(bad.validate_exposure().is_err());
    }

    #[test]
    fn missing_json_fields_take_defaults() {
        let c: TrainConfig = serde_json::from_str(r#"{"steps": 7000, "max_gaussians": 1000}"#)
            .expect("valid config");
        assert_eq!(c.steps, 7000);
        assert_eq!(c.max_gaussians, Some(1000));
        assert_eq!(c.densify_until, 15_000);
        let back: TrainConfig =
            serde_json::from_str(&serde_json::to_string(&c).expect("serialise")).expect("parse");
        assert_eq!(back, c);
    }

    #[test]
    fn short_runs_scale_the_schedule_proportionally() {
        let c = TrainConfig::default().scaled_to(3000);
        assert_eq!(
            (c.densify_from, c.densify_until, c.densify_interval),
            (50, 1500, 100)
        );
        assert_eq!(TrainConfig::default().scaled_to(200).densify_interval, 20);
        assert_eq!(
            (c.opacity_reset_interval, c.sh_degree_interval),
            (3000, 100)
        );
        let tiny = TrainConfig::default().scaled_to(10);
        assert!(tiny.densify_interval >= 1 && tiny.sh_degree_interval >= 1);
        let long = TrainConfig::default().scaled_to(60_000);
        assert_eq!(long.densify_until, 15_000);
    }

    #[test]
    fn sh_degree_grows_every_interval_up_to_three() {
        let c = TrainConfig::default();
        assert_eq!(c.sh_degree_at(0), 0);
        assert_eq!(c.sh_degree_at(999), 0);
        assert_eq!(c.sh_degree_at(1000), 1);
        assert_eq!(c.sh_degree_at(29_999), 3);
    }
}
