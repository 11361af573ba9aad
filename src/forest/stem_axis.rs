//! A stem's axis: circle centres of horizontal slices and a straight line through them
//! (least squares of x and y against z, weighted by each slice's support).

use glam::{Vec2, Vec3};

use super::ransac::fit_circle_robust;
use super::stems::StemParams;

/// Circle centres of horizontal slices: (z of the slice middle, centre, radius, weight).
pub(crate) fn slice_centres(
    points: &[Vec3],
    heights: &[f32],
    idx: &[u32],
    params: &StemParams,
) -> Vec<(f32, Vec2, f32, f32)> {
    let mut out = Vec::new();
    let mut h = params.axis_min_m;
    while h < params.axis_max_m - 1e-4 {
        let top = h + params.axis_slice_m;
        let (mut pts, mut zsum) = (Vec::new(), 0.0f64);
        for &i in idx {
            let hi = heights[i as usize];
            if hi >= h && hi < top {
                let p = points[i as usize];
                pts.push([p.x as f64, p.y as f64]);
                zsum += p.z as f64;
            }
        }
        if let Some(fit) = fit_circle_robust(&pts, &params.circle)
            && fit.fit.n >= 8
            && fit.arc_coverage >= 0.25
        {
            let z = (zsum / pts.len() as f64) as f32;
            let c = Vec2::new(fit.fit.center[0] as f32, fit.fit.center[1] as f32);
            let w = (fit.arc_coverage * fit.fit.n as f64).sqrt() as f32;
            out.push((z, c, fit.fit.radius as f32, w));
        }
        h = top;
    }
    out
}

/// Weighted least-squares line x = x0 + a (z - zm), y = y0 + b (z - zm) through slice
/// centres; returns (point on the axis at zm, unit direction up). Vertical for one centre.
pub(crate) fn fit_axis(
    centres: &[(f32, Vec2, f32, f32)],
    max_lean_deg: f32,
) -> Option<(Vec3, Vec3)> {
    let sw: f32 = centres.iter().map(|c| c.3).sum();
    if centres.is_empty() || sw <= 0.0 {
        return None;
    }
    let zm = centres.iter().map(|c| c.0 * c.3).sum::<f32>() / sw;
    let cm = centres.iter().map(|c| c.1 * c.3).sum::<Vec2>() / sw;
    let szz: f32 = centres.iter().map(|c| c.3 * (c.0 - zm).powi(2)).sum();
    let mut slope = Vec2::ZERO;
    if centres.len() >= 2 && szz > 1e-4 {
        slope = centres
            .iter()
            .map(|c| (c.1 - cm) * (c.0 - zm) * c.3)
            .sum::<Vec2>()
            / szz;
    }
    let max_slope = max_lean_deg.to_radians().tan();
    if slope.length() > max_slope {
        slope = slope.normalize_or_zero() * max_slope;
    }
    Some((
        Vec3::new(cm.x, cm.y, zm),
        Vec3::new(slope.x, slope.y, 1.0).normalize(),
    ))
}

/// Horizontal distance from `p` to the axis line at p's height.
pub(crate) fn off_axis(p: Vec3, origin: Vec3, axis: Vec3) -> f32 {
    let at = origin + axis * ((p.z - origin.z) / axis.z.max(1e-3));
    Vec2::new(p.x - at.x, p.y - at.y).length()
}
