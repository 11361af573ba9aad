//! Fine registration against the LiDAR surface itself (docs/method.md Stage 1.2, final step):
//! every SfM point is compared with a small quadric surface fitted to the LiDAR points
//! around it, and the similarity (rotation, translation, scale) that minimises the robust sum
//! of squared point-to-surface distances is found by Gauss-Newton, optionally together with
//! control point pairs as extra observations.
//!
//! Why not nearest-neighbour ICP for the last millimetres: a nearest LiDAR point (or its
//! plane through it) on a thinned cloud carries the thinning and the surface curvature into
//! every residual, and the few surfaces that fix yaw and scale on a forest plot (stems,
//! stones, terrain slopes) are exactly the curved ones. A quadric h(u, v) = a u² + b uv +
//! c v² + d u + e v + f in the patch's principal frame follows a stem of 10 cm radius to a
//! millimetre over the patch, so the point-to-surface distance is unbiased to that level and
//! the estimate reaches the statistical limit set by the SfM point noise.
//!
//! Patches are fitted once per outer round at the points' current positions (the LiDAR is
//! fixed, so a patch stays valid while the points move by much less than its radius); a
//! patch is used only if it is a surface (enough neighbours, spread in two directions, a
//! small fit RMS: foliage and edges fail) and the point lies over its middle.
//!
//! The result carries the standard errors of the parameters from the Gauss-Newton normal
//! matrix and the residual variance, which the registration report uses as its confidence.

use glam::{DMat3, DQuat, DVec3, Vec3};
use serde::{Deserialize, Serialize};

use super::index::par_map_chunked;
use super::linalg::solve;
use super::{GeomError, PointIndex, Similarity, covariance, symmetric_eigen3};
use crate::progress::Progress;
use crate::rng::SplitMix64;

/// Smallest pivot of the refinement's normal equations, relative to their largest diagonal
/// entry, below which the system is degenerate.
const PIVOT: f64 = 1e-14;

/// Parameters of [`refine_on_surface`]; lengths in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SurfaceParams {
    /// Radius of the LiDAR patch fitted around each SfM point (default 0.08 m: large enough
    /// for a few dozen points at 1 cm spacing and a stable quadric, small against the
    /// radius of the thinnest stems the presets hold, 7.5 cm, at which the fit still holds).
    pub radius_m: f64,
    /// Where the LiDAR is too sparse for `radius_m`, the radius doubles up to this (default
    /// 0.32 m: terrain relief of decimetres over metres is still a quadric at that size;
    /// a stem is not, and its patch fails the RMS test instead of biasing the fit).
    pub max_radius_m: f64,
    /// A patch needs at least this many LiDAR points (default 12: six quadric coefficients
    /// with a two-fold redundancy).
    pub min_neighbours: usize,
    /// A patch whose quadric fit leaves an RMS above this is not a surface (default 0.008 m:
    /// the LiDAR range noise is 1 cm along the beam, its patch RMS on a true surface is
    /// below that; foliage and edges leave several centimetres).
    pub max_fit_rms_m: f64,
    /// The point must project within this share of the radius from the patch centroid
    /// (default 0.5: a point past a patch's rim is compared with an extrapolation).
    pub max_offset_share: f64,
    /// Point-to-surface distances beyond this are not used (default 0.05 m: five times the
    /// SfM point noise of 1 cm after a control-point or ICP alignment).
    pub max_distance_m: f64,
    /// Huber scale of the point-to-surface distances (default 0.015 m, 1.5 times the SfM
    /// point noise: the usual 95 % efficiency point of the Huber estimator is 1.345 sigma).
    pub huber_m: f64,
    /// Outer rounds: patches refitted at the points' new positions (default 3, it stops
    /// early once a round moves no point by more than `tolerance_m`; on `tiny` plots with one
    /// stem, more rounds let the weakly determined yaw wander further: docs/results/registration.md).
    pub rounds: usize,
    /// Iterations per round, each re-weighting the residuals (Huber) and solving the
    /// linear least squares on the round's tangent planes (default 3).
    pub iterations: usize,
    /// A round stops when an update moves no point by more than this (default 1e-5 m).
    pub tolerance_m: f64,
    /// Estimate scale (default true).
    pub estimate_scale: bool,
    /// Estimate rotation (default true).
    pub estimate_rotation: bool,
    /// Take a patch's points from a disc of `radius_m` about the normal through their
    /// centroid (searched in a ball of √2 · `radius_m`, the frame refitted twice) rather than
    /// from the ball of `radius_m` about the point (default false: the registration's patches
    /// as measured in docs/results/registration.md).
    ///
    /// Why: a ball about a point on a convex surface keeps, near its rim, the points that
    /// scatter outward and drops those that scatter inward, so the quadric comes out flatter
    /// and its foot inside the surface. On voxelised anchors (2 cm voxels of a 1 cm
    /// range-noise scan, `splat::bind`'s test) about stems of 10 and 15 cm radius at 0.08 m:
    /// the ball's feet −1.45 and −0.88 mm off the stem, the disc's +0.66 and −0.01 mm, with
    /// the same scatter (1.3–1.5 mm); on the anchors of `tiny` seed 31's three stems (±0.2 m
    /// about breast height), the ball's feet 0.9–1.2 mm inside the LiDAR circle, the disc's
    /// 0.55–0.72 mm, the anchors themselves 0.1–0.5 mm. Below about
    /// 7.5 cm of radius a quadric of this radius no longer follows the stem either way.
    /// Sylva's trunk binding takes its surface this way (`splat::bind`).
    pub tangent_disc: bool,
}

