//! Iterative closest point (METHOD.md Stage 1.2): refines a coarse similarity from SfM points
//! (source) to the LiDAR cloud (target) by alternating nearest-neighbour correspondences
//! within a shrinking maximum distance and a weighted least-squares update.
//!
//! - Point-to-point (the paper's objective) solves each update in closed form with the
//!   weighted Umeyama/Horn fit, with or without scale.
//! - Point-to-plane linearises sum w ((s R p + t - q) · n_q)^2 about the current pose (small
//!   rotation, translation and log-scale about the correspondences' centroid) and solves the
//!   6×6 or 7×7 normal equations in f64.
//!
//! Robust weights: trimming keeps the best fraction of residuals (weight 1, others 0); Huber
//! weights are min(1, delta / r). The result mirrors Open3D's `RegistrationResult`.

use std::sync::OnceLock;

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

use rayon::prelude::*;

use super::index::CHUNK;
use super::index::Neighbour;
use super::similarity::fit_similarity;
use super::{GeomError, NormalOrientation, NormalParams, PointIndex, Similarity};
use crate::progress::{Progress, SubProgress};
use grid::{ColumnGrid, NONE};
use plane::point_to_plane_step;

/// The ICP objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum IcpMethod {
    /// min sum w |T(p) - q|^2 (the paper's objective).
    PointToPoint,
    /// min sum w ((T(p) - q) · n_q)^2; converges faster on surfaces, needs target normals.
    PointToPlane,
}

/// Robust weighting of correspondences.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum RobustKernel {
    /// All correspondences within the max distance weigh 1.
    None,
    /// Keep the `keep_fraction` (0, 1] of correspondences with the smallest residuals.
    Trimmed { keep_fraction: f64 },
    /// Huber weights min(1, scale / r), `scale` in metres.
    Huber { scale: f64 },
}

/// Parameters of [`icp`]; distances in target units (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct IcpParams {
    /// Objective. Default point-to-point, the paper's (METHOD.md Stage 1.2).
    pub method: IcpMethod,
    /// Estimate scale too (similarity ICP). Default true: METHOD.md Stage 1.2, SfM scale is
    /// only approximately fixed by the coarse step.
    pub estimate_scale: bool,
    /// Estimate rotation (default true). Point-to-plane only: false keeps the initial
    /// rotation and refines translation (and scale, if asked) alone, for surfaces that pin
    /// position well but rotation poorly (ground plus one stem: yaw about the stem is free).
    pub estimate_rotation: bool,
    /// Iteration cap. Default 50 (Open3D's default is 30; the shrinking schedule uses ~15).
    pub max_iterations: usize,
    /// Max correspondence distance at the first iteration. Default 1.0 m: a coarse
    /// registration from control points is good to decimetres.
    pub start_distance: f64,
    /// Factor applied to the max distance after each iteration, in (0, 1]. Default 0.8.
    pub shrink: f64,
    /// Floor of the max distance. Default 0.05 m: a few LiDAR point spacings after 2 cm
    /// voxelisation, well above SfM point noise after alignment.
    pub min_distance: f64,
    /// Robust weighting. Default trimmed, keeping the best 80% (SfM clouds carry sky and
    /// mismatched points that LiDAR does not see).
    pub robust: RobustKernel,
    /// Converged once the max distance is at its floor and the weighted RMSE changes by less
    /// than this fraction between iterations. Default 1e-6, the value of Open3D's
    /// `relative_rmse` (which Open3D compares with the absolute change, together with the
    /// fitness's).
    pub relative_rmse_tolerance: f64,
    /// Neighbours for target normals when point-to-plane is asked for without normals.
    /// Default 20 (as [`NormalParams`]).
    pub normal_k: usize,
}

impl Default for IcpParams {
    fn default() -> Self {
        Self {
            method: IcpMethod::PointToPoint,
            estimate_scale: true,
            estimate_rotation: true,
            max_iterations: 50,
            start_distance: 1.0,
            shrink: 0.8,
            min_distance: 0.05,
            robust: RobustKernel::Trimmed { keep_fraction: 0.8 },
            relative_rmse_tolerance: 1e-6,
            normal_k: 20,
        }
    }
}

