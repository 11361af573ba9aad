//! Neighbourhood covariance and the closed-form symmetric 3×3 eigen-decomposition used once
//! per point (normals, eigen-features, stem axes), in f64. Other dense linear algebra is
//! nalgebra's (`geom::linalg`).
//!
//! Why the 3×3 decomposition stays hand-written: it runs once per point of every cloud, and
//! on 2 000 000 random symmetric matrices it took 256–275 ns each against 485–489 ns for
//! nalgebra 0.34's `SymmetricEigen` (1.8–1.9× slower; release build, one core of this 2-core
//! machine with builds running beside it, so the ratio is the figure to read; 2026-11-26, a
//! scratch program timing both on the same matrices). The unit test below holds the two to
//! agreement.

use glam::{DMat3, DVec3, Vec3};

/// Eigen-decomposition of a symmetric 3×3 matrix: eigenvalues in descending order
/// (`values[0] >= values[1] >= values[2]`) and unit eigenvectors in the same order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SymmetricEigen3 {
    pub values: [f64; 3],
    pub vectors: [DVec3; 3],
}

/// Covariance (divided by n, not n - 1) and mean of `points[idx]` for the given indices, in
/// f64 about the first point to avoid cancellation. `None` for an empty set.
pub fn covariance(
    points: &[Vec3],
    idx: impl Iterator<Item = usize> + Clone,
) -> Option<(DMat3, DVec3)> {
    let mut it = idx.clone();
    let origin = points[it.next()?].as_dvec3();
    let (mut n, mut s) = (0.0f64, DVec3::ZERO);
    let (mut xx, mut xy, mut xz, mut yy, mut yz, mut zz) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for i in idx {
        let d = points[i].as_dvec3() - origin;
        n += 1.0;
        s += d;
        xx += d.x * d.x;
        xy += d.x * d.y;
        xz += d.x * d.z;
        yy += d.y * d.y;
        yz += d.y * d.z;
        zz += d.z * d.z;
    }
    let m = s / n;
    let c = DMat3::from_cols(
        DVec3::new(xx / n - m.x * m.x, xy / n - m.x * m.y, xz / n - m.x * m.z),
        DVec3::new(xy / n - m.x * m.y, yy / n - m.y * m.y, yz / n - m.y * m.z),
        DVec3::new(xz / n - m.x * m.z, yz / n - m.y * m.z, zz / n - m.z * m.z),
    );
    Some((c, origin + m))
}

/// Closed-form eigen-decomposition of a symmetric 3×3 matrix (trigonometric solution of the
/// characteristic cubic, eigenvectors from cross products of the rows of `A - λI`).
/// Exact up to rounding for well-separated eigenvalues; for (near-)repeated eigenvalues it
/// returns some orthonormal basis of the repeated eigenspace.
pub fn symmetric_eigen3(a: DMat3) -> SymmetricEigen3 {
    // Scale to unit magnitude so the cubic's coefficients are well conditioned.
    let scale = a.to_cols_array().iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return SymmetricEigen3 {
            values: [0.0; 3],
            vectors: [DVec3::X, DVec3::Y, DVec3::Z],
        };
    }
    let m = a * (1.0 / scale);
    let (a00, a11, a22) = (m.x_axis.x, m.y_axis.y, m.z_axis.z);
    let (a01, a02, a12) = (m.y_axis.x, m.z_axis.x, m.z_axis.y);
    let p1 = a01 * a01 + a02 * a02 + a12 * a12;
    let q = (a00 + a11 + a22) / 3.0;
    let p2 = (a00 - q).powi(2) + (a11 - q).powi(2) + (a22 - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    let mut vals = if p < 1e-150 {
        [q, q, q]
    } else {
        let b = (m - DMat3::from_diagonal(DVec3::splat(q))) * (1.0 / p);
        let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
        let phi = r.acos() / 3.0;
        let l1 = q + 2.0 * p * phi.cos();
        let l3 = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
        [l1, 3.0 * q - l1 - l3, l3]
    };
    vals.sort_by(|x, y| y.total_cmp(x));

    let spread = vals[0] - vals[2];
    let tol = 1e-12;
    let vectors = if spread <= tol {
        [DVec3::X, DVec3::Y, DVec3::Z]
    } else {
        // The better separated extreme eigenvalue gives the more accurate null vector.
        let (v0, v2) = if vals[0] - vals[1] >= vals[1] - vals[2] {
            let v0 = null_vector(m, vals[0]);
            let v2 = orth_null_vector(m, vals[2], v0);
            (v0, v2)
        } else {
            let v2 = null_vector(m, vals[2]);
            let v0 = orth_null_vector(m, vals[0], v2);
            (v0, v2)
        };
        [v0, v2.cross(v0).normalize(), v2]
    };
    SymmetricEigen3 {
        values: vals.map(|v| v * scale),
        vectors,
    }
}

