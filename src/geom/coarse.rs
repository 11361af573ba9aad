//! Automatic coarse registration of an SfM reconstruction onto a LiDAR cloud, without
//! control points (beyond the paper, which needs a person with CloudCompare).
//!
//! 1. Up: UAV cameras fly at a roughly constant height and look down, so the normal of the
//!    plane through the camera centres, signed against the mean viewing direction, is "up"
//!    in the SfM frame (the mean viewing direction alone when the centres are not planar).
//! 2. Level the SfM points so that up is +z; the LiDAR frame is assumed z-up (metres).
//! 3. Search yaw, scale and horizontal offset by matching two rasters of both clouds: a
//!    canopy-height model (highest point minus the local lowest) and the detrended terrain
//!    (local lowest point). Normalised cross-correlation on a coarse grid over every yaw and
//!    a log-spaced range of scales (from the ratio of robust horizontal and vertical
//!    extents); the best few distinct hypotheses are then refined on rasters of a third and
//!    a ninth of the coarse cell.
//! 4. The residual tilt and the vertical offset come from the terrain rasters (a robust
//!    plane through the per-cell height differences; cameras that follow a slope leave the
//!    plane of the flight, and so "up", tilted); each hypothesis carries a raster
//!    confidence (how clearly it beats the best distinct other one, and its correlation).
//!
//! The raster confidence cannot tell a right alignment from a wrong one reliably, so stage
//! `register` runs ICP and the surface refinement from every candidate and decides on how
//! well the SfM points then lie on the LiDAR cloud ([`super::register::verify_candidates`]).

use glam::{DMat3, DVec3, Vec3};
use serde::{Deserialize, Serialize};

use super::{GeomError, Similarity, symmetric_eigen3};
use crate::progress::Progress;

/// Search settings; the defaults suit plots of 10–100 m.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoarseParams {
    /// Yaw step of the coarse search, degrees (default 4°; the fine search goes to 1°).
    pub yaw_step_deg: f64,
    /// Ratio between consecutive candidate scales (default 1.04, i.e. 4 %).
    pub scale_step: f64,
    /// How far the scale search reaches beyond the extent-based estimates (default 1.35×;
    /// 1.6× let wrong hypotheses at far scales crowd the right one out of a partial scan's
    /// candidates, `register_cases partial` seed 5).
    pub scale_margin: f64,
    /// Cells across the LiDAR cloud's larger side in the coarse raster (default 24).
    pub coarse_cells: usize,
    /// Fraction of the smaller cloud's valid raster cells that must overlap the other's for
    /// a hypothesis to count (default 0.6).
    pub min_overlap: f64,
    /// Distinct hypotheses kept from the coarse search, refined and returned by
    /// [`align_candidates`] (default 6: each that stays distinct after refinement costs one ICP
    /// and the surface passes in stage `register`, most collapse into others; with 4, a
    /// partial scan's wrong hypotheses near one yaw took every place and left out the right
    /// one, `register_cases partial` seed 5).
    pub candidates: usize,
}

impl Default for CoarseParams {
    fn default() -> Self {
        Self {
            yaw_step_deg: 4.0,
            scale_step: 1.04,
            scale_margin: 1.35,
            coarse_cells: 24,
            min_overlap: 0.6,
            candidates: 6,
        }
    }
}

/// The coarse alignment found, SfM → LiDAR (local frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoarseAlignment {
    pub transform: Similarity,
    /// In [0, 1]: how clearly the best hypothesis wins (0: no match).
    pub confidence: f64,
    /// Correlation score of the best hypothesis (sum of two NCCs, up to 1.5).
    pub score: f64,
    /// Score of the best hypothesis at least 20° or 3 coarse cells away from the best.
    pub runner_up: f64,
    pub yaw_deg: f64,
    pub scale: f64,
}