impl Default for SurfaceParams {
    fn default() -> Self {
        Self {
            radius_m: 0.08,
            max_radius_m: 0.32,
            min_neighbours: 12,
            max_fit_rms_m: 0.008,
            max_offset_share: 0.5,
            max_distance_m: 0.05,
            huber_m: 0.015,
            rounds: 3,
            iterations: 3,
            tolerance_m: 1e-5,
            estimate_scale: true,
            estimate_rotation: true,
            tangent_disc: false,
        }
    }
}

/// Control point pairs used as extra observations: `sfm[i]` maps to `lidar[i]`, each
/// coordinate with standard deviation `sigma_m` (metres, LiDAR frame).
#[derive(Debug, Clone, Copy)]
pub struct PairPrior<'a> {
    pub sfm: &'a [DVec3],
    pub lidar: &'a [DVec3],
    pub sigma_m: f64,
}

/// Outcome of [`refine_on_surface`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SurfaceResult {
    pub transform: Similarity,
    /// Share of the source points matched to a LiDAR surface patch in the last round.
    pub fitness: f64,
    /// Source points used in the last round.
    pub used: usize,
    /// Robust RMS of the point-to-surface distances in the last round (metres).
    pub rmse_m: f64,
    /// Gauss-Newton iterations in all rounds.
    pub iterations: usize,
    pub converged: bool,
    /// Standard errors: rotation about x, y, z (degrees), translation at the points'
    /// centroid (metres, per axis) and scale (relative).
    pub std_rotation_deg: [f64; 3],
    pub std_translation_m: [f64; 3],
    pub std_scale: f64,
}

/// The LiDAR surface near one point, linearised where the point stood when it was fitted:
/// the foot of the point on the patch's quadric (`centre`) and the quadric's unit normal
/// there (`n`). Within a round the objective is then quadratic (no point can slide along an
/// extrapolated quadric to hide its noise); the next round refits where the points moved.
#[derive(Debug, Clone, Copy, Default)]
struct Patch {
    valid: bool,
    centre: DVec3,
    n: DVec3,
}

impl Patch {
    /// Signed distance of `q` from the patch's tangent plane at the foot of the point it was
    /// fitted for, and that plane's unit normal.
    fn distance(&self, q: DVec3) -> (f64, DVec3) {
        ((q - self.centre).dot(self.n), self.n)
    }
}

/// Why a point got no surface patch (for diagnostics): 0 patch fitted, 1 too few LiDAR
/// neighbours, 2 not spread in two directions, 3 the point lies off the patch's middle, 4
/// singular or too steep a fit, 5 fit RMS too high (not a surface).
pub fn patch_status(cloud: &[Vec3], index: &PointIndex, q: DVec3, p: &SurfaceParams) -> u8 {
    fit_patch_why(cloud, index, q, p).map_or_else(|e| e, |_| 0)
}

/// The foot of `q` on the quadric fitted to the points of `cloud` around it (the patch rules
/// of [`SurfaceParams`]) and the surface's unit normal there; `None` where no patch fits.
/// Sylva's trunk binding takes the anchors' own surface from it (`splat::bind`).
pub fn surface_foot(
    cloud: &[Vec3],
    index: &PointIndex,
    q: DVec3,
    p: &SurfaceParams,
) -> Option<(DVec3, DVec3)> {
    fit_patch_why(cloud, index, q, p)
        .ok()
        .map(|patch| (patch.centre, patch.n))
}

/// Fits the patch of `cloud` within `radius` of `q`.
fn fit_patch(cloud: &[Vec3], index: &PointIndex, q: DVec3, p: &SurfaceParams) -> Patch {
    fit_patch_why(cloud, index, q, p).unwrap_or_default()
}

