//! Normals and eigen features from k-NN principal component analysis.
//!
//! For each point the covariance of its k nearest neighbours (the point itself included, as
//! Open3D does) is decomposed in f64: the normal is the eigenvector of the smallest
//! eigenvalue, and the eigenvalues l1 >= l2 >= l3 give the shape features of docs/method.md
//! Stage 3.1 (linearity, planarity, sphericity) that the wood/leaf stage reuses.
//!
//! PCA leaves the sign of a normal open. It is fixed towards a viewpoint (the sensor) when one
//! is known, else by propagation over the k-NN graph (Hoppe et al. 1992): a minimum-spanning-
//! tree walk with edge weight 1 - |n_i · n_j| from a seed oriented upward, flipping each
//! newly reached normal to agree with the one it was reached from (see `orient.rs`).

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::index::Neighbour;
use super::orient::{GRAPH_K, propagate};
use super::pca::{covariance, symmetric_eigen3};
use super::{GeomError, PointIndex};
use crate::progress::{Progress, SubProgress};

/// How the sign of each normal is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum NormalOrientation {
    /// n · (viewpoint - p) >= 0: towards one sensor position (metres, cloud frame).
    TowardsViewpoint(Vec3),
    /// n · up >= 0 for every point independently (fast; right for terrain and crowns seen
    /// from above, arbitrary on vertical stems).
    Up(Vec3),
    /// Consistent orientation propagated over the k-NN graph; each connected component is
    /// seeded at its point whose normal is most parallel to `up`, oriented along `up`.
    Propagate { up: Vec3 },
    /// Leave the sign as PCA returns it.
    None,
}

/// Parameters of [`estimate_normals`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct NormalParams {
    /// Neighbours per point, the point itself included. Default 20: docs/method.md Stage 3.1 uses
    /// k = 20 for the eigen features, and Open3D's benchmark uses KNN 20 for normals.
    pub k: usize,
    /// Sign convention. Default: propagation seeded along +Z (up in the LiDAR frame).
    pub orientation: NormalOrientation,
}

impl Default for NormalParams {
    fn default() -> Self {
        Self {
            k: 20,
            orientation: NormalOrientation::Propagate { up: Vec3::Z },
        }
    }
}

/// Normals and covariance eigenvalues per point.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Normals {
    /// Unit normals. Points with fewer than 3 neighbours get +Z.
    pub normals: Vec<Vec3>,
    /// Covariance eigenvalues l1 >= l2 >= l3 >= 0 (m²) of each neighbourhood.
    pub eigenvalues: Vec<[f32; 3]>,
}

impl Normals {
    /// The eigen features of every point, from the stored eigenvalues.
    pub fn features(&self) -> Vec<EigenFeatures> {
        self.eigenvalues
            .par_iter()
            .map(|&l| EigenFeatures::from_eigenvalues(l))
            .collect()
    }
}

/// Shape features of a neighbourhood (docs/method.md Stage 3.1), each in [0, 1].
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct EigenFeatures {
    /// (l1 - l2) / l1: 1 on a line (stems, branches).
    pub linearity: f32,
    /// (l2 - l3) / l1: 1 on a plane (ground, bark patches).
    pub planarity: f32,
    /// l3 / l1: 1 for an isotropic blob (foliage).
    pub sphericity: f32,
}

impl EigenFeatures {
    /// Features from eigenvalues l1 >= l2 >= l3 >= 0. A neighbourhood with l1 = 0
    /// (coincident points) has no shape: all three features are 0.
    pub fn from_eigenvalues(l: [f32; 3]) -> Self {
        let l1 = l[0];
        if l1.is_nan() || l1 <= 0.0 {
            return Self::default();
        }
        let l2 = l[1].clamp(0.0, l1);
        let l3 = l[2].clamp(0.0, l2);
        Self {
            linearity: (l1 - l2) / l1,
            planarity: (l2 - l3) / l1,
            sphericity: l3 / l1,
        }
    }
}

/// Eigen features of every point from its `k` nearest neighbours (self included); k = 20 in
/// docs/method.md Stage 3.1. Builds its own index.
pub fn eigen_features(
    points: &[Vec3],
    k: usize,
    progress: &dyn Progress,
) -> Result<Vec<EigenFeatures>, GeomError> {
    check_k(k)?;
    let index = PointIndex::new(points)?;
    index.map_knn(points, k, &SubProgress::new(progress, 0.1, 0.9), |_, nb| {
        EigenFeatures::from_eigenvalues(pca_at(points, nb).1)
    })
}

