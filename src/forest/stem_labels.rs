//! Stem-guided relabelling (a refinement of docs/method.md Stage 3, run after the stems are found):
//! each detected stem is followed up and down from breast height by circle fits of
//! horizontal slices (region growing along the stem axis), and the points on the fitted stem
//! surface are labelled trunk.
//!
//! Why: the eigen-feature 2-means labels stems well where they stand free, but near the
//! ground (butt flare, shrubs, roots, the edge of the ground filter's class threshold) a
//! neighbourhood mixes stem with clutter and the stem's lowest metres go to leaf (on the
//! generated stands about a quarter of the stem points below 2 m). A stem is a cylinder with
//! a known axis and radius there, so the points on its surface are wood by construction.
//!
//! Each slice is predicted from the previous one (centre moved along the stem axis, the
//! previous radius), the points within `search_margin_m` of the predicted circle are fitted
//! with the robust circle of [`fit_circle_robust`], and a fit is accepted when its radius and
//! centre stay close to the prediction. Points within `band_m` of an accepted circle become
//! trunk. Growth stops after `max_misses` slices in a row without an accepted circle (the
//! crown, a fork, the top of the scan).

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ransac::{CircleParams, fit_circle_robust};
use super::segment::TRUNK;
use super::stems::{Buckets, Stem};

/// Parameters of [`label_stem_points`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct StemLabelParams {
    /// Run the stem-guided relabelling (true by default; false gives docs/method.md's labels).
    pub enabled: bool,
    /// Thickness of one slice, metres. 0.25 m: the stem slices of [`super::StemParams`]; thin
    /// enough that taper and lean change a slice's circle by millimetres, thick enough to hold
    /// a few dozen points on the thinnest stems (DBH 8 cm).
    pub slice_m: f32,
    /// A point within this distance of an accepted slice circle is trunk, metres. 0.03 m is
    /// three times the range noise of a handheld scanner (docs/method.md: sigma 1 cm).
    pub band_m: f32,
    /// Points within the predicted radius plus this margin enter a slice's fit, metres.
    pub search_margin_m: f32,
    /// Largest relative change of the radius from one slice to the next, [0, 1]. 0.25 admits
    /// the butt flare (15–20 % over 0.4 m in the generator, similar in real stems) and a
    /// fork's first slice, and rejects a branch or a bush fitted instead of the stem.
    pub max_radius_change: f32,
    /// Consecutive slices without an accepted circle that end the growth.
    pub max_misses: usize,
    /// Fewest inliers an accepted slice circle needs.
    pub min_inliers: usize,
    /// Least arc coverage (share of 10° sectors) an accepted slice circle needs, [0, 1]:
    /// a quarter of the circumference is what a single scan position shows of a stem.
    pub min_arc_coverage: f64,
    /// Growth stops at this height above ground, metres.
    pub max_height_m: f32,
}

impl Default for StemLabelParams {
    fn default() -> Self {
        Self {
            enabled: true,
            slice_m: 0.25,
            band_m: 0.03,
            search_margin_m: 0.08,
            max_radius_change: 0.25,
            max_misses: 2,
            min_inliers: 12,
            min_arc_coverage: 0.25,
            max_height_m: 40.0,
        }
    }
}

/// Labels the points on every stem's surface trunk, sets their trunk probability to at least
/// 0.5 (keeping `P >= 0.5` exactly for trunk points) and returns how many labels changed.
/// `heights` are heights above the DTM; ground points are never relabelled.
pub fn label_stem_points(
    points: &[Vec3],
    heights: &[f32],
    is_ground: &[bool],
    stems: &[Stem],
    labels: &mut [u8],
    probability: &mut [f32],
    params: &StemLabelParams,
) -> usize {
    if !params.enabled
        || stems.is_empty()
        || !(params.slice_m > 0.0 && params.band_m > 0.0)
        || heights.len() != points.len()
        || is_ground.len() != points.len()
        || labels.len() != points.len()
        || probability.len() != points.len()
    {
        return 0;
    }
    let candidates: Vec<u32> = (0..points.len() as u32)
        .filter(|&i| !is_ground[i as usize] && heights[i as usize] >= -0.2)
        .collect();
    let buckets = Buckets::new(points, &candidates, 0.5);
    // Stems are followed in parallel, their points labelled in stem order.
    let surfaces: Vec<Vec<u32>> = stems
        .par_iter()
        .map(|stem| stem_surface(points, heights, &buckets, stem, params))
        .collect();
    let mut changed = 0;
    for surface in surfaces {
        for i in surface {
            let i = i as usize;
            if labels[i] != TRUNK {
                labels[i] = TRUNK;
                changed += 1;
            }
            probability[i] = probability[i].max(0.5);
        }
    }
    changed
}

