//! The point-to-plane update of ICP: one Gauss-Newton step of
//! min sum w ((s R p + t - q) · n_q)^2, linearised about the current pose as a small rotation
//! omega, translation tau and log-scale sigma about the weighted centroid c of the moved
//! source points, so that the unknowns are well conditioned and decoupled.

use glam::{DQuat, DVec3};
use rayon::prelude::*;

use super::Pair;
use crate::geom::index::CHUNK;
use crate::geom::linalg::solve;
use crate::geom::{GeomError, Similarity};

/// Smallest pivot of the point-to-plane normal equations, relative to their largest diagonal
/// entry, below which the system is degenerate.
const PIVOT: f64 = 1e-12;

// Index loops mirror the matrix algebra.
#[allow(clippy::needless_range_loop, clippy::too_many_arguments)]
/// One Gauss-Newton step of point-to-plane (similarity) ICP from the pairs found under `t`
/// (each holds its source point moved by `t`); returns the updated transform.
pub(super) fn point_to_plane_step(
    pairs: &[Pair],
    t: &Similarity,
    with_scale: bool,
    with_rotation: bool,
) -> Result<Similarity, GeomError> {
    let dim = if with_scale { 7 } else { 6 };
    // Sums over fixed chunks of pairs in parallel, added in chunk order: the same result on
    // any number of threads.
    let parts: Vec<(f64, DVec3)> = pairs
        .par_chunks(CHUNK)
        .map(|chunk| {
            let (mut sw, mut c) = (0.0, DVec3::ZERO);
            for p in chunk.iter().filter(|p| p.weight > 0.0) {
                let q = p.q;
                sw += p.weight;
                c += q * p.weight;
            }
            (sw, c)
        })
        .collect();
    let (sw, mut c) = parts
        .iter()
        .fold((0.0, DVec3::ZERO), |(s, c), (ps, pc)| (s + ps, c + *pc));
    if sw.is_nan() || sw <= 0.0 {
        return Err(GeomError::Degenerate(
            "no correspondence has a positive weight",
        ));
    }
    c /= sw;
    let parts: Vec<([[f64; 7]; 7], [f64; 7])> = pairs
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut ata = [[0.0f64; 7]; 7];
            let mut atb = [0.0f64; 7];
            for p in chunk.iter().filter(|p| p.weight > 0.0) {
                let q = p.q;
                let n = p.n.as_dvec3();
                let x = q - c;
                let r0 = (q - p.tp.as_dvec3()).dot(n);
                let xn = x.cross(n);
                // Scale column from the foot of the point on the plane, (x - r0 n) · n: with
                // x · n the source noise along n, scaled with the points, would pay for a
                // smaller scale (the bias explained in `geom::surface::gauss_newton`).
                let row = [xn.x, xn.y, xn.z, n.x, n.y, n.z, x.dot(n) - r0];
                for a in 0..dim {
                    atb[a] -= p.weight * row[a] * r0;
                    for b in a..dim {
                        ata[a][b] += p.weight * row[a] * row[b];
                    }
                }
            }
            (ata, atb)
        })
        .collect();
    let mut ata = [[0.0f64; 7]; 7];
    let mut atb = [0.0f64; 7];
    for (pa, pb) in &parts {
        for a in 0..dim {
            atb[a] += pb[a];
            for b in a..dim {
                ata[a][b] += pa[a][b];
            }
        }
    }
    for a in 0..dim {
        for b in 0..a {
            ata[a][b] = ata[b][a];
        }
    }
    if !with_rotation {
        // Pin omega to 0: its rows and columns become the identity, its right side 0.
        for a in 0..3 {
            for b in 0..dim {
                ata[a][b] = 0.0;
                ata[b][a] = 0.0;
            }
            ata[a][a] = ata[3][3].max(ata[4][4]).max(ata[5][5]).max(1.0);
            atb[a] = 0.0;
        }
    }
    let delta = solve(ata, atb, dim, PIVOT).ok_or(GeomError::Degenerate(
        "point-to-plane system is singular: the overlapping surfaces do not constrain all axes",
    ))?;
    let omega = DVec3::new(delta[0], delta[1], delta[2]);
    let tau = DVec3::new(delta[3], delta[4], delta[5]);
    let s_inc = if with_scale { delta[6].exp() } else { 1.0 };
    let r_inc = glam::DMat3::from_quat(DQuat::from_scaled_axis(omega));
    let inc = Similarity {
        scale: s_inc,
        rotation: r_inc,
        translation: c + tau - r_inc * c * s_inc,
    };
    Ok(t.then(&inc))
}