/// Estimates normals and eigenvalues, building a spatial index over `points` first.
pub fn estimate_normals(
    points: &[Vec3],
    params: &NormalParams,
    progress: &dyn Progress,
) -> Result<Normals, GeomError> {
    PointIndex::build_then(points, progress, |index, rest| {
        estimate_normals_with_index(points, index, params, rest)
    })
}

/// As [`estimate_normals`], with a prebuilt index over exactly `points`.
pub fn estimate_normals_with_index(
    points: &[Vec3],
    index: &PointIndex,
    params: &NormalParams,
    progress: &dyn Progress,
) -> Result<Normals, GeomError> {
    check_k(params.k)?;
    GeomError::check_len("index vs points", index.len(), points.len())?;
    let k = params.k;
    match params.orientation {
        NormalOrientation::Propagate { up } => {
            if !up.is_finite() || up.length_squared() == 0.0 {
                return Err(GeomError::InvalidParameter(
                    "up must be a non-zero vector".into(),
                ));
            }
            let pass = SubProgress::new(progress, 0.0, 0.8);
            let recs: Vec<(Vec3, [f32; 3], [u32; GRAPH_K])> =
                index.map_knn(points, k.max(GRAPH_K + 1), &pass, |i, nb| {
                    let (n, l) = pca_at(points, &nb[..k.min(nb.len())]);
                    let mut g = [u32::MAX; GRAPH_K];
                    for (slot, m) in g
                        .iter_mut()
                        .zip(nb.iter().filter(|m| m.index as usize != i))
                    {
                        *slot = m.index;
                    }
                    (n, l, g)
                })?;
            let mut normals: Vec<Vec3> = recs.iter().map(|r| r.0).collect();
            let eigenvalues = recs.iter().map(|r| r.1).collect();
            let graph: Vec<[u32; GRAPH_K]> = recs.into_iter().map(|r| r.2).collect();
            propagate(
                &mut normals,
                &graph,
                up.normalize(),
                &SubProgress::new(progress, 0.8, 0.2),
            )?;
            Ok(Normals {
                normals,
                eigenvalues,
            })
        }
        orientation => {
            let recs: Vec<(Vec3, [f32; 3])> = index.map_knn(points, k, progress, |i, nb| {
                let (n, l) = pca_at(points, nb);
                let flip = match orientation {
                    NormalOrientation::TowardsViewpoint(v) => n.dot(v - points[i]) < 0.0,
                    NormalOrientation::Up(u) => n.dot(u) < 0.0,
                    _ => false,
                };
                (if flip { -n } else { n }, l)
            })?;
            let (normals, eigenvalues) = recs.into_iter().unzip();
            Ok(Normals {
                normals,
                eigenvalues,
            })
        }
    }
}

fn check_k(k: usize) -> Result<(), GeomError> {
    if k < 3 {
        return Err(GeomError::InvalidParameter(format!(
            "PCA needs k >= 3 neighbours, got {k}"
        )));
    }
    Ok(())
}

