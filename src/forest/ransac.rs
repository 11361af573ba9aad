//! Robust circle fit of one stem slice: RANSAC on 3-point samples (docs/method.md Stage 5.2), the
//! weighted algebraic fit on the inliers (Stage 5.3), an optional geometric Gauss–Newton
//! refinement, and the quality figures (RMS residual, arc coverage, inlier share).
//!
//! Sampling is deterministic: a SplitMix64 generator seeded from `CircleParams::seed` and the
//! number of points, so the same slice always gives the same circle.

use serde::{Deserialize, Serialize};

use crate::rng::SplitMix64;

use super::circle::{
    CircleFit, arc_coverage, fit_circle_weighted, refine_circle_geometric_with_prior,
};

/// Parameters of [`fit_circle_robust`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct CircleParams {
    /// A point within this distance of a candidate circle is an inlier, metres. docs/method.md
    /// Stage 5.2: "of the order of 1–2 cm"; 1.5 cm is 1.5 sigma of a handheld scanner's range
    /// noise (1 cm).
    pub inlier_threshold_m: f64,
    /// RANSAC samples. 3-point samples with 30% inliers need 169 draws for 99% confidence;
    /// 250 leaves margin.
    pub iterations: usize,
    /// Seed of the deterministic sampler.
    pub seed: u64,
    /// Circles with a radius outside [min, max] are rejected, metres (DBH 4 cm – 3 m).
    pub min_radius_m: f64,
    pub max_radius_m: f64,
    /// Gauss–Newton steps of the geometric refinement (0 = algebraic fit only).
    pub refine_iterations: usize,
    /// Below this arc coverage (share of 10° sectors, [0, 1]) the fit is a partial arc.
    pub min_arc_coverage: f64,
}

impl Default for CircleParams {
    fn default() -> Self {
        Self {
            inlier_threshold_m: 0.015,
            iterations: 250,
            seed: 0x5eed_c1c1e,
            min_radius_m: 0.02,
            max_radius_m: 1.5,
            refine_iterations: 20,
            min_arc_coverage: 0.45,
        }
    }
}

/// A robust circle fit with its quality figures.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RobustCircle {
    /// The final circle: `n` inliers, `rms` over them (metres).
    pub fit: CircleFit,
    /// Share of the 36 ten-degree sectors around the centre holding an inlier, [0, 1].
    pub arc_coverage: f64,
    /// Inliers / points given, [0, 1].
    pub inlier_share: f64,
    /// True when the arc coverage is below `min_arc_coverage`.
    pub partial_arc: bool,
    /// Whether the Gauss–Newton refinement converged (true when it was not asked for).
    pub converged: bool,
}

/// Circle through three points; `None` when they are (nearly) collinear.
fn circle_through(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> Option<([f64; 2], f64)> {
    let (bx, by) = (b[0] - a[0], b[1] - a[1]);
    let (cx, cy) = (c[0] - a[0], c[1] - a[1]);
    let d = 2.0 * (bx * cy - by * cx);
    if d.abs() < 1e-12 {
        return None;
    }
    let (b2, c2) = (bx * bx + by * by, cx * cx + cy * cy);
    let ux = (cy * b2 - by * c2) / d;
    let uy = (bx * c2 - cx * b2) / d;
    Some(([a[0] + ux, a[1] + uy], ux.hypot(uy)))
}

fn inliers_of(points: &[[f64; 2]], center: [f64; 2], radius: f64, thr: f64) -> Vec<usize> {
    (0..points.len())
        .filter(|&i| {
            let p = points[i];
            ((p[0] - center[0]).hypot(p[1] - center[1]) - radius).abs() <= thr
        })
        .collect()
}

/// A prior on the circle centre: a RANSAC candidate circle whose centre lies further than
/// `max_offset_m` from `center` is rejected, and so is a final circle that ends up there.
/// Used to keep a fit on the stem it belongs to when other surfaces (a neighbouring stem, a
/// branch) lie within reach; see [`super::dbh::measure_dbh_of`] for the values it gets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CenterPrior {
    /// Expected centre in the plane of the points, metres.
    pub center: [f64; 2],
    /// Largest accepted distance of a circle centre from `center`, metres.
    pub max_offset_m: f64,
    /// Weight of `center` in the geometric refinement, as a pseudo-observation worth this many
    /// points of weight 1 (λ = σ_point² / σ_centre²); 0: the prior only gates.
    pub weight: f64,
}

impl CenterPrior {
    fn admits(&self, c: [f64; 2]) -> bool {
        (c[0] - self.center[0]).hypot(c[1] - self.center[1]) <= self.max_offset_m
    }
}

