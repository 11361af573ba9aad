//! Where a stem stands: the intersection of its axis with the ground, from a plane fitted to
//! the ground points around it or, failing that, from the DTM.

use glam::Vec3;

use super::ground::Dtm;
use super::stems::{Buckets, Stem, StemParams};

/// Where the line `origin + t axis` meets the DTM (fixed-point iteration on the height).
pub(crate) fn base_on_dtm(origin: Vec3, axis: Vec3, dtm: &Dtm) -> Vec3 {
    let mut p = origin;
    for _ in 0..8 {
        let g = dtm.height_at(p.x, p.y);
        let t = (g - origin.z) / axis.z.max(1e-3);
        p = origin + axis * t;
    }
    Vec3::new(p.x, p.y, dtm.height_at(p.x, p.y))
}

/// Ground points further than this from the DTM (metres) are left out of the local plane:
/// stones, litter, low shrubs and root collars inside the ground filter's class threshold
/// (0.5 m) would lift it. 0.06 m is six times the range noise (docs/method.md: sigma 1 cm) and
/// above the DTM's own error on the generated stands (at most 2.3 cm at a stem).
pub(crate) const LOCAL_GROUND_BAND_M: f32 = 0.06;

/// The stem's base on a plane fitted to the ground points in an annulus around it (from the
/// stem's surface + `axis_margin_m` out to 1.5 m), rather than on the DTM raster: the raster
/// cell under a stem holds no ground of its own and its neighbours' means include the
/// lowest centimetres of the stem (the ground filter keeps points up to 0.1 m above the
/// cloth). The fit is least squares, repeated once without points more than 3 median
/// absolute residuals off. `None` (keep the DTM base) with fewer than 10 ground points.
pub(crate) fn base_on_local_ground(
    points: &[Vec3],
    ground: &Buckets,
    dtm: &Dtm,
    stem: &Stem,
    params: &StemParams,
) -> Option<Vec3> {
    let c = stem.base;
    let (inner, outer) = (stem.radius_estimate + params.axis_margin_m, 1.5f32);
    let mut local: Vec<Vec3> = ground
        .near(c.truncate(), outer)
        .into_iter()
        .map(|i| points[i as usize])
        .filter(|p| (p.z - dtm.height_at(p.x, p.y)).abs() <= LOCAL_GROUND_BAND_M)
        .map(|p| p - c)
        .filter(|d| (inner..=outer).contains(&d.truncate().length()))
        .collect();
    let mut plane = None;
    for _ in 0..2 {
        if local.len() < 10 {
            return None;
        }
        // z = a + b x + c y, normal equations in f64.
        let rows: Vec<[f64; 2]> = local.iter().map(|d| [d.x as f64, d.y as f64]).collect();
        let z: Vec<f64> = local.iter().map(|d| d.z as f64).collect();
        let p = fit_plane(&rows, &z)?;
        let res: Vec<f64> = rows
            .iter()
            .zip(&z)
            .map(|(r, z)| (z - (p[0] + p[1] * r[0] + p[2] * r[1])).abs())
            .collect();
        let mut sorted = res.clone();
        sorted.sort_by(f64::total_cmp);
        let mad = sorted[sorted.len() / 2].max(1e-3);
        local = local
            .into_iter()
            .zip(&res)
            .filter(|(_, r)| **r <= 3.0 * mad)
            .map(|(d, _)| d)
            .collect();
        plane = Some(p);
    }
    let p = plane?;
    // Intersect the axis with the plane: c + t a, height p(x, y) relative to c.
    let a = stem.axis;
    let denom = a.z as f64 - p[1] * a.x as f64 - p[2] * a.y as f64;
    if denom.abs() < 0.1 {
        return None;
    }
    let t = (p[0] / denom) as f32;
    Some(c + a * t)
}

/// Least-squares plane z = p0 + p1 x + p2 y.
fn fit_plane(xy: &[[f64; 2]], z: &[f64]) -> Option<[f64; 3]> {
    let mut m = glam::DMat3::ZERO;
    let mut b = glam::DVec3::ZERO;
    for (r, z) in xy.iter().zip(z) {
        let v = glam::DVec3::new(1.0, r[0], r[1]);
        m += glam::DMat3::from_cols(v * v.x, v * v.y, v * v.z);
        b += v * *z;
    }
    if m.determinant().abs() < 1e-9 {
        return None;
    }
    Some((m.inverse() * b).to_array())
}
