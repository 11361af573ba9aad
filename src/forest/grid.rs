//! Uniform-grid helpers of the coarse wood/leaf features: voxel centroids of a cloud and the
//! covariance of every centroid's neighbours within a radius, both on all cores.
//!
//! Why not the k-d tree of `geom`: the coarse scales ask one radius query per voxel with a
//! few hundred neighbours each and need only their moments. Bucketing the centroids in cells
//! of edge = radius and scanning those of the 27 cells around each query cell that the radius
//! reaches, with the moments summed on the fly, needs no per-query allocation or sorting and visits the points of a cell in
//! memory order.

use std::collections::HashMap;

use glam::{DMat3, DVec3, Vec3};
use rayon::prelude::*;

use super::ForestError;
use crate::progress::Progress;

/// Integer cell of `p` on a grid of edge `edge`, metres.
fn cell(p: Vec3, edge: f32) -> [i32; 3] {
    [
        (p.x / edge).floor() as i32,
        (p.y / edge).floor() as i32,
        (p.z / edge).floor() as i32,
    ]
}

/// Occupied cells: (cell, start, end) with start..end the range of its points in the sorted
/// index list.
type Cells = Vec<([i32; 3], usize, usize)>;

/// Point indices sorted by cell (ties by index) and the cells with their ranges in it.
fn bucket(points: &[Vec3], edge: f32) -> (Vec<u32>, Cells) {
    let mut keyed: Vec<([i32; 3], u32)> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| (cell(*p, edge), i as u32))
        .collect();
    keyed.par_sort_unstable();
    let mut cells = Vec::new();
    let mut start = 0;
    for i in 1..=keyed.len() {
        if i == keyed.len() || keyed[i].0 != keyed[start].0 {
            cells.push((keyed[start].0, start, i));
            start = i;
        }
    }
    (keyed.into_iter().map(|(_, i)| i).collect(), cells)
}

/// Centroid of every occupied voxel of edge `voxel` (metres) and the voxel of every point.
/// Voxels are numbered in cell order, points summed in index order, so the result does not
/// depend on the thread count.
pub fn voxel_centroids(points: &[Vec3], voxel: f32) -> (Vec<u32>, Vec<Vec3>) {
    let (order, cells) = bucket(points, voxel);
    let centres: Vec<Vec3> = cells
        .par_iter()
        .map(|&(_, s, e)| {
            let mut sum = DVec3::ZERO;
            for &i in &order[s..e] {
                sum += points[i as usize].as_dvec3();
            }
            (sum / (e - s).max(1) as f64).as_vec3()
        })
        .collect();
    let mut member = vec![0u32; points.len()];
    for (v, &(_, s, e)) in cells.iter().enumerate() {
        for &i in &order[s..e] {
            member[i as usize] = v as u32;
        }
    }
    (member, centres)
}

