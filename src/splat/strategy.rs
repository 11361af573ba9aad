//! Densification strategies: how the set of Gaussians changes during training.
//!
//! The training loop knows nothing about cloning or pruning; it calls a [`Strategy`] at fixed
//! hooks (after each backward pass, after each optimiser step), as gsplat's `Strategy` objects.
//! [`DefaultStrategy`] is the reference adaptive density control of Kerbl et al. 2023
//! (`densify_and_prune`, `reset_opacity`); [`crate::splat::mcmc::McmcStrategy`] (relocation
//! under a budget) implements the same trait without touching the loop.
//!
//! Step numbers are 1-based, as the reference's `iteration`: hook calls for step `s` happen
//! during the `s`-th optimisation step.

use crate::splat::model::{Gaussian, Gaussians, sigmoid};

use crate::rng::SplitMix64;
use crate::splat::adam::{AdamState, LearningRates};
use crate::splat::config::TrainConfig;
use crate::splat::cpu::linalg::quat_rows;

/// Per-view screen-space statistics from one backward pass.
#[derive(Debug, Clone, Copy)]
pub struct ViewStats<'a> {
    /// dL/d(projected mean), pixels, one per Gaussian (docs/splatting.md "Backward").
    pub mean2d_grads: &'a [[f32; 2]],
    /// Screen radius in pixels, one per Gaussian; 0 where the Gaussian was culled.
    pub radii: &'a [f32],
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

/// What a refinement did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RefineReport {
    /// Gaussians before.
    pub before: usize,
    /// Gaussians after.
    pub after: usize,
    /// Copies added by cloning.
    pub cloned: usize,
    /// Parents replaced by two children each.
    pub split: usize,
    /// Gaussians removed by pruning (counting new children pruned at once).
    pub pruned: usize,
    /// Dead Gaussians moved onto live ones ([`crate::splat::mcmc`]; 0 for the reference).
    pub relocated: usize,
    /// True when opacities were reset.
    pub opacity_reset: bool,
}

/// View-space statistics accumulated on the device over the steps since the last read, one
/// entry per Gaussian (what [`Strategy::after_backward`] would have summed view by view).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DensifyStats {
    /// Sum over views of the NDC-scaled view-space gradient norm.
    pub grad_sum: Vec<f32>,
    /// Views in which the Gaussian was visible.
    pub visible_count: Vec<u32>,
    /// Largest screen radius, pixels.
    pub max_radius: Vec<f32>,
}

impl DensifyStats {
    /// Zero statistics for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        DensifyStats {
            grad_sum: vec![0.0; n],
            visible_count: vec![0; n],
            max_radius: vec![0.0; n],
        }
    }

    /// Adds one view: `grad_stat` is the NDC-scaled gradient norm and `radii` the screen radii
    /// (0 where culled), one per Gaussian.
    pub fn add_view(&mut self, grad_stat: &[f32], radii: &[f32]) {
        for (i, (&g, &r)) in grad_stat.iter().zip(radii).enumerate() {
            if r > 0.0 && i < self.grad_sum.len() {
                self.grad_sum[i] += g;
                self.visible_count[i] += 1;
                self.max_radius[i] = self.max_radius[i].max(r);
            }
        }
    }
}

