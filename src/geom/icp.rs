//! Iterative closest point (docs/method.md Stage 1.2): refines a coarse similarity from SfM points
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
//!
//! Correspondences are exact nearest neighbours within the max distance, found fast three
//! ways: the source is visited in Z order; each source point keeps its few nearest target
//! points and their clearance, which answers the next iteration's query without a search
//! while the point has moved less than the clearance allows (`Slot`); and a source of
//! `COARSE_MIN_SOURCE` points or more first iterates on an even subsample until that
//! settles, so the searches on all points start where points barely move.

use std::sync::OnceLock;

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

use rayon::prelude::*;

use super::index::CHUNK;
use super::index::Neighbour;
use super::similarity::fit_similarity;
use super::{GeomError, NormalOrientation, NormalParams, PointIndex, Similarity};
use crate::progress::{Progress, SubProgress};
use grid::{ColumnGrid, KNN, Knn, NONE};
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
    /// Objective. Default point-to-point, the paper's (docs/method.md Stage 1.2).
    pub method: IcpMethod,
    /// Estimate scale too (similarity ICP). Default true: docs/method.md Stage 1.2, SfM scale is
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
    /// than this fraction between iterations (or by less than a nanometre, see
    /// `RMSE_FLOOR_M`). Default 1e-6, the value of Open3D's
    /// `relative_rmse` (which Open3D compares with the absolute change, together with the
    /// fitness's).
    pub relative_rmse_tolerance: f64,
    /// Neighbours for target normals when point-to-plane is asked for without normals.
    /// Default 20 (as [`NormalParams`]).
    pub normal_k: usize,
    /// Let a source of 65,536 points or more (`COARSE_MIN_SOURCE`) iterate first on every
    /// 16th point until that settles, then on all points. Default true: the same fixed point
    /// for a fraction of the searches (see the module docs). false: every iteration uses
    /// every point, as Open3D's `registration_icp` does.
    pub coarse_start: bool,
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
            coarse_start: true,
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
    /// Iterations run, counting those on the subsample of a large source (see
    /// `COARSE_MIN_SOURCE`).
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

