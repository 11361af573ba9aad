//! MCMC densification under a fixed budget (Kheradmand et al. 2024, "3D Gaussian Splatting as
//! Markov Chain Monte Carlo"; gsplat's `MCMCStrategy` follows the same paper), behind the same
//! [`Strategy`] trait as the reference adaptive density control.
//!
//! Three parts, with the paper's defaults (docs/splatting.md "MCMC strategy"):
//!
//! - **Relocation** ([`McmcStrategy::refine`], on the CPU every `densify_interval` steps between
//!   `densify_from` and `densify_until`): every dead Gaussian (opacity ≤
//!   [`McmcConfig::min_opacity`]) moves onto a live one drawn with probability ∝ opacity; a
//!   live Gaussian drawn N − 1 times becomes N copies whose opacity and scale
//!   ([`relocated`]) keep what the N of them render close to what it rendered alone.
//! - **Growth**: at the same steps, `growth` × N more Gaussians (at most up to the cap) are
//!   added the same way, so the model fills its budget instead of crossing it.
//! - **Noise and regularisers** (every step, on the device): positions move by Gaussian noise
//!   shaped by each Gaussian's covariance and scaled by the position learning rate and by how
//!   transparent the Gaussian is (stochastic gradient Langevin dynamics, paper eq. 11), and
//!   the loss gains λ_o · mean(opacity) + λ_s · mean(scale). The GPU kernel is
//!   `shaders/mcmc.wgsl`; [`regularise_grads`] and [`add_noise`] are its CPU twins, which draw
//!   the same random numbers ([`normal3`], a counter-based hash, so CPU and GPU agree).
//!
//! Sylva's departures, each for the twin: Gaussians bound to a stem by the trunk binding
//! ([`crate::splat::bind`]) get no noise (they sit on the LiDAR surface) and are never the
//! source of a relocation (N copies of one surfel would stay stacked: the binding keeps them
//! on the same spot and they get no noise to part); the background dome (trunk probability
//! < 0, [`crate::splat::init::add_sky`]) is exempt from the scale regulariser, being large by
//! design, as it is from size pruning.

use serde::{Deserialize, Serialize};

use super::adam::AdamState;
use super::model::{Gaussians, sigmoid};
use super::strategy::{RefineReport, Strategy, quat_to_matrix};
use crate::rng::SplitMix64;

/// The knobs of the MCMC strategy (defaults: Kheradmand et al. 2024 and gsplat's
/// `MCMCStrategy` / `simple_trainer` MCMC preset).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct McmcConfig {
    /// Gaussians with opacity at or below this are dead and relocated, [0, 1]. Default 0.005
    /// (paper and gsplat `min_opacity`; the reference's prune threshold).
    pub min_opacity: f32,
    /// Fraction of the current count added at each refinement until the cap. Default 0.05
    /// (paper: 5 %; gsplat `cap_max` growth `1.05 ×`).
    pub growth: f32,
    /// Multiplier of the position learning rate that scales the noise (units: 1/m², the
    /// noise is this × lr × Σ ε with Σ the covariance in m²). Default 5e5 (gsplat `noise_lr`).
    pub noise_lr: f32,
    /// Weight λ_o of the opacity regulariser λ_o · mean(opacity). Default 0.01 (paper; gsplat
    /// `opacity_reg`).
    pub opacity_reg: f32,
    /// Weight λ_s of the scale regulariser λ_s · mean(exp(log-scale)) over every axis, m⁻¹.
    /// Default 0.01 (paper; gsplat `scale_reg`).
    pub scale_reg: f32,
}

impl Default for McmcConfig {
    fn default() -> Self {
        McmcConfig {
            min_opacity: 0.005,
            growth: 0.05,
            noise_lr: 5e5,
            opacity_reg: 0.01,
            scale_reg: 0.01,
        }
    }
}

impl McmcConfig {
    /// Checks the ranges; the message names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..1.0).contains(&self.min_opacity) {
            return Err(format!(
                "mcmc min_opacity must be in [0, 1), got {}",
                self.min_opacity
            ));
        }
        for (name, v) in [
            ("growth", self.growth),
            ("noise_lr", self.noise_lr),
            ("opacity_reg", self.opacity_reg),
            ("scale_reg", self.scale_reg),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("mcmc {name} must be finite and ≥ 0, got {v}"));
            }
        }
        Ok(())
    }
}

