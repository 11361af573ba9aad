//! Diameter at breast height of one stem (docs/method.md Stage 5, LiDAR-only baseline): the stem's
//! points in a slice 1.3 m ± 0.1 m above ground, cut perpendicular to the stem's own axis,
//! a robust circle fit, and neighbouring slices when that one is poor.
//!
//! Fallback (as 3DFin does): when the 1.3 m slice gives no acceptable fit, the slices at
//! `fallback_heights_m` are tried in order (closest to 1.3 m first) and the diameter of the
//! first acceptable one is reported as it is, flagged `fallback_slice`. It is not corrected
//! to 1.3 m: a taper of ~1 cm per metre changes a diameter by 2–4 mm over 0.2–0.4 m, less
//! than the fit's own error, and a taper estimated from two noisy slices would add more.
//!
//! The same measurement serves any point set ([`measure_dbh_of`]): the LiDAR points of a stem
//! (weights 1) and the centres of its trunk Gaussians (weights = opacity, docs/method.md Stage 5.3),
//! so the two diameters differ only by what they are fitted to. The Gaussian fit adds a reach
//! limit around the axis and a centre prior from the LiDAR circle ([`SliceCenterPrior`]), and
//! with a prior an acceptable partial arc at breast height is kept rather than traded for a
//! full circle at another height: the prior holds the arc's centre, and on `stand` the taper
//! between slices reached 1.2 cm of diameter over 0.4 m (stage `dbh` also starts at the
//! LiDAR fit's own slice).

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::ransac::{CenterPrior, CircleParams, RobustCircle, fit_circle_robust_weighted};
use super::stems::Stem;

/// A cluster whose best slice covers less of a circle than this (a quarter) is no stem.
pub const MIN_STEM_ARC: f64 = 0.25;

/// Parameters of [`measure_dbh`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct DbhParams {
    /// Breast height along the stem above the ground, metres (docs/method.md Stage 5: 1.3 m).
    pub breast_height_m: f32,
    /// Half the slice thickness, metres (docs/method.md Stage 5: ± 0.1 m).
    pub half_thickness_m: f32,
    /// Slice heights tried, in order, when the breast-height slice is poor, metres.
    pub fallback_heights_m: Vec<f32>,
    /// A fit needs at least this many inliers to be acceptable.
    pub min_points: usize,
    /// A fit is acceptable when its RMS residual is at most this share of its radius...
    pub max_rms_relative: f64,
    /// ...or at most this many metres (whichever is larger).
    pub max_rms_m: f64,
    /// A fit needs at least this inlier share, [0, 1].
    pub min_inlier_share: f64,
    /// Circle fitting (RANSAC threshold, iterations, refinement, partial-arc limit).
    pub circle: CircleParams,
}

impl Default for DbhParams {
    fn default() -> Self {
        Self {
            breast_height_m: 1.3,
            half_thickness_m: 0.1,
            fallback_heights_m: vec![1.1, 1.5, 0.9, 1.7, 0.7, 1.9],
            min_points: 10,
            max_rms_relative: 0.1,
            max_rms_m: 0.01,
            min_inlier_share: 0.3,
            circle: CircleParams::default(),
        }
    }
}

/// How much a diameter can be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FitQuality {
    /// The breast-height slice gave an acceptable fit over enough of the circumference.
    Good,
    /// The breast-height fit is acceptable except that it covers too little of the circle.
    PartialArc,
    /// The breast-height slice was poor; a neighbouring slice gave the diameter.
    FallbackSlice,
    /// No slice gave an acceptable fit; the least bad one is reported.
    Poor,
}

impl FitQuality {
    /// The short name written to trees.csv: good, partial_arc, fallback_slice or poor.
    pub fn as_str(self) -> &'static str {
        match self {
            FitQuality::Good => "good",
            FitQuality::PartialArc => "partial_arc",
            FitQuality::FallbackSlice => "fallback_slice",
            FitQuality::Poor => "poor",
        }
    }
}

/// The diameter of one stem with the fit it came from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StemDbh {
    /// Diameter, metres.
    pub diameter_m: f64,
    /// Height of the slice used, along the axis above the base, metres.
    pub slice_height_m: f32,
    /// Circle centre in local 3D coordinates (on the axis frame at the slice height).
    pub center: Vec3,
    /// The circle in the slice plane with its quality figures.
    pub circle: RobustCircle,
    pub quality: FitQuality,
}