impl CoarseAlignment {
    /// A start that was given, not searched: confidence 1, no scores, its own yaw (about z)
    /// and scale.
    pub fn fixed(transform: Similarity) -> Self {
        let x = transform.rotation * DVec3::X;
        Self {
            transform,
            confidence: 1.0,
            score: 0.0,
            runner_up: 0.0,
            yaw_deg: x.y.atan2(x.x).to_degrees(),
            scale: transform.scale,
        }
    }
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    let (_, x, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    *x
}

/// Up direction of the SfM frame from camera centres and viewing directions.
pub fn up_from_cameras(cameras: &[(DVec3, DVec3)]) -> Result<DVec3, GeomError> {
    if cameras.len() < 3 {
        return Err(GeomError::Degenerate(
            "fewer than 3 cameras to find the up direction",
        ));
    }
    let down: DVec3 = cameras.iter().map(|c| c.1.normalize_or_zero()).sum();
    let mean_up = (-down).normalize_or_zero();
    let centres: Vec<DVec3> = cameras.iter().map(|c| c.0).collect();
    if let Some(cov) = covariance_of(&centres) {
        let e = symmetric_eigen3(cov);
        // values sorted descending: the plane is good when the smallest is tiny.
        let planar = e.values[2] <= 0.05 * e.values[1].max(1e-300);
        let mut n = e.vectors[2].normalize_or_zero();
        if mean_up != DVec3::ZERO && n.dot(mean_up) < 0.0 {
            n = -n;
        }
        if planar && (mean_up == DVec3::ZERO || n.dot(mean_up) > 0.5) {
            return Ok(n);
        }
    }
    if mean_up == DVec3::ZERO {
        return Err(GeomError::Degenerate(
            "cameras give no consistent up direction",
        ));
    }
    Ok(mean_up)
}

/// Covariance of a set of f64 points (None for fewer than 3).
fn covariance_of(points: &[DVec3]) -> Option<DMat3> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let m = points.iter().copied().sum::<DVec3>() / n;
    let mut c = DMat3::ZERO;
    for p in points {
        let d = *p - m;
        c += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    Some(c * (1.0 / n))
}

/// Rotation taking `u` to +z (the shortest arc).
fn level(u: DVec3) -> DMat3 {
    DMat3::from_quat(glam::DQuat::from_rotation_arc(u.normalize(), DVec3::Z))
}

/// Two rasters of a cloud on a grid: canopy height and detrended terrain (NaN: empty).
struct Rasters {
    nx: usize,
    ny: usize,
    chm: Vec<f64>,
    dtm: Vec<f64>,
}

fn rasterise(
    points: impl Iterator<Item = DVec3>,
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    half: usize,
) -> Rasters {
    let mut hi = vec![f64::NAN; nx * ny];
    let mut lo = vec![f64::NAN; nx * ny];
    for p in points {
        let Some(k) = cell_index(p, x0, y0, cell, nx, ny) else {
            continue;
        };
        hi[k] = if hi[k].is_nan() { p.z } else { hi[k].max(p.z) };
        lo[k] = if lo[k].is_nan() { p.z } else { lo[k].min(p.z) };
    }
    // Local ground: lowest point within the (2h+1)² neighbourhood (separable min filter).
    let ground = min_filter(&lo, nx, ny, half);
    let chm: Vec<f64> = hi.iter().zip(&ground).map(|(h, g)| h - g).collect();
    // Detrend the terrain by its least-squares plane so only its shape counts: a planar slope
    // correlates with itself at every scale and offset, and on a steep one it drowned the
    // relief that tells them apart (`register_cases slope`: the search chose scales 8-14 %
    // off with the mean alone).
    let plane = terrain_plane(&ground, nx);
    let dtm = ground
        .iter()
        .enumerate()
        .map(|(k, g)| g - plane((k % nx) as f64, (k / nx) as f64))
        .collect();
    Rasters { nx, ny, chm, dtm }
}

/// The least-squares plane z = a + b·i + c·j through the valid cells of a raster (row-major,
/// `nx` wide), as a function of the cell's column and row; the mean where the cells are too
/// few or in a line.
fn terrain_plane(v: &[f64], nx: usize) -> impl Fn(f64, f64) -> f64 {
    let cells = v
        .iter()
        .enumerate()
        .filter(|(_, z)| !z.is_nan())
        .map(|(k, z)| ((k % nx) as f64, (k / nx) as f64, *z));
    let (n, sum) = cells
        .clone()
        .fold((0usize, 0.0), |(n, s), c| (n + 1, s + c.2));
    let mean = sum / n.max(1) as f64;
    let (gi, gj, c) = if n >= 3 {
        plane_fit(cells, (0.0, 0.0)).unwrap_or((0.0, 0.0, mean))
    } else {
        (0.0, 0.0, mean)
    };
    move |i, j| c + gi * i + gj * j
}

/// Lowest non-NaN value within `half` cells in x and y of each cell (NaN where none).
fn min_filter(v: &[f64], nx: usize, ny: usize, half: usize) -> Vec<f64> {
    let rows = min_pass(v, nx, ny, half, true);
    min_pass(&rows, nx, ny, half, false)
}

/// One pass of [`min_filter`]: the lowest non-NaN value within `half` cells of each cell along x
/// (`along_x`) or along y (NaN where none).
fn min_pass(v: &[f64], nx: usize, ny: usize, half: usize, along_x: bool) -> Vec<f64> {
    let nanmin = |a: f64, b: f64| {
        if a.is_nan() || (!b.is_nan() && b < a) {
            b
        } else {
            a
        }
    };
    let mut out = vec![f64::NAN; nx * ny];
    for j in 0..ny {
        for i in 0..nx {
            let (c, n) = if along_x { (i, nx) } else { (j, ny) };
            let mut m = f64::NAN;
            for a in c.saturating_sub(half)..(c + half + 1).min(n) {
                m = nanmin(
                    m,
                    if along_x {
                        v[j * nx + a]
                    } else {
                        v[a * nx + i]
                    },
                );
            }
            out[j * nx + i] = m;
        }
    }
    out
}

/// A view of one raster: values row-major, `ny` rows of `nx`.
#[derive(Clone, Copy)]
struct View<'a> {
    v: &'a [f64],
    nx: usize,
    ny: usize,
}

/// Normalised cross-correlation of `a` (placed at offset (ox, oy) inside `b`) over cells
/// valid in both; None when they overlap on fewer than `min_cells` cells.
fn ncc(a: View<'_>, b: View<'_>, ox: i64, oy: i64, min_cells: usize) -> Option<f64> {
    let (anx, any, bnx, bny) = (a.nx, a.ny, b.nx, b.ny);
    let (a, b) = (a.v, b.v);
    let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0usize, 0.0, 0.0, 0.0, 0.0, 0.0);
    for j in 0..any {
        let bj = j as i64 + oy;
        if bj < 0 || bj >= bny as i64 {
            continue;
        }
        for i in 0..anx {
            let bi = i as i64 + ox;
            if bi < 0 || bi >= bnx as i64 {
                continue;
            }
            let (x, y) = (a[j * anx + i], b[bj as usize * bnx + bi as usize]);
            if x.is_nan() || y.is_nan() {
                continue;
            }
            n += 1;
            sa += x;
            sb += y;
            saa += x * x;
            sbb += y * y;
            sab += x * y;
        }
    }
    if n < min_cells.max(8) {
        return None;
    }
    let nf = n as f64;
    let va = saa - sa * sa / nf;
    let vb = sbb - sb * sb / nf;
    if va <= 1e-12 || vb <= 1e-12 {
        return Some(0.0);
    }
    Some((sab - sa * sb / nf) / (va * vb).sqrt())
}

#[derive(Debug, Clone, Copy)]
struct Hypothesis {
    yaw: f64,
    scale: f64,
    /// Horizontal translation (metres) after levelling, rotating and scaling.
    t: [f64; 2],
    score: f64,
}

impl Hypothesis {
    /// Whether `self` and `other` are different hypotheses: yaws more than 20° apart, or
    /// offsets more than three coarse cells.
    fn distinct_from(&self, other: &Hypothesis, coarse_cell: f64) -> bool {
        let dyaw = ((self.yaw - other.yaw + 540.0) % 360.0 - 180.0).abs();
        let dt = ((self.t[0] - other.t[0]).powi(2) + (self.t[1] - other.t[1]).powi(2)).sqrt();
        dyaw > 20.0 || dt > 3.0 * coarse_cell
    }
}

struct Scene<'a> {
    level: &'a [DVec3],
    lidar: Rasters,
    x0: f64,
    y0: f64,
    cell: f64,
    /// Valid cells of the LiDAR rasters.
    valid: usize,
    min_overlap: f64,
    /// Half-width of the local-ground window, cells.
    half: usize,
}

