//! Statistical outlier filter (docs/method.md Stage 2.2, paper 3.3.2): for each point,
//! d_m = mean distance to its k nearest neighbours; keep the point iff
//! d_m <= mu + alpha * sigma, with mu and sigma the mean and standard deviation of all d_m.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::{GeomError, PointIndex};
use crate::progress::Progress;

/// Parameters of [`statistical_outlier_filter`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct OutlierParams {
    /// Neighbours per point, the point itself not counted. Paper 3.3.2: k = 16.
    pub k: usize,
    /// Threshold in standard deviations above the mean. Paper 3.3.2: alpha = 2.5.
    pub alpha: f64,
}

impl Default for OutlierParams {
    fn default() -> Self {
        Self { k: 16, alpha: 2.5 }
    }
}

/// Result of [`statistical_outlier_filter`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OutlierFilter {
    /// `keep[i]` is true for the points that pass (the anchors).
    pub keep: Vec<bool>,
    /// Mean of the per-point mean neighbour distances d_m (metres).
    pub mu: f64,
    /// Standard deviation of d_m (metres; sample, n - 1, as Open3D).
    pub sigma: f64,
    /// The threshold mu + alpha * sigma (metres).
    pub threshold: f64,
    /// Number of kept points.
    pub kept: usize,
}

/// Runs the filter, building a spatial index over `points` first.
///
/// Choices where the paper is silent: the point itself is not one of its k neighbours (an
/// exact duplicate is); a cloud with at most k points keeps everything (mu, sigma from the
/// available neighbours).
pub fn statistical_outlier_filter(
    points: &[Vec3],
    params: &OutlierParams,
    progress: &dyn Progress,
) -> Result<OutlierFilter, GeomError> {
    PointIndex::build_then(points, progress, |index, rest| {
        statistical_outlier_filter_with_index(points, index, params, rest)
    })
}

/// As [`statistical_outlier_filter`], with a prebuilt index over exactly `points`.
pub fn statistical_outlier_filter_with_index(
    points: &[Vec3],
    index: &PointIndex,
    params: &OutlierParams,
    progress: &dyn Progress,
) -> Result<OutlierFilter, GeomError> {
    if params.k == 0 || !params.alpha.is_finite() {
        return Err(GeomError::InvalidParameter(format!(
            "outlier filter needs k >= 1 and a finite alpha, got k = {}, alpha = {}",
            params.k, params.alpha
        )));
    }
    GeomError::check_len("index vs points", index.len(), points.len())?;
    let n = points.len();
    if n < 2 {
        return Ok(OutlierFilter {
            keep: vec![true; n],
            kept: n,
            ..Default::default()
        });
    }
    let k = params.k;
    let mean_d: Vec<f32> = index.map_knn(points, k + 1, progress, |i, nb| {
        // Drop the query point itself (or, among duplicates, the farthest extra neighbour).
        let skip = nb
            .iter()
            .position(|m| m.index as usize == i)
            .unwrap_or(nb.len() - 1);
        let (mut s, mut c) = (0.0f32, 0u32);
        for (j, m) in nb.iter().enumerate() {
            if j != skip {
                s += m.dist2.sqrt();
                c += 1;
            }
        }
        s / c.max(1) as f32
    })?;
    let (sum, sum2) = mean_d.iter().fold((0.0f64, 0.0f64), |(a, b), &d| {
        let d = d as f64;
        (a + d, b + d * d)
    });
    let nf = n as f64;
    let mu = sum / nf;
    let var = ((sum2 - nf * mu * mu) / (nf - 1.0)).max(0.0);
    let sigma = var.sqrt();
    let threshold = mu + params.alpha * sigma;
    let keep: Vec<bool> = mean_d.iter().map(|&d| d as f64 <= threshold).collect();
    let kept = keep.iter().filter(|&&b| b).count();
    progress.set(1.0);
    Ok(OutlierFilter {
        keep,
        mu,
        sigma,
        threshold,
        kept,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;
    use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

    #[test]
    fn removes_planted_far_points_and_keeps_plane_and_cylinder() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut pts = Vec::new();
        // A 4 × 4 m plane on a 2 cm grid with 2 mm jitter.
        for i in 0..200 {
            for j in 0..200 {
                pts.push(Vec3::new(
                    i as f32 * 0.02 + rng.random_range(-0.002..0.002),
                    j as f32 * 0.02 + rng.random_range(-0.002..0.002),
                    rng.random_range(-0.002..0.002),
                ));
            }
        }
        // A stem: cylinder r = 0.15 m at (2, 2), 2 cm spacing along the arc and up.
        let arc = (2.0 * std::f32::consts::PI * 0.15 / 0.02) as usize;
        for h in 1..100 {
            for a in 0..arc {
                let t = a as f32 / arc as f32 * std::f32::consts::TAU;
                pts.push(Vec3::new(
                    2.0 + 0.15 * t.cos(),
                    2.0 + 0.15 * t.sin(),
                    h as f32 * 0.02,
                ));
            }
        }
        let clean = pts.len();
        // 50 isolated points floating 1–3 m above the scene.
        for _ in 0..50 {
            pts.push(Vec3::new(
                rng.random_range(0.0..4.0),
                rng.random_range(0.0..4.0),
                rng.random_range(3.0..5.0),
            ));
        }
        let out = statistical_outlier_filter(&pts, &OutlierParams::default(), &NoProgress).unwrap();
        assert!(
            out.keep[clean..].iter().all(|&k| !k),
            "a planted outlier survived"
        );
        let kept_clean = out.keep[..clean].iter().filter(|&&k| k).count();
        assert!(
            kept_clean as f64 >= 0.995 * clean as f64,
            "kept {kept_clean} of {clean} clean points"
        );
        assert!(out.mu > 0.02 && out.mu < 0.1, "mu {}", out.mu);
        assert_eq!(out.kept, kept_clean);
    }

    #[test]
    fn tiny_clouds_and_bad_parameters() {
        let one = [Vec3::ZERO];
        let out = statistical_outlier_filter(&one, &OutlierParams::default(), &NoProgress).unwrap();
        assert_eq!(out.keep, vec![true]);
        let bad = OutlierParams { k: 0, alpha: 2.5 };
        assert!(statistical_outlier_filter(&one, &bad, &NoProgress).is_err());
    }
}