/// RANSAC → weighted algebraic fit on the inliers → Gauss–Newton, with quality figures.
///
/// The RANSAC score is the inlier count, ties broken by the smaller sum of squared residuals.
/// After the refinement the inliers are selected once more against the refined circle and the
/// fit repeated on them. `None` when fewer than 5 points are given or no candidate circle with
/// at least 5 inliers and a radius within bounds exists.
///
/// The unweighted, unconstrained case of [`fit_circle_robust_weighted`].
pub fn fit_circle_robust(points: &[[f64; 2]], params: &CircleParams) -> Option<RobustCircle> {
    fit_circle_robust_weighted(points, None, None, params)
}

/// [`fit_circle_robust`] with optional per-point weights and an optional centre prior.
///
/// The RANSAC stage is the same as the unweighted one (uniform 3-point samples, scored by the
/// inlier count): a weight says how much a point counts in the fit, not whether it lies on the
/// circle. The weights enter the algebraic fit on the inliers (docs/method.md Stage 5.3, the
/// opacity-weighted fit of the Gaussians), the Gauss–Newton refinement and the reported RMS
/// (weighted RMS); `n`, the inlier share and the arc coverage still count points. With
/// `weights` `None` the result is exactly that of [`fit_circle_robust`]. `None` as well when
/// the weights do not match the points in number or are negative or not finite, or when the
/// centre `prior` rejects every candidate or the final circle.
pub fn fit_circle_robust_weighted(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    prior: Option<&CenterPrior>,
    params: &CircleParams,
) -> Option<RobustCircle> {
    let n = points.len();
    if n < 5
        || points
            .iter()
            .any(|p| !p[0].is_finite() || !p[1].is_finite())
    {
        return None;
    }
    if let Some(w) = weights
        && (w.len() != n || w.iter().any(|w| !w.is_finite() || *w < 0.0))
    {
        return None;
    }
    let thr = params.inlier_threshold_m.max(1e-6);
    let radius_ok = |r: f64| r >= params.min_radius_m && r <= params.max_radius_m;
    let center_ok = |c: [f64; 2]| prior.is_none_or(|p| p.admits(c));
    let mut rng = SplitMix64::new(params.seed ^ (n as u64).wrapping_mul(0x2545_F491_4F6C_DD1D));
    let mut best: Option<(usize, f64, [f64; 2], f64)> = None;
    for _ in 0..params.iterations.max(1) {
        let mut pick = || rng.below(n as u64) as usize;
        let (i, j, k) = (pick(), pick(), pick());
        if i == j || j == k || i == k {
            continue;
        }
        let Some((c, r)) = circle_through(points[i], points[j], points[k]) else {
            continue;
        };
        if !radius_ok(r) || !center_ok(c) {
            continue;
        }
        let (mut count, mut sse) = (0usize, 0.0f64);
        for p in points {
            let e = (p[0] - c[0]).hypot(p[1] - c[1]) - r;
            if e.abs() <= thr {
                count += 1;
                sse += e * e;
            }
        }
        let better = match best {
            None => true,
            Some((bc, bs, _, _)) => count > bc || (count == bc && sse < bs),
        };
        if better {
            best = Some((count, sse, c, r));
        }
    }
    let (count, _, c, r) = best?;
    if count < 5 {
        return None;
    }
    let mut inliers = inliers_of(points, c, r, thr);
    let mut fit = algebraic_on(points, weights, &inliers)?;
    let mut converged = true;
    for _ in 0..2 {
        let (pts, w) = gather(points, weights, &inliers);
        if params.refine_iterations > 0 {
            let (refined, ok) = refine_circle_geometric_with_prior(
                &pts,
                w.as_deref(),
                &fit,
                params.refine_iterations,
                prior.map(|p| (p.center, p.weight)),
            );
            fit = refined;
            converged = ok;
        }
        let again = inliers_of(points, fit.center, fit.radius, thr);
        if again == inliers || again.len() < 5 {
            break;
        }
        inliers = again;
        fit = algebraic_on(points, weights, &inliers)?;
    }
    if !radius_ok(fit.radius) || !center_ok(fit.center) {
        return None;
    }
    let (pts, w) = gather(points, weights, &inliers);
    fit.n = pts.len();
    fit.rms = super::circle::weighted_rms(&pts, w.as_deref(), fit.center, fit.radius);
    let coverage = arc_coverage(&pts, fit.center);
    Some(RobustCircle {
        fit,
        arc_coverage: coverage,
        inlier_share: pts.len() as f64 / n as f64,
        partial_arc: coverage < params.min_arc_coverage,
        converged,
    })
}

/// The points at `idx` with their weights (`None` when unweighted).
fn gather(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    idx: &[usize],
) -> (Vec<[f64; 2]>, Option<Vec<f64>>) {
    let pts = idx.iter().map(|&i| points[i]).collect();
    let w = weights.map(|w| idx.iter().map(|&i| w[i]).collect());
    (pts, w)
}

fn algebraic_on(points: &[[f64; 2]], weights: Option<&[f64]>, idx: &[usize]) -> Option<CircleFit> {
    let (pts, w) = gather(points, weights, idx);
    fit_circle_weighted(&pts, w.as_deref())
}