/// Horizontal centre of the stem axis at height `z` (absolute), from its base.
fn axis_at(stem: &Stem, z: f32) -> Vec2 {
    let a = stem.axis;
    let t = (z - stem.base.z) / a.z.max(0.1);
    (stem.base + a * t).truncate()
}

/// Indices of the points on one stem's surface.
fn stem_surface(
    points: &[Vec3],
    heights: &[f32],
    buckets: &Buckets,
    stem: &Stem,
    params: &StemLabelParams,
) -> Vec<u32> {
    let r0 = stem.radius_estimate.max(0.02);
    // Reach: how far from the straight axis the stem may wander (curvature, a fit's drift).
    let reach = r0 * (1.0 + params.max_radius_change) * 1.5 + params.search_margin_m + 0.2;
    // Gather once: points within reach of the axis, every 0.5 m up to the top.
    let mut near: Vec<u32> = Vec::new();
    let mut z = stem.base.z - 0.5;
    while z < stem.base.z + params.max_height_m {
        for i in buckets.near(axis_at(stem, z), reach) {
            let p = points[i as usize];
            if p.z >= z && p.z < z + 0.5 && (p.truncate() - axis_at(stem, p.z)).length() <= reach {
                near.push(i);
            }
        }
        z += 0.5;
    }
    // Slices by height above ground.
    let n_slices = (params.max_height_m / params.slice_m).ceil() as usize + 1;
    let mut slices: Vec<Vec<u32>> = vec![Vec::new(); n_slices];
    for &i in &near {
        let h = heights[i as usize];
        if h >= 0.0 {
            let k = (h / params.slice_m) as usize;
            if k < n_slices {
                slices[k].push(i);
            }
        }
    }
    let start = ((1.3 / params.slice_m) as usize).min(n_slices - 1);
    let mut out = Vec::new();
    for dir in [1i64, -1] {
        let mut k = if dir > 0 {
            start as i64
        } else {
            start as i64 - 1
        };
        let mut offset = Vec2::ZERO; // fitted centre minus the straight axis
        let mut radius = r0;
        let mut misses = 0;
        while k >= 0 && (k as usize) < n_slices && misses <= params.max_misses {
            let slice = &slices[k as usize];
            let z_mid = slice.iter().map(|&i| points[i as usize].z).sum::<f32>()
                / slice.len().max(1) as f32;
            let centre = axis_at(stem, z_mid) + offset;
            let sel: Vec<u32> = slice
                .iter()
                .copied()
                .filter(|&i| {
                    (points[i as usize].truncate() - centre).length()
                        <= radius + params.search_margin_m
                })
                .collect();
            let pts: Vec<[f64; 2]> = sel
                .iter()
                .map(|&i| {
                    let p = points[i as usize];
                    [p.x as f64, p.y as f64]
                })
                .collect();
            let circle = CircleParams {
                min_radius_m: (radius * (1.0 - params.max_radius_change)) as f64,
                max_radius_m: (radius * (1.0 + params.max_radius_change)) as f64,
                ..CircleParams::default()
            };
            let fit = fit_circle_robust(&pts, &circle).filter(|f| {
                let c = Vec2::new(f.fit.center[0] as f32, f.fit.center[1] as f32);
                f.fit.n >= params.min_inliers
                    && f.arc_coverage >= params.min_arc_coverage
                    && (c - centre).length() <= 0.5 * radius + 0.02
            });
            match fit {
                Some(f) => {
                    let c = Vec2::new(f.fit.center[0] as f32, f.fit.center[1] as f32);
                    let r = f.fit.radius as f32;
                    out.extend(sel.iter().copied().filter(|&i| {
                        ((points[i as usize].truncate() - c).length() - r).abs() <= params.band_m
                    }));
                    offset = c - axis_at(stem, z_mid);
                    radius = r;
                    misses = 0;
                }
                None => misses += 1,
            }
            k += dir;
        }
    }
    out
}
