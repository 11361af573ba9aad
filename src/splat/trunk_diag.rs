//! What holds the trunk Gaussians, measured while training (issue 22, item 1): every
//! [`TrunkMonitor::every`] steps the loop hands the model and the latest position gradients to
//! [`TrunkMonitor::observe`], whose figures go into `loss.csv` and the stage report.
//!
//! - |S| and Σw: the paper's candidate set S = {w = α P q ≥ threshold} of L_geo (docs/method.md
//!   Stage 4) and its total weight, whatever arm trains (so the "bind" and "off" arms show what
//!   the paper's term would have held);
//! - the share of the DBH-slice trunk Gaussians (those stage `dbh` fits) that are in S;
//! - the ratio of L_geo's position gradient at full weight gamma_max to the photometric one,
//!   mean |·| over the trunk Gaussians in S;
//! - the signed and absolute mean offset of the DBH-slice trunk Gaussians from the LiDAR stem
//!   surface (positive outside), millimetres.
//!
//! The slice and the stem circles are the forest stage's; the caller passes them in as a
//! function (`slice`) so this room needs nothing of `forest`.

use glam::Vec3;

use super::model::{Gaussians, sigmoid};
use super::semantic::{self, AnchorIndex, SemanticConfig};

/// Indices of the given centres that lie in a stem's breast-height slice, each with its signed
/// distance from that stem's LiDAR circle (metres, positive outside).
pub type SliceFn = dyn Fn(&[Vec3]) -> Vec<(usize, f32)> + Send + Sync;

/// One measurement (see the module doc); `None` where the figure has no members.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct TrunkDiag {
    /// Gaussians in S.
    pub s_count: usize,
    /// Σ w over S.
    pub s_weight: f64,
    /// Trunk Gaussians in the DBH slices.
    pub slice_count: usize,
    /// Share of those in S, [0, 1].
    pub slice_in_s: Option<f64>,
    /// mean |gamma_max ∇_mu L_geo| / mean |∇_mu L_photo| over the trunk Gaussians in S.
    pub geo_photo_grad_ratio: Option<f64>,
    /// Mean signed offset of the slice Gaussians from the LiDAR surface, mm (+ outside).
    pub surface_offset_mm: Option<f64>,
    /// Mean absolute offset, mm.
    pub surface_abs_mm: Option<f64>,
}

/// The anchors, stems and settings the measurements need.
pub struct TrunkMonitor {
    /// Steps between measurements.
    pub every: u32,
    index: AnchorIndex,
    n_pos: f32,
    cfg: SemanticConfig,
    slice: Box<SliceFn>,
    /// Trunk Gaussians: trunk probability at or above this (0.5, the label; as stage `dbh`).
    pub min_trunk_prob: f32,
    /// ... and opacity at or above this (0.005; stage `dbh` sets its `min_opacity`).
    pub min_opacity: f32,
}

impl TrunkMonitor {
    /// A monitor over `anchors` with L_geo's settings `cfg` (its weight ramp is ignored: the
    /// ratio is taken at `cfg.gamma_max`), measuring every `every` steps.
    pub fn new(
        anchors: &semantic::SemanticAnchors,
        cfg: &SemanticConfig,
        slice: Box<SliceFn>,
        every: u32,
    ) -> Option<Self> {
        Some(TrunkMonitor {
            every: every.max(1),
            index: AnchorIndex::new(anchors)?,
            n_pos: anchors.n_pos,
            cfg: cfg.clone(),
            slice,
            min_trunk_prob: 0.5,
            min_opacity: 0.005,
        })
    }

    /// The figures of `model`; `grads` are dL/d(mean) of the latest step (photometric plus
    /// `gamma` × L_geo's when that term trained), `None` when not available.
    pub fn observe(&self, model: &Gaussians, grads: Option<&[[f32; 3]]>, gamma: f32) -> TrunkDiag {
        let targets = semantic::geo_targets_indexed(model, &self.index, &self.cfg);
        let in_s = |i: usize| targets.get(i).is_some_and(|t| t.weight > 0.0);
        let s_count = (0..model.len()).filter(|&i| in_s(i)).count();
        let s_weight = targets.iter().map(|t| t.weight).sum();
        // The DBH-slice trunk Gaussians, as stage dbh picks them.
        let trunk: Vec<usize> = (0..model.len())
            .filter(|&i| {
                model.trunk_prob[i] >= self.min_trunk_prob
                    && sigmoid(model.opacity_logits[i]) >= self.min_opacity
            })
            .collect();
        let centres: Vec<Vec3> = trunk
            .iter()
            .map(|&i| Vec3::from_array(model.means[i]))
            .collect();
        let sliced = (self.slice)(&centres);
        let n = sliced.len();
        let mean = |f: &dyn Fn(f32) -> f64| {
            (n > 0).then(|| sliced.iter().map(|&(_, o)| f(o)).sum::<f64>() / n as f64)
        };
        let slice_in_s = (n > 0)
            .then(|| sliced.iter().filter(|&&(k, _)| in_s(trunk[k])).count() as f64 / n as f64);
        let ratio = grads.and_then(|g| self.grad_ratio(model, &targets, g, gamma));
        TrunkDiag {
            s_count,
            s_weight,
            slice_count: n,
            slice_in_s,
            geo_photo_grad_ratio: ratio,
            surface_offset_mm: mean(&|o| f64::from(o) * 1000.0),
            surface_abs_mm: mean(&|o| f64::from(o.abs()) * 1000.0),
        }
    }

