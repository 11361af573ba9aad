//! Handheld SLAM LiDAR simulator: an operator walks a closed loop around and between the
//! stems with a 16-beam spinning head on a tilted, rotating mount; every pulse is a ray cast
//! into the scene, with range noise, beam dropout, a range limit, incidence- and material-
//! dependent intensity and optional colour.
//!
//! Scanner defaults imitate a Velodyne VLP-16 class head as used in handheld SLAM units (the
//! paper's SHARE S20 is of that kind): 16 beams from −15° to +15° in 2° steps, 10 Hz spin,
//! 1800 firings per turn (18 kHz); the head's spin axis is tilted 45° forward and the mount turns
//! about the vertical at 0.5 Hz, so the beams sweep the ground, the stems and the canopy.
//!
//! The operator walks at [`WALK_SPEED_M_S`]; a real head would deliver ~300 000 points per
//! second, far more than a test needs, so the simulated firings are a uniform subsample in
//! time of the real ones (the walk keeps its real duration, the firings per second drop),
//! with the head azimuth advancing by the golden ratio of a turn from one simulated firing
//! to the next so that the subsample covers all azimuths evenly. Firings are processed in
//! blocks; each block has its own random stream and blocks are collected in time order, so
//! the cloud does not depend on the thread count.

use glam::{DVec2, Mat3, Vec3};
use rayon::prelude::*;

use super::layout::Plot;
use super::rng::{Stream, domain};
use super::scene::linear_to_srgb;
use crate::progress::Progress;

/// Beams of the head (VLP-16).
const BEAMS: usize = 16;
/// Simulated firings per processing block.
const FIRINGS_PER_TURN: usize = 1800;
/// Walking speed of the operator, m/s (a slow walk, as handheld SLAM needs).
pub const WALK_SPEED_M_S: f64 = 0.8;
/// Golden ratio conjugate: the head azimuth step between simulated firings, in turns.
const GOLDEN: f64 = 0.618_033_988_749_894_8;
/// Tilt of the spin axis from vertical, degrees.
const TILT_DEG: f32 = 45.0;
/// Rotation rate of the mount about the vertical, Hz.
const MOUNT_HZ: f64 = 0.5;
/// Scanner height above ground while walking, metres (issue: 1.2–1.5 m).
const SCANNER_HEIGHT_M: f64 = 1.35;
/// Nearest range kept, metres (the operator's own body).
const MIN_RANGE_M: f32 = 0.5;
/// Laps walked at most before giving up on the point target.
const MAX_LAPS: usize = 4;
/// Blocks (head turns) processed per parallel batch.
const BATCH: usize = 32;

/// LiDAR settings (resolved from [`super::SynthParams`]).
#[derive(Debug, Clone, Copy)]
pub struct LidarParams {
    /// Number of points to deliver (the scan stops when reached).
    pub points: usize,
    /// Range noise sigma, metres (issue default 0.01).
    pub noise_m: f64,
    /// Maximum range, metres.
    pub max_range_m: f32,
    /// Dropout probability of a return at normal incidence and short range, [0, 1].
    pub dropout: f64,
    /// Store colours from the surface albedo.
    pub rgb: bool,
}

/// The simulated cloud in the scene frame, in acquisition order.
pub struct LidarScan {
    pub positions: Vec<Vec3>,
    pub colors: Option<Vec<[u8; 3]>>,
    pub intensity: Vec<u16>,
    pub labels: Vec<u8>,
    /// Per return: the id of the tree it hit (1-based, [`super::trees::TreeTruth::id`]), 0 for
    /// ground, stones and shrubs.
    pub owners: Vec<u16>,
    pub trajectory_length_m: f64,
    pub rays_cast: u64,
    pub laps: f64,
}

#[derive(Clone, Copy)]
struct Return {
    pos: Vec3,
    rgb: [u8; 3],
    intensity: u16,
    label: u8,
    owner: u16,
}

/// A closed polyline walked at constant speed.
struct Loop {
    pts: Vec<DVec2>,
    /// Cumulative length at each vertex; last entry is the loop length.
    cum: Vec<f64>,
}

