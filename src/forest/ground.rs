//! Ground: a cloth-simulation filter (Zhang et al. 2016, "An Easy-to-Use Airborne LiDAR Data
//! Filtering Method Based on Cloth Simulation") and a digital terrain model (DTM).
//!
//! The cloud is turned upside down and a cloth of particles on a regular grid falls onto it
//! under gravity. Where the upside-down cloud is high — the real ground — particles hit it
//! and stop; springs between particles (the rigidness) keep the cloth from sagging into the
//! gaps under stems and crowns. Points within `class_threshold_m` of the cloth are ground.
//! The DTM is then built from the ground points themselves (mean height per cell), with cells
//! without ground filled by diffusion from their neighbours, so "1.3 m above ground" means
//! above the measured ground, not above the cloth.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::progress::Progress;

/// Cloth-simulation parameters. Defaults follow the CSF reference implementation and lidR's
/// `csf()` (cloth resolution 0.5 m, time step 0.65, class threshold 0.5 m, 500 iterations),
/// except rigidness 2 ("relief"), which suits sloped forest plots better than 1 ("steep").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct CsfParams {
    /// Grid spacing of the cloth particles, metres.
    pub cloth_resolution_m: f64,
    /// Spring stiffness: constraint passes per step, 1 (steep terrain) to 3 (flat).
    pub rigidness: u32,
    /// Integration time step of the cloth simulation (dimensionless, CSF: 0.65).
    pub time_step: f64,
    /// A point within this vertical distance of the settled cloth is ground, metres.
    pub class_threshold_m: f64,
    /// Most simulation steps.
    pub max_iterations: u32,
    /// Cell size of the DTM raster built from the ground points, metres.
    pub dtm_cell_m: f64,
}

impl Default for CsfParams {
    fn default() -> Self {
        Self {
            cloth_resolution_m: 0.5,
            rigidness: 2,
            time_step: 0.65,
            class_threshold_m: 0.5,
            max_iterations: 500,
            dtm_cell_m: 0.5,
        }
    }
}

/// Ground points more than this far above the settled cloth (metres) are left out of the DTM:
/// they are stem bases, roots or litter inside the class threshold. 0.1 m is ten times the
/// range noise of a handheld scanner (docs/method.md: sigma 1 cm).
pub const DTM_TOLERANCE_M: f64 = 0.1;

/// A regular raster of ground heights over the plot (local coordinates, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dtm {
    /// Lower-left corner (x, y) of cell (0, 0)'s centre, metres.
    pub origin: [f32; 2],
    pub cell: f32,
    pub nx: usize,
    pub ny: usize,
    /// Row-major heights, `ny` rows of `nx`, metres.
    pub heights: Vec<f32>,
}

impl Dtm {
    /// Ground height under (x, y) by bilinear interpolation; clamped at the raster's edge.
    pub fn height_at(&self, x: f32, y: f32) -> f32 {
        self.bilinear_with(&self.heights, x, y)
    }

    /// Height of every point above the ground model, metres.
    pub fn heights_above(&self, points: &[Vec3]) -> Vec<f32> {
        points
            .iter()
            .map(|p| p.z - self.height_at(p.x, p.y))
            .collect()
    }
}