impl Scene<'_> {
    /// The best hypothesis around `seed` on this raster: yaws ±4 `ystep` (degrees), scales
    /// ×`sstep`^±2, offsets within `radius` cells of the seed's.
    fn refine(&self, seed: &Hypothesis, ystep: f64, sstep: f64, radius: i64) -> Option<Hypothesis> {
        use rayon::prelude::*;
        let mut cands = Vec::new();
        for dy in -4..=4 {
            for ds in -2..=2 {
                cands.push((seed.yaw + dy as f64 * ystep, seed.scale * sstep.powi(ds)));
            }
        }
        cands
            .par_iter()
            .filter_map(|&(y, s)| self.evaluate(y, s, Some((seed.t, radius))))
            .max_by(|a, b| a.score.total_cmp(&b.score))
    }

    /// Best offset of the SfM rasters for one yaw and scale, searching offsets within
    /// `around` (metres, cells) or everywhere.
    fn evaluate(
        &self,
        yaw: f64,
        scale: f64,
        around: Option<([f64; 2], i64)>,
    ) -> Option<Hypothesis> {
        let (s, c) = yaw.to_radians().sin_cos();
        let moved: Vec<DVec3> = self
            .level
            .iter()
            .map(|p| {
                DVec3::new(
                    scale * (c * p.x - s * p.y),
                    scale * (s * p.x + c * p.y),
                    scale * p.z,
                )
            })
            .collect();
        let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
        for p in &moved {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        let anx = ((hi.x - lo.x) / self.cell).ceil().max(1.0);
        let any = ((hi.y - lo.y) / self.cell).ceil().max(1.0);
        // A reconstruction scaled to several times the LiDAR plot cannot overlap it enough.
        if anx > 3.0 * self.lidar.nx as f64 + 4.0 || any > 3.0 * self.lidar.ny as f64 + 4.0 {
            return None;
        }
        let (anx, any) = (anx as usize, any as usize);
        let a = rasterise(
            moved.iter().copied(),
            lo.x,
            lo.y,
            self.cell,
            anx,
            any,
            self.half,
        );
        let b = &self.lidar;
        // Overlap is measured against the smaller footprint: a handheld scan often reaches
        // far beyond the photographed area, or the photos beyond the walk.
        let valid_a = a.chm.iter().filter(|v| !v.is_nan()).count();
        let min_cells = (valid_a.min(self.valid) as f64 * self.min_overlap) as usize;
        let mut best: Option<Hypothesis> = None;
        let (range_x, range_y) = match around {
            Some((t, r)) => {
                let cx = ((lo.x + t[0] - self.x0) / self.cell).round() as i64;
                let cy = ((lo.y + t[1] - self.y0) / self.cell).round() as i64;
                ((cx - r)..=(cx + r), (cy - r)..=(cy + r))
            }
            None => (-(anx as i64)..=(b.nx as i64), -(any as i64)..=(b.ny as i64)),
        };
        let va = |v| View {
            v,
            nx: anx,
            ny: any,
        };
        let vb = |v| View {
            v,
            nx: b.nx,
            ny: b.ny,
        };
        for oy in range_y {
            for ox in range_x.clone() {
                let Some(s1) = ncc(va(&a.chm), vb(&b.chm), ox, oy, min_cells) else {
                    continue;
                };
                let s2 = ncc(va(&a.dtm), vb(&b.dtm), ox, oy, min_cells).unwrap_or(0.0);
                let score = s1 + 0.5 * s2;
                if best.is_none_or(|h| score > h.score) {
                    best = Some(Hypothesis {
                        yaw,
                        scale,
                        t: [
                            self.x0 + ox as f64 * self.cell - lo.x,
                            self.y0 + oy as f64 * self.cell - lo.y,
                        ],
                        score,
                    });
                }
            }
        }
        best
    }
}

/// Finds the similarity mapping `sfm` points onto `lidar` (local frame, z up) from the
/// camera poses and the two clouds' shapes: the best of [`align_candidates`].
pub fn align(
    sfm: &[DVec3],
    cameras: &[(DVec3, DVec3)],
    lidar: &[Vec3],
    params: &CoarseParams,
    progress: &dyn Progress,
) -> Result<CoarseAlignment, GeomError> {
    align_candidates(sfm, cameras, lidar, params, progress)?
        .into_iter()
        .next()
        .ok_or(GeomError::Degenerate(
            "the clouds never overlap enough to compare",
        ))
}

