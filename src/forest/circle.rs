//! Circle fitting in the plane: the weighted algebraic (Kåsa) fit of docs/method.md Stage 5.3, a
//! RANSAC front end that drops gross outliers (Stage 5.2), a geometric Gauss–Newton
//! refinement, and the quality figures every stem diameter is reported with.
//!
//! The algebraic fit minimises `sum w_i (x_i² + y_i² + u x_i + v y_i + c)²` through its 3×3
//! normal equations. It is closed-form and never diverges, but it is biased towards small
//! circles on partial arcs; the Gauss–Newton step then minimises the true geometric distance
//! `sum w_i (|p_i - centre| - r)²` from the algebraic solution.

use serde::{Deserialize, Serialize};

/// A circle fitted to planar points (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CircleFit {
    /// Centre (x, y), metres.
    pub center: [f64; 2],
    /// Radius, metres.
    pub radius: f64,
    /// Root-mean-square geometric residual `|p - centre| - r` of the points used, metres.
    pub rms: f64,
    /// Number of points used by the fit.
    pub n: usize,
}

/// Weighted algebraic (Kåsa) circle fit: solves the 3×3 weighted normal equations of
/// `E(u, v, c) = sum w_i (x_i² + y_i² + u x_i + v y_i + c)²`; centre (-u/2, -v/2),
/// r = sqrt(u²/4 + v²/4 - c) (docs/method.md Stage 5.3). `weights` default to 1.
///
/// `None` for fewer than 3 points with positive weight, non-finite input, mismatched lengths
/// or (near-)collinear points.
pub fn fit_circle_weighted(points: &[[f64; 2]], weights: Option<&[f64]>) -> Option<CircleFit> {
    if weights.is_some_and(|w| w.len() != points.len()) {
        return None;
    }
    let w_at = |i: usize| weights.map_or(1.0, |w| w[i]);
    // Centre the data on the weighted mean for conditioning.
    let (mut sw, mut mx, mut my, mut used) = (0.0, 0.0, 0.0, 0usize);
    for (i, p) in points.iter().enumerate() {
        let w = w_at(i);
        if !(w.is_finite() && p[0].is_finite() && p[1].is_finite()) || w < 0.0 {
            return None;
        }
        if w > 0.0 {
            sw += w;
            mx += w * p[0];
            my += w * p[1];
            used += 1;
        }
    }
    if used < 3 || sw <= 0.0 {
        return None;
    }
    let (mx, my) = (mx / sw, my / sw);
    // Normal matrix of rows [x, y, 1] and right-hand side -(x² + y²) [x, y, 1].
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    let mut scale = 0.0f64;
    for (i, p) in points.iter().enumerate() {
        let w = w_at(i);
        if w <= 0.0 {
            continue;
        }
        let (x, y) = (p[0] - mx, p[1] - my);
        let z = x * x + y * y;
        scale = scale.max(z);
        let row = [x, y, 1.0];
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] += w * row[r] * row[c];
            }
            b[r] -= w * z * row[r];
        }
    }
    let sol = solve3(a, b, scale.max(1e-300))?;
    let (u, v, c) = (sol[0], sol[1], sol[2]);
    let r2 = u * u / 4.0 + v * v / 4.0 - c;
    if !(r2 > 0.0 && r2.is_finite()) {
        return None;
    }
    let center = [mx - u / 2.0, my - v / 2.0];
    let radius = r2.sqrt();
    let rms = weighted_rms(points, weights, center, radius);
    Some(CircleFit {
        center,
        radius,
        rms,
        n: used,
    })
}

/// Solves a 3×3 system; `None` when its determinant is negligible relative to the data scale
/// (collinear or coincident points).
fn solve3(a: [[f64; 3]; 3], b: [f64; 3], scale: f64) -> Option<[f64; 3]> {
    let d = glam::DMat3::from_cols_array_2d(&a).determinant();
    // The determinant scales like n³ · (length²)²; compare with that magnitude.
    let mag = a[2][2].powi(3) * scale * scale;
    if !d.is_finite() || d.abs() <= 1e-12 * mag {
        return None;
    }
    crate::geom::solve3(a, b)
}

/// Weighted RMS of the geometric residuals `|p - centre| - r` (weights default to 1).
pub fn weighted_rms(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    center: [f64; 2],
    radius: f64,
) -> f64 {
    let (mut s, mut sw) = (0.0, 0.0);
    for (i, p) in points.iter().enumerate() {
        let w = weights.map_or(1.0, |w| w[i]);
        let e = (p[0] - center[0]).hypot(p[1] - center[1]) - radius;
        s += w * e * e;
        sw += w;
    }
    if sw > 0.0 { (s / sw).sqrt() } else { 0.0 }
}