/// Normal and eigenvalues (descending, m²) of one neighbourhood.
fn pca_at(points: &[Vec3], nb: &[Neighbour]) -> (Vec3, [f32; 3]) {
    if nb.len() < 3 {
        return (Vec3::Z, [0.0; 3]);
    }
    let Some((cov, _)) = covariance(points, nb.iter().map(|m| m.index as usize)) else {
        return (Vec3::Z, [0.0; 3]);
    };
    let e = symmetric_eigen3(cov);
    let n = e.vectors[2].as_vec3().normalize_or(Vec3::Z);
    (n, e.values.map(|v| v.max(0.0) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::{Cancelled, NoProgress};
    use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

    fn tilted_plane(rng: &mut ChaCha8Rng) -> (Vec<Vec3>, Vec3) {
        let normal = Vec3::new(0.2, -0.1, 1.0).normalize();
        let e1 = normal.any_orthonormal_vector();
        let e2 = normal.cross(e1);
        let pts = (0..4000)
            .map(|_| e1 * rng.random_range(-1.0..1.0) + e2 * rng.random_range(-1.0..1.0))
            .collect();
        (pts, normal)
    }

    fn cylinder(rng: &mut ChaCha8Rng) -> Vec<Vec3> {
        (0..6000)
            .map(|_| {
                let t = rng.random_range(0.0..std::f32::consts::TAU);
                Vec3::new(
                    1.0 + 0.2 * t.cos(),
                    -2.0 + 0.2 * t.sin(),
                    rng.random_range(0.0..2.0),
                )
            })
            .collect()
    }

    #[test]
    fn plane_normals_are_exact_and_point_up() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (pts, normal) = tilted_plane(&mut rng);
        for orientation in [
            NormalOrientation::Propagate { up: Vec3::Z },
            NormalOrientation::Up(Vec3::Z),
            NormalOrientation::TowardsViewpoint(Vec3::new(0.0, 0.0, 10.0)),
        ] {
            let params = NormalParams { k: 20, orientation };
            let out = estimate_normals(&pts, &params, &NoProgress).unwrap();
            for (n, l) in out.normals.iter().zip(&out.eigenvalues) {
                assert!(n.dot(normal) > 0.9999, "{n} vs {normal} ({orientation:?})");
                assert!(l[2] < 1e-10 && l[0] >= l[1] && l[1] >= l[2]);
            }
        }
    }

    #[test]
    fn cylinder_normals_are_radial_and_consistent() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let pts = cylinder(&mut rng);
        let radial = |p: Vec3| Vec3::new(p.x - 1.0, p.y + 2.0, 0.0).normalize();
        let params = NormalParams::default();
        let out = estimate_normals(&pts, &params, &NoProgress).unwrap();
        let signs: Vec<f32> = pts
            .iter()
            .zip(&out.normals)
            .map(|(p, n)| n.dot(radial(*p)))
            .collect();
        assert!(signs.iter().all(|s| s.abs() > 0.99), "normals not radial");
        let outward = signs.iter().filter(|&&s| s > 0.0).count();
        assert!(
            outward == 0 || outward == pts.len(),
            "{outward} of {} outward",
            pts.len()
        );

        // Towards a viewpoint on the axis: every normal points inward.
        let params = NormalParams {
            k: 20,
            orientation: NormalOrientation::TowardsViewpoint(Vec3::new(1.0, -2.0, 1.0)),
        };
        let out = estimate_normals(&pts, &params, &NoProgress).unwrap();
        assert!(
            pts.iter()
                .zip(&out.normals)
                .all(|(p, n)| n.dot(radial(*p)) < -0.99)
        );
    }

    #[test]
    fn eigen_features_separate_line_plane_and_blob() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let line: Vec<Vec3> = (0..500)
            .map(|i| Vec3::new(i as f32 * 0.01, 0.0005 * rng.random::<f32>(), 0.0))
            .collect();
        let (plane, _) = tilted_plane(&mut rng);
        let blob: Vec<Vec3> = (0..3000)
            .map(|_| {
                Vec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
            })
            .collect();
        let mean = |f: &[EigenFeatures], g: fn(&EigenFeatures) -> f32| {
            f.iter().map(g).sum::<f32>() / f.len() as f32
        };
        let fl = eigen_features(&line, 20, &NoProgress).unwrap();
        assert!(mean(&fl, |f| f.linearity) > 0.99);
        let fp = eigen_features(&plane, 20, &NoProgress).unwrap();
        assert!(
            mean(&fp, |f| f.planarity) > 0.6,
            "{}",
            mean(&fp, |f| f.planarity)
        );
        assert!(mean(&fp, |f| f.sphericity) < 1e-4);
        let fb = eigen_features(&blob, 20, &NoProgress).unwrap();
        assert!(
            mean(&fb, |f| f.sphericity) > 0.2,
            "{}",
            mean(&fb, |f| f.sphericity)
        );
        assert!(mean(&fb, |f| f.sphericity) > 10.0 * mean(&fp, |f| f.sphericity));
        for f in fl.iter().chain(&fp).chain(&fb) {
            let s = f.linearity + f.planarity + f.sphericity;
            assert!((s - 1.0).abs() < 1e-5, "features sum to 1");
        }
    }

    #[test]
    fn normals_stop_on_cancel() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let pts = cylinder(&mut rng);
        let err = estimate_normals(&pts, &NormalParams::default(), &Cancelled).unwrap_err();
        assert_eq!(err, GeomError::Cancelled);
    }
}