fn fit_patch_why(
    cloud: &[Vec3],
    index: &PointIndex,
    q: DVec3,
    p: &SurfaceParams,
) -> Result<Patch, u8> {
    let mut radius = p.radius_m;
    // The disc's points lie within √2 of its radius when they are within one radius of
    // the tangent plane: the sag of a stem of the disc's radius, and the LiDAR noise.
    let search = if p.tangent_disc {
        std::f64::consts::SQRT_2
    } else {
        1.0
    };
    let nb = loop {
        let nb = index.within(q.as_vec3(), (radius * search) as f32);
        if nb.len() >= p.min_neighbours.max(6) {
            break nb;
        }
        if radius * 2.0 > p.max_radius_m * (1.0 + 1e-9) {
            return Err(1);
        }
        radius *= 2.0;
    };
    let p = &SurfaceParams {
        radius_m: radius,
        ..*p
    };
    let mut nb: Vec<usize> = nb.iter().map(|n| n.index as usize).collect();
    if p.tangent_disc {
        let candidates = nb.clone();
        for _ in 0..2 {
            let Some((cov, centre)) = covariance(cloud, nb.iter().copied()) else {
                return Err(1);
            };
            let n = symmetric_eigen3(cov).vectors[2];
            nb = candidates
                .iter()
                .copied()
                .filter(|&i| {
                    let d = cloud[i].as_dvec3() - centre;
                    (d - n * d.dot(n)).length_squared() < radius * radius
                })
                .collect();
            if nb.len() < p.min_neighbours.max(6) {
                return Err(1);
            }
        }
    }
    let Some((cov, centre)) = covariance(cloud, nb.iter().copied()) else {
        return Err(1);
    };
    let eig = symmetric_eigen3(cov);
    let [l1, l2, _] = eig.values;
    // Spread in two directions: a scan line or a twig does not define a surface.
    let min_spread = 0.2 * p.radius_m;
    if l1 <= 0.0 || l2 < min_spread * min_spread {
        return Err(2);
    }
    let (e1, e2) = (eig.vectors[0], eig.vectors[1]);
    let n = e1.cross(e2).normalize();
    let off = q - centre;
    let (uq, vq) = (off.dot(e1), off.dot(e2));
    if uq.hypot(vq) > p.max_offset_share * p.radius_m {
        return Err(3);
    }
    // Least squares of w = a u² + b uv + c v² + d u + e v + f, coordinates in units of the
    // radius so the normal matrix is well conditioned.
    let s = 1.0 / p.radius_m;
    let mut ata = [[0.0f64; 7]; 7];
    let mut atb = [0.0f64; 7];
    let rows: Vec<([f64; 6], f64)> = nb
        .iter()
        .map(|&m| {
            let d = cloud[m].as_dvec3() - centre;
            let (u, v, w) = (d.dot(e1) * s, d.dot(e2) * s, d.dot(n) * s);
            ([u * u, u * v, v * v, u, v, 1.0], w)
        })
        .collect();
    for (r, w) in &rows {
        for a in 0..6 {
            atb[a] += r[a] * w;
            for b in 0..6 {
                ata[a][b] += r[a] * r[b];
            }
        }
    }
    let Some(x) = solve(ata, atb, 6, PIVOT) else {
        return Err(4);
    };
    let sse: f64 = rows
        .iter()
        .map(|(r, w)| {
            let h: f64 = r.iter().zip(&x).map(|(a, b)| a * b).sum();
            (w - h).powi(2)
        })
        .sum();
    let rms = (sse / rows.len() as f64).sqrt() / s;
    if !rms.is_finite() || rms > p.max_fit_rms_m {
        return Err(5);
    }
    // Back to metres: u = s u_m etc., w_m = w / s.
    let [a, b, c, du, dv, f] = [x[0] * s, x[1] * s, x[2] * s, x[3], x[4], x[5] / s];
    let h = a * uq * uq + b * uq * vq + c * vq * vq + du * uq + dv * vq + f;
    let hu = 2.0 * a * uq + b * vq + du;
    let hv = b * uq + 2.0 * c * vq + dv;
    // A steep quadric in the patch's own principal frame is a poor fit (two surfaces, a
    // rim): a slope above 1 (45 degrees) is refused.
    if hu.hypot(hv) > 1.0 {
        return Err(4);
    }
    let g = n - e1 * hu - e2 * hv;
    Ok(Patch {
        valid: true,
        centre: centre + e1 * uq + e2 * vq + n * h,
        n: g.normalize(),
    })
}