/// A stem's axis with its LiDAR fit, in local coordinates (metres): what the band of its DBH
/// slices ([`in_dbh_band`]) needs.
#[derive(Debug, Clone, Copy)]
pub struct StemAxis {
    /// Where the axis meets the ground.
    pub base: Vec3,
    /// Axis direction, pointing up (normalised here where it is not unit).
    pub axis: Vec3,
    /// The LiDAR fit.
    pub lidar: StemDbh,
}

/// How far around the LiDAR axis the Gaussians of a stem are looked for: 2 × the LiDAR
/// radius + 0.10 m, metres (room for a Gaussian circle twice as wide, and for the axis being
/// off by a few centimetres).
pub fn reach_m(lidar: &StemDbh) -> f32 {
    lidar.diameter_m as f32 + 0.10
}

/// The slice heights `p` may use on a stem whose LiDAR fit is `lidar`, lowest and highest,
/// metres along the axis (with the slice half thickness): 1.3 m, the fallback slices and the
/// LiDAR fit's own slice.
pub fn slice_height_range(lidar: &StemDbh, p: &DbhParams) -> (f32, f32) {
    let hs = p
        .fallback_heights_m
        .iter()
        .chain([&p.breast_height_m, &lidar.slice_height_m]);
    let lo = hs.clone().fold(f32::INFINITY, |a, &h| a.min(h));
    let hi = hs.fold(f32::NEG_INFINITY, |a, &h| a.max(h));
    (lo - p.half_thickness_m, hi + p.half_thickness_m)
}

/// Per point of `means`, whether it lies in the band of some stem's DBH slices: within
/// [`reach_m`] of the axis and within the heights any slice of `p` may use
/// ([`slice_height_range`], and 0.1 m more for a Gaussian's extent). The initial draw of a
/// capped splat model keeps this band dense (`crate::splat::budget`).
///
/// The stems are binned by the horizontal boxes of their bands in a grid of 1 m cells, so a
/// point tests only the stems of its own cell: linear in points and stems together, for
/// millions of anchors and thousands of stems.
pub fn in_dbh_band(means: &[[f32; 3]], stems: &[StemAxis], p: &DbhParams) -> Vec<bool> {
    const CELL_M: f32 = 1.0;
    let bands: Vec<(Vec3, Vec3, f32, f32, f32)> = stems
        .iter()
        .map(|s| {
            let (lo, hi) = slice_height_range(&s.lidar, p);
            let axis = s.axis.try_normalize().unwrap_or(Vec3::Z);
            (s.base, axis, reach_m(&s.lidar), lo - 0.1, hi + 0.1)
        })
        .filter(|(base, ..)| base.is_finite())
        .collect();
    let cell = |x: f32| (x / CELL_M).floor() as i64;
    let mut grid: std::collections::HashMap<(i64, i64), Vec<usize>> =
        std::collections::HashMap::new();
    for (k, &(base, axis, reach, lo, hi)) in bands.iter().enumerate() {
        let (a, b) = (base + axis * lo, base + axis * hi);
        let (min, max) = (a.min(b) - Vec3::splat(reach), a.max(b) + Vec3::splat(reach));
        for x in cell(min.x)..=cell(max.x) {
            for y in cell(min.y)..=cell(max.y) {
                grid.entry((x, y)).or_default().push(k);
            }
        }
    }
    means
        .iter()
        .map(|m| {
            let m = Vec3::from_array(*m);
            grid.get(&(cell(m.x), cell(m.y))).is_some_and(|ks| {
                ks.iter().any(|&k| {
                    let (base, axis, reach, lo, hi) = bands[k];
                    let d = m - base;
                    let s = d.dot(axis);
                    s >= lo && s <= hi && (d - axis * s).length() <= reach
                })
            })
        })
        .collect()
}

/// Orthonormal basis (e1, e2) of the plane perpendicular to `axis`.
fn plane_basis(axis: Vec3) -> (Vec3, Vec3) {
    let e1 = axis.any_orthonormal_vector();
    (e1, axis.cross(e1))
}

/// `axis` as a unit vector: kept as it is when it already has unit length (so a stem's own
/// axis is used bit for bit), normalised otherwise; `None` when zero or not finite.
fn unit_axis(axis: Vec3) -> Option<Vec3> {
    if !axis.is_finite() {
        return None;
    }
    if (axis.length_squared() - 1.0).abs() <= 1e-6 {
        Some(axis)
    } else {
        axis.try_normalize()
    }
}