/// What the device adds to every step while the MCMC strategy runs (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepTerms {
    /// Noise scale per unit of position learning rate ([`McmcConfig::noise_lr`]).
    pub noise_lr: f32,
    /// λ_o.
    pub opacity_reg: f32,
    /// λ_s.
    pub scale_reg: f32,
    /// Seed of the noise (with the optimiser step and the Gaussian's index).
    pub seed: u32,
    /// Gaussians with a trunk probability at or above this are bound and get no noise
    /// (`None`: the binding is off).
    pub bound_min_prob: Option<f32>,
}

/// Per-Gaussian flag: bound to a stem (no noise).
pub const FLAG_BOUND: u32 = 1;
/// Per-Gaussian flag: background dome (no scale regulariser).
pub const FLAG_BACKGROUND: u32 = 2;

/// The flags ([`FLAG_BOUND`], [`FLAG_BACKGROUND`]) of Gaussians with trunk probabilities
/// `trunk_prob` under `terms`.
pub fn flags(trunk_prob: &[f32], terms: &StepTerms) -> Vec<u32> {
    trunk_prob
        .iter()
        .map(|&p| {
            let mut f = 0;
            if terms.bound_min_prob.is_some_and(|m| p >= m) {
                f |= FLAG_BOUND;
            }
            if p < 0.0 {
                f |= FLAG_BACKGROUND;
            }
            f
        })
        .collect()
}

/// PCG's output hash of one 32-bit word (the "RXS-M-XS" variant of O'Neill's PCG family,
/// recommended as a GPU hash by Jarzynski & Olano 2020). `shaders/mcmc.wgsl` has the same.
pub fn pcg_hash(v: u32) -> u32 {
    let s = v.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let w = ((s >> ((s >> 28) + 4)) ^ s).wrapping_mul(277_803_737);
    (w >> 22) ^ w
}

/// A uniform in (0, 1) from 24 bits of `h`.
fn unit(h: u32) -> f32 {
    ((h >> 8) as f32 + 0.5) * (1.0 / 16_777_216.0)
}

/// Three standard normal numbers for Gaussian `index` at optimiser step `step` under `seed`
/// (Box–Muller on four hashed uniforms), as `shaders/mcmc.wgsl` draws them.
pub fn normal3(seed: u32, step: u32, index: u32) -> [f32; 3] {
    let key = pcg_hash(seed ^ pcg_hash(step));
    let mut h = pcg_hash(key ^ index.wrapping_mul(0x9E37_79B9));
    let mut u = [0.0f32; 4];
    for x in &mut u {
        h = pcg_hash(h);
        *x = unit(h);
    }
    let r0 = (-2.0 * u[0].ln()).sqrt();
    let r1 = (-2.0 * u[2].ln()).sqrt();
    let t0 = std::f32::consts::TAU * u[1];
    let t1 = std::f32::consts::TAU * u[3];
    [r0 * t0.cos(), r0 * t0.sin(), r1 * t1.cos()]
}

/// How much noise a Gaussian of opacity `o` gets, in [0, 1]: σ(k (1 − o − t)) with k = 100,
/// t = 0.995 (paper eq. 11; gsplat `op_sigmoid`) — 1 for the transparent, ≈ 0 above o ≈ 0.05.
pub fn noise_gate(o: f32) -> f32 {
    1.0 / (1.0 + (-100.0 * ((1.0 - o) - 0.995)).exp())
}

/// CPU twin of the `noise` pass: every Gaussian not bound moves by
/// `lr_position · noise_lr · gate(opacity) · Σ ε` (Σ = R S² Rᵀ, ε from [`normal3`] at `step`).
pub fn add_noise(model: &mut Gaussians, flags: &[u32], terms: &StepTerms, lr: f32, step: u32) {
    let scaler = lr * terms.noise_lr;
    for i in 0..model.len() {
        if flags.get(i).is_some_and(|f| f & FLAG_BOUND != 0) {
            continue;
        }
        let gate = noise_gate(sigmoid(model.opacity_logits[i]));
        let e = normal3(terms.seed, step, i as u32);
        let r = quat_to_matrix(model.rotations[i]);
        let s2 = model.log_scales[i].map(|l| (2.0 * l).exp());
        // Σ ε = R (S² (Rᵀ ε)).
        let local: [f32; 3] =
            std::array::from_fn(|k| s2[k] * (r[0][k] * e[0] + r[1][k] * e[1] + r[2][k] * e[2]));
        for (a, row) in r.iter().enumerate() {
            let d = row[0] * local[0] + row[1] * local[1] + row[2] * local[2];
            model.means[i][a] += scaler * gate * d;
        }
    }
}