/// Hooks the training loop calls; every method has a do-nothing default.
pub trait Strategy {
    /// True when [`Strategy::refine`] may change the model at `step`: only then does the loop
    /// bring the model and the statistics back from the device.
    fn wants_refine(&self, _step: u32) -> bool {
        true
    }
    /// Statistics the device accumulated since the last call (instead of per-view
    /// [`Strategy::after_backward`] calls).
    fn absorb_stats(&mut self, _stats: &DensifyStats) {}
    /// After the backward pass of step `step`, with that view's screen-space statistics.
    fn after_backward(&mut self, _step: u32, _stats: &ViewStats<'_>) {}
    /// After the optimiser step of step `step` (e.g. to add noise to positions).
    fn after_optimizer_step(
        &mut self,
        _step: u32,
        _gaussians: &mut Gaussians,
        _lr: &LearningRates,
    ) {
    }
    /// After the optimiser step: may add, remove or edit Gaussians; must keep `adam` aligned
    /// with `gaussians`. `scene_extent` in metres.
    fn refine(
        &mut self,
        step: u32,
        gaussians: &mut Gaussians,
        adam: &mut AdamState,
        scene_extent: f32,
    ) -> RefineReport;
    /// What the device must add to every step for this strategy (the MCMC noise and
    /// regularisers), given the run's seed; `None` (the default) adds nothing.
    fn step_terms(&self, _seed: u64) -> Option<crate::splat::mcmc::StepTerms> {
        None
    }
}

/// Reference adaptive density control (Kerbl et al. 2023, section 5; docs/method.md Stage 4).
#[derive(Debug, Clone)]
pub struct DefaultStrategy {
    cfg: TrainConfig,
    rng: SplitMix64,
    /// Sum over views of the NDC-scaled view-space gradient norm, per Gaussian.
    grad_sum: Vec<f32>,
    /// Views in which each Gaussian was visible since the last densification.
    visible_count: Vec<u32>,
    /// Largest screen radius (pixels) since the last densification.
    max_radius: Vec<f32>,
}

impl DefaultStrategy {
    /// A strategy with the schedule and thresholds of `cfg`, seeded with `cfg.seed`.
    pub fn new(cfg: &TrainConfig) -> Self {
        DefaultStrategy {
            cfg: cfg.clone(),
            rng: SplitMix64::new(cfg.seed),
            grad_sum: Vec::new(),
            visible_count: Vec::new(),
            max_radius: Vec::new(),
        }
    }

    fn reset_stats(&mut self, n: usize) {
        self.grad_sum = vec![0.0; n];
        self.visible_count = vec![0; n];
        self.max_radius = vec![0.0; n];
    }

    /// Mean view-space gradient of Gaussian `i` since the last densification (0 if never seen).
    pub fn mean_grad(&self, i: usize) -> f32 {
        match self.visible_count.get(i) {
            Some(&c) if c > 0 => self.grad_sum[i] / c as f32,
            _ => 0.0,
        }
    }

    /// Clones, splits and prunes in a scene of `extent` metres; once `after_first_reset` (the
    /// first opacity reset has passed), also prunes Gaussians too large in the world or on
    /// screen.
    fn densify_and_prune(
        &mut self,
        g: &mut Gaussians,
        adam: &mut AdamState,
        extent: f32,
        after_first_reset: bool,
    ) -> RefineReport {
        let n = g.len();
        if self.grad_sum.len() != n {
            self.reset_stats(n);
        }
        let large = self.cfg.percent_dense * extent;
        let max_scale = |g: &Gaussians, i: usize| {
            g.log_scales[i]
                .iter()
                .copied()
                .fold(f32::MIN, f32::max)
                .exp()
        };
        let mut candidates: Vec<usize> = (0..n)
            .filter(|&i| self.mean_grad(i) >= self.cfg.densify_grad_threshold)
            .collect();
        if let Some(cap) = self.cfg.max_gaussians {
            // Each clone or split adds one Gaussian net; keep the highest gradients.
            let budget = cap.saturating_sub(n);
            if candidates.len() > budget {
                candidates.sort_by(|&a, &b| self.mean_grad(b).total_cmp(&self.mean_grad(a)));
                candidates.truncate(budget);
                candidates.sort_unstable();
            }
        }
        let mut is_split_parent = vec![false; n];
        let mut clones = Vec::new();
        let mut children = Vec::new();
        for &i in &candidates {
            let parent = g.get(i);
            if max_scale(g, i) <= large {
                clones.push(parent);
            } else {
                is_split_parent[i] = true;
                children.extend(self.split_children(&parent));
            }
        }
        // New order: surviving originals, clones, split children (as the reference appends).
        let mut entries: Vec<(Option<usize>, Gaussian)> = (0..n)
            .filter(|&i| !is_split_parent[i])
            .map(|i| (Some(i), g.get(i)))
            .collect();
        entries.extend(clones.iter().chain(&children).map(|c| (None, *c)));

        let max_world = self.cfg.prune_world_size * extent;
        let keep: Vec<bool> = entries
            .iter()
            .map(|(src, e)| {
                if sigmoid(e.opacity_logit) < self.cfg.prune_opacity {
                    return false;
                }
                // The background dome is large by design (`init::sky_dome`).
                if after_first_reset && e.trunk_prob >= 0.0 {
                    let radius = src.map_or(0.0, |i| self.max_radius[i]);
                    let world = e.log_scale.iter().copied().fold(f32::MIN, f32::max).exp();
                    return radius <= self.cfg.prune_screen_radius_px && world <= max_world;
                }
                true
            })
            .collect();
        let mut out = Gaussians {
            sh_degree: g.sh_degree,
            ..Default::default()
        };
        let mut sources = Vec::with_capacity(entries.len());
        for ((src, e), _) in entries.iter().zip(&keep).filter(|(_, k)| **k) {
            out.push(*e);
            sources.push(*src);
        }
        adam.remap(&sources);
        let report = RefineReport {
            before: n,
            after: out.len(),
            cloned: clones.len(),
            split: children.len() / 2,
            pruned: entries.len() - out.len(),
            relocated: 0,
            opacity_reset: false,
        };
        *g = out;
        self.reset_stats(g.len());
        report
    }