/// The centre prior of a slice fit: the circle of a stem measured before (in the slices'
/// frame, the LiDAR circle for the Gaussian fit) and how far a fitted centre may lie from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SliceCenterPrior {
    /// The expected centre, local 3D coordinates, metres (as [`StemDbh::center`] stores it);
    /// only its position in the plane perpendicular to the axis counts, so it holds for every
    /// slice height.
    pub center: Vec3,
    /// Largest distance of a fitted centre from `center` in the slice plane, metres.
    pub max_offset_m: f32,
    /// Weight of `center` in the geometric refinement, in points of weight 1
    /// ([`CenterPrior::weight`]); 0: the prior only gates.
    pub weight: f64,
}

/// How far the trunk surfels of Sylva's binding scatter about the LiDAR stem circle, metres:
/// 4 mm (measured: 2.4–4.1 mm mean absolute on `stand` and `tiny`, docs/results/twin.md), the
/// σ_point of the centre prior's weight.
pub const SURFEL_SCATTER_M: f64 = 0.004;

impl SliceCenterPrior {
    /// The prior the Gaussian fit gets from the LiDAR fit `lidar`: its centre, and
    /// max(0.5 × its radius, 2 cm). Half a radius lets a Gaussian circle of a different size
    /// (the fits differ by a few millimetres) keep its own centre, while a circle through the
    /// arc of a neighbouring stem or a branch — whose centre lies at least a radius away —
    /// is refused; 2 cm keeps room for thin stems, where half a radius is below the fits'
    /// own centre noise (~1 cm, the scanner's range noise).
    ///
    /// Its weight makes the LiDAR centre a pseudo-observation of the centre's own standard
    /// error, rms × √(2 / n) of the LiDAR fit (at least 1 mm), against [`SURFEL_SCATTER_M`]
    /// per surfel: a partial arc of surfels, whose centre its points hardly fix, is held
    /// there, while a full circle of many surfels keeps its own.
    pub fn from_lidar(lidar: &StemDbh) -> Self {
        let fit = &lidar.circle.fit;
        let se = (fit.rms * (2.0 / fit.n.max(1) as f64).sqrt()).max(0.001);
        Self {
            center: lidar.center,
            max_offset_m: (0.25 * lidar.diameter_m as f32).max(0.02),
            weight: (SURFEL_SCATTER_M / se).powi(2),
        }
    }
}

/// What [`measure_dbh_of`] measures: a point set, which of its points may belong to the stem,
/// their weights, and the stem's frame.
#[derive(Debug, Clone, Copy)]
pub struct SliceSource<'a> {
    /// The points, local coordinates, metres.
    pub points: &'a [Vec3],
    /// Indices into `points` of the candidates (the LiDAR: [`Stem::points`]); `None`: all.
    pub candidates: Option<&'a [u32]>,
    /// One weight per point of `points` (the Gaussians: their opacity); `None`: all 1.
    /// A point with a weight that is zero, negative or not finite is left out.
    pub weights: Option<&'a [f64]>,
    /// Where the stem's axis meets the ground, local coordinates, metres.
    pub base: Vec3,
    /// The stem's axis direction, pointing up (normalised here if it is not a unit vector).
    pub axis: Vec3,
    /// Only points within this distance of the axis line are candidates, metres; `None`: no
    /// limit (the LiDAR stem's points are already the ones within reach).
    pub reach_m: Option<f32>,
    /// A centre prior for every slice fit (the Gaussian fit: [`SliceCenterPrior::from_lidar`]).
    pub center_prior: Option<SliceCenterPrior>,
    /// One standard deviation along the axis per point of `points`, metres (the Gaussians:
    /// each one's extent along the stem); `None`: points, of no extent (the LiDAR). With them
    /// a point takes part in a slice by the share of its mass inside the slab
    /// ([`slab_mass`]), which multiplies its weight: a surfel that straddles the slab is in
    /// it as much as its mass is, as a LiDAR point is when its centre is.
    pub extents: Option<&'a [f32]>,
}

/// A point enters a slice when at least this share of its mass lies inside the slab (5 %:
/// beyond it a Gaussian barely touches the slab; Sylva's choice).
pub const MIN_SLAB_MASS: f64 = 0.05;