/// Up to `params.candidates` distinct hypotheses of the similarity mapping `sfm` points onto
/// `lidar` (local frame, z up), best raster score first. Each comes from the coarse search
/// over every yaw and scale, refined on two finer rasters (a third and a ninth of the coarse
/// cell). Raster scores alone do not tell a right alignment from a wrong one reliably
/// (docs/results/registration.md): the caller verifies each candidate (stage `register`
/// runs ICP from each and compares how well the SfM points then lie on the LiDAR cloud).
pub fn align_candidates(
    sfm: &[DVec3],
    cameras: &[(DVec3, DVec3)],
    lidar: &[Vec3],
    params: &CoarseParams,
    progress: &dyn Progress,
) -> Result<Vec<CoarseAlignment>, GeomError> {
    if sfm.len() < 10 || lidar.len() < 10 {
        return Err(GeomError::Empty(
            "too few points for automatic registration",
        ));
    }
    let r_up = level(up_from_cameras(cameras)?);
    let levelled: Vec<DVec3> = sfm.iter().map(|p| r_up * *p).collect();
    let lid: Vec<DVec3> = lidar.iter().map(|p| p.as_dvec3()).collect();
    let scales = scale_candidates(&levelled, &lid, params)?;

    // LiDAR rasters.
    let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
    for p in &lid {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let side = (hi.x - lo.x).max(hi.y - lo.y).max(1e-3);
    let coarse_cell = side / params.coarse_cells as f64;
    // The local ground is the lowest point within two coarse cells at every level, so the
    // canopy heights of the finer rasters mean the same as the coarse one's.
    let ground_radius = 2.0 * coarse_cell;
    let make = |cell: f64| {
        let nx = ((hi.x - lo.x) / cell).ceil() as usize + 1;
        let ny = ((hi.y - lo.y) / cell).ceil() as usize + 1;
        let half = (ground_radius / cell).round().max(1.0) as usize;
        let r = rasterise(lid.iter().copied(), lo.x, lo.y, cell, nx, ny, half);
        let valid = r.chm.iter().filter(|v| !v.is_nan()).count();
        Scene {
            level: &levelled,
            lidar: r,
            x0: lo.x,
            y0: lo.y,
            cell,
            valid,
            min_overlap: params.min_overlap,
            half,
        }
    };

    let mut seeds = coarse_seeds(&make(coarse_cell), &scales, coarse_cell, params, progress)?;
    // Refine every seed on two finer rasters: yaw ±1 coarse step, scale ±1 coarse step,
    // offsets ±2 coarse cells; then yaw ±1/4 step, scale ±1/4 step, offsets ±4/9 cell.
    let levels = [
        (
            3.0,
            params.yaw_step_deg / 4.0,
            params.scale_step.sqrt(),
            6i64,
        ),
        (
            9.0,
            params.yaw_step_deg / 16.0,
            params.scale_step.powf(0.125),
            4i64,
        ),
    ];
    let mut finest = None;
    for (li, &(div, ystep, sstep, radius)) in levels.iter().enumerate() {
        let fine = make(coarse_cell / div);
        for (k, seed) in seeds.iter_mut().enumerate() {
            if progress.is_cancelled() {
                return Err(GeomError::Cancelled);
            }
            progress.set(
                0.5 + 0.5 * (li * params.candidates.max(1) + k) as f64
                    / (levels.len() * params.candidates.max(1)) as f64,
            );
            if let Some(b) = fine.refine(seed, ystep, sstep, radius) {
                *seed = b;
            }
        }
        finest = Some(fine);
    }
    let Some(fine) = finest else {
        return Err(GeomError::Degenerate("no raster level"));
    };
    seeds.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<Hypothesis> = Vec::new();
    for h in seeds {
        if kept.iter().all(|s| h.distinct_from(s, coarse_cell)) {
            kept.push(h);
        }
    }
    let out = alignments(&kept, r_up, sfm, &lid, &fine);
    progress.set(1.0);
    Ok(out)
}

/// The least-squares plane z = c + gx·(x − x̄) + gy·(y − ȳ) through `points` (x, y, z), about
/// the given centre (x̄, ȳ): `(gx, gy, c)`, or `None` when the points are too few or lie on a
/// line.
fn plane_fit(
    points: impl IntoIterator<Item = (f64, f64, f64)>,
    centre: (f64, f64),
) -> Option<(f64, f64, f64)> {
    let (mut m, mut v) = (DMat3::ZERO, DVec3::ZERO);
    for (x, y, z) in points {
        let a = DVec3::new(x - centre.0, y - centre.1, 1.0);
        m += DMat3::from_cols(a * a.x, a * a.y, a * a.z);
        v += a * z;
    }
    if m.determinant().abs() < 1e-9 {
        return None;
    }
    let sol = m.inverse() * v;
    Some((sol.x, sol.y, sol.z))
}

/// Robust extents of a cloud: its horizontal spread (the fourth root of the determinant of
/// the horizontal covariance, rotation-invariant) and the 2–98 % range of its heights above
/// its least-squares plane. On a slope the raw height range is mostly the ramp under each
/// cloud's own footprint (the photos reach further than the scan), which put both scale
/// estimates 8-10 % under the truth on a 40 % grade (`register_cases slope`).
fn robust_extents(pts: &[DVec3]) -> (f64, f64) {
    let n = pts.len() as f64;
    let m = pts.iter().copied().sum::<DVec3>() / n;
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in pts {
        let d = *p - m;
        sxx += d.x * d.x;
        syy += d.y * d.y;
        sxy += d.x * d.y;
    }
    let det = ((sxx * syy - sxy * sxy) / (n * n)).max(0.0);
    let (gx, gy, _) =
        plane_fit(pts.iter().map(|p| (p.x, p.y, p.z)), (m.x, m.y)).unwrap_or((0.0, 0.0, 0.0));
    let mut z: Vec<f64> = pts
        .iter()
        .map(|p| p.z - gx * (p.x - m.x) - gy * (p.y - m.y))
        .collect();
    let lo = percentile(&mut z, 0.02);
    let hi = percentile(&mut z, 0.98);
    (det.powf(0.25), hi - lo)
}

/// The scales the coarse search tries: log-spaced by `params.scale_step` between the two
/// robust estimates (horizontal spread and height range, LiDAR over SfM), widened by
/// `params.scale_margin`; at most 64 (a wider disagreement gets coarser steps).
fn scale_candidates(
    levelled: &[DVec3],
    lidar: &[DVec3],
    params: &CoarseParams,
) -> Result<Vec<f64>, GeomError> {
    let (hs, vs) = robust_extents(levelled);
    let (hl, vl) = robust_extents(lidar);
    if hs <= 0.0 || vs <= 0.0 || hl <= 0.0 || vl <= 0.0 {
        return Err(GeomError::Degenerate("a cloud is flat or a single line"));
    }
    let (r1, r2) = (hl / hs, vl / vs);
    let (smin, smax) = (
        r1.min(r2) / params.scale_margin,
        r1.max(r2) * params.scale_margin,
    );
    let steps = ((smax / smin).ln() / params.scale_step.ln())
        .ceil()
        .clamp(1.0, 63.0);
    let ratio = (smax / smin).powf(1.0 / steps);
    Ok((0..=steps as usize)
        .map(|k| smin * ratio.powi(k as i32))
        .collect())
}

/// The coarse search over every yaw (`params.yaw_step_deg`) and scale on `scene`: the best
/// `params.candidates` distinct hypotheses by raster score (progress 0 to 0.5).
fn coarse_seeds(
    scene: &Scene<'_>,
    scales: &[f64],
    coarse_cell: f64,
    params: &CoarseParams,
    progress: &dyn Progress,
) -> Result<Vec<Hypothesis>, GeomError> {
    use rayon::prelude::*;
    let yaws: Vec<f64> = (0..)
        .map(|k| k as f64 * params.yaw_step_deg)
        .take_while(|y| *y < 360.0)
        .collect();
    let total = (yaws.len() * scales.len()).max(1);
    let mut hyps: Vec<Hypothesis> = Vec::new();
    for (k, &yaw) in yaws.iter().enumerate() {
        if progress.is_cancelled() {
            return Err(GeomError::Cancelled);
        }
        progress.set(0.5 * (k * scales.len()) as f64 / total as f64);
        hyps.par_extend(
            scales
                .par_iter()
                .filter_map(|&s| scene.evaluate(yaw, s, None)),
        );
    }
    hyps.sort_by(|a, b| b.score.total_cmp(&a.score));
    if hyps.is_empty() {
        return Err(GeomError::Degenerate(
            "the clouds never overlap enough to compare",
        ));
    }
    let mut seeds: Vec<Hypothesis> = Vec::new();
    for h in &hyps {
        if seeds.len() >= params.candidates.max(1) {
            break;
        }
        if seeds.iter().all(|s| h.distinct_from(s, coarse_cell)) {
            seeds.push(*h);
        }
    }
    Ok(seeds)
}

/// Each kept hypothesis as a similarity (levelling, yaw, scale and horizontal offset, then
/// tilted and moved vertically onto the LiDAR's terrain), with its confidence: its margin
/// over the best other (a 0.15 lead counts as sure), capped by its own score.
fn alignments(
    kept: &[Hypothesis],
    r_up: DMat3,
    sfm: &[DVec3],
    lid: &[DVec3],
    fine: &Scene<'_>,
) -> Vec<CoarseAlignment> {
    let grid = Grid {
        x0: fine.x0,
        y0: fine.y0,
        cell: fine.cell,
        nx: fine.lidar.nx,
        ny: fine.lidar.ny,
    };
    let ground_b = rasterise_ground(lid, grid.x0, grid.y0, grid.cell, grid.nx, grid.ny);
    kept.iter()
        .enumerate()
        .map(|(k, h)| {
            let (sn, cs) = h.yaw.to_radians().sin_cos();
            let rz = DMat3::from_cols(DVec3::new(cs, sn, 0.0), DVec3::new(-sn, cs, 0.0), DVec3::Z);
            let partial = Similarity {
                scale: h.scale,
                rotation: rz * r_up,
                translation: DVec3::new(h.t[0], h.t[1], 0.0),
            };
            let transform = settle_on_terrain(&partial, sfm, lid, &grid, &ground_b);
            let runner_up = kept
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != k)
                .map(|(_, o)| o.score)
                .fold(0.0, f64::max);
            let margin = ((h.score - runner_up) / 0.15).clamp(0.0, 1.0);
            CoarseAlignment {
                transform,
                confidence: margin.min(h.score.clamp(0.0, 1.0)),
                score: h.score,
                runner_up,
                yaw_deg: h.yaw,
                scale: h.scale,
            }
        })
        .collect()
}