impl Loop {
    fn new(plot: &Plot, seed: u64, lap: usize) -> Loop {
        let mut rng = Stream::new(seed, domain::LIDAR, u64::MAX - lap as u64);
        let many = plot.trees.len() > 3;
        let scale = [1.0, 1.35, 0.7, 1.15][lap % 4];
        let base = if many {
            0.6 * plot.radius_m
        } else {
            plot.radius_m.max(2.5) + 1.0
        } * scale;
        let (p2, p3) = (rng.range(0.0, 6.3), rng.range(0.0, 6.3));
        let (a2, a3) = if many { (0.25, 0.12) } else { (0.08, 0.04) };
        let n = 1440;
        let mut pts: Vec<DVec2> = (0..n)
            .map(|i| {
                let th = i as f64 / n as f64 * std::f64::consts::TAU;
                let r = base * (1.0 + a2 * (2.0 * th + p2).sin() + a3 * (3.0 * th + p3).sin());
                DVec2::new(r * th.cos(), r * th.sin())
            })
            .collect();
        // Keep clear of stems: push vertices radially away from every stem base.
        for p in &mut pts {
            for t in &plot.trees {
                let c = DVec2::new(t.base.x, t.base.y);
                let clear = t.semi_axes_m[0] + 1.0;
                let v = *p - c;
                let d = v.length();
                if d < clear {
                    *p = c + if d > 1e-6 { v / d } else { DVec2::X } * clear;
                }
            }
        }
        let mut cum = Vec::with_capacity(n + 1);
        cum.push(0.0);
        for i in 0..n {
            let l = cum[i] + pts[i].distance(pts[(i + 1) % n]);
            cum.push(l);
        }
        Loop { pts, cum }
    }

    fn length(&self) -> f64 {
        self.cum.last().copied().unwrap_or(0.0)
    }

    /// Position and unit heading at arc-length fraction `f` in [0, 1).
    fn at(&self, f: f64) -> (DVec2, DVec2) {
        let s = f.rem_euclid(1.0) * self.length();
        let i = self
            .cum
            .partition_point(|&c| c <= s)
            .saturating_sub(1)
            .min(self.pts.len() - 1);
        let (a, b) = (self.pts[i], self.pts[(i + 1) % self.pts.len()]);
        let seg = (self.cum[i + 1] - self.cum[i]).max(1e-9);
        let u = ((s - self.cum[i]) / seg).clamp(0.0, 1.0);
        (a + (b - a) * u, (b - a).normalize_or(DVec2::X))
    }
}