/// The share of a 1-D normal distribution of standard deviation `sigma_m` centred `d_m`
/// from a slab's middle that lies within ± `half_m` of it; the indicator |d| ≤ half for a
/// zero, negative or non-finite `sigma_m` (a point).
pub fn slab_mass(d_m: f64, half_m: f64, sigma_m: f64) -> f64 {
    if !(sigma_m.is_finite() && sigma_m > 0.0) {
        return if d_m.abs() <= half_m { 1.0 } else { 0.0 };
    }
    let s = sigma_m * std::f64::consts::SQRT_2;
    0.5 * (libm::erf((half_m - d_m) / s) - libm::erf((-half_m - d_m) / s))
}

/// Fits the slice at height `h` (along the axis) of `src`; returns the fit and its 3D centre.
fn fit_slice(
    src: &SliceSource<'_>,
    axis: Vec3,
    h: f32,
    params: &DbhParams,
) -> Option<(RobustCircle, Vec3)> {
    let (e1, e2) = plane_basis(axis);
    let mut pts: Vec<[f64; 2]> = Vec::new();
    let mut weights: Vec<f64> = Vec::new();
    let mut take = |i: usize| {
        let Some(&p) = src.points.get(i) else {
            return;
        };
        let w = match src.weights {
            Some(ws) => match ws.get(i) {
                Some(&w) if w.is_finite() && w > 0.0 => w,
                _ => return,
            },
            None => 1.0,
        };
        let d = p - src.base;
        let s = d.dot(axis);
        // Written as the comparisons that keep a point, so a NaN never gets in.
        let (in_slice, w) = match src.extents {
            None => ((s - h).abs() <= params.half_thickness_m, w),
            Some(e) => {
                let sigma = e.get(i).copied().unwrap_or(0.0);
                let m = slab_mass(
                    f64::from(s - h),
                    f64::from(params.half_thickness_m),
                    f64::from(sigma),
                );
                (m >= MIN_SLAB_MASS, w * m)
            }
        };
        let in_reach = src.reach_m.is_none_or(|r| (d - axis * s).length() <= r);
        if in_slice && in_reach {
            pts.push([d.dot(e1) as f64, d.dot(e2) as f64]);
            weights.push(w);
        }
    };
    match src.candidates {
        Some(idx) => idx.iter().for_each(|&i| take(i as usize)),
        None => (0..src.points.len()).for_each(&mut take),
    }
    let prior = src.center_prior.map(|p| {
        let d = p.center - src.base;
        CenterPrior {
            center: [d.dot(e1) as f64, d.dot(e2) as f64],
            max_offset_m: f64::from(p.max_offset_m),
            weight: p.weight,
        }
    });
    let fit = fit_circle_robust_weighted(
        &pts,
        (src.weights.is_some() || src.extents.is_some()).then_some(weights.as_slice()),
        prior.as_ref(),
        &params.circle,
    )?;
    let c = src.base + axis * h + e1 * fit.fit.center[0] as f32 + e2 * fit.fit.center[1] as f32;
    Some((fit, c))
}

fn acceptable(fit: &RobustCircle, params: &DbhParams) -> bool {
    fit.converged
        && fit.fit.n >= params.min_points
        && fit.fit.rms
            <= params
                .max_rms_m
                .max(params.max_rms_relative * fit.fit.radius)
        && fit.inlier_share >= params.min_inlier_share
}

/// Relative badness used to pick the least bad fit: RMS over radius, doubled for partial arcs.
fn badness(fit: &RobustCircle) -> f64 {
    let b = fit.fit.rms / fit.fit.radius.max(1e-6);
    if fit.partial_arc { 2.0 * b + 1.0 } else { b }
}

/// Measures the DBH of `stem` (see the module doc for the fallback rule). `None` when no
/// slice holds a circle with `min_points` inliers over a quarter of the circumference — then
/// the cluster was no stem.
///
/// [`measure_dbh_of`] on the stem's own points, unweighted, without a reach limit or prior.
pub fn measure_dbh(points: &[Vec3], stem: &Stem, params: &DbhParams) -> Option<StemDbh> {
    measure_dbh_of(
        &SliceSource {
            points,
            candidates: Some(&stem.points),
            weights: None,
            base: stem.base,
            axis: stem.axis,
            reach_m: None,
            center_prior: None,
            extents: None,
        },
        params,
    )
}