/// The ground filter's result.
#[derive(Debug, Clone)]
pub struct GroundResult {
    pub is_ground: Vec<bool>,
    pub dtm: Dtm,
    /// Simulation steps until the cloth stopped moving (or the cap).
    pub iterations: u32,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GroundError {
    #[error("the cloud is empty")]
    Empty,
    #[error("invalid ground parameters: {0}")]
    Params(String),
    #[error("cancelled")]
    Cancelled,
}

/// A grid over the x/y bounds of the points.
struct Grid {
    x0: f32,
    y0: f32,
    res: f32,
    nx: usize,
    ny: usize,
}

impl Grid {
    fn over(points: &[Vec3], res: f32) -> Grid {
        let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for p in points {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        let nx = ((hi.x - lo.x) / res).ceil() as usize + 1;
        let ny = ((hi.y - lo.y) / res).ceil() as usize + 1;
        Grid {
            x0: lo.x,
            y0: lo.y,
            res,
            nx,
            ny,
        }
    }
    /// Index of the grid node nearest to (x, y).
    fn nearest(&self, x: f32, y: f32) -> usize {
        let i = (((x - self.x0) / self.res).round() as isize).clamp(0, self.nx as isize - 1);
        let j = (((y - self.y0) / self.res).round() as isize).clamp(0, self.ny as isize - 1);
        j as usize * self.nx + i as usize
    }
    fn bilinear(&self, values: &[f32], x: f32, y: f32) -> f32 {
        Dtm {
            origin: [self.x0, self.y0],
            cell: self.res,
            nx: self.nx,
            ny: self.ny,
            heights: Vec::new(),
        }
        .bilinear_with(values, x, y)
    }
}

impl Dtm {
    fn bilinear_with(&self, values: &[f32], x: f32, y: f32) -> f32 {
        let fx = ((x - self.origin[0]) / self.cell).clamp(0.0, (self.nx - 1) as f32);
        let fy = ((y - self.origin[1]) / self.cell).clamp(0.0, (self.ny - 1) as f32);
        let (i, j) = (fx.floor() as usize, fy.floor() as usize);
        let (i1, j1) = ((i + 1).min(self.nx - 1), (j + 1).min(self.ny - 1));
        let (tx, ty) = (fx - i as f32, fy - j as f32);
        let v = |i: usize, j: usize| values[j * self.nx + i];
        let a = v(i, j) * (1.0 - tx) + v(i1, j) * tx;
        let b = v(i, j1) * (1.0 - tx) + v(i1, j1) * tx;
        a * (1.0 - ty) + b * ty
    }
}

/// Fills `None` cells from their neighbours: first nearest-known by breadth-first growth,
/// then a few smoothing passes over the filled cells only, keeping measured cells fixed.
fn fill_gaps(nx: usize, ny: usize, cells: &[Option<f32>]) -> Vec<f32> {
    let mut out: Vec<f32> = cells.iter().map(|c| c.unwrap_or(0.0)).collect();
    let mut known: Vec<bool> = cells.iter().map(Option::is_some).collect();
    let filled_from_gap: Vec<bool> = known.iter().map(|k| !k).collect();
    let mut frontier: Vec<usize> = (0..cells.len()).filter(|&k| known[k]).collect();
    while !frontier.is_empty() {
        let mut next = Vec::new();
        let mut sums: std::collections::HashMap<usize, (f32, u32)> = Default::default();
        for &k in &frontier {
            let (i, j) = (k % nx, k / nx);
            for (di, dj) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (a, b) = (i as i64 + di, j as i64 + dj);
                if a < 0 || b < 0 || a >= nx as i64 || b >= ny as i64 {
                    continue;
                }
                let n = b as usize * nx + a as usize;
                if !known[n] {
                    let e = sums.entry(n).or_insert((0.0, 0));
                    e.0 += out[k];
                    e.1 += 1;
                }
            }
        }
        for (n, (s, c)) in sums {
            out[n] = s / c as f32;
            known[n] = true;
            next.push(n);
        }
        frontier = next;
    }
    for _ in 0..8 {
        let prev = out.clone();
        for k in 0..out.len() {
            if !filled_from_gap[k] {
                continue;
            }
            let (i, j) = (k % nx, k / nx);
            let (mut s, mut c) = (prev[k], 1.0);
            for (di, dj) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (a, b) = (i as i64 + di, j as i64 + dj);
                if a >= 0 && b >= 0 && a < nx as i64 && b < ny as i64 {
                    s += prev[b as usize * nx + a as usize];
                    c += 1.0;
                }
            }
            out[k] = s / c;
        }
    }
    out
}