/// Geometric refinement: Gauss–Newton on `sum w_i (|p_i - c| - r)²` from `start`, at most
/// `max_iterations` steps, stopping when the centre and radius move less than 1e-7 m.
/// Returns the refined fit and whether it converged; a step that raises the cost is halved
/// (up to 10 times) so the refinement never makes the fit worse.
pub fn refine_circle_geometric(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    start: &CircleFit,
    max_iterations: usize,
) -> (CircleFit, bool) {
    refine_circle_geometric_with_prior(points, weights, start, max_iterations, None)
}

/// [`refine_circle_geometric`] with a soft prior on the centre: `(p, λ)` adds
/// λ · |c − p|² to the cost, the centre as a pseudo-observation worth λ points of weight 1
/// (MAP estimate under a Gaussian prior; λ = σ_point² / σ_centre²).
pub fn refine_circle_geometric_with_prior(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    start: &CircleFit,
    max_iterations: usize,
    prior: Option<([f64; 2], f64)>,
) -> (CircleFit, bool) {
    let w_at = |i: usize| weights.map_or(1.0, |w| w[i]);
    let (pc, lambda) = prior
        .filter(|(p, l)| l.is_finite() && *l > 0.0 && p[0].is_finite() && p[1].is_finite())
        .unwrap_or(([0.0; 2], 0.0));
    let cost = |c: [f64; 2], r: f64| {
        let mut s = lambda * ((c[0] - pc[0]).powi(2) + (c[1] - pc[1]).powi(2));
        for (i, p) in points.iter().enumerate() {
            let e = (p[0] - c[0]).hypot(p[1] - c[1]) - r;
            s += w_at(i) * e * e;
        }
        s
    };
    let (mut c, mut r) = (start.center, start.radius);
    let mut current = cost(c, r);
    for _ in 0..max_iterations {
        // J rows: d e_i / d(cx, cy, r) = (-(x - cx)/d, -(y - cy)/d, -1).
        let mut a = [[0.0f64; 3]; 3];
        let mut g = [0.0f64; 3];
        for (i, p) in points.iter().enumerate() {
            let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
            let d = dx.hypot(dy);
            if d < 1e-12 {
                continue;
            }
            let w = w_at(i);
            let j = [-dx / d, -dy / d, -1.0];
            let e = d - r;
            for (rr, jr) in j.iter().enumerate() {
                for (cc, jc) in j.iter().enumerate() {
                    a[rr][cc] += w * jr * jc;
                }
                g[rr] -= w * jr * e;
            }
        }
        // The prior's pseudo-residuals √λ (c − p), Jacobian √λ I on the centre.
        a[0][0] += lambda;
        a[1][1] += lambda;
        g[0] -= lambda * (c[0] - pc[0]);
        g[1] -= lambda * (c[1] - pc[1]);
        let Some(step) = solve3(a, g, 1.0) else {
            return (with_rms(points, weights, c, r, start.n), false);
        };
        let mut t = 1.0;
        let mut accepted = false;
        for _ in 0..10 {
            let nc = [c[0] + t * step[0], c[1] + t * step[1]];
            let nr = r + t * step[2];
            let nv = cost(nc, nr);
            if nr > 0.0 && nv <= current {
                c = nc;
                r = nr;
                current = nv;
                accepted = true;
                break;
            }
            t *= 0.5;
        }
        let moved = t * (step[0].abs() + step[1].abs() + step[2].abs());
        if !accepted || moved < 1e-7 {
            return (with_rms(points, weights, c, r, start.n), true);
        }
    }
    (with_rms(points, weights, c, r, start.n), false)
}

fn with_rms(
    points: &[[f64; 2]],
    weights: Option<&[f64]>,
    center: [f64; 2],
    radius: f64,
    n: usize,
) -> CircleFit {
    CircleFit {
        center,
        radius,
        rms: weighted_rms(points, weights, center, radius),
        n,
    }
}

/// Share of the 36 ten-degree sectors around `center` that hold at least one point, in
/// [0, 1] (docs/method.md Stage 5: arc coverage).
pub fn arc_coverage(points: &[[f64; 2]], center: [f64; 2]) -> f64 {
    let mut occupied = [false; 36];
    for p in points {
        let a = (p[1] - center[1]).atan2(p[0] - center[0]).to_degrees();
        let k = (((a + 360.0) % 360.0) / 10.0) as usize;
        occupied[k.min(35)] = true;
    }
    occupied.iter().filter(|o| **o).count() as f64 / 36.0
}