    /// Two children sampled from the parent's Gaussian, scale / 1.6 (reference: `/(0.8 N)`, N = 2).
    fn split_children(&mut self, parent: &Gaussian) -> [Gaussian; 2] {
        let rot = quat_to_matrix(parent.rotation);
        let shrink = 1.6f32.ln();
        std::array::from_fn(|_| {
            let z: [f32; 3] =
                std::array::from_fn(|k| self.rng.normal() as f32 * parent.log_scale[k].exp());
            let mut child = *parent;
            for (row, m) in rot.iter().zip(child.mean.iter_mut()) {
                *m += row[0] * z[0] + row[1] * z[1] + row[2] * z[2];
            }
            child.log_scale = parent.log_scale.map(|s| s - shrink);
            child
        })
    }

    fn reset_opacity(&mut self, g: &mut Gaussians, adam: &mut AdamState) {
        let cap = (0.01f32 / 0.99).ln();
        for o in &mut g.opacity_logits {
            *o = o.min(cap);
        }
        adam.reset_opacity_moments();
    }
}

impl Strategy for DefaultStrategy {
    fn wants_refine(&self, step: u32) -> bool {
        let c = &self.cfg;
        step < c.densify_until
            && ((step > c.densify_from && step.is_multiple_of(c.densify_interval.max(1)))
                || step.is_multiple_of(c.opacity_reset_interval.max(1)))
    }

    fn absorb_stats(&mut self, stats: &DensifyStats) {
        let n = stats.grad_sum.len();
        if self.grad_sum.len() != n {
            self.reset_stats(n);
        }
        for i in 0..n {
            self.grad_sum[i] += stats.grad_sum[i];
            self.visible_count[i] += stats.visible_count.get(i).copied().unwrap_or(0);
            self.max_radius[i] =
                self.max_radius[i].max(stats.max_radius.get(i).copied().unwrap_or(0.0));
        }
    }

    fn after_backward(&mut self, step: u32, stats: &ViewStats<'_>) {
        if step >= self.cfg.densify_until {
            return;
        }
        let n = stats.radii.len().min(stats.mean2d_grads.len());
        if self.grad_sum.len() != n {
            self.reset_stats(n);
        }
        // The reference accumulates the gradient w.r.t. NDC: d/d(ndc) = d/d(px) · size / 2.
        let (hx, hy) = (0.5 * stats.width as f32, 0.5 * stats.height as f32);
        for i in 0..n {
            let r = stats.radii[i];
            if r > 0.0 {
                let [gx, gy] = stats.mean2d_grads[i];
                self.grad_sum[i] += (gx * hx).hypot(gy * hy);
                self.visible_count[i] += 1;
                self.max_radius[i] = self.max_radius[i].max(r);
            }
        }
    }

    fn refine(
        &mut self,
        step: u32,
        g: &mut Gaussians,
        adam: &mut AdamState,
        extent: f32,
    ) -> RefineReport {
        let c = &self.cfg;
        let mut report = RefineReport {
            before: g.len(),
            after: g.len(),
            ..Default::default()
        };
        if step >= c.densify_until {
            return report;
        }
        if step > c.densify_from && step.is_multiple_of(c.densify_interval.max(1)) {
            let after_first_reset = step > c.opacity_reset_interval;
            report = self.densify_and_prune(g, adam, extent, after_first_reset);
        }
        if step.is_multiple_of(self.cfg.opacity_reset_interval.max(1)) {
            self.reset_opacity(g, adam);
            report.opacity_reset = true;
        }
        report
    }
}

/// Rotation matrix (row-major) of the normalised quaternion (w, x, y, z).
pub fn quat_to_matrix(q: [f32; 4]) -> [[f32; 3]; 3] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        .sqrt()
        .max(1e-12);
    quat_rows(q.map(|v| v / n))
}

#[cfg(test)]
#[path = "strategy_tests.rs"]
mod tests;