/// The DBH of one stem from any point set — the LiDAR points ([`measure_dbh`]) or the centres
/// of the trunk Gaussians (stage `dbh`, weights = opacity) — measured one way for both: slices
/// `half_thickness_m` thick cut perpendicular to `src.axis` at `breast_height_m` above
/// `src.base` (then at `fallback_heights_m`), RANSAC → weighted algebraic → geometric fit
/// ([`fit_circle_robust_weighted`]), the same acceptance and badness rules and the same
/// [`FitQuality`] (see the module doc). `None` when no slice holds a circle with `min_points`
/// inliers over a quarter of the circumference, or the axis is zero or not finite.
pub fn measure_dbh_of(src: &SliceSource<'_>, params: &DbhParams) -> Option<StemDbh> {
    let axis = unit_axis(src.axis)?;
    let make = |(circle, center): (RobustCircle, Vec3), h: f32, quality| StemDbh {
        diameter_m: 2.0 * circle.fit.radius,
        slice_height_m: h,
        center,
        circle,
        quality,
    };
    let breast = fit_slice(src, axis, params.breast_height_m, params);
    if let Some(b) = breast
        && acceptable(&b.0, params)
    {
        let q = if b.0.partial_arc {
            FitQuality::PartialArc
        } else {
            FitQuality::Good
        };
        // A partial arc at 1.3 m gives way to a full, acceptable neighbouring slice — unless a
        // centre prior holds the arc's centre (the Gaussian fit): then another height would
        // trade a held arc for the stem's taper (about 1 cm of diameter per 40 cm). Not an arc
        // under a quarter of the circle ([`MIN_STEM_ARC`]), the least a stem shows: the prior
        // then holds little more than a few points' distance from the LiDAR centre (measured on
        // `stand` seed 11: 8 branch Gaussians on a sixth of the arc, 4.5 cm outside the stem,
        // taken for its diameter; docs/results/twin.md).
        if q == FitQuality::Good || (src.center_prior.is_some() && b.0.arc_coverage >= MIN_STEM_ARC)
        {
            return Some(make(b, params.breast_height_m, q));
        }
    }
    let mut least_bad: Option<(RobustCircle, Vec3, f32)> =
        breast.map(|(f, c)| (f, c, params.breast_height_m));
    for &h in &params.fallback_heights_m {
        let Some((fit, c)) = fit_slice(src, axis, h, params) else {
            continue;
        };
        if acceptable(&fit, params) && !fit.partial_arc {
            return Some(make((fit, c), h, FitQuality::FallbackSlice));
        }
        if least_bad.is_none_or(|(b, _, _)| badness(&fit) < badness(&b)) {
            least_bad = Some((fit, c, h));
        }
    }
    if let Some(b) = breast
        && acceptable(&b.0, params)
        && (src.center_prior.is_none() || b.0.arc_coverage >= MIN_STEM_ARC)
    {
        return Some(make(b, params.breast_height_m, FitQuality::PartialArc));
    }
    // Reported as poor only when some slice holds a real piece of a circle; otherwise the
    // cluster was no stem (a branch or a bush crossing the band).
    least_bad
        .filter(|(f, _, _)| f.fit.n >= params.min_points && f.arc_coverage >= MIN_STEM_ARC)
        .map(|(f, c, h)| make((f, c), h, FitQuality::Poor))
}

/// The points of `points` in the slice at `height_m` along `axis` above `base` (± `half_thickness_m`,
/// measured along the axis, as the LiDAR slice), within `reach_m` of the axis line, each with its
/// signed distance from the circle `center`/`radius_m` in the slice plane (positive outside), metres.
///
/// `center` is a 3D circle centre as [`StemDbh::center`] stores it; only its position in the
/// plane perpendicular to the axis counts. `axis` need not be unit length; a zero or
/// non-finite axis gives no points. Indices are into `points`, in increasing order.
#[allow(clippy::too_many_arguments)]
pub fn slice_offsets(
    points: &[glam::Vec3],
    base: glam::Vec3,
    axis: glam::Vec3,
    height_m: f32,
    half_thickness_m: f32,
    reach_m: f32,
    center: glam::Vec3,
    radius_m: f32,
) -> Vec<(usize, f32)> {
    let Some(axis) = unit_axis(axis) else {
        return Vec::new();
    };
    let dc = center - base;
    let c = dc - axis * dc.dot(axis);
    points
        .iter()
        .enumerate()
        .filter_map(|(i, &p)| {
            let d = p - base;
            let s = d.dot(axis);
            let q = d - axis * s;
            let keep = (s - height_m).abs() <= half_thickness_m && q.length() <= reach_m;
            keep.then(|| (i, q.distance(c) - radius_m))
        })
        .collect()
}