/// Separates ground from everything else with the cloth-simulation filter and builds a DTM.
pub fn classify_ground(
    points: &[Vec3],
    params: &CsfParams,
    progress: &dyn Progress,
) -> Result<GroundResult, GroundError> {
    if points.is_empty() {
        return Err(GroundError::Empty);
    }
    if !(params.cloth_resolution_m > 0.0 && params.dtm_cell_m > 0.0 && params.time_step > 0.0)
        || params.rigidness == 0
    {
        return Err(GroundError::Params(
            "cloth_resolution_m, dtm_cell_m and time_step must be positive, rigidness >= 1".into(),
        ));
    }
    let grid = Grid::over(points, params.cloth_resolution_m as f32);
    let n = grid.nx * grid.ny;
    // Highest upside-down point (= lowest real point) nearest to each particle.
    let mut ihv: Vec<Option<f32>> = vec![None; n];
    for p in points {
        let k = grid.nearest(p.x, p.y);
        let inv = -p.z;
        ihv[k] = Some(ihv[k].map_or(inv, |h| h.max(inv)));
    }
    let ihv = fill_gaps(grid.nx, grid.ny, &ihv);
    let top = ihv.iter().copied().fold(f32::MIN, f32::max) + 1.0;
    let mut h = vec![top; n];
    let mut prev = h.clone();
    let mut movable = vec![true; n];
    // Gravity step as in CSF: displacement g·dt² per step, with damping 0.01.
    let drop = (9.81 * params.time_step * params.time_step / 100.0) as f32;
    let damping = 0.99f32;
    let mut iterations = 0;
    for it in 0..params.max_iterations {
        iterations = it + 1;
        if it % 25 == 0 {
            if progress.is_cancelled() {
                return Err(GroundError::Cancelled);
            }
            progress.set(0.8 * it as f64 / params.max_iterations as f64);
        }
        let mut max_move = 0.0f32;
        for k in 0..n {
            if movable[k] {
                let next = h[k] + (h[k] - prev[k]) * damping - drop;
                prev[k] = h[k];
                h[k] = next;
            }
        }
        // Springs: each pass moves a particle halfway towards a neighbour (all the way when
        // the neighbour is fixed), along rows then columns.
        for _ in 0..params.rigidness {
            for j in 0..grid.ny {
                for i in 0..grid.nx {
                    let a = j * grid.nx + i;
                    for b in [
                        (i + 1 < grid.nx).then(|| a + 1),
                        (j + 1 < grid.ny).then(|| a + grid.nx),
                    ]
                    .into_iter()
                    .flatten()
                    {
                        let d = h[b] - h[a];
                        match (movable[a], movable[b]) {
                            (true, true) => {
                                h[a] += d * 0.5;
                                h[b] -= d * 0.5;
                            }
                            (true, false) => h[a] += d * 0.5,
                            (false, true) => h[b] -= d * 0.5,
                            (false, false) => {}
                        }
                    }
                }
            }
        }
        for k in 0..n {
            if movable[k] && h[k] <= ihv[k] {
                h[k] = ihv[k];
                movable[k] = false;
            }
            max_move = max_move.max((h[k] - prev[k]).abs());
        }
        if max_move < 1e-4 && it > 10 {
            break;
        }
    }
    let cloth: Vec<f32> = h.iter().map(|v| -v).collect();
    let is_ground: Vec<bool> = points
        .iter()
        .map(|p| (p.z - grid.bilinear(&cloth, p.x, p.y)).abs() <= params.class_threshold_m as f32)
        .collect();
    progress.set(0.9);

    // DTM from the ground points that lie on the cloth (within `DTM_TOLERANCE_M`), so stem
    // bases and low shrubs inside the class threshold do not lift it: mean height per cell,
    // gaps filled from neighbours.
    let dgrid = Grid::over(points, params.dtm_cell_m as f32);
    let mut sums = vec![(0.0f64, 0u32); dgrid.nx * dgrid.ny];
    let tol = DTM_TOLERANCE_M.min(params.class_threshold_m) as f32;
    for (p, g) in points.iter().zip(&is_ground) {
        if *g && p.z - grid.bilinear(&cloth, p.x, p.y) <= tol {
            let k = dgrid.nearest(p.x, p.y);
            sums[k].0 += p.z as f64;
            sums[k].1 += 1;
        }
    }
    let cells: Vec<Option<f32>> = sums
        .iter()
        .map(|(s, c)| (*c > 0).then(|| (*s / *c as f64) as f32))
        .collect();
    let heights = if cells.iter().any(Option::is_some) {
        fill_gaps(dgrid.nx, dgrid.ny, &cells)
    } else {
        vec![points.iter().map(|p| p.z).fold(f32::MAX, f32::min); cells.len()]
    };
    progress.set(1.0);
    Ok(GroundResult {
        is_ground,
        dtm: Dtm {
            origin: [dgrid.x0, dgrid.y0],
            cell: dgrid.res,
            nx: dgrid.nx,
            ny: dgrid.ny,
            heights,
        },
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;

    /// Terrain z = 0.1 x + 0.3 sin(0.3 y), with trunks and crown blobs on top.
    fn terrain(x: f32, y: f32) -> f32 {
        0.1 * x + 0.3 * (0.3 * y).sin()
    }

    fn forest() -> (Vec<Vec3>, Vec<bool>) {
        let mut pts = Vec::new();
        let mut truth = Vec::new();
        let mut s = 12345u32;
        let mut rnd = || {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            (s as f32) / (u32::MAX as f32)
        };
        for i in 0..120 {
            for j in 0..120 {
                let (x, y) = (i as f32 * 0.25 + rnd() * 0.1, j as f32 * 0.25 + rnd() * 0.1);
                pts.push(Vec3::new(x, y, terrain(x, y) + (rnd() - 0.5) * 0.02));
                truth.push(true);
            }
        }
        for (cx, cy) in [(8.0f32, 8.0f32), (20.0, 12.0), (14.0, 24.0), (25.0, 25.0)] {
            for k in 0..150 {
                let z = 0.1 + k as f32 * 0.1;
                for a in 0..30 {
                    let t = a as f32 / 30.0 * std::f32::consts::TAU;
                    let (x, y) = (cx + 0.2 * t.cos(), cy + 0.2 * t.sin());
                    pts.push(Vec3::new(x, y, terrain(cx, cy) + z));
                    truth.push(z < 0.05);
                }
            }
            for _ in 0..3000 {
                let (dx, dy, dz) = (rnd() * 8.0 - 4.0, rnd() * 8.0 - 4.0, rnd() * 5.0);
                pts.push(Vec3::new(cx + dx, cy + dy, terrain(cx, cy) + 8.0 + dz));
                truth.push(false);
            }
        }
        (pts, truth)
    }

    #[test]
    fn cloth_separates_ground_from_stems_and_crowns_on_a_slope() {
        let (pts, truth) = forest();
        let r = classify_ground(&pts, &CsfParams::default(), &NoProgress).expect("csf");
        // Every true ground point is found, and nothing more than the class threshold above
        // the terrain is called ground (stem bases within it are ground by construction).
        let thr = CsfParams::default().class_threshold_m as f32;
        let (mut tp, mut fneg, mut fp, mut high) = (0, 0, 0, 0);
        for ((g, t), p) in r.is_ground.iter().zip(&truth).zip(&pts) {
            let above = p.z - terrain(p.x, p.y);
            match (g, t) {
                (true, true) => tp += 1,
                (false, true) => fneg += 1,
                (true, false) if above > thr => fp += 1,
                _ => {}
            }
            if above > thr {
                high += 1;
            }
        }
        let recall = tp as f64 / (tp + fneg) as f64;
        assert!(recall > 0.98, "recall {recall}");
        assert!(
            fp as f64 / (high as f64) < 0.001,
            "{fp} of {high} high points called ground"
        );
        // The DTM follows the terrain, also under the crowns.
        for (x, y) in [
            (8.0, 8.0),
            (20.0, 12.0),
            (14.0, 24.0),
            (3.0, 27.0),
            (15.0, 15.0),
        ] {
            let err = (r.dtm.height_at(x, y) - terrain(x, y)).abs();
            assert!(err < 0.03, "DTM error {err} m at ({x}, {y})");
        }
        let hag = r.dtm.heights_above(&pts);
        assert!(
            hag.iter()
                .zip(&truth)
                .filter(|(_, t)| **t)
                .all(|(h, _)| h.abs() < 0.2)
        );
    }

    #[test]
    fn bad_parameters_and_empty_clouds_are_refused() {
        let p = CsfParams {
            rigidness: 0,
            ..Default::default()
        };
        assert!(matches!(
            classify_ground(&[Vec3::ZERO], &p, &NoProgress),
            Err(GroundError::Params(_))
        ));
        assert_eq!(
            classify_ground(&[], &CsfParams::default(), &NoProgress).err(),
            Some(GroundError::Empty)
        );
    }

    #[test]
    fn real_plots_give_a_plausible_dtm() {
        for file in ["CSF_sample/sample.ply", "TreeLS_extdata/pine_plot.laz"] {
            let Some(path) = crate::io::real_data(file) else {
                continue;
            };
            let cloud =
                crate::io::pointcloud::read_point_cloud(&path, &NoProgress).expect("read cloud");
            let r =
                classify_ground(&cloud.positions, &CsfParams::default(), &NoProgress).expect("csf");
            let share = r.is_ground.iter().filter(|g| **g).count() as f64 / cloud.len() as f64;
            assert!(
                (0.05..0.95).contains(&share),
                "{file}: ground share {share}"
            );
            let (zmin, zmax) = cloud
                .positions
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p.z), b.max(p.z)));
            assert!(r.dtm.heights.iter().all(|h| *h >= zmin - 0.5 && *h <= zmax));
            // Ground points lie on the DTM.
            let hag = r.dtm.heights_above(&cloud.positions);
            let off: Vec<f32> = hag
                .iter()
                .zip(&r.is_ground)
                .filter(|(_, g)| **g)
                .map(|(h, _)| h.abs())
                .collect();
            let mean = off.iter().sum::<f32>() / off.len().max(1) as f32;
            assert!(mean < 0.25, "{file}: ground points {mean} m off the DTM");
        }
    }
}