    fn grad_ratio(
        &self,
        model: &Gaussians,
        targets: &[semantic::GeoTarget],
        grads: &[[f32; 3]],
        gamma: f32,
    ) -> Option<f64> {
        if grads.len() != model.len() {
            return None;
        }
        let (_, d_mu, _) = semantic::geo_loss_and_grad(model, targets, self.n_pos);
        let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let (mut geo, mut photo, mut n) = (0.0, 0.0, 0usize);
        for (i, t) in targets.iter().enumerate() {
            if t.weight <= 0.0 || model.trunk_prob[i] < self.min_trunk_prob {
                continue;
            }
            let g = d_mu[i];
            let total = grads[i].map(f64::from);
            let p = std::array::from_fn(|a| total[a] - f64::from(gamma) * g[a]);
            geo += f64::from(self.cfg.gamma_max) * norm(g);
            photo += norm(p);
            n += 1;
        }
        (n > 0 && photo > 0.0).then(|| geo / photo)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::semantic::test_scene;

    /// The test scene's trunk is a cylinder of radius 0.15 m about the z axis; its "slice" is
    /// 1.2–1.4 m.
    fn slice() -> Box<SliceFn> {
        Box::new(|c: &[Vec3]| {
            c.iter()
                .enumerate()
                .filter(|(_, p)| (p.z - 1.3).abs() <= 0.1 && p.x.hypot(p.y) < 0.4)
                .map(|(i, p)| (i, p.x.hypot(p.y) - 0.15))
                .collect()
        })
    }

    #[test]
    fn offsets_and_the_candidate_set_are_measured() {
        let (mut g, anchors) = test_scene(2, 2000);
        let cfg = SemanticConfig::default();
        let m = TrunkMonitor::new(&anchors, &cfg, slice(), 10).expect("monitor");
        // Put the trunk Gaussians exactly 2 cm outside the cylinder.
        for i in 0..g.len() {
            if g.trunk_prob[i] >= 0.5 {
                let p = Vec3::from_array(g.means[i]);
                let r = p.x.hypot(p.y).max(1e-6);
                g.means[i] = [p.x * 0.17 / r, p.y * 0.17 / r, p.z];
            }
        }
        let d = m.observe(&g, None, 0.0);
        assert!(d.slice_count > 10, "{d:?}");
        assert!((d.surface_offset_mm.expect("offset") - 20.0).abs() < 0.01);
        assert!((d.surface_abs_mm.expect("abs") - 20.0).abs() < 0.01);
        let targets = semantic::geo_targets(&g, &anchors, &cfg);
        assert_eq!(d.s_count, targets.iter().filter(|t| t.weight > 0.0).count());
        assert!(d.s_count > 0 && d.s_weight >= 0.5 * d.s_count as f64);
        let share = d.slice_in_s.expect("share");
        assert!((0.0..=1.0).contains(&share));
        // With every opacity at 0.1 (the initial value) no Gaussian can be in S (w ≤ 0.1).
        let mut faint = g.clone();
        faint
            .opacity_logits
            .iter_mut()
            .for_each(|o| *o = (0.1f32 / 0.9).ln());
        let d = m.observe(&faint, None, 0.0);
        assert_eq!((d.s_count, d.slice_in_s), (0, Some(0.0)));
    }

    #[test]
    fn the_gradient_ratio_compares_l_geo_with_the_photometric_part() {
        let (g, anchors) = test_scene(3, 500);
        let cfg = SemanticConfig::default();
        let m = TrunkMonitor::new(&anchors, &cfg, slice(), 10).expect("monitor");
        let targets = semantic::geo_targets(&g, &anchors, &cfg);
        let (_, d_mu, _) = semantic::geo_loss_and_grad(&g, &targets, anchors.n_pos);
        // A photometric gradient 10x gamma_max times L_geo's, plus L_geo's own at gamma 0.01:
        // the ratio must come out 0.1.
        let grads: Vec<[f32; 3]> = d_mu
            .iter()
            .map(|d| d.map(|v| (v * (10.0 * 0.02 + 0.01)) as f32))
            .collect();
        let r = m.observe(&g, Some(&grads), 0.01).geo_photo_grad_ratio;
        assert!((r.expect("ratio") - 0.1).abs() < 1e-4, "{r:?}");
    }
}
