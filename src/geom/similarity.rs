//! Closed-form least-squares similarity between point pairs (docs/method.md Stage 1.1, Umeyama
//! 1991): find s, R, t minimising sum_i w_i |s R x_i + t - y_i|^2.
//!
//! The rotation comes from Horn's unit-quaternion method (the top eigenvector of a 4×4
//! symmetric matrix), which always yields a proper rotation and needs no SVD sign fix; it
//! is the same optimum as Umeyama's. Scale and translation follow Umeyama:
//! s = sum w (y'·R x') / sum w |x'|^2, t = mean_y - s R mean_x (primes: centred).

use glam::{DMat3, DQuat, DVec3, Vec3};
use serde::{Deserialize, Serialize};

use super::GeomError;
use super::linalg::top_eigenvector4;
use super::pca::symmetric_eigen3;

/// A similarity transform x' = scale * rotation * x + translation (7 DoF).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    /// Scale factor (> 0), dimensionless.
    pub scale: f64,
    /// Proper rotation matrix.
    pub rotation: DMat3,
    /// Translation in the destination frame's units (metres for the LiDAR frame).
    pub translation: DVec3,
}

impl Default for Similarity {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Similarity {
    /// The identity transform.
    pub const IDENTITY: Self = Self {
        scale: 1.0,
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// Applies the transform to a point.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.rotation * p * self.scale + self.translation
    }

    /// Applies the transform to an f32 point (computed in f64).
    pub fn apply_f32(&self, p: Vec3) -> Vec3 {
        self.apply(p.as_dvec3()).as_vec3()
    }

    /// The transform that applies `self` first, then `next`.
    pub fn then(&self, next: &Similarity) -> Similarity {
        Similarity {
            scale: next.scale * self.scale,
            rotation: next.rotation * self.rotation,
            translation: next.apply(self.translation),
        }
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Similarity {
        let rt = self.rotation.transpose();
        let inv_s = 1.0 / self.scale;
        Similarity {
            scale: inv_s,
            rotation: rt,
            translation: -(rt * self.translation) * inv_s,
        }
    }

    /// Rotation angle in degrees (for reports and tolerances).
    pub fn rotation_angle_deg(&self) -> f64 {
        DQuat::from_mat3(&self.rotation)
            .angle_between(DQuat::IDENTITY)
            .to_degrees()
    }
}

/// A fitted similarity with its per-pair residuals.
#[derive(Debug, Clone, PartialEq)]
pub struct SimilarityFit {
    pub transform: Similarity,
    /// |s R x_i + t - y_i| per pair, destination units (metres).
    pub residuals: Vec<f64>,
    /// Root mean square of the residuals.
    pub rmse: f64,
}

/// Least-squares similarity mapping `src[i]` onto `dst[i]` (scale fixed to 1 when
/// `with_scale` is false), with per-pair residuals.
///
/// Errors: [`GeomError::TooFewPairs`] below 3 pairs, [`GeomError::NonFinite`],
/// [`GeomError::Degenerate`] for coincident points, [`GeomError::Collinear`] for pairs on
/// one line (rotation about it undetermined).
pub fn similarity_from_pairs(
    src: &[DVec3],
    dst: &[DVec3],
    with_scale: bool,
) -> Result<SimilarityFit, GeomError> {
    let transform = weighted_similarity(src, dst, None, with_scale)?;
    let residuals: Vec<f64> = src
        .iter()
        .zip(dst)
        .map(|(x, y)| (transform.apply(*x) - *y).length())
        .collect();
    let rmse = (residuals.iter().map(|r| r * r).sum::<f64>() / residuals.len() as f64).sqrt();
    Ok(SimilarityFit {
        transform,
        residuals,
        rmse,
    })
}

/// Weighted least-squares similarity (weights >= 0; `None` = all 1).
pub fn weighted_similarity(
    src: &[DVec3],
    dst: &[DVec3],
    weights: Option<&[f64]>,
    with_scale: bool,
) -> Result<Similarity, GeomError> {
    GeomError::check_len("source vs destination points", src.len(), dst.len())?;
    if let Some(w) = weights {
        GeomError::check_len("weights vs pairs", w.len(), src.len())?;
    }
    fit_similarity(
        src.len(),
        |i| (src[i], dst[i], weights.map_or(1.0, |w| w[i])),
        with_scale,
    )
}

/// Core of the similarity fit over `n` pairs given by `pair(i) = (x, y, w)`.
pub(crate) fn fit_similarity(
    n: usize,
    pair: impl Fn(usize) -> (DVec3, DVec3, f64),
    with_scale: bool,
) -> Result<Similarity, GeomError> {
    let mut used = 0usize;
    let (mut sw, mut mx, mut my) = (0.0f64, DVec3::ZERO, DVec3::ZERO);
    for i in 0..n {
        let (x, y, w) = pair(i);
        if !(x.is_finite() && y.is_finite() && w.is_finite()) || w < 0.0 {
            return Err(GeomError::NonFinite("point pairs or weights"));
        }
        if w > 0.0 {
            used += 1;
            sw += w;
            mx += x * w;
            my += y * w;
        }
    }
    if used < 3 {
        return Err(GeomError::TooFewPairs(used));
    }
    mx /= sw;
    my /= sw;
    // Centred second moments: cxx (source spread), cyy (destination spread), s_xy[a][b].
    let (mut cxx, mut cyy, mut sxy) = (DMat3::ZERO, DMat3::ZERO, [[0.0f64; 3]; 3]);
    for i in 0..n {
        let (x, y, w) = pair(i);
        if w == 0.0 {
            continue;
        }
        let (a, b) = (x - mx, y - my);
        cxx += outer(a, a * w);
        cyy += outer(b, b * w);
        for (r, row) in sxy.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v += w * a[r] * b[c];
            }
        }
    }
    check_spread(cxx * (1.0 / sw), mx)?;
    check_spread(cyy * (1.0 / sw), my)?;