/// The regularisers' value, λ_o · mean(opacity) + λ_s · mean over Gaussians and axes of
/// exp(log-scale) (the background dome left out of the scale term and its mean).
pub fn regulariser(model: &Gaussians, flags: &[u32], terms: &StepTerms) -> f64 {
    let n = model.len().max(1) as f64;
    let o: f64 = model
        .opacity_logits
        .iter()
        .map(|&l| 1.0 / (1.0 + (-f64::from(l)).exp()))
        .sum();
    let s: f64 = model
        .log_scales
        .iter()
        .enumerate()
        .filter(|(i, _)| flags.get(*i).is_none_or(|f| f & FLAG_BACKGROUND == 0))
        .map(|(_, ls)| ls.iter().map(|&l| f64::from(l).exp()).sum::<f64>())
        .sum();
    f64::from(terms.opacity_reg) * o / n + f64::from(terms.scale_reg) * s / (3.0 * n)
}

/// CPU twin of the `regularise` pass: adds the gradient of [`regulariser`] to `opacity_grads`
/// and `scale_grads` (one entry per Gaussian).
pub fn regularise_grads(
    model: &Gaussians,
    flags: &[u32],
    terms: &StepTerms,
    opacity_grads: &mut [f32],
    scale_grads: &mut [[f32; 3]],
) {
    let n = model.len().max(1) as f32;
    for i in 0..model.len() {
        let o = sigmoid(model.opacity_logits[i]);
        opacity_grads[i] += terms.opacity_reg / n * o * (1.0 - o);
        if flags.get(i).is_none_or(|f| f & FLAG_BACKGROUND == 0) {
            for (g, l) in scale_grads[i].iter_mut().zip(model.log_scales[i]) {
                *g += terms.scale_reg / (3.0 * n) * l.exp();
            }
        }
    }
}

/// Most copies one Gaussian is split into at a refinement (gsplat's binomial table has 51
/// rows); draws beyond it still relocate, with this N.
pub const MAX_COPIES: usize = 51;