/// Refines `initial` (source → target) so the moved `source` points lie on the surface of
/// `cloud` (indexed by `index`), optionally with control point pairs as extra observations.
/// `source_weights` (one in [0, 1] per source point) scale each point's influence.
#[allow(clippy::too_many_arguments)]
pub fn refine_on_surface(
    source: &[DVec3],
    source_weights: Option<&[f64]>,
    cloud: &[Vec3],
    index: &PointIndex,
    initial: &Similarity,
    pairs: Option<PairPrior<'_>>,
    params: &SurfaceParams,
    progress: &dyn Progress,
) -> Result<SurfaceResult, GeomError> {
    validate(source, source_weights, cloud, index, pairs, params)?;
    let mut t = *initial;
    let mut iterations = 0;
    let mut converged = false;
    let mut last = None;
    for round in 0..params.rounds {
        let moved: Vec<DVec3> = source.iter().map(|p| t.apply(*p)).collect();
        let patches: Vec<Patch> = par_map_chunked(
            source.len(),
            &crate::progress::NoProgress,
            |i, _| match source_weights {
                Some(w) if w[i] <= 0.0 => Patch::default(),
                _ => fit_patch(cloud, index, moved[i], params),
            },
        )?;
        if progress.is_cancelled() {
            return Err(GeomError::Cancelled);
        }
        let mut round_converged = false;
        for k in 0..params.iterations {
            let step = gauss_newton(source, source_weights, &patches, &t, pairs, params)?;
            t = step.updated;
            iterations += 1;
            progress.log(&format!(
                "surface refinement round {}, iteration {iterations}: {} points on surfaces, robust RMS {:.4} m, largest update {:.2e} m",
                round + 1,
                step.used,
                step.rmse,
                step.max_motion
            ));
            let moved_most = step.max_motion;
            last = Some(step);
            if moved_most <= params.tolerance_m {
                round_converged = k == 0;
                break;
            }
        }
        progress.set((round + 1) as f64 / params.rounds as f64);
        if round_converged {
            converged = true;
            break;
        }
    }
    let Some(step) = last else {
        return Err(GeomError::InvalidParameter(
            "surface refinement needs rounds >= 1 and iterations >= 1".into(),
        ));
    };
    Ok(SurfaceResult {
        transform: t,
        fitness: step.used as f64 / source.len() as f64,
        used: step.used,
        rmse_m: step.rmse,
        iterations,
        converged,
        std_rotation_deg: [
            step.std[0].to_degrees(),
            step.std[1].to_degrees(),
            step.std[2].to_degrees(),
        ],
        std_translation_m: [step.std[3], step.std[4], step.std[5]],
        std_scale: step.std[6],
    })
}

/// Standard errors of a refinement measured by resampling its source points rather than read
/// from its normal matrix (see [`split_half_spread`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SplitHalfSpread {
    /// Random halvings of the source points that were refined.
    pub splits: usize,
    /// Rotation about x, y, z (degrees), translation at the source points' centroid (metres,
    /// per axis) and scale (relative), as in [`SurfaceResult`].
    pub std_rotation_deg: [f64; 3],
    pub std_translation_m: [f64; 3],
    pub std_scale: f64,
}

/// The spread of [`refine_on_surface`] measured on the data: the source points are split
/// into two random halves `splits` times, each half is refined from `fit`, and the halves'
/// disagreement gives the standard errors of the whole set. Two independent halves each
/// have twice the variance of the whole, so their difference has four times it:
/// σ² = mean(d²) / 4 per parameter.
///
/// Why: the normal-matrix errors of [`SurfaceResult`] hold for one linearisation on fixed
/// patches, but the refinement refits its patches where the points move (from any start it
/// could really have) and the patch normals carry the LiDAR's range noise, which the normal
/// matrix counts as information. On `tiny` plots where the ground relief holds the yaw, 20
/// Monte Carlo draws of the SfM noise spread the yaw 1.3-1.9 times wider than the normal
/// matrix says, from the truth or from 0.2° off alike (docs/results/registration.md).
///
/// The halves are drawn from a SplitMix64 stream seeded with the split number, so the
/// result is repeatable. Control pairs are left out: both halves would share them.
pub fn split_half_spread(
    source: &[DVec3],
    cloud: &[Vec3],
    index: &PointIndex,
    fit: &Similarity,
    params: &SurfaceParams,
    splits: usize,
    progress: &dyn Progress,
) -> Result<SplitHalfSpread, GeomError> {
    if splits == 0 {
        return Err(GeomError::InvalidParameter(
            "split-half spread needs at least one split".into(),
        ));
    }
    let centroid = source.iter().copied().sum::<DVec3>() / source.len().max(1) as f64;
    let mut sum = [0.0f64; 7];
    for k in 0..splits {
        if progress.is_cancelled() {
            return Err(GeomError::Cancelled);
        }
        let mut rng = SplitMix64::new(k as u64);
        let half: Vec<bool> = source.iter().map(|_| rng.next_u64() & 1 == 1).collect();
        let refine = |side: bool| {
            let w: Vec<f64> = half
                .iter()
                .map(|&h| f64::from(u8::from(h == side)))
                .collect();
            refine_on_surface(
                source,
                Some(&w),
                cloud,
                index,
                fit,
                None,
                params,
                &crate::progress::NoProgress,
            )
        };
        let (a, b) = (refine(false)?.transform, refine(true)?.transform);
        let omega = DQuat::from_mat3(&(b.rotation * a.rotation.transpose())).to_scaled_axis();
        let shift = b.apply(centroid) - a.apply(centroid);
        let d = [
            omega.x.to_degrees(),
            omega.y.to_degrees(),
            omega.z.to_degrees(),
            shift.x,
            shift.y,
            shift.z,
            (b.scale / a.scale).ln(),
        ];
        for (s, v) in sum.iter_mut().zip(d) {
            *s += v * v;
        }
        progress.set((k + 1) as f64 / splits as f64);
    }
    let std = sum.map(|s| (s / (4.0 * splits as f64)).sqrt());
    Ok(SplitHalfSpread {
        splits,
        std_rotation_deg: [std[0], std[1], std[2]],
        std_translation_m: [std[3], std[4], std[5]],
        std_scale: std[6],
    })
}