/// Outcome of [`icp`], after Open3D's `RegistrationResult`: x_target = s R x_source + t.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IcpResult {
    pub rotation: glam::DMat3,
    pub translation: DVec3,
    pub scale: f64,
    /// Share of source points with a target point within the final max distance, [0, 1].
    pub fitness: f64,
    /// RMS Euclidean distance of those correspondences (metres).
    pub inlier_rmse: f64,
    /// Final max correspondence distance (metres).
    pub max_distance: f64,
    pub iterations: usize,
    /// True when the RMSE change fell below the tolerance before the iteration cap.
    pub converged: bool,
}

impl IcpResult {
    /// The estimated transform as a [`Similarity`].
    pub fn transform(&self) -> Similarity {
        Similarity {
            scale: self.scale,
            rotation: self.rotation,
            translation: self.translation,
        }
    }
}

/// Prior weights of the correspondences, each in [0, 1] (`None`: all 1). A pair's weight is
/// the source point's prior times the target point's prior times its robust weight; a pair
/// with a zero prior is not used at all.
#[derive(Debug, Clone, Copy, Default)]
pub struct IcpWeights<'a> {
    /// One per source point (for SfM points: how well the point is triangulated).
    pub source: Option<&'a [f32]>,
    /// One per target point (for LiDAR points: how well the local surface is defined).
    pub target: Option<&'a [f32]>,
}

/// One correspondence: source index, target index, residual (metres), prior weight and
/// final weight (prior times robust weight).
#[derive(Debug, Clone, Copy, Default)]
struct Pair {
    src: u32,
    tgt: u32,
    residual: f64,
    prior: f64,
    weight: f64,
}