/// A raster grid: corner (`x0`, `y0`), `cell` metres, `nx` × `ny` cells.
struct Grid {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
}

/// The vertical offset (metres) that puts the levelled, placed SfM points `moved` on the
/// LiDAR's terrain: the median over the cells of `grid` both clouds cover of the LiDAR's
/// lowest point (`ground_lidar`, from [`rasterise_ground`]) minus the SfM's; without a shared
/// cell, the difference of the two clouds' 2nd height percentiles.
fn terrain_offset(moved: &[DVec3], lidar: &[DVec3], grid: &Grid, ground_lidar: &[f64]) -> f64 {
    let ground_sfm = rasterise_ground(moved, grid.x0, grid.y0, grid.cell, grid.nx, grid.ny);
    let mut dz: Vec<f64> = ground_sfm
        .iter()
        .zip(ground_lidar)
        .filter(|(x, y)| !x.is_nan() && !y.is_nan())
        .map(|(x, y)| y - x)
        .collect();
    if dz.is_empty() {
        let mut za: Vec<f64> = moved.iter().map(|p| p.z).collect();
        let mut zb: Vec<f64> = lidar.iter().map(|p| p.z).collect();
        percentile(&mut zb, 0.02) - percentile(&mut za, 0.02)
    } else {
        percentile(&mut dz, 0.5)
    }
}

/// Largest tilt, degrees, that [`settle_on_terrain`] corrects: beyond it the plane through
/// the height differences is not a tilt of the right pose but a wrong one.
const MAX_TILT_DEG: f64 = 15.0;
/// Smallest tilt, degrees, worth correcting: below it the fine steps take over.
const MIN_TILT_DEG: f64 = 0.2;

/// The slope (dz/dx, dz/dy) of the plane through the per-cell height differences between the
/// LiDAR's terrain (`ground_lidar`) and the placed SfM points' lowest points: a residual tilt
/// of "up" (cameras that follow a slope leave the plane of the flight tilted). Robust: cells
/// where the SfM's lowest point is canopy, not ground, are dropped as outliers (three rounds
/// of least squares keeping residuals within 3 robust sigmas, and at least 0.15 m). `None`
/// with fewer than 30 cells or too little spread to fit a plane.
fn terrain_tilt(moved: &[DVec3], grid: &Grid, ground_lidar: &[f64]) -> Option<(f64, f64)> {
    let ground_sfm = rasterise_ground(moved, grid.x0, grid.y0, grid.cell, grid.nx, grid.ny);
    let cells: Vec<(f64, f64, f64)> = ground_sfm
        .iter()
        .zip(ground_lidar)
        .enumerate()
        .filter(|(_, (a, b))| !a.is_nan() && !b.is_nan())
        .map(|(k, (a, b))| {
            let (i, j) = ((k % grid.nx) as f64, (k / grid.nx) as f64);
            (
                grid.x0 + (i + 0.5) * grid.cell,
                grid.y0 + (j + 0.5) * grid.cell,
                b - a,
            )
        })
        .collect();
    if cells.len() < 30 {
        return None;
    }
    let mut dz: Vec<f64> = cells.iter().map(|c| c.2).collect();
    let mut plane = (0.0, 0.0, percentile(&mut dz, 0.5));
    let (xm, ym) = (
        cells.iter().map(|c| c.0).sum::<f64>() / cells.len() as f64,
        cells.iter().map(|c| c.1).sum::<f64>() / cells.len() as f64,
    );
    for _ in 0..3 {
        let r: Vec<f64> = cells
            .iter()
            .map(|c| c.2 - (plane.2 + plane.0 * (c.0 - xm) + plane.1 * (c.1 - ym)))
            .collect();
        let mut abs: Vec<f64> = r.iter().map(|v| v.abs()).collect();
        let limit = (3.0 * 1.4826 * percentile(&mut abs, 0.5)).max(0.15);
        let kept: Vec<(f64, f64, f64)> = cells
            .iter()
            .zip(&r)
            .filter(|(_, ri)| ri.abs() <= limit)
            .map(|(c, _)| *c)
            .collect();
        if kept.len() < 30 {
            return None;
        }
        plane = plane_fit(kept, (xm, ym))?;
    }
    Some((plane.0, plane.1))
}