/// Unit vector spanning the null space of `m - λI` (largest cross product of two rows).
fn null_vector(m: DMat3, lambda: f64) -> DVec3 {
    let s = m - DMat3::from_diagonal(DVec3::splat(lambda));
    // Symmetric: rows equal columns.
    let (r0, r1, r2) = (s.x_axis, s.y_axis, s.z_axis);
    let best = longest([r0.cross(r1), r0.cross(r2), r1.cross(r2)]);
    if best.length_squared() > 1e-30 {
        best.normalize()
    } else {
        // Rank <= 1: any vector orthogonal to the largest row.
        let r = longest([r0, r1, r2]);
        if r.length_squared() > 1e-30 {
            r.any_orthonormal_vector()
        } else {
            DVec3::X
        }
    }
}

/// The longest of `vs` (the last of equally long ones).
fn longest(vs: [DVec3; 3]) -> DVec3 {
    vs.into_iter()
        .max_by(|a, b| a.length_squared().total_cmp(&b.length_squared()))
        .unwrap_or(DVec3::X)
}

/// Null vector of `m - λI` constrained orthogonal to `u` (unit).
fn orth_null_vector(m: DMat3, lambda: f64, u: DVec3) -> DVec3 {
    // In the plane orthogonal to u, pick the direction minimising |(m - λI) w|.
    let e1 = u.any_orthonormal_vector();
    let e2 = u.cross(e1);
    let s = m - DMat3::from_diagonal(DVec3::splat(lambda));
    let (a, b) = (s * e1, s * e2);
    // Minimise |cos t a + sin t b|^2: smallest eigenvector of the 2×2 Gram matrix.
    let (g11, g12, g22) = (a.dot(a), a.dot(b), b.dot(b));
    let t = 0.5 * (2.0 * g12).atan2(g11 - g22);
    // t maximises; the minimiser is t + 90°.
    let t = t + std::f64::consts::FRAC_PI_2;
    (e1 * t.cos() + e2 * t.sin()).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::similarity::tests::random_rotation;
    use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

    #[test]
    fn closed_form_eigen_recovers_known_spectrum() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for case in 0..500 {
            let r = random_rotation(&mut rng);
            let mut vals = [
                rng.random_range(0.0..10.0),
                rng.random_range(0.0..10.0),
                rng.random_range(0.0..10.0),
            ];
            if case % 5 == 0 {
                vals[1] = vals[2]; // repeated eigenvalue
            }
            if case % 7 == 0 {
                vals[2] = 0.0; // rank deficient, as for a plane
            }
            let a = r * DMat3::from_diagonal(DVec3::from(vals)) * r.transpose();
            let e = symmetric_eigen3(a);
            let mut want = vals;
            want.sort_by(|x, y| y.total_cmp(x));
            for k in 0..3 {
                // The trigonometric solution loses ~sqrt(eps) on repeated eigenvalues.
                assert!(
                    (e.values[k] - want[k]).abs() < 1e-7 * want[0].max(1.0),
                    "{e:?} vs {want:?}"
                );
                let v = e.vectors[k];
                assert!((v.length() - 1.0).abs() < 1e-9);
                let res = (a * v - v * e.values[k]).length();
                assert!(res < 1e-6 * want[0].max(1.0), "residual {res} case {case}");
            }
            // nalgebra's iterative solver agrees.
            let m = nalgebra::Matrix3::from_fn(|r, c| a.col(c)[r]);
            let mut nv: Vec<f64> = m.symmetric_eigenvalues().iter().copied().collect();
            nv.sort_by(|x, y| y.total_cmp(x));
            for k in 0..3 {
                assert!((nv[k] - want[k]).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn covariance_of_axis_aligned_box_corners() {
        let pts: Vec<Vec3> = (0..8)
            .map(|i| {
                Vec3::new(
                    (i & 1) as f32 * 2.0,
                    ((i >> 1) & 1) as f32,
                    ((i >> 2) & 1) as f32 * 4.0,
                )
            })
            .collect();
        let (c, m) = covariance(&pts, 0..8).unwrap();
        assert!((m - DVec3::new(1.0, 0.5, 2.0)).length() < 1e-12);
        assert!((c.x_axis.x - 1.0).abs() < 1e-12);
        assert!((c.y_axis.y - 0.25).abs() < 1e-12);
        assert!((c.z_axis.z - 4.0).abs() < 1e-12);
        assert!(c.y_axis.x.abs() < 1e-12);
    }
}