/// Registers `source` onto `target` from `initial`, building the target index (and target
/// normals for point-to-plane when `target_normals` is `None`).
pub fn icp(
    source: &[Vec3],
    target: &[Vec3],
    target_normals: Option<&[Vec3]>,
    initial: &Similarity,
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<IcpResult, GeomError> {
    if target.len() >= u32::MAX as usize {
        return Err(GeomError::InvalidParameter(format!(
            "{} target points exceed the index limit of 2^32 - 1",
            target.len()
        )));
    }
    if !target.par_iter().all(|p| p.is_finite()) {
        return Err(GeomError::NonFinite("point positions"));
    }
    if let (IcpMethod::PointToPlane, None) = (params.method, target_normals) {
        let index = PointIndex::new(target)?;
        let np = NormalParams {
            k: params.normal_k,
            orientation: NormalOrientation::None,
        };
        let estimated = super::estimate_normals_with_index(
            target,
            &index,
            &np,
            &SubProgress::new(progress, 0.0, 0.3),
        )?;
        return run(
            source,
            target,
            Some(&index),
            Some(&estimated.normals),
            IcpWeights::default(),
            initial,
            params,
            &SubProgress::new(progress, 0.3, 0.7),
        );
    }
    // The k-d tree is built only if the column grid hands a query back (a far outlier).
    run(
        source,
        target,
        None,
        target_normals,
        IcpWeights::default(),
        initial,
        params,
        progress,
    )
}

/// As [`icp`], with a prebuilt index over exactly `target`. Point-to-plane needs
/// `target_normals`.
pub fn icp_with_index(
    source: &[Vec3],
    target: &[Vec3],
    index: &PointIndex,
    target_normals: Option<&[Vec3]>,
    initial: &Similarity,
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<IcpResult, GeomError> {
    icp_weighted(
        source,
        target,
        index,
        target_normals,
        IcpWeights::default(),
        initial,
        params,
        progress,
    )
}

/// As [`icp_with_index`], with prior weights per source and per target point.
#[allow(clippy::too_many_arguments)]
pub fn icp_weighted(
    source: &[Vec3],
    target: &[Vec3],
    index: &PointIndex,
    target_normals: Option<&[Vec3]>,
    weights: IcpWeights<'_>,
    initial: &Similarity,
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<IcpResult, GeomError> {
    if index.len() != target.len() {
        return Err(GeomError::LengthMismatch {
            what: "index vs target",
            left: index.len(),
            right: target.len(),
        });
    }
    run(
        source,
        target,
        Some(index),
        target_normals,
        weights,
        initial,
        params,
        progress,
    )
}

/// The ICP loop over finite target points (checked by the callers: `PointIndex::new` or
/// [`icp`]); `index`, when given, indexes exactly `target`, else it is built on first need.
#[allow(clippy::too_many_arguments)]
fn run(
    source: &[Vec3],
    target: &[Vec3],
    index: Option<&PointIndex>,
    target_normals: Option<&[Vec3]>,
    weights: IcpWeights<'_>,
    initial: &Similarity,
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<IcpResult, GeomError> {
    validate(source, target, target_normals, initial, params)?;
    validate_weights(weights.source, source.len(), "source weights")?;
    validate_weights(weights.target, target.len(), "target weights")?;
    let plane = params.method == IcpMethod::PointToPlane;
    let normals = target_normals.unwrap_or(&[]);
    let mut t = *initial;
    let mut dist = params.start_distance;
    let mut prev_rmse: Option<f64> = None;
    let mut converged = false;
    let mut iterations = 0;
    // Correspondence search: the column grid, seeded with each source point's previous
    // correspondence; the k-d tree for queries the grid hands back.
    let search = Search {
        target,
        index,
        lazy: OnceLock::new(),
        grid: ColumnGrid::new(target),
    };
    let mut prev = vec![NONE; source.len()];
    while iterations < params.max_iterations {
        if progress.is_cancelled() {
            return Err(GeomError::Cancelled);
        }
        let at_floor = dist <= params.min_distance;
        let mut pairs = correspond(source, &search, &mut prev, weights, &t, dist, |q, j| {
            if plane {
                (q - target[j].as_dvec3()).dot(normals[j].as_dvec3()).abs()
            } else {
                (q - target[j].as_dvec3()).length()
            }
        })?;
        let min_pairs = if plane { 7 } else { 3 };
        if pairs.len() < min_pairs {
            return Err(GeomError::Empty(
                "ICP correspondences within the max distance; improve the initial alignment or raise start_distance",
            ));
        }
        weigh(&mut pairs, params.robust);
        let sw: f64 = pairs.iter().map(|p| p.weight).sum();
        let rmse = (pairs
            .iter()
            .map(|p| p.weight * p.residual * p.residual)
            .sum::<f64>()
            / sw.max(1e-300))
        .sqrt();
        t = if plane {
            point_to_plane_step(
                source,
                target,
                normals,
                &pairs,
                &t,
                params.estimate_scale,
                params.estimate_rotation,
            )?
        } else {
            fit_similarity(
                pairs.len(),
                |k| {
                    let p = pairs[k];
                    (
                        source[p.src as usize].as_dvec3(),
                        target[p.tgt as usize].as_dvec3(),
                        p.weight,
                    )
                },
                params.estimate_scale,
            )?
        };
        iterations += 1;
        progress.log(&format!(
            "ICP iteration {iterations}: max distance {dist:.4} m, {} correspondences, weighted RMSE {rmse:.5} m, scale {:.6}",
            pairs.len(),
            t.scale
        ));
        progress.set(iterations as f64 / params.max_iterations as f64);
        if at_floor {
            if let Some(prev) = prev_rmse
                && (rmse == 0.0 || (prev - rmse).abs() <= params.relative_rmse_tolerance * prev)
            {
                converged = true;
                break;
            }
            prev_rmse = Some(rmse);
        }
        dist = (dist * params.shrink).max(params.min_distance);
    }
    let final_pairs = correspond(
        source,
        &search,
        &mut prev,
        IcpWeights::default(),
        &t,
        dist,
        |q, j| (q - target[j].as_dvec3()).length(),
    )?;
    let inlier_rmse = if final_pairs.is_empty() {
        0.0
    } else {
        (final_pairs
            .iter()
            .map(|p| p.residual * p.residual)
            .sum::<f64>()
            / final_pairs.len() as f64)
            .sqrt()
    };
    progress.set(1.0);
    Ok(IcpResult {
        rotation: t.rotation,
        translation: t.translation,
        scale: t.scale,
        fitness: final_pairs.len() as f64 / source.len() as f64,
        inlier_rmse,
        max_distance: dist,
        iterations,
        converged,
    })
}

fn validate(
    source: &[Vec3],
    target: &[Vec3],
    target_normals: Option<&[Vec3]>,
    initial: &Similarity,
    p: &IcpParams,
) -> Result<(), GeomError> {
    if source.is_empty() || target.is_empty() {
        return Err(GeomError::Empty(
            "ICP needs non-empty source and target clouds",
        ));
    }
    if p.method == IcpMethod::PointToPlane {
        match target_normals {
            None => {
                return Err(GeomError::InvalidParameter(
                    "point-to-plane ICP needs target normals".into(),
                ));
            }
            Some(n) if n.len() != target.len() => {
                return Err(GeomError::LengthMismatch {
                    what: "target normals vs target",
                    left: n.len(),
                    right: target.len(),
                });
            }
            Some(n) if !n.iter().all(|v| v.is_finite()) => {
                return Err(GeomError::NonFinite("target normals"));
            }
            _ => {}
        }
    }
    if !source.iter().all(|v| v.is_finite()) {
        return Err(GeomError::NonFinite("source points"));
    }
    let finite_init = initial.scale.is_finite()
        && initial.scale > 0.0
        && initial.rotation.is_finite()
        && initial.translation.is_finite();
    if !finite_init {
        return Err(GeomError::NonFinite(
            "initial transform (scale must be > 0)",
        ));
    }
    if !p.estimate_rotation && p.method != IcpMethod::PointToPlane {
        return Err(GeomError::InvalidParameter(
            "a fixed rotation (estimate_rotation = false) needs point-to-plane ICP".into(),
        ));
    }
    let ok = p.max_iterations > 0
        && p.start_distance.is_finite()
        && p.min_distance.is_finite()
        && p.min_distance > 0.0
        && p.start_distance >= p.min_distance
        && p.shrink > 0.0
        && p.shrink <= 1.0
        && p.relative_rmse_tolerance >= 0.0
        && match p.robust {
            RobustKernel::None => true,
            RobustKernel::Trimmed { keep_fraction } => keep_fraction > 0.0 && keep_fraction <= 1.0,
            RobustKernel::Huber { scale } => scale > 0.0 && scale.is_finite(),
        };
    if !ok {
        return Err(GeomError::InvalidParameter(format!(
            "ICP parameters out of range: {p:?} (need 0 < min_distance <= start_distance, 0 < shrink <= 1, max_iterations >= 1, keep_fraction in (0, 1], Huber scale > 0)"
        )));
    }
    Ok(())
}

/// Each prior weight must be finite and in [0, 1].
fn validate_weights(w: Option<&[f32]>, n: usize, what: &'static str) -> Result<(), GeomError> {
    match w {
        Some(w) if w.len() != n => Err(GeomError::LengthMismatch {
            what,
            left: w.len(),
            right: n,
        }),
        Some(w) if !w.iter().all(|v| (0.0..=1.0).contains(v)) => Err(GeomError::InvalidParameter(
            format!("{what} must lie in [0, 1]"),
        )),
        _ => Ok(()),
    }
}

/// The correspondence search over one target.
struct Search<'a> {
    target: &'a [Vec3],
    /// The caller's k-d tree over `target`, if any.
    index: Option<&'a PointIndex>,
    /// Else one built on the first query the grid hands back (`None`: the build failed).
    lazy: OnceLock<Option<PointIndex>>,
    grid: Option<ColumnGrid>,
}

impl Search<'_> {
    /// The nearest target point to `q` with squared distance at most `max_d2` (m²), starting
    /// from the closer of two hints (target indices or [`NONE`]: the point's previous
    /// correspondence and the previous query's); exact either way.
    fn nearest(&self, q: Vec3, max_d2: f32, hints: [u32; 2]) -> Option<Neighbour> {
        let mut start = (max_d2, NONE);
        for hint in hints {
            if let Some(p) = self.target.get(hint as usize) {
                let e = *p - q;
                let d2 = e.x * e.x + e.y * e.y + e.z * e.z;
                if d2 < start.0 || (d2 == start.0 && start.1 == NONE) {
                    start = (d2, hint);
                }
            }
        }
        match self.grid.as_ref().and_then(|g| g.nearest(q, start)) {
            Some((dist2, index)) => (index != NONE).then_some(Neighbour { index, dist2 }),
            None => {
                let index = match self.index {
                    Some(i) => Some(i),
                    None => self
                        .lazy
                        .get_or_init(|| PointIndex::new(self.target).ok())
                        .as_ref(),
                };
                let m = match index {
                    Some(i) => i.nearest(q),
                    None => self.brute(q),
                };
                m.filter(|m| m.dist2 <= max_d2)
            }
        }
    }

    /// The nearest target point by a full scan (only if no k-d tree could be built).
    fn brute(&self, q: Vec3) -> Option<Neighbour> {
        self.target
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let e = *p - q;
                Neighbour {
                    index: i as u32,
                    dist2: e.x * e.x + e.y * e.y + e.z * e.z,
                }
            })
            .min_by(|a, b| a.dist2.total_cmp(&b.dist2))
    }
}