/// For every point of `points`: `f(n, covariance)` of the points within `radius` metres of
/// it (itself included; the covariance is the population one, about their mean). Cells of
/// the grid are processed in parallel; reports progress and stops on cancel.
pub fn map_radius_covariance<R: Clone + Default + Send>(
    points: &[Vec3],
    radius: f32,
    progress: &dyn Progress,
    f: impl Fn(usize, DMat3) -> R + Sync,
) -> Result<Vec<R>, ForestError> {
    if !(radius > 0.0 && radius.is_finite()) {
        return Err(ForestError::Params(format!(
            "radius search needs a finite radius > 0 (got {radius} m)"
        )));
    }
    let (order, cells) = bucket(points, radius);
    let lookup: HashMap<[i32; 3], usize> = cells
        .iter()
        .enumerate()
        .map(|(c, &(k, _, _))| (k, c))
        .collect();
    let r2 = radius * radius;
    let done = std::sync::atomic::AtomicUsize::new(0);
    let per_cell: Vec<Vec<(u32, R)>> = cells
        .par_iter()
        .map(|&(key, s, e)| {
            if progress.is_cancelled() {
                return Vec::new();
            }
            // Neighbour cells: box min corner and range in `order`.
            let mut ranges: Vec<(Vec3, usize, usize)> = Vec::with_capacity(27);
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let k = [key[0] + dx, key[1] + dy, key[2] + dz];
                        if let Some(&c) = lookup.get(&k) {
                            let lo = Vec3::new(k[0] as f32, k[1] as f32, k[2] as f32) * radius;
                            ranges.push((lo, cells[c].1, cells[c].2));
                        }
                    }
                }
            }
            let out: Vec<(u32, R)> = order[s..e]
                .iter()
                .map(|&q| {
                    let p = points[q as usize];
                    // Moments about the query point (small numbers, no cancellation).
                    let (mut n, mut m1, mut m2) = (0usize, [0.0f64; 3], [0.0f64; 6]);
                    for &(lo, a, b) in &ranges {
                        // A cell whose box lies beyond the radius (with a margin for
                        // rounding) holds no neighbour: about half of the 27 for a query.
                        let gap = (lo - p).max(p - (lo + Vec3::splat(radius))).max(Vec3::ZERO);
                        if gap.length_squared() > r2 * 1.0001 {
                            continue;
                        }
                        for &j in &order[a..b] {
                            let d = points[j as usize] - p;
                            if d.length_squared() <= r2 {
                                let (x, y, z) = (d.x as f64, d.y as f64, d.z as f64);
                                n += 1;
                                m1[0] += x;
                                m1[1] += y;
                                m1[2] += z;
                                m2[0] += x * x;
                                m2[1] += x * y;
                                m2[2] += x * z;
                                m2[3] += y * y;
                                m2[4] += y * z;
                                m2[5] += z * z;
                            }
                        }
                    }
                    let k = n.max(1) as f64;
                    let m = DVec3::new(m1[0] / k, m1[1] / k, m1[2] / k);
                    let (xx, xy, xz) = (
                        m2[0] / k - m.x * m.x,
                        m2[1] / k - m.x * m.y,
                        m2[2] / k - m.x * m.z,
                    );
                    let (yy, yz, zz) = (
                        m2[3] / k - m.y * m.y,
                        m2[4] / k - m.y * m.z,
                        m2[5] / k - m.z * m.z,
                    );
                    let cov = DMat3::from_cols(
                        DVec3::new(xx, xy, xz),
                        DVec3::new(xy, yy, yz),
                        DVec3::new(xz, yz, zz),
                    );
                    (q, f(n, cov))
                })
                .collect();
            let d = done.fetch_add(e - s, std::sync::atomic::Ordering::Relaxed) + (e - s);
            progress.set(d as f64 / points.len().max(1) as f64);
            out
        })
        .collect();
    if progress.is_cancelled() {
        return Err(ForestError::Cancelled);
    }
    let mut result = vec![R::default(); points.len()];
    for (q, r) in per_cell.into_iter().flatten() {
        result[q as usize] = r;
    }
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{PointIndex, covariance};
    use crate::progress::NoProgress;

    #[test]
    fn radius_covariance_matches_the_kd_tree() {
        // A helix and a plane: lines, planes and empty cells.
        let mut pts: Vec<Vec3> = (0..2000)
            .map(|i| {
                let t = i as f32 * 0.01;
                Vec3::new(t.cos() * 0.3, t.sin() * 0.3, t * 0.05)
            })
            .collect();
        pts.extend(
            (0..1600).map(|i| Vec3::new((i % 40) as f32 * 0.02, (i / 40) as f32 * 0.02, -1.0)),
        );
        // Off the plane's 2 cm lattice, so no distance ties the radius.
        let r = 0.105;
        let ours = map_radius_covariance(&pts, r, &NoProgress, |n, c| (n, c)).expect("grid");
        let index = PointIndex::new(&pts).expect("index");
        for (i, p) in pts.iter().enumerate().step_by(37) {
            let nb = index.within(*p, r);
            let (cov, _) = covariance(&pts, nb.iter().map(|m| m.index as usize)).expect("cov");
            assert_eq!(ours[i].0, nb.len(), "point {i}");
            let diff = (ours[i].1 - cov).to_cols_array();
            assert!(diff.iter().all(|d| d.abs() < 1e-7), "point {i}: {diff:?}");
        }
    }

    #[test]
    fn voxel_centroids_average_their_points() {
        let pts = vec![
            Vec3::new(0.01, 0.01, 0.01),
            Vec3::new(0.03, 0.03, 0.03),
            Vec3::new(0.51, 0.0, 0.0),
        ];
        let (member, centres) = voxel_centroids(&pts, 0.1);
        assert_eq!(centres.len(), 2);
        assert_eq!(member[0], member[1]);
        assert_ne!(member[0], member[2]);
        assert!((centres[member[0] as usize] - Vec3::splat(0.02)).length() < 1e-6);
    }
}
