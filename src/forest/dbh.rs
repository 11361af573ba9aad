//! Diameter at breast height of one stem (METHOD.md Stage 5, LiDAR-only baseline): the stem's
//! points in a slice 1.3 m ± 0.1 m above ground, cut perpendicular to the stem's own axis,
//! a robust circle fit, and neighbouring slices when that one is poor.
//!
//! Fallback (as 3DFin does): when the 1.3 m slice gives no acceptable fit, the slices at
//! `fallback_heights_m` are tried in order (closest to 1.3 m first) and the diameter of the
//! first acceptable one is reported as it is, flagged `fallback_slice`. It is not corrected
//! to 1.3 m: a taper of ~1 cm per metre changes a diameter by 2–4 mm over 0.2–0.4 m, less
//! than the fit's own error, and a taper estimated from two noisy slices would add more.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::ransac::{CircleParams, RobustCircle, fit_circle_robust};
use super::stems::Stem;

/// A cluster whose best slice covers less of a circle than this (a quarter) is no stem.
pub const MIN_STEM_ARC: f64 = 0.25;

/// Parameters of [`measure_dbh`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct DbhParams {
    /// Breast height along the stem above the ground, metres (METHOD.md Stage 5: 1.3 m).
    pub breast_height_m: f32,
    /// Half the slice thickness, metres (METHOD.md Stage 5: ± 0.1 m).
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

/// Orthonormal basis (e1, e2) of the plane perpendicular to `axis`.
fn plane_basis(axis: Vec3) -> (Vec3, Vec3) {
    let e1 = axis.any_orthonormal_vector();
    (e1, axis.cross(e1))
}

/// Fits the slice at height `h` (along the axis) of `stem`; returns the fit and its 3D centre.
fn fit_slice(
    points: &[Vec3],
    stem: &Stem,
    h: f32,
    params: &DbhParams,
) -> Option<(RobustCircle, Vec3)> {
    let (e1, e2) = plane_basis(stem.axis);
    let pts: Vec<[f64; 2]> = stem
        .points
        .iter()
        .filter_map(|&i| {
            let d = *points.get(i as usize)? - stem.base;
            let s = d.dot(stem.axis);
            ((s - h).abs() <= params.half_thickness_m).then(|| [d.dot(e1) as f64, d.dot(e2) as f64])
        })
        .collect();
    let fit = fit_circle_robust(&pts, &params.circle)?;
    let c =
        stem.base + stem.axis * h + e1 * fit.fit.center[0] as f32 + e2 * fit.fit.center[1] as f32;
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
pub fn measure_dbh(points: &[Vec3], stem: &Stem, params: &DbhParams) -> Option<StemDbh> {
    let make = |(circle, center): (RobustCircle, Vec3), h: f32, quality| StemDbh {
        diameter_m: 2.0 * circle.fit.radius,
        slice_height_m: h,
        center,
        circle,
        quality,
    };
    let breast = fit_slice(points, stem, params.breast_height_m, params);
    if let Some(b) = breast
        && acceptable(&b.0, params)
    {
        let q = if b.0.partial_arc {
            FitQuality::PartialArc
        } else {
            FitQuality::Good
        };
        // A partial arc at 1.3 m gives way to a full, acceptable neighbouring slice.
        if q == FitQuality::Good {
            return Some(make(b, params.breast_height_m, q));
        }
    }
    let mut least_bad: Option<(RobustCircle, Vec3, f32)> =
        breast.map(|(f, c)| (f, c, params.breast_height_m));
    for &h in &params.fallback_heights_m {
        let Some((fit, c)) = fit_slice(points, stem, h, params) else {
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
#[allow(clippy::too_many_arguments)]
pub fn slice_offsets(
    points: &[Vec3],
    base: Vec3,
    axis: Vec3,
    height_m: f32,
    half_thickness_m: f32,
    reach_m: f32,
    center: Vec3,
    radius_m: f32,
) -> Vec<(usize, f32)> {
    let axis = axis.try_normalize().unwrap_or(Vec3::Z);
    points
        .iter()
        .enumerate()
        .filter_map(|(i, &p)| {
            let along = (p - base).dot(axis);
            if (along - height_m).abs() > half_thickness_m {
                return None;
            }
            let off_axis = (p - base) - axis * along;
            if off_axis.length() > reach_m {
                return None;
            }
            let d = p - center;
            let r = (d - axis * d.dot(axis)).length();
            Some((i, r - radius_m))
        })
        .collect()
}