    let [[sxx, sxy_, sxz], [syx, syy, syz], [szx, szy, szz]] = sxy;
    let (sxy, sxz, syx, syz, szx, szy) = (sxy_, sxz, syx, syz, szx, szy);
    let nmat = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let q = top_eigenvector4(nmat);
    let quat = DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
    let rotation = DMat3::from_quat(quat);

    let scale = if with_scale {
        let mut num = 0.0;
        for i in 0..n {
            let (x, y, w) = pair(i);
            if w > 0.0 {
                num += w * (y - my).dot(rotation * (x - mx));
            }
        }
        let s = num / (cxx.x_axis.x + cxx.y_axis.y + cxx.z_axis.z);
        if !(s > 0.0 && s.is_finite()) {
            return Err(GeomError::Degenerate("the pairs give a non-positive scale"));
        }
        s
    } else {
        1.0
    };
    Ok(Similarity {
        scale,
        rotation,
        translation: my - rotation * mx * scale,
    })
}

/// Errors for coincident or collinear point sets (relative to their own size).
fn check_spread(cov: DMat3, mean: DVec3) -> Result<(), GeomError> {
    let e = symmetric_eigen3(cov).values;
    let size2 = mean.length_squared().max(1e-30);
    if e[0].is_nan() || e[0] <= 1e-20 * size2 {
        return Err(GeomError::Degenerate("all points coincide"));
    }
    if e[1] <= 1e-10 * e[0] {
        return Err(GeomError::Collinear);
    }
    Ok(())
}

fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

    /// A rotation from a normalised quaternion of four uniform draws in [-1, 1) (x, y, z, w).
    pub(in crate::geom) fn random_rotation(rng: &mut ChaCha8Rng) -> DMat3 {
        let q = DQuat::from_xyzw(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        DMat3::from_quat(q)
    }

    fn random_similarity(rng: &mut ChaCha8Rng) -> Similarity {
        let rotation = random_rotation(rng);
        Similarity {
            scale: rng.random_range(0.2..5.0),
            rotation,
            translation: DVec3::new(
                rng.random_range(-100.0..100.0),
                rng.random_range(-100.0..100.0),
                rng.random_range(-10.0..10.0),
            ),
        }
    }

    #[test]
    fn recovers_known_similarity_exactly() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for case in 0..200 {
            let truth = random_similarity(&mut rng);
            let n = 3 + case % 10;
            let src: Vec<DVec3> = (0..n)
                .map(|_| {
                    DVec3::new(
                        rng.random_range(-20.0..20.0),
                        rng.random_range(-20.0..20.0),
                        rng.random_range(-5.0..5.0),
                    )
                })
                .collect();
            let dst: Vec<DVec3> = src.iter().map(|p| truth.apply(*p)).collect();
            let fit = similarity_from_pairs(&src, &dst, true).unwrap();
            let t = fit.transform;
            assert!((t.scale / truth.scale - 1.0).abs() < 1e-9, "scale");
            let dr = (t.rotation * truth.rotation.transpose()).to_cols_array();
            let id = DMat3::IDENTITY.to_cols_array();
            assert!(
                dr.iter().zip(id).all(|(a, b)| (a - b).abs() < 1e-9),
                "rotation"
            );
            assert!(
                (t.translation - truth.translation).length() < 1e-7,
                "translation"
            );
            assert!(fit.rmse < 1e-7 && fit.residuals.len() == n);
        }
    }

    #[test]
    fn rigid_fit_and_residuals_with_noise() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut truth = random_similarity(&mut rng);
        truth.scale = 1.0;
        let src: Vec<DVec3> = (0..50)
            .map(|_| DVec3::new(rng.random(), rng.random(), rng.random()) * 10.0)
            .collect();
        let mut dst: Vec<DVec3> = src.iter().map(|p| truth.apply(*p)).collect();
        dst[3] += DVec3::new(1.0, 0.0, 0.0); // one bad control point
        let fit = similarity_from_pairs(&src, &dst, false).unwrap();
        assert_eq!(fit.transform.scale, 1.0);
        let worst = fit
            .residuals
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(i, _)| i);
        assert_eq!(worst, Some(3), "the bad pair has the largest residual");
    }

    #[test]
    fn inverse_and_composition() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let a = random_similarity(&mut rng);
        let b = random_similarity(&mut rng);
        let p = DVec3::new(1.0, -2.0, 3.0);
        assert!((a.then(&b).apply(p) - b.apply(a.apply(p))).length() < 1e-9);
        assert!((a.inverse().apply(a.apply(p)) - p).length() < 1e-9);
    }

    #[test]
    fn errors_on_bad_pairs() {
        let p = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
        let two = [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0)];
        assert_eq!(
            similarity_from_pairs(&two, &two, true).unwrap_err(),
            GeomError::TooFewPairs(2)
        );
        let same = [p(1.0, 2.0, 3.0); 4];
        let other = [
            p(0.0, 0.0, 0.0),
            p(1.0, 0.0, 0.0),
            p(0.0, 1.0, 0.0),
            p(0.0, 0.0, 1.0),
        ];
        assert!(matches!(
            similarity_from_pairs(&same, &other, true),
            Err(GeomError::Degenerate(_))
        ));
        assert!(matches!(
            similarity_from_pairs(&other, &same, true),
            Err(GeomError::Degenerate(_))
        ));
        let line = [
            p(0.0, 0.0, 0.0),
            p(1.0, 1.0, 1.0),
            p(2.0, 2.0, 2.0),
            p(5.0, 5.0, 5.0),
        ];
        assert_eq!(
            similarity_from_pairs(&line, &line, true).unwrap_err(),
            GeomError::Collinear
        );
        let mut nan = other;
        nan[2].y = f64::NAN;
        assert!(matches!(
            similarity_from_pairs(&nan, &other, true),
            Err(GeomError::NonFinite(_))
        ));
        assert!(matches!(
            similarity_from_pairs(&other, &two, true),
            Err(GeomError::LengthMismatch { .. })
        ));
    }
}