/// One correspondence: source index, the moved source point, the target point and normal,
/// residual (metres), prior weight and final weight (prior times robust weight).
#[derive(Debug, Clone, Copy, Default)]
struct Pair {
    src: u32,
    /// The source point moved by the current transform.
    q: DVec3,
    /// The target point and its normal (zero for point-to-point).
    tp: Vec3,
    n: Vec3,
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
        return icp_weighted(
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
    icp_weighted(
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

/// RMSE changes below this many metres count as settled whatever the relative change: a
/// nanometre, far below any survey's precision and above the f64 rounding of plot
/// coordinates (identical clouds otherwise never settle on rounding noise).
const RMSE_FLOOR_M: f64 = 1e-9;

/// Sources of at least this many points run their first iterations on every
/// [`COARSE_STRIDE`]-th point (in Z order, so spread evenly) until those converge, then go on
/// with all points from there. The early iterations move points by centimetres, which makes
/// every full-size search a fresh one; on the subsample they cost a sixteenth. Chosen on
/// `sylva bench geom --icp-tile-m 100` (256 k source points); SfM clouds are usually smaller
/// and run every iteration on all points.
const COARSE_MIN_SOURCE: usize = 65_536;

/// Stride of the coarse subsample (see [`COARSE_MIN_SOURCE`]).
const COARSE_STRIDE: usize = 16;

/// The subsample's iterations stop once its weighted RMSE changes by at most this fraction
/// (or the caller's tolerance, if looser), or after half the iteration cap: its optimum is
/// only near the full one, which the iterations on all points then settle.
const COARSE_TOLERANCE: f64 = 1e-4;

/// As [`icp`], with prior weights per source and per target point and, when given, a prebuilt
/// `index` over exactly `target` (else one is built on first need). Point-to-plane needs
/// `target_normals`. The target points must be finite (checked by `PointIndex::new` or
/// [`icp`]).
#[allow(clippy::too_many_arguments)]
pub fn icp_weighted(
    source: &[Vec3],
    target: &[Vec3],
    index: Option<&PointIndex>,
    target_normals: Option<&[Vec3]>,
    weights: IcpWeights<'_>,
    initial: &Similarity,
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<IcpResult, GeomError> {
    if let Some(index) = index {
        GeomError::check_len("index vs target", index.len(), target.len())?;
    }
    validate(source, target, target_normals, initial, params)?;
    validate_weights(weights.source, source.len(), "source weights")?;
    validate_weights(weights.target, target.len(), "target weights")?;
    // The source in Z order: consecutive queries then touch neighbouring grid columns and
    // cache lines. Nothing outside this function sees source indices.
    let order = z_order(source);
    let source: Vec<Vec3> = order.iter().map(|&i| source[i as usize]).collect();
    let source_weights: Option<Vec<f32>> = weights
        .source
        .map(|w| order.iter().map(|&i| w[i as usize]).collect());
    let weights = IcpWeights {
        source: source_weights.as_deref(),
        target: weights.target,
    };
    // Correspondence search: the column grid, seeded with each source point's previous
    // correspondence; the k-d tree for queries the grid hands back.
    let search = Search {
        target,
        normals: target_normals.unwrap_or(&[]),
        index,
        lazy: OnceLock::new(),
        grid: ColumnGrid::new(target),
    };
    let mut state = LoopState {
        t: *initial,
        dist: params.start_distance,
        iterations: 0,
        converged: false,
    };
    if params.coarse_start && source.len() >= COARSE_MIN_SOURCE {
        let sub: Vec<Vec3> = source.iter().step_by(COARSE_STRIDE).copied().collect();
        let sub_w: Option<Vec<f32>> = weights
            .source
            .map(|w| w.iter().step_by(COARSE_STRIDE).copied().collect());
        let sub_weights = IcpWeights {
            source: sub_w.as_deref(),
            target: weights.target,
        };
        // Points move by centimetres per iteration here: cached neighbourhoods would not
        // hold, so every query walks the grid from its previous match.
        let mut sub_side = Side::new(&sub, sub_weights, false);
        progress.log(&format!(
            "ICP: first iterations on {} of the {} source points",
            sub.len(),
            source.len()
        ));
        iterate(
            &mut sub_side,
            &search,
            params,
            (
                params.relative_rmse_tolerance.max(COARSE_TOLERANCE),
                params.max_iterations / 2,
            ),
            &mut state,
            progress,
        )?;
        state.converged = false;
    }
    let mut side = Side::new(&source, weights, true);
    iterate(
        &mut side,
        &search,
        params,
        (params.relative_rmse_tolerance, params.max_iterations),
        &mut state,
        progress,
    )?;
    let final_pairs = correspond(
        &mut side,
        &search,
        false,
        &state.t,
        state.dist,
        |q, tp, _| (q - tp).length(),
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
    let t = state.t;
    Ok(IcpResult {
        rotation: t.rotation,
        translation: t.translation,
        scale: t.scale,
        fitness: final_pairs.len() as f64 / source.len() as f64,
        inlier_rmse,
        max_distance: state.dist,
        iterations: state.iterations,
        converged: state.converged,
    })
}

/// Where the ICP loop stands: pose, max distance (metres), iterations done, converged.
struct LoopState {
    t: Similarity,
    dist: f64,
    iterations: usize,
    converged: bool,
}

/// Iterates on `source` from `state` until the weighted RMSE changes by at most `tolerance`
/// (relative) at the distance floor, or `state.iterations` reaches `cap`.
fn iterate(
    side: &mut Side<'_>,
    search: &Search<'_>,
    params: &IcpParams,
    (tolerance, cap): (f64, usize),
    state: &mut LoopState,
    progress: &dyn Progress,
) -> Result<(), GeomError> {
    let plane = params.method == IcpMethod::PointToPlane;
    let mut prev_rmse: Option<f64> = None;
    while state.iterations < cap {
        if progress.is_cancelled() {
            return Err(GeomError::Cancelled);
        }
        let dist = state.dist;
        let at_floor = dist <= params.min_distance;
        let mut pairs = correspond(side, search, true, &state.t, dist, |q, tp, n| {
            if plane {
                (q - tp).dot(n).abs()
            } else {
                (q - tp).length()
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
        let t = &state.t;
        state.t = if plane {
            point_to_plane_step(&pairs, t, params.estimate_scale, params.estimate_rotation)?
        } else {
            fit_similarity(
                pairs.len(),
                |k| {
                    let p = pairs[k];
                    (
                        side.points[p.src as usize].as_dvec3(),
                        p.tp.as_dvec3(),
                        p.weight,
                    )
                },
                params.estimate_scale,
            )?
        };
        state.iterations += 1;
        progress.log(&format!(
            "ICP iteration {}: max distance {dist:.4} m, {} correspondences, weighted RMSE {rmse:.5} m, scale {:.6}",
            state.iterations,
            pairs.len(),
            state.t.scale
        ));
        progress.set(state.iterations as f64 / params.max_iterations as f64);
        if at_floor {
            if let Some(prev) = prev_rmse
                && (rmse == 0.0 || (prev - rmse).abs() <= tolerance * prev + RMSE_FLOOR_M)
            {
                state.converged = true;
                return Ok(());
            }
            prev_rmse = Some(rmse);
        }
        state.dist = (dist * params.shrink).max(params.min_distance);
    }
    Ok(())
}

/// Indices of `points` (finite) sorted by their Morton key on a 2^21 grid over the bounding
/// cube.
fn z_order(points: &[Vec3]) -> Vec<u32> {
    let Some(first) = points.first() else {
        return Vec::new();
    };
    let (lo, hi) = points
        .iter()
        .fold((*first, *first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    let extent = (hi - lo).max_element().max(1e-6);
    let inv = ((1u32 << 21) - 1) as f32 / extent;
    let mut keyed: Vec<(u64, u32)> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let c = ((*p - lo) * inv).clamp(Vec3::ZERO, Vec3::splat(((1u32 << 21) - 1) as f32));
            (
                super::voxel::morton3(c.x as u64, c.y as u64, c.z as u64),
                i as u32,
            )
        })
        .collect();
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
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
        let Some(n) = target_normals else {
            return Err(GeomError::InvalidParameter(
                "point-to-plane ICP needs target normals".into(),
            ));
        };
        GeomError::check_len("target normals vs target", n.len(), target.len())?;
        if !n.iter().all(|v| v.is_finite()) {
            return Err(GeomError::NonFinite("target normals"));
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
    let Some(w) = w else {
        return Ok(());
    };
    GeomError::check_len(what, w.len(), n)?;
    if !w.iter().all(|v| (0.0..=1.0).contains(v)) {
        return Err(GeomError::InvalidParameter(format!(
            "{what} must lie in [0, 1]"
        )));
    }
    Ok(())
}

/// Relative and absolute (metres) margins of the cache certificate, above the f32 rounding
/// of distances between points of a plot-sized local frame (about 1e-5 m at 100 m).
const CACHE_REL: f32 = 1e-5;
const CACHE_ABS_M: f32 = 5e-5;

/// Largest cache [`icp`] keeps (bytes): about 3.6 M source points; larger sources search
/// the grid afresh every iteration.
const CACHE_MAX_BYTES: usize = 512 << 20;

/// One source point's cached neighbourhood: the [`KNN`] target points nearest to `anchor`
/// (its transformed position when they were found) and the clearance, the distance from
/// `anchor` within which they are all the target points there are. After the point moves
/// to q, |q - anchor| = m, every other target point lies at least `clear - m` from q
/// (triangle inequality), so the nearest cached point is the nearest of all when its
/// distance (or the max distance, if less) is at most `clear - m`. ICP's late iterations
/// move points by millimetres against clearances of centimetres: most queries are then a
/// few distance computations instead of a grid walk. Exact, like the walk.
#[derive(Debug, Clone, Copy)]
struct Slot {
    anchor: Vec3,
    /// Metres; 0: nothing cached.
    clear: f32,
    n: u32,
    index: [u32; KNN],
    pos: [Vec3; KNN],
}

impl Default for Slot {
    fn default() -> Self {
        Self {
            anchor: Vec3::ZERO,
            clear: 0.0,
            n: 0,
            index: [NONE; KNN],
            pos: [Vec3::ZERO; KNN],
        }
    }
}

/// One source cloud (in Z order) with its prior weights and its search state, kept from
/// one iteration to the next: each point's last correspondence (the next search's starting
/// bound) and its [`Slot`].
struct Side<'a> {
    points: &'a [Vec3],
    weights: IcpWeights<'a>,
    prev: Vec<u32>,
    /// One per point, or none: not asked for, or over [`CACHE_MAX_BYTES`].
    slots: Vec<Slot>,
}

impl<'a> Side<'a> {
    fn new(points: &'a [Vec3], weights: IcpWeights<'a>, cached: bool) -> Self {
        let n = points.len();
        let fits = n.saturating_mul(std::mem::size_of::<Slot>()) <= CACHE_MAX_BYTES;
        Side {
            points,
            weights,
            prev: vec![NONE; n],
            slots: if cached && fits {
                vec![Slot::default(); n]
            } else {
                Vec::new()
            },
        }
    }
}

/// The correspondence search over one target.
struct Search<'a> {
    target: &'a [Vec3],
    /// Target normals (empty for point-to-point).
    normals: &'a [Vec3],
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

    /// As [`Search::nearest`], answered from the source point's cached neighbours when
    /// their clearance certifies it (see [`Slot`]), else by a fresh k-nearest query that
    /// refills the cache (or by [`Search::nearest`] when the grid hands the query back).
    fn nearest_cached(
        &self,
        q: Vec3,
        max_d2: f32,
        hints: [u32; 2],
        slot: &mut Slot,
        scratch: &mut Knn,
    ) -> Option<(Neighbour, Vec3)> {
        if slot.clear > 0.0 {
            let mut best = (f32::INFINITY, NONE, Vec3::ZERO);
            for (p, &i) in slot.pos.iter().zip(&slot.index).take(slot.n as usize) {
                let e = *p - q;
                let d2 = e.x * e.x + e.y * e.y + e.z * e.z;
                if d2 < best.0 {
                    best = (d2, i, *p);
                }
            }
            let reach = best.0.min(max_d2).sqrt();
            let moved = (q - slot.anchor).length();
            if (reach + moved) * (1.0 + CACHE_REL) + CACHE_ABS_M <= slot.clear {
                return (best.1 != NONE && best.0 <= max_d2).then_some((
                    Neighbour {
                        index: best.1,
                        dist2: best.0,
                    },
                    best.2,
                ));
            }
        }
        if let Some(clear2) = self
            .grid
            .as_ref()
            .and_then(|g| g.nearest_k(q, max_d2, scratch))
        {
            slot.anchor = q;
            slot.clear = clear2.sqrt();
            slot.n = scratch.n as u32;
            slot.index = scratch.index;
            slot.pos = scratch.pos;
            return (scratch.n > 0 && scratch.d2[0] <= max_d2).then_some((
                Neighbour {
                    index: scratch.index[0],
                    dist2: scratch.d2[0],
                },
                scratch.pos[0],
            ));
        }
        slot.clear = 0.0;
        self.nearest(q, max_d2, hints)
            .map(|m| (m, self.target[m.index as usize]))
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

/// Nearest target point of every source point moved by `t` within `max_dist`, in parallel
/// chunks, updating the side's search state; with `priors`, only points whose prior weight
/// is positive, and each pair weighted by its priors (else every point, weight 1).
fn correspond(
    side: &mut Side<'_>,
    search: &Search<'_>,
    priors: bool,
    t: &Similarity,
    max_dist: f64,
    residual: impl Fn(DVec3, DVec3, DVec3) -> f64 + Sync,
) -> Result<Vec<Pair>, GeomError> {
    let max2 = max_dist * max_dist;
    // The f32 bound just above max_dist^2; pairs are then checked in f64 as before.
    let max_d2 = (max2 as f32).next_up();
    let source = side.points;
    let weights = if priors {
        side.weights
    } else {
        IcpWeights::default()
    };
    let mut slots: Vec<Option<&mut [Slot]>> = if side.slots.len() == source.len() {
        side.slots.chunks_mut(CHUNK).map(Some).collect()
    } else {
        (0..source.len().div_ceil(CHUNK)).map(|_| None).collect()
    };
    let parts: Vec<Vec<Pair>> = source
        .par_chunks(CHUNK)
        .zip(side.prev.par_chunks_mut(CHUNK))
        .zip(slots.par_iter_mut())
        .enumerate()
        .map(|(c, ((src, prv), slots))| {
            let mut out = Vec::with_capacity(src.len());
            let mut scratch = Knn::default();
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
                let found = match slots.as_deref_mut() {
                    Some(s) => search.nearest_cached(
                        q.as_vec3(),
                        max_d2,
                        [*pv, last],
                        &mut s[k],
                        &mut scratch,
                    ),
                    None => search
                        .nearest(q.as_vec3(), max_d2, [*pv, last])
                        .map(|m| (m, search.target[m.index as usize])),
                };
                let Some((m, tp)) = found else {
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
                    let n = search
                        .normals
                        .get(m.index as usize)
                        .copied()
                        .unwrap_or(Vec3::ZERO);
                    out.push(Pair {
                        src: i as u32,
                        q,
                        tp,
                        n,
                        residual: residual(q, tp.as_dvec3(), n.as_dvec3()),
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