struct Step {
    updated: Similarity,
    used: usize,
    rmse: f64,
    max_motion: f64,
    /// Standard errors of omega (rad), tau (m), log-scale.
    std: [f64; 7],
}

// Index loops mirror the matrix algebra.
#[allow(clippy::needless_range_loop)]
fn gauss_newton(
    source: &[DVec3],
    source_weights: Option<&[f64]>,
    patches: &[Patch],
    t: &Similarity,
    pairs: Option<PairPrior<'_>>,
    p: &SurfaceParams,
) -> Result<Step, GeomError> {
    let dim = if p.estimate_scale { 7 } else { 6 };
    // Observations: (moved point, unit direction, residual along it, prior weight).
    let mut obs: Vec<(DVec3, DVec3, f64, f64)> = Vec::with_capacity(source.len());
    for (i, patch) in patches.iter().enumerate() {
        if !patch.valid {
            continue;
        }
        let q = t.apply(source[i]);
        let (r, g) = patch.distance(q);
        if !r.is_finite() || r.abs() > p.max_distance_m {
            continue;
        }
        let w = source_weights.map_or(1.0, |w| w[i]);
        let huber = if r.abs() <= p.huber_m {
            1.0
        } else {
            p.huber_m / r.abs()
        };
        obs.push((q, g, r, w * huber));
    }
    let used = obs.len();
    if used < dim {
        return Err(GeomError::Empty(
            "SfM points on a LiDAR surface; the alignment is too far off or the clouds do not overlap",
        ));
    }
    let sw: f64 = obs.iter().map(|o| o.3).sum();
    let rmse = (obs.iter().map(|o| o.3 * o.2 * o.2).sum::<f64>() / sw.max(1e-300)).sqrt();
    if let Some(pp) = pairs {
        // Each control pair gives three observations, weighted against the surface ones by
        // the ratio of variances (the surface residual variance is estimated by `rmse`).
        let w = (rmse.max(1e-4) / pp.sigma_m.max(1e-6)).powi(2);
        for (a, b) in pp.sfm.iter().zip(pp.lidar) {
            let q = t.apply(*a);
            for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
                obs.push((q, axis, (q - *b).dot(axis), w));
            }
        }
    }
    let sw: f64 = obs.iter().map(|o| o.3).sum();
    let c = obs.iter().map(|o| o.0 * o.3).sum::<DVec3>() / sw;
    let mut ata = [[0.0f64; 7]; 7];
    let mut atb = [0.0f64; 7];
    for &(q, g, r, w) in &obs {
        let x = q - c;
        let xg = x.cross(g);
        // Scale column: the noise lies in the source points, and a similarity scales it with
        // them, so plain least squares on target-frame distances prefers to shrink the source
        // (every residual holds its point's noise, and shrinking scales that noise down by s).
        // The estimate then falls short by about sigma² / var((x - c) · g): -0.2 to -1 % on a
        // `tiny` plot whose points lie mostly on flat ground (docs/results/registration.md). Measuring
        // the residual in source units, r / s, removes the bias; at the current estimate its
        // derivative in ln s is the foot's lever arm (x - r g - c) · g = x · g - r instead of
        // x · g (rotation and translation columns change only by the common factor 1 / s).
        let row = [xg.x, xg.y, xg.z, g.x, g.y, g.z, x.dot(g) - r];
        for a in 0..dim {
            atb[a] -= w * row[a] * r;
            for b in 0..dim {
                ata[a][b] += w * row[a] * row[b];
            }
        }
    }
    if !p.estimate_rotation {
        let pin = ata[3][3].max(ata[4][4]).max(ata[5][5]).max(1.0);
        for a in 0..3 {
            for b in 0..dim {
                ata[a][b] = 0.0;
                ata[b][a] = 0.0;
            }
            ata[a][a] = pin;
            atb[a] = 0.0;
        }
    }
    let delta = solve(ata, atb, dim, PIVOT).ok_or(GeomError::Degenerate(
        "surface refinement is singular: the matched surfaces do not constrain all axes",
    ))?;
    // Standard errors: sigma² (AᵀWA)⁻¹ with the robust residual variance.
    let dof = (used as f64 - dim as f64).max(1.0);
    let sigma2 = rmse * rmse * used as f64 / dof;
    let mut std = [0.0; 7];
    for k in 0..dim {
        let mut e = [0.0; 7];
        e[k] = 1.0;
        if let Some(col) = solve(ata, e, dim, PIVOT) {
            std[k] = (sigma2 * col[k].max(0.0)).sqrt();
        }
    }
    if !p.estimate_rotation {
        std[0..3].fill(0.0);
    }
    let omega = DVec3::new(delta[0], delta[1], delta[2]);
    let tau = DVec3::new(delta[3], delta[4], delta[5]);
    let s_inc = if p.estimate_scale {
        delta[6].exp()
    } else {
        1.0
    };
    let r_inc = DMat3::from_quat(DQuat::from_scaled_axis(omega));
    let inc = Similarity {
        scale: s_inc,
        rotation: r_inc,
        translation: c + tau - r_inc * c * s_inc,
    };
    let max_motion = obs
        .iter()
        .map(|o| (inc.apply(o.0) - o.0).length())
        .fold(0.0, f64::max);
    Ok(Step {
        updated: t.then(&inc),
        used,
        rmse,
        max_motion,
        std,
    })
}