/// Simulates the scan.
pub fn scan(
    plot: &Plot,
    params: &LidarParams,
    seed: u64,
    progress: &dyn Progress,
) -> Result<LidarScan, crate::io::IoError> {
    let loops: Vec<Loop> = (0..MAX_LAPS).map(|k| Loop::new(plot, seed, k)).collect();
    // Plan one lap for the target at an expected 70 % return rate; more laps if needed.
    let rays_per_lap = (params.points as f64 / 0.7).max(BEAMS as f64 * FIRINGS_PER_TURN as f64);
    let blocks_per_lap = (rays_per_lap / (BEAMS * FIRINGS_PER_TURN) as f64).ceil() as usize;
    let firings_per_lap = (blocks_per_lap * FIRINGS_PER_TURN) as f64;
    let max_blocks = blocks_per_lap * MAX_LAPS;
    let elev: Vec<(f32, f32)> = (0..BEAMS)
        .map(|j| (-15.0f32 + 2.0 * j as f32).to_radians().sin_cos())
        .collect();
    let tilt = Mat3::from_rotation_y(TILT_DEG.to_radians());
    // Per primitive owner (tree index + 1): the tree's base, axis and hidden band of heights
    // along the axis ([`super::SynthParams::hidden_stem_m`]).
    let hidden: Vec<Option<(Vec3, Vec3, f32, f32)>> = std::iter::once(None)
        .chain(plot.trees.iter().map(|t| {
            t.hidden_m
                .map(|[lo, hi]| (t.base.as_vec3(), t.axis.as_vec3(), lo as f32, hi as f32))
        }))
        .collect();
    let is_hidden = |prim: u32, p: Vec3| {
        let owner = plot.scene.prims.get(prim as usize).map_or(0, |q| q.owner) as usize;
        hidden
            .get(owner)
            .copied()
            .flatten()
            .is_some_and(|(base, axis, lo, hi)| (lo..=hi).contains(&(p - base).dot(axis)))
    };

    let run_block = |block: usize| -> Vec<Return> {
        let mut rng = Stream::new(seed, domain::LIDAR, block as u64);
        let mut out = Vec::with_capacity(BEAMS * FIRINGS_PER_TURN);
        for f in 0..FIRINGS_PER_TURN {
            let firing = block * FIRINGS_PER_TURN + f;
            let lap_f = firing as f64 / firings_per_lap;
            let lap = (lap_f as usize).min(MAX_LAPS - 1);
            let (xy, heading) = loops[lap].at(lap_f);
            // Real time since the start of the walk, seconds.
            let t = lap as f64 * 1000.0 + lap_f.fract() * loops[lap].length() / WALK_SPEED_M_S;
            let ground = plot.scene.terrain.height(xy.x, xy.y);
            let z = ground + SCANNER_HEIGHT_M + 0.02 * (std::f64::consts::TAU * 1.8 * t).sin();
            let origin = Vec3::new(xy.x as f32, xy.y as f32, z as f32);
            let yaw = heading.y.atan2(heading.x) as f32;
            let wobble = (0.03 * (2.1 * t).sin()) as f32;
            let body = Mat3::from_rotation_z(yaw)
                * Mat3::from_rotation_x(wobble)
                * Mat3::from_rotation_y(wobble * 0.7);
            let mount = Mat3::from_rotation_z(
                (std::f64::consts::TAU * MOUNT_HZ * t).rem_euclid(std::f64::consts::TAU) as f32,
            );
            let m = body * mount * tilt;
            let phi = (std::f64::consts::TAU * (firing as f64 * GOLDEN).fract()) as f32;
            let (sp, cp) = phi.sin_cos();
            for &(se, ce) in &elev {
                let d = (m * Vec3::new(ce * cp, ce * sp, se)).normalize();
                let Some(hit) = plot
                    .scene
                    .intersect(origin, d, MIN_RANGE_M, params.max_range_m)
                else {
                    continue;
                };
                let s = plot.scene.surface(origin, d, hit);
                let grazing = (1.0 - s.cos_incidence as f64).powi(4);
                let far = (hit.t as f64 / params.max_range_m as f64).powi(4);
                let p_drop = params.dropout + 0.3 * grazing + 0.5 * far;
                let drop = rng.chance(p_drop);
                let noise = rng.normal() * params.noise_m;
                if drop || is_hidden(hit.prim, origin + d * hit.t) {
                    continue;
                }
                let r = hit.t as f64 + noise;
                let refl = s.material.nir_reflectance() as f64;
                let level = refl
                    * (0.3 + 0.7 * s.cos_incidence as f64)
                    * (1.0 - 0.4 * hit.t as f64 / params.max_range_m as f64);
                out.push(Return {
                    pos: origin + d * r as f32,
                    rgb: linear_to_srgb(s.albedo * (0.55 + 0.45 * s.cos_incidence)),
                    intensity: (level.clamp(0.0, 1.0) * 65535.0) as u16,
                    label: s.material.label() as u8,
                    owner: plot
                        .scene
                        .prims
                        .get(hit.prim as usize)
                        .map_or(0, |q| q.owner),
                });
            }
        }
        out
    };

    let mut returns: Vec<Return> = Vec::with_capacity(params.points);
    let mut next = 0;
    while returns.len() < params.points && next < max_blocks {
        if progress.is_cancelled() {
            return Err(crate::io::IoError::Cancelled);
        }
        let end = (next + BATCH).min(max_blocks);
        let batch: Vec<Vec<Return>> = (next..end).into_par_iter().map(run_block).collect();
        batch.into_iter().for_each(|b| returns.extend(b));
        next = end;
        progress.set(returns.len() as f64 / params.points.max(1) as f64);
    }
    returns.truncate(params.points);
    let laps = next as f64 / blocks_per_lap as f64;
    let walked: f64 = loops
        .iter()
        .enumerate()
        .map(|(k, l)| (laps - k as f64).clamp(0.0, 1.0) * l.length())
        .sum();
    Ok(LidarScan {
        positions: returns.iter().map(|r| r.pos).collect(),
        colors: params.rgb.then(|| returns.iter().map(|r| r.rgb).collect()),
        intensity: returns.iter().map(|r| r.intensity).collect(),
        labels: returns.iter().map(|r| r.label).collect(),
        owners: returns.iter().map(|r| r.owner).collect(),
        trajectory_length_m: walked,
        rays_cast: (next * BEAMS * FIRINGS_PER_TURN) as u64,
        laps,
    })
}