/// The opacity and scale factor of each of `n` copies that replace a Gaussian of opacity `o`
/// (paper eq. 9): 1 − o' = (1 − o)^(1/n), and every axis scaled by
/// o / Σ_{i=1..n} Σ_{k=0..i−1} C(i−1, k) (−1)^k o'^(k+1) / √(k+1). n = 1 changes nothing.
/// The opacity is clamped to [`min_opacity`, 1 − 1e-6] as gsplat does.
pub fn relocated(o: f32, n: usize, min_opacity: f32) -> (f32, f32) {
    let n = n.clamp(1, MAX_COPIES);
    let o = f64::from(o.clamp(1e-6, 1.0 - 1e-6));
    let on = (1.0 - (1.0 - o).powf(1.0 / n as f64)).clamp(f64::from(min_opacity), 1.0 - 1e-6);
    let mut denom = 0.0f64;
    for i in 1..=n {
        let mut binom = 1.0f64; // C(i−1, k)
        for k in 0..i {
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            denom += binom * sign * on.powi(k as i32 + 1) / ((k + 1) as f64).sqrt();
            binom = binom * (i - 1 - k) as f64 / (k + 1) as f64;
        }
    }
    let factor = if denom > 0.0 { o / denom } else { 1.0 };
    (on as f32, factor as f32)
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// The MCMC strategy (see the module docs).
#[derive(Debug, Clone)]
pub struct McmcStrategy {
    cfg: McmcConfig,
    cap: usize,
    from: u32,
    until: u32,
    every: u32,
    bound_min_prob: Option<f32>,
    rng: SplitMix64,
}

impl McmcStrategy {
    /// The strategy of `train` (schedule: `densify_from`, `densify_until`, `densify_interval`;
    /// budget: `max_gaussians`, which MCMC needs).
    pub fn new(train: &super::config::TrainConfig) -> Result<Self, String> {
        train.mcmc.validate()?;
        let cap = train.max_gaussians.ok_or_else(|| {
            "the MCMC strategy needs a Gaussian budget (max_gaussians)".to_string()
        })?;
        Ok(McmcStrategy {
            cfg: train.mcmc.clone(),
            cap,
            from: train.densify_from,
            until: train.densify_until,
            every: train.densify_interval.max(1),
            bound_min_prob: train.bind.enabled.then_some(train.bind.min_trunk_prob),
            rng: SplitMix64::new(train.seed ^ 0x6D63_6D63),
        })
    }

    /// The per-step terms the backend applies.
    pub fn terms(&self, seed: u64) -> StepTerms {
        StepTerms {
            noise_lr: self.cfg.noise_lr,
            opacity_reg: self.cfg.opacity_reg,
            scale_reg: self.cfg.scale_reg,
            seed: (seed ^ (seed >> 32)) as u32,
            bound_min_prob: self.bound_min_prob,
        }
    }

    /// `count` draws of live Gaussians with probability ∝ opacity (bound ones never drawn).
    fn draw(&mut self, weights: &[f64], count: usize) -> Vec<usize> {
        let mut cdf = Vec::with_capacity(weights.len());
        let mut total = 0.0;
        for w in weights {
            total += w;
            cdf.push(total);
        }
        if total <= 0.0 {
            return Vec::new();
        }
        (0..count)
            .map(|_| {
                let u = self.rng.uniform() * total;
                cdf.partition_point(|&c| c <= u).min(weights.len() - 1)
            })
            .collect()
    }

    fn relocate_and_grow(&mut self, g: &mut Gaussians, adam: &mut AdamState) -> RefineReport {
        let n = g.len();
        let opac: Vec<f32> = g.opacity_logits.iter().map(|&l| sigmoid(l)).collect();
        let dead: Vec<usize> = (0..n)
            .filter(|&i| opac[i] <= self.cfg.min_opacity)
            .collect();
        let weights: Vec<f64> = (0..n)
            .map(|i| {
                let bound = self.bound_min_prob.is_some_and(|m| g.trunk_prob[i] >= m);
                if bound || opac[i] <= self.cfg.min_opacity {
                    0.0
                } else {
                    f64::from(opac[i])
                }
            })
            .collect();
        // Rounded up (gsplat rounds down), so that a model of fewer than 20 Gaussians grows too.
        let target =
            ((n as f64 * (1.0 + f64::from(self.cfg.growth))).ceil() as usize).min(self.cap);
        let grow = target.saturating_sub(n);
        let sources = self.draw(&weights, dead.len() + grow);
        let mut report = RefineReport {
            before: n,
            after: n,
            ..Default::default()
        };
        if sources.is_empty() {
            return report;
        }
        let mut copies = vec![1usize; n];
        for &s in &sources {
            copies[s] += 1;
        }
        let mut fresh = vec![false; n];
        // The drawn sources take their new opacity and scale; every copy then copies them.
        for (i, &c) in copies.iter().enumerate() {
            if c > 1 {
                let (o, f) = relocated(opac[i], c, self.cfg.min_opacity);
                g.opacity_logits[i] = logit(o);
                let lf = f.max(1e-12).ln();
                for s in &mut g.log_scales[i] {
                    *s += lf;
                }
                fresh[i] = true;
            }
        }
        let (relocate, add) = sources.split_at(dead.len().min(sources.len()));
        for (&d, &s) in dead.iter().zip(relocate) {
            let src = g.get(s);
            g.means[d] = src.mean;
            g.log_scales[d] = src.log_scale;
            g.rotations[d] = src.rotation;
            g.opacity_logits[d] = src.opacity_logit;
            g.sh[d] = src.sh;
            g.trunk_prob[d] = src.trunk_prob;
            fresh[d] = true;
        }
        // New Gaussians' optimiser state starts at zero, and so does that of every Gaussian
        // whose parameters the refinement replaced (gsplat zeroes the sources' state).
        let mut map: Vec<Option<usize>> = (0..n).map(|i| (!fresh[i]).then_some(i)).collect();
        for &s in add {
            g.push(g.get(s));
            map.push(None);
        }
        adam.remap(&map);
        report.after = g.len();
        report.cloned = add.len();
        report.relocated = relocate.len();
        report
    }
}

impl Strategy for McmcStrategy {
    fn wants_refine(&self, step: u32) -> bool {
        step > self.from && step < self.until && step.is_multiple_of(self.every)
    }

    fn refine(
        &mut self,
        step: u32,
        gaussians: &mut Gaussians,
        adam: &mut AdamState,
        _scene_extent: f32,
    ) -> RefineReport {
        if !self.wants_refine(step) {
            let n = gaussians.len();
            return RefineReport {
                before: n,
                after: n,
                ..Default::default()
            };
        }
        self.relocate_and_grow(gaussians, adam)
    }

    fn step_terms(&self, seed: u64) -> Option<StepTerms> {
        Some(self.terms(seed))
    }
}

#[cfg(test)]
#[path = "mcmc_tests.rs"]
mod tests;