/// `partial` (a placed, levelled SfM frame) tilted by the slope of [`terrain_tilt`] about the
/// moved points' centroid when that tilt lies between [`MIN_TILT_DEG`] and [`MAX_TILT_DEG`],
/// then moved vertically onto the terrain ([`terrain_offset`]).
fn settle_on_terrain(
    partial: &Similarity,
    sfm: &[DVec3],
    lidar: &[DVec3],
    grid: &Grid,
    ground_lidar: &[f64],
) -> Similarity {
    let mut t = *partial;
    let moved: Vec<DVec3> = sfm.iter().map(|p| t.apply(*p)).collect();
    if let Some((gx, gy)) = terrain_tilt(&moved, grid, ground_lidar) {
        let n = DVec3::new(-gx, -gy, 1.0).normalize();
        let angle = n.z.acos().to_degrees();
        if (MIN_TILT_DEG..=MAX_TILT_DEG).contains(&angle) {
            let pivot = moved.iter().copied().sum::<DVec3>() / moved.len().max(1) as f64;
            let r = DMat3::from_quat(glam::DQuat::from_rotation_arc(DVec3::Z, n));
            t = t.then(&Similarity {
                scale: 1.0,
                rotation: r,
                translation: pivot - r * pivot,
            });
        }
    }
    let moved: Vec<DVec3> = sfm.iter().map(|p| t.apply(*p)).collect();
    let dz = terrain_offset(&moved, lidar, grid, ground_lidar);
    Similarity {
        translation: t.translation + DVec3::new(0.0, 0.0, dz),
        ..t
    }
}