/// Nearest target point of every transformed source point within `max_dist` whose prior
/// weight is positive, in parallel chunks. `prev` holds each source point's correspondence
/// of the last call (the search's starting bound) and is updated.
fn correspond(
    source: &[Vec3],
    search: &Search<'_>,
    prev: &mut [u32],
    weights: IcpWeights<'_>,
    t: &Similarity,
    max_dist: f64,
    residual: impl Fn(DVec3, usize) -> f64 + Sync,
) -> Result<Vec<Pair>, GeomError> {
    let max2 = max_dist * max_dist;
    // The f32 bound just above max_dist^2; pairs are then checked in f64 as before.
    let max_d2 = (max2 as f32).next_up();
    let parts: Vec<Vec<Pair>> = source
        .par_chunks(CHUNK)
        .zip(prev.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(c, (src, prv))| {
            let mut out = Vec::with_capacity(src.len());
            // Consecutive source points are usually close: the last match is a second hint.
            let mut last = NONE;
            for (k, (p, pv)) in src.iter().zip(prv.iter_mut()).enumerate() {
                let i = c * CHUNK + k;
                let ws = weights.source.map_or(1.0, |w| w[i] as f64);
                if ws <= 0.0 {
                    *pv = NONE;
                    continue;
                }
                let q = t.apply(p.as_dvec3());
                let Some(m) = search.nearest(q.as_vec3(), max_d2, [*pv, last]) else {
                    *pv = NONE;
                    continue;
                };
                *pv = m.index;
                last = m.index;
                if (m.dist2 as f64) > max2 {
                    continue;
                }
                let prior = ws * weights.target.map_or(1.0, |w| w[m.index as usize] as f64);
                if prior > 0.0 {
                    out.push(Pair {
                        src: i as u32,
                        tgt: m.index,
                        residual: residual(q, m.index as usize),
                        prior,
                        weight: prior,
                    });
                }
            }
            out
        })
        .collect();
    Ok(parts.concat())
}

/// Sets each pair's weight: its prior times the robust weight.
fn weigh(pairs: &mut [Pair], kernel: RobustKernel) {
    match kernel {
        RobustKernel::None => {}
        RobustKernel::Trimmed { keep_fraction } => {
            let keep = ((pairs.len() as f64 * keep_fraction).ceil() as usize).clamp(1, pairs.len());
            let mut r: Vec<f64> = pairs.iter().map(|p| p.residual).collect();
            let (_, cut, _) = r.select_nth_unstable_by(keep - 1, |a, b| a.total_cmp(b));
            let cut = *cut;
            let mut kept = 0;
            for p in pairs.iter_mut() {
                // Ties at the cut keep at most `keep` pairs.
                p.weight = if p.residual <= cut && kept < keep {
                    kept += 1;
                    p.prior
                } else {
                    0.0
                };
            }
        }
        RobustKernel::Huber { scale } => {
            for p in pairs.iter_mut() {
                p.weight = p.prior
                    * if p.residual <= scale {
                        1.0
                    } else {
                        scale / p.residual
                    };
            }
        }
    }
}

mod grid;
mod plane;

#[cfg(test)]
mod tests;