fn validate(
    source: &[DVec3],
    source_weights: Option<&[f64]>,
    cloud: &[Vec3],
    index: &PointIndex,
    pairs: Option<PairPrior<'_>>,
    p: &SurfaceParams,
) -> Result<(), GeomError> {
    if source.is_empty() || cloud.is_empty() {
        return Err(GeomError::Empty(
            "surface refinement needs source points and a LiDAR cloud",
        ));
    }
    GeomError::check_len("index vs cloud", index.len(), cloud.len())?;
    if let Some(w) = source_weights {
        GeomError::check_len("source weights vs source", w.len(), source.len())?;
        if !w.iter().all(|v| (0.0..=1.0).contains(v)) {
            return Err(GeomError::InvalidParameter(
                "source weights must lie in [0, 1]".into(),
            ));
        }
    }
    if let Some(pp) = pairs
        && (pp.sfm.len() != pp.lidar.len() || !(pp.sigma_m > 0.0 && pp.sigma_m.is_finite()))
    {
        return Err(GeomError::InvalidParameter(
            "control pairs need as many SfM as LiDAR points and a positive sigma".into(),
        ));
    }
    if !source.iter().all(|v| v.is_finite()) {
        return Err(GeomError::NonFinite("source points"));
    }
    let ok = p.radius_m > 0.0
        && p.radius_m.is_finite()
        && p.max_radius_m.is_finite()
        && p.max_fit_rms_m > 0.0
        && p.max_offset_share > 0.0
        && p.max_distance_m > 0.0
        && p.huber_m > 0.0
        && p.rounds >= 1
        && p.iterations >= 1
        && p.tolerance_m >= 0.0;
    if !ok {
        return Err(GeomError::InvalidParameter(format!(
            "surface refinement parameters out of range: {p:?}"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;
    use crate::synth::rng::Stream;

    /// Height of the test terrain at (x, y), metres.
    fn ground(x: f64, y: f64) -> f64 {
        0.15 * (0.8 * x).sin() + 0.1 * (0.6 * y).cos()
    }

    /// Stem centres of the test scene (x, y) and their radius, metres.
    const STEMS: [(f64, f64); 4] = [(-1.5, -1.0), (1.8, -0.5), (0.5, 2.0), (-1.0, 1.6)];
    const STEM_RADIUS: f64 = 0.15;

    /// Rolling terrain with four vertical stems (radius 0.15 m): the LiDAR samples it on a
    /// 2 cm grid with 3 mm noise, the "SfM" points are random surface points with 1 cm
    /// noise in a frame scaled by 2.5, turned and shifted.
    fn scene() -> (Vec<Vec3>, Vec<DVec3>, Similarity) {
        let stems = STEMS;
        let radius = STEM_RADIUS;
        let mut rng = Stream::new(7, 0, 0);
        let mut lidar = Vec::new();
        let n = 300;
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (
                    -3.0 + 6.0 * i as f64 / n as f64,
                    -3.0 + 6.0 * j as f64 / n as f64,
                );
                let inside = stems.iter().any(|(sx, sy)| (x - sx).hypot(y - sy) < radius);
                if !inside {
                    let z = ground(x, y) + 0.003 * rng.normal();
                    lidar.push(Vec3::new(x as f32, y as f32, z as f32));
                }
            }
        }
        for (sx, sy) in stems {
            for a in 0..63 {
                let t = a as f64 / 63.0 * std::f64::consts::TAU;
                for h in 0..130 {
                    let z = -0.3 + h as f64 * 0.015;
                    let r = radius + 0.003 * rng.normal();
                    let p = DVec3::new(sx + r * t.cos(), sy + r * t.sin(), z);
                    lidar.push(p.as_vec3());
                }
            }
        }
        let mut world = Vec::new();
        for k in 0..3000 {
            let p = if k % 5 == 0 {
                let (sx, sy) = stems[k / 5 % 4];
                let t = rng.range(0.0, std::f64::consts::TAU);
                let z = rng.range(0.2, 1.5);
                DVec3::new(sx + radius * t.cos(), sy + radius * t.sin(), z)
            } else {
                let (x, y) = (rng.range(-2.8, 2.8), rng.range(-2.8, 2.8));
                if stems
                    .iter()
                    .any(|(sx, sy)| (x - sx).hypot(y - sy) < radius + 0.05)
                {
                    continue;
                }
                DVec3::new(x, y, ground(x, y))
            };
            let noise = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.01;
            world.push(p + noise);
        }
        let truth = test_truth();
        let to_sfm = truth.inverse();
        let sfm = world.iter().map(|p| to_sfm.apply(*p)).collect();
        (lidar, sfm, truth)
    }

    /// The SfM → LiDAR similarity of the test scenes.
    fn test_truth() -> Similarity {
        Similarity {
            scale: 2.5,
            rotation: DMat3::from_quat(DQuat::from_euler(glam::EulerRot::ZYX, 1.0, 0.3, -0.2)),
            translation: DVec3::new(4.0, -2.0, 1.0),
        }
    }

    /// The split-half standard errors must agree with the spread of the refinement over
    /// independent draws of the SfM noise (the quantity they stand for) and be repeatable.
    /// Ground points only, on the rolling terrain, so the yaw rests on the relief as on a
    /// one-stem `tiny` plot.
    #[test]
    fn split_half_spread_matches_the_spread_over_noise_draws() {
        let (lidar, _, _) = scene();
        let index = PointIndex::new(&lidar).expect("index");
        let truth = test_truth();
        let mut rng = Stream::new(21, 0, 0);
        let world: Vec<DVec3> = (0..4000)
            .map(|_| {
                let (x, y) = (rng.range(-2.8, 2.8), rng.range(-2.8, 2.8));
                DVec3::new(x, y, ground(x, y))
            })
            .filter(|p| {
                STEMS
                    .iter()
                    .all(|(sx, sy)| (p.x - sx).hypot(p.y - sy) > STEM_RADIUS + 0.05)
            })
            .collect();
        let draw = |d: u64| -> Vec<DVec3> {
            let mut rng = Stream::new(100 + d, 0, 0);
            let to_sfm = truth.inverse();
            world
                .iter()
                .map(|p| {
                    let noise = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.01;
                    to_sfm.apply(*p + noise)
                })
                .collect()
        };
        let params = SurfaceParams::default();
        let refine = |sfm: &[DVec3]| {
            refine_on_surface(
                sfm,
                None,
                &lidar,
                &index,
                &truth,
                None,
                &params,
                &NoProgress,
            )
            .expect("refine")
        };
        // Yaw about the LiDAR vertical, degrees, of each draw's estimate against the truth.
        let draws = 16;
        let yaw: Vec<f64> = (0..draws)
            .map(|d| {
                let t = refine(&draw(d)).transform;
                let rel = t.rotation * truth.rotation.transpose();
                DQuat::from_mat3(&rel).to_scaled_axis().z.to_degrees()
            })
            .collect();
        let mean = yaw.iter().sum::<f64>() / draws as f64;
        let spread =
            (yaw.iter().map(|y| (y - mean).powi(2)).sum::<f64>() / (draws - 1) as f64).sqrt();
        let sfm = draw(0);
        let fit = refine(&sfm);
        let measure = || {
            split_half_spread(
                &sfm,
                &lidar,
                &index,
                &fit.transform,
                &params,
                8,
                &NoProgress,
            )
            .expect("split half")
        };
        let (split, again) = (measure(), measure());
        println!(
            "yaw spread over {draws} draws {spread:.4}°, split half {:.4}°, normal matrix {:.4}°",
            split.std_rotation_deg[2], fit.std_rotation_deg[2]
        );
        assert_eq!(split, again, "the halves are drawn repeatably");
        // Sixteen draws and eight splits each know a standard error to about ±20-25 %.
        let ratio = split.std_rotation_deg[2] / spread;
        assert!((0.6..1.6).contains(&ratio), "split half / spread = {ratio}");
        assert!(split.std_scale > 0.0 && split.std_translation_m.iter().all(|s| *s > 0.0));
    }

    #[test]
    fn recovers_a_known_similarity_from_a_perturbed_start() {
        let (lidar, sfm, truth) = scene();
        let index = PointIndex::new(&lidar).expect("index");
        let off = Similarity {
            scale: 1.003,
            rotation: DMat3::from_rotation_z(0.3f64.to_radians()),
            translation: DVec3::new(0.02, -0.015, 0.01),
        };
        let start = truth.then(&off);
        let r = refine_on_surface(
            &sfm,
            None,
            &lidar,
            &index,
            &start,
            None,
            &SurfaceParams::default(),
            &NoProgress,
        )
        .expect("refine");
        let err = truth.inverse().then(&r.transform);
        let rot = err.rotation_angle_deg();
        let scale = (r.transform.scale / truth.scale - 1.0).abs();
        let shift = err.apply(DVec3::ZERO).length();
        println!(
            "rotation {rot:.4}° (std {:.4?}), scale {:.4}% (std {:.4}%), shift {:.2} mm, fitness {:.2}",
            r.std_rotation_deg,
            scale * 100.0,
            r.std_scale * 100.0,
            shift * 1000.0,
            r.fitness
        );
        // Measured: rotation 0.011° (standard error 0.02°), translation 0.4 mm, scale 0.046 %
        // from a start 0.3 % off, 1.5 times its standard error of 0.03 % (0.075 % before the
        // scale column was freed of the points' noise: test below).
        assert!(rot < 0.02, "rotation error {rot}°");
        assert!(scale < 1e-3, "scale error {scale}");
        assert!(shift < 0.005, "translation error {shift} m");
        assert!(r.std_rotation_deg.iter().all(|s| *s > 0.0 && *s < 0.02));
        assert!(r.fitness > 0.8, "fitness {}", r.fitness);
    }

    /// Noisy points on gently rolling ground, refined from the true pose: least squares on
    /// target-frame distances shrinks the source (sigma² / var((x - c) · n) per step, and the
    /// rounds compound it): -4.2 % against a standard error of 0.2 % before the scale column
    /// used the foot's lever arm, -0.016 % after. The estimate must stay within three of its
    /// own standard errors of the truth.
    #[test]
    fn scale_is_not_biased_by_the_source_points_noise() {
        let mut rng = Stream::new(11, 0, 0);
        let n = 300;
        let mut lidar = Vec::with_capacity(n * n);
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (
                    -3.0 + 6.0 * i as f64 / n as f64,
                    -3.0 + 6.0 * j as f64 / n as f64,
                );
                let z = ground(x, y) + 0.003 * rng.normal();
                lidar.push(Vec3::new(x as f32, y as f32, z as f32));
            }
        }
        let sfm: Vec<DVec3> = (0..8000)
            .map(|_| {
                let (x, y) = (rng.range(-2.8, 2.8), rng.range(-2.8, 2.8));
                let noise = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.01;
                DVec3::new(x, y, ground(x, y)) + noise
            })
            .collect();
        let index = PointIndex::new(&lidar).expect("index");
        let r = refine_on_surface(
            &sfm,
            None,
            &lidar,
            &index,
            &Similarity::IDENTITY,
            None,
            &SurfaceParams::default(),
            &NoProgress,
        )
        .expect("refine");
        let err = r.transform.scale - 1.0;
        println!(
            "scale error {:.4} % (std {:.4} %)",
            err * 100.0,
            r.std_scale * 100.0
        );
        assert!(
            err.abs() < 3.0 * r.std_scale && err.abs() < 6e-3,
            "scale error {err} (std {})",
            r.std_scale
        );
    }

    #[test]
    fn a_cloud_elsewhere_gives_no_surface() {
        let (lidar, sfm, truth) = scene();
        let index = PointIndex::new(&lidar).expect("index");
        let away = truth.then(&Similarity {
            translation: DVec3::new(50.0, 0.0, 0.0),
            ..Similarity::IDENTITY
        });
        let r = refine_on_surface(
            &sfm,
            None,
            &lidar,
            &index,
            &away,
            None,
            &SurfaceParams::default(),
            &NoProgress,
        );
        assert!(matches!(r, Err(GeomError::Empty(_))), "{r:?}");
    }
}