/// `t` tilted and moved vertically so that the SfM points it moves sit on the LiDAR's terrain
/// ([`settle_on_terrain`] on 1 m cells over the LiDAR's extent, coarser beyond 2 km): for
/// starts whose heights and "up" are not to be trusted (GPS altitudes, cameras that followed
/// a slope, a model aligned in another vertical datum).
pub fn on_terrain(t: &Similarity, sfm: &[DVec3], lidar: &[Vec3]) -> Similarity {
    let lid: Vec<DVec3> = lidar.iter().map(|p| p.as_dvec3()).collect();
    let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
    for p in &lid {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    if lid.is_empty() {
        return *t;
    }
    // 1 m cells, coarser beyond 2 km so the grid stays within 2049² cells.
    let cell = ((hi.x - lo.x).max(hi.y - lo.y) / 2048.0).max(1.0);
    let grid = Grid {
        x0: lo.x,
        y0: lo.y,
        cell,
        nx: ((hi.x - lo.x) / cell).ceil() as usize + 1,
        ny: ((hi.y - lo.y) / cell).ceil() as usize + 1,
    };
    let ground = rasterise_ground(&lid, grid.x0, grid.y0, grid.cell, grid.nx, grid.ny);
    let level = Similarity {
        translation: DVec3::new(t.translation.x, t.translation.y, 0.0),
        ..*t
    };
    settle_on_terrain(&level, sfm, &lid, &grid, &ground)
}

/// A coarse alignment from measured camera positions (e.g. GPS), with how well they fit.
#[derive(Debug, Clone, PartialEq)]
pub struct PositionFit {
    /// SfM → LiDAR local; `confidence` 1, `score` 0, `runner_up` 0 (nothing was searched).
    pub alignment: CoarseAlignment,
    /// RMS horizontal residual of the pairs kept, metres (the positions' noise).
    pub rms_m: f64,
    /// Pairs kept, and pairs given.
    pub used: usize,
    pub given: usize,
    /// One standard error of the yaw from the residuals and the pairs' spread, degrees.
    pub yaw_std_deg: f64,
}

/// Smallest horizontal RMS spread of the measured camera positions around their centroid,
/// metres, that pins the yaw: with a few metres of GPS noise a 10 m spread leaves it within a
/// few degrees, which ICP and the surface refinement then take (their reach is the ICP's
/// 1 m start distance at the plot's edge).
pub const MIN_POSITION_SPREAD_M: f64 = 10.0;

/// The coarse similarity from where the photos were taken: `pairs` of (camera centre in the
/// SfM frame, its measured position in the LiDAR local frame, e.g. a GPS fix projected into
/// the LiDAR's CRS minus the ingest offset). Measured heights are not used (GPS altitudes
/// are noisy and their vertical datum unknown): up comes from the cameras as in [`align`],
/// yaw, scale and the horizontal offset from a least-squares 2-D similarity of the levelled
/// centres onto the measured x, y (dropping pairs more than 3 robust sigmas, and at least
/// 1 m, off and fitting again, three times), and the vertical offset from the terrain of
/// both clouds. At least 4 pairs spread [`MIN_POSITION_SPREAD_M`] or more.
pub fn from_positions(
    sfm: &[DVec3],
    cameras: &[(DVec3, DVec3)],
    pairs: &[(DVec3, DVec3)],
    lidar: &[Vec3],
) -> Result<PositionFit, GeomError> {
    if pairs.len() < 4 {
        return Err(GeomError::Empty("fewer than 4 photos with a position"));
    }
    if sfm.len() < 10 || lidar.is_empty() {
        return Err(GeomError::Empty("too few points for registration"));
    }
    // Twice: the terrain's tilt correction changes the levelling, and with it where the
    // cameras, high above the ground, stand horizontally.
    let mut r_level = level(up_from_cameras(cameras)?);
    let mut out = None;
    for _ in 0..2 {
        let fit = fit_positions(pairs, &r_level)?;
        let transform = on_terrain(&fit.alignment.transform, sfm, lidar);
        let (sn, cs) = fit.alignment.yaw_deg.to_radians().sin_cos();
        let rz = DMat3::from_cols(DVec3::new(cs, sn, 0.0), DVec3::new(-sn, cs, 0.0), DVec3::Z);
        // transform.rotation = tilt · rz · r_level: the levelling the tilt asks for.
        r_level = rz.transpose() * transform.rotation;
        out = Some(PositionFit {
            alignment: CoarseAlignment::fixed(transform),
            ..fit
        });
    }
    out.ok_or(GeomError::Degenerate("no fit"))
}

/// The robust 2-D similarity of [`from_positions`] with the SfM frame levelled by `r_level`:
/// `alignment.transform` has no vertical offset, `alignment.yaw_deg` is the yaw about the
/// levelled z.
fn fit_positions(pairs: &[(DVec3, DVec3)], r_level: &DMat3) -> Result<PositionFit, GeomError> {
    let src: Vec<[f64; 2]> = pairs
        .iter()
        .map(|(c, _)| {
            let l = *r_level * *c;
            [l.x, l.y]
        })
        .collect();
    let dst: Vec<[f64; 2]> = pairs.iter().map(|(_, m)| [m.x, m.y]).collect();
    let mut keep = vec![true; pairs.len()];
    // 2-D similarity as complex numbers: w = c z + t, c = s e^{i yaw}.
    let fit = |keep: &[bool]| -> Option<([f64; 2], [f64; 2], f64)> {
        let n = keep.iter().filter(|k| **k).count() as f64;
        if n < 4.0 {
            return None;
        }
        let mean = |v: &[[f64; 2]]| {
            let s = v
                .iter()
                .zip(keep)
                .filter(|(_, k)| **k)
                .fold([0.0, 0.0], |a, (p, _)| [a[0] + p[0], a[1] + p[1]]);
            [s[0] / n, s[1] / n]
        };
        let (ms, md) = (mean(&src), mean(&dst));
        let (mut re, mut im, mut norm, mut spread) = (0.0, 0.0, 0.0, 0.0);
        for ((a, b), k) in src.iter().zip(&dst).zip(keep) {
            if !*k {
                continue;
            }
            let (zx, zy) = (a[0] - ms[0], a[1] - ms[1]);
            let (wx, wy) = (b[0] - md[0], b[1] - md[1]);
            re += zx * wx + zy * wy;
            im += zx * wy - zy * wx;
            norm += zx * zx + zy * zy;
            spread += wx * wx + wy * wy;
        }
        if norm <= 0.0 {
            return None;
        }
        let c = [re / norm, im / norm];
        let t = [
            md[0] - (c[0] * ms[0] - c[1] * ms[1]),
            md[1] - (c[1] * ms[0] + c[0] * ms[1]),
        ];
        Some((c, t, (spread / n).sqrt()))
    };
    let residual = |c: [f64; 2], t: [f64; 2], i: usize| {
        let (a, b) = (src[i], dst[i]);
        let x = c[0] * a[0] - c[1] * a[1] + t[0];
        let y = c[1] * a[0] + c[0] * a[1] + t[1];
        ((x - b[0]).powi(2) + (y - b[1]).powi(2)).sqrt()
    };
    let mut model = fit(&keep).ok_or(GeomError::Degenerate("the photos' positions coincide"))?;
    for _ in 0..3 {
        let (c, t, _) = model;
        let mut r: Vec<f64> = (0..pairs.len()).map(|i| residual(c, t, i)).collect();
        let mut sorted = r.clone();
        let sigma = 1.4826 * percentile(&mut sorted, 0.5);
        let limit = (3.0 * sigma).max(1.0);
        for (k, ri) in keep.iter_mut().zip(r.iter_mut()) {
            *k = *ri <= limit;
        }
        model = fit(&keep).ok_or(GeomError::Degenerate(
            "the photos' positions disagree with their cameras",
        ))?;
    }
    let (c, t, spread) = model;
    if spread < MIN_POSITION_SPREAD_M {
        return Err(GeomError::Degenerate(
            "the photos' positions spread too little to give a direction",
        ));
    }
    let used = keep.iter().filter(|k| **k).count();
    let sq: f64 = (0..pairs.len())
        .filter(|&i| keep[i])
        .map(|i| residual(c, t, i).powi(2))
        .sum();
    let rms_m = (sq / used as f64).sqrt();
    let scale = (c[0] * c[0] + c[1] * c[1]).sqrt();
    let yaw = c[1].atan2(c[0]);
    let (sn, cs) = yaw.sin_cos();
    let rz = DMat3::from_cols(DVec3::new(cs, sn, 0.0), DVec3::new(-sn, cs, 0.0), DVec3::Z);
    let transform = Similarity {
        scale,
        rotation: rz * *r_level,
        translation: DVec3::new(t[0], t[1], 0.0),
    };
    Ok(PositionFit {
        alignment: CoarseAlignment {
            yaw_deg: yaw.to_degrees(),
            ..CoarseAlignment::fixed(transform)
        },
        rms_m,
        used,
        given: pairs.len(),
        yaw_std_deg: (rms_m / (spread * (used as f64).sqrt())).to_degrees(),
    })
}

/// Row-major index of the cell holding `p` in the `nx` × `ny` grid of `cell`-metre cells whose
/// corner is (`x0`, `y0`); `None` outside the grid.
fn cell_index(p: DVec3, x0: f64, y0: f64, cell: f64, nx: usize, ny: usize) -> Option<usize> {
    let i = ((p.x - x0) / cell).floor();
    let j = ((p.y - y0) / cell).floor();
    if i < 0.0 || j < 0.0 || i >= nx as f64 || j >= ny as f64 {
        return None;
    }
    Some(j as usize * nx + i as usize)
}

/// The lowest point of each cell (NaN when empty), metres.
fn rasterise_ground(
    points: &[DVec3],
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
) -> Vec<f64> {
    let mut lo = vec![f64::NAN; nx * ny];
    for &p in points {
        let Some(k) = cell_index(p, x0, y0, cell, nx, ny) else {
            continue;
        };
        lo[k] = if lo[k].is_nan() { p.z } else { lo[k].min(p.z) };
    }
    lo
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::ChaCha8Rng;
    use rand::{RngExt, SeedableRng};

    /// A 60 × 60 m plot: rolling ground (0.25 m spacing) with 3 m posts on a 10 m grid, in the
    /// LiDAR local frame.
    fn plot() -> Vec<Vec3> {
        let mut pts = Vec::new();
        for i in 0..240 {
            for j in 0..240 {
                let (x, y) = (i as f32 * 0.25 - 30.0, j as f32 * 0.25 - 30.0);
                pts.push(Vec3::new(x, y, 0.05 * x + 0.6 * (0.2 * y).sin()));
            }
        }
        for i in -2..=2 {
            for j in -2..=2 {
                for k in 0..30 {
                    let (x, y) = (i as f32 * 10.0 + 1.0, j as f32 * 10.0 - 2.0);
                    pts.push(Vec3::new(x, y, 0.05 * x + k as f32 * 0.1));
                }
            }
        }
        pts
    }

    fn gauss(rng: &mut ChaCha8Rng) -> f64 {
        let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// SfM frame = truth⁻¹ of the LiDAR frame; 49 nadir cameras at 40 m on a 7 × 7 grid over
    /// the plot; GPS with 3 m horizontal noise, a 35 m altitude bias (another vertical datum)
    /// and two fixes 60 m off.
    /// 49 cameras 40 m over the plot on a 7 × 7 grid, turned by `tilt`, looking down (plus
    /// `jitter`): centres and view directions in the LiDAR frame.
    fn grid_cameras(tilt: DMat3, mut jitter: impl FnMut() -> DVec3) -> Vec<(DVec3, DVec3)> {
        (0..49)
            .map(|k| {
                let (i, j) = ((k / 7) as f64, (k % 7) as f64);
                let c = tilt * DVec3::new(i * 8.0 - 24.0, j * 8.0 - 24.0, 40.0);
                (c, tilt * (DVec3::NEG_Z + jitter()))
            })
            .collect()
    }

    /// The plot's points (every 7th) and `cameras` moved into the SfM frame by `inv`.
    fn in_sfm(
        lidar: &[Vec3],
        cameras: &[(DVec3, DVec3)],
        inv: &Similarity,
    ) -> (Vec<DVec3>, Vec<(DVec3, DVec3)>) {
        let sfm = lidar
            .iter()
            .step_by(7)
            .map(|p| inv.apply(p.as_dvec3()))
            .collect();
        let cams = cameras
            .iter()
            .map(|(c, d)| (inv.apply(*c), (inv.rotation * *d).normalize()))
            .collect();
        (sfm, cams)
    }

    #[test]
    fn camera_positions_with_gps_noise_give_a_start_within_icp_reach() {
        let lidar = plot();
        let truth = Similarity {
            scale: 0.37,
            rotation: DMat3::from_euler(glam::EulerRot::ZYX, 2.1, 0.4, -0.7),
            translation: DVec3::new(5.0, -3.0, 1.5),
        };
        let inv = truth.inverse();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let flight = grid_cameras(DMat3::IDENTITY, || {
            DVec3::new(0.02 * gauss(&mut rng), 0.02 * gauss(&mut rng), 0.0)
        });
        let (sfm, cameras) = in_sfm(&lidar, &flight, &inv);
        let pairs: Vec<(DVec3, DVec3)> = flight
            .iter()
            .zip(&cameras)
            .enumerate()
            .map(|(k, ((c, _), (cs, _)))| {
                let mut gps = *c + DVec3::new(3.0 * gauss(&mut rng), 3.0 * gauss(&mut rng), 35.0);
                if k == 21 || k == 22 {
                    gps.x += 60.0;
                }
                (*cs, gps)
            })
            .collect();
        let fit = from_positions(&sfm, &cameras, &pairs, &lidar).expect("a start");
        assert_eq!((fit.used, fit.given), (47, 49), "{fit:?}");
        assert!(fit.rms_m > 2.0 && fit.rms_m < 4.5, "{fit:?}");
        let rel = truth.inverse().then(&fit.alignment.transform);
        assert!(
            rel.rotation_angle_deg() < 2.0,
            "{} °",
            rel.rotation_angle_deg()
        );
        assert!((rel.scale - 1.0).abs() < 0.03, "scale {}", rel.scale);
        let centre = inv.apply(DVec3::ZERO);
        let off = fit.alignment.transform.apply(centre);
        assert!(off.truncate().length() < 1.5, "horizontal {off}");
        assert!(
            off.z.abs() < 0.3,
            "vertical {off} (the 35 m altitude bias must not leak)"
        );
        assert!(fit.yaw_std_deg > 0.1 && fit.yaw_std_deg < 2.0, "{fit:?}");
    }

    /// Cameras that followed a slope: their centres' plane is tilted 4° from the horizontal,
    /// so "up" from the cameras is 4° off. The plane through the terrain's height
    /// differences takes the tilt out of the start.
    #[test]
    fn a_flight_tilted_with_the_slope_is_levelled_on_the_terrain() {
        let lidar = plot();
        let truth = Similarity {
            scale: 2.5,
            rotation: DMat3::from_euler(glam::EulerRot::ZYX, -0.9, 0.2, 0.3),
            translation: DVec3::new(-4.0, 7.0, -2.0),
        };
        let inv = truth.inverse();
        let flight = grid_cameras(DMat3::from_rotation_x(4f64.to_radians()), || DVec3::ZERO);
        let (sfm, cameras) = in_sfm(&lidar, &flight, &inv);
        let pairs: Vec<(DVec3, DVec3)> = flight
            .iter()
            .zip(&cameras)
            .map(|(c, s)| (s.0, c.0))
            .collect();
        let fit = from_positions(&sfm, &cameras, &pairs, &lidar).expect("a start");
        let rel = truth.inverse().then(&fit.alignment.transform);
        assert!(
            rel.rotation_angle_deg() < 0.3,
            "{} ° left of a 4° tilt",
            rel.rotation_angle_deg()
        );
        let off = fit.alignment.transform.apply(inv.apply(DVec3::ZERO));
        assert!(off.length() < 0.3, "{off}");
    }

    #[test]
    fn too_few_or_bunched_positions_are_refused() {
        let lidar = plot();
        let sfm: Vec<DVec3> = lidar.iter().step_by(7).map(|p| p.as_dvec3()).collect();
        let cam = |x: f64, y: f64| (DVec3::new(x, y, 40.0), DVec3::NEG_Z);
        let cameras: Vec<_> = (0..9)
            .map(|k| cam((k % 3) as f64 * 2.0, (k / 3) as f64 * 2.0))
            .collect();
        let pairs: Vec<_> = cameras.iter().map(|c| (c.0, c.0)).collect();
        assert!(matches!(
            from_positions(&sfm, &cameras, &pairs[..3], &lidar),
            Err(GeomError::Empty(_))
        ));
        // Nine photos within 4 m: no direction.
        assert!(matches!(
            from_positions(&sfm, &cameras, &pairs, &lidar),
            Err(GeomError::Degenerate(_))
        ));
    }
}
