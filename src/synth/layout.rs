//! Lays out a plot: terrain, tree positions and sizes, stones and low shrubs, then builds the
//! scene. Every draw comes from a stream keyed by the seed, so the plot is a pure function of
//! the parameters; trees are built in parallel, each from its own stream.

use glam::{DVec3, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use super::presets::PresetConfig;
use super::rng::{Stream, domain};
use super::scene::{Material, Prim, Scene};
use super::shapes::{Disc, Ellipsoid, Shape};
use super::terrain::Terrain;
use super::trees::{TreeSpec, TreeTruth, build_tree};

/// Terrain margin beyond the plot radius, metres (nadir views over the plot edge and oblique
/// views see ground, not a void).
const TERRAIN_MARGIN_M: f64 = 24.0;

/// A partly buried stone (scene frame).
#[derive(Debug, Clone, Serialize)]
pub struct Stone {
    pub id: usize,
    pub center: DVec3,
    pub radii: DVec3,
    pub yaw_deg: f64,
    /// Highest point of the stone: a well-defined control point.
    pub top: DVec3,
}

/// A generated plot and what is true of it.
pub struct Plot {
    pub scene: Scene,
    pub trees: Vec<TreeTruth>,
    pub stones: Vec<Stone>,
    pub shrubs: usize,
    /// Radius of the plot disc around the origin, metres.
    pub radius_m: f64,
}

/// Plot inputs resolved from the preset and the user's overrides.
pub struct LayoutParams {
    pub config: PresetConfig,
    pub seed: u64,
    pub trees: Option<usize>,
    pub leafless: bool,
    /// DBH of the first trees, centimetres, in place of the draw (see
    /// [`super::SynthParams::stem_dbh_cm`]).
    pub stem_dbh_cm: Vec<f64>,
    /// Grade of the terrain's planar part, percent, in place of the draw.
    pub slope_pct: Option<f64>,
    /// Longest hidden band of the upper stem, metres (see
    /// [`super::SynthParams::hidden_stem_m`]).
    pub hidden_stem_m: Option<f64>,
    /// Crown reach added after placement, as a share (see
    /// [`super::SynthParams::crown_interlock`]).
    pub crown_interlock: Option<f64>,
}

/// Lognormal DBH (cm) truncated to the species range.
fn draw_dbh_cm(rng: &mut Stream, (median, sigma, lo, hi): (f64, f64, f64, f64)) -> f64 {
    for _ in 0..200 {
        let d = median * (sigma * rng.normal()).exp();
        if (lo..=hi).contains(&d) {
            return d;
        }
    }
    median.clamp(lo, hi)
}

/// Builds the plot.
pub fn build_plot(p: &LayoutParams) -> Plot {
    let cfg = &p.config;
    let sp = &cfg.species;
    let mut rng = Stream::new(p.seed, domain::LAYOUT, 0);
    let n = p
        .trees
        .unwrap_or_else(|| cfg.trees.0 + rng.below(cfg.trees.1 - cfg.trees.0 + 1))
        .max(1);

    // Sizes first, then the plot radius they imply, then positions.
    let mut specs: Vec<TreeSpec> = (0..n)
        .map(|i| {
            let drawn = draw_dbh_cm(&mut rng, sp.dbh_cm);
            let d_cm = p.stem_dbh_cm.get(i).copied().unwrap_or(drawn);
            let height = sp.height_m(d_cm) * rng.range(0.92, 1.08);
            let lean = sp.max_lean_deg * rng.uniform().powi(2);
            TreeSpec {
                id: i + 1,
                base: DVec3::ZERO,
                dbh_m: d_cm / 100.0,
                height_m: height,
                crown_radius_m: sp.crown_radius_m(d_cm) * rng.range(0.9, 1.1),
                crown_base_m: (height * rng.range(sp.crown_base.0, sp.crown_base.1)).max(2.5),
                lean_deg: lean,
                lean_azimuth_deg: rng.range(0.0, 360.0),
                ellipse_ratio: rng.range(0.95, 1.0),
                ellipse_azimuth_deg: rng.range(0.0, 180.0),
                leafless: p.leafless,
            }
        })
        .collect();
    let crown_area: f64 = specs.iter().map(|s| s.crown_radius_m.powi(2)).sum();
    let radius = match cfg.canopy_closure {
        // Crowns overlap and their foliage has gaps, so they cover less than their disc area:
        // sizing for 1.2 × the target closure gives about the target when measured.
        Some(c) => (crown_area / (1.2 * c)).sqrt(),
        None if cfg.plot_radius_m > 0.0 => cfg.plot_radius_m,
        None => specs[0].crown_radius_m + 3.0,
    };
    let noise_seed = (p.seed ^ (p.seed >> 32)) as u32;
    let terrain = Terrain::generate(
        &mut rng,
        radius + TERRAIN_MARGIN_M,
        cfg.relief_m,
        noise_seed,
        p.slope_pct.map(|g| g / 100.0),
    );

    let mut placed: Vec<[f64; 2]> = Vec::with_capacity(n);
    if n == 1 {
        placed.push([0.0, 0.0]);
    } else {
        for s in &specs {
            let mut spacing = 1.0;
            let mut tries = 0;
            let xy = loop {
                let a = rng.range(0.0, std::f64::consts::TAU);
                let r = 0.85 * radius * rng.uniform().sqrt();
                let c = [r * a.cos(), r * a.sin()];
                let ok = placed.iter().zip(&specs).all(|(q, o)| {
                    let min = (0.6 * (s.crown_radius_m + o.crown_radius_m)).max(2.0) * spacing;
                    (c[0] - q[0]).hypot(c[1] - q[1]) >= min
                });
                tries += 1;
                if ok || spacing < 0.3 {
                    break c;
                }
                if tries % 200 == 0 {
                    spacing *= 0.9;
                }
            };
            placed.push(xy);
        }
    }
    for (s, xy) in specs.iter_mut().zip(&placed) {
        s.base = DVec3::new(xy[0], xy[1], terrain.height(xy[0], xy[1]));
        // Placed for their own reach, grown into each other's (no draw: the default plot
        // is unchanged).
        if let Some(more) = p.crown_interlock {
            s.crown_radius_m *= 1.0 + more;
        }
    }

    let mut prims = terrain.triangles();
    let built: Vec<(Vec<Prim>, TreeTruth)> = specs
        .par_iter()
        .map(|s| build_tree(s, sp, &mut Stream::new(p.seed, domain::TREE, s.id as u64)))
        .collect();
    let mut trees = Vec::with_capacity(n);
    for (tp, mut truth) in built {
        prims.extend(tp);
        // The band of the upper stem the scan does not see, from its own stream so that
        // every other draw stays as it was.
        if let Some(longest) = p.hidden_stem_m {
            let mut r = Stream::new(p.seed, domain::HIDDEN, truth.id as u64);
            let len = r.range(0.3, longest.max(0.3));
            truth.hidden_m = Some([truth.crown_base_m, truth.crown_base_m + len]);
        }
        trees.push(truth);
    }

    // Low shrubs beside some stems.
    let mut shrubs = 0;
    for t in &trees {
        if !rng.chance(cfg.shrub_share) {
            continue;
        }
        for _ in 0..1 + rng.below(3) {
            let a = rng.range(0.0, std::f64::consts::TAU);
            let d = t.semi_axes_m[0] + rng.range(0.7, 1.6);
            let (x, y) = (t.base.x + d * a.cos(), t.base.y + d * a.sin());
            let c = DVec3::new(x, y, terrain.height(x, y));
            shrub(
                &mut prims,
                &mut Stream::new(p.seed, domain::SHRUB, shrubs as u64),
                c,
                &terrain,
            );
            shrubs += 1;
        }
    }

    // Stones: half beside stems, half anywhere in the plot, never inside a stem or stone.
    let mut stones: Vec<Stone> = Vec::new();
    let mut attempts = 0;
    while stones.len() < cfg.stones && attempts < 5000 {
        attempts += 1;
        let rx = rng.range(0.18, 0.45);
        let radii = DVec3::new(rx, rx * rng.range(0.6, 1.0), rx * rng.range(0.4, 0.65));
        let (x, y) = if rng.chance(0.5) {
            let t = &trees[rng.below(trees.len())];
            let a = rng.range(0.0, std::f64::consts::TAU);
            let d = t.semi_axes_m[0] + rx + rng.range(0.5, 2.0);
            (t.base.x + d * a.cos(), t.base.y + d * a.sin())
        } else {
            let a = rng.range(0.0, std::f64::consts::TAU);
            let r = 0.9 * radius * rng.uniform().sqrt();
            (r * a.cos(), r * a.sin())
        };
        let clear_stems = trees
            .iter()
            .all(|t| (x - t.base.x).hypot(y - t.base.y) > t.semi_axes_m[0] * 1.3 + rx + 0.3);
        let clear_stones = stones
            .iter()
            .all(|s| (x - s.center.x).hypot(y - s.center.y) > s.radii.x + rx + 0.3);
        if !(clear_stems && clear_stones) {
            continue;
        }
        let center = DVec3::new(x, y, terrain.height(x, y) - 0.3 * radii.z);
        let yaw = rng.range(0.0, 180.0);
        let grey = rng.range(105.0, 150.0);
        prims.push(Prim {
            shape: Shape::Ellipsoid(Ellipsoid {
                center: center.as_vec3(),
                yaw: (yaw.to_radians().cos() as f32, yaw.to_radians().sin() as f32),
                radii: radii.as_vec3(),
            }),
            material: Material::Stone,
            tint: [grey as u8, (grey * 0.98) as u8, (grey * 0.93) as u8],
            owner: 0,
        });
        stones.push(Stone {
            id: stones.len() + 1,
            center,
            radii,
            yaw_deg: yaw,
            top: center + DVec3::new(0.0, 0.0, radii.z),
        });
    }

    Plot {
        scene: Scene::new(prims, terrain, noise_seed ^ 0x5a5a),
        trees,
        stones,
        shrubs,
        radius_m: radius,
    }
}

/// A low shrub at ground point `c`: leaf discs in a half-buried ellipsoid, 0.4–0.9 m tall.
fn shrub(prims: &mut Vec<Prim>, rng: &mut Stream, c: DVec3, terrain: &Terrain) {
    let h = rng.range(0.4, 0.9);
    let r = rng.range(0.35, 0.7);
    let n = 80 + rng.below(80);
    for _ in 0..n {
        let off = rng.in_ball();
        let p = DVec3::new(c.x + off.x * r, c.y + off.y * r, 0.0);
        let ground = terrain.height(p.x, p.y);
        let z = ground + 0.05 + (off.z * 0.5 + 0.5) * h;
        let normal = (rng.unit_vector() + DVec3::new(0.0, 0.0, 0.5)).normalize_or(DVec3::Z);
        let b = rng.range(0.7, 1.2);
        prims.push(Prim {
            shape: Shape::Disc(Disc {
                center: Vec3::new(p.x as f32, p.y as f32, z as f32),
                normal: normal.as_vec3(),
                radius: rng.range(0.035, 0.065) as f32,
            }),
            material: Material::Shrub,
            tint: [(58.0 * b) as u8, (84.0 * b) as u8, (36.0 * b) as u8],
            owner: 0,
        });
    }
}

/// Share of the plot disc covered by tree parts more than 2 m above ground, seen from above
/// (canopy closure; 0.25 m sample grid).
pub fn canopy_closure(plot: &Plot) -> f64 {
    let step = 0.25;
    let n = (2.0 * plot.radius_m / step).ceil() as usize;
    let (covered, total) = (0..n)
        .into_par_iter()
        .map(|j| {
            let mut c = (0usize, 0usize);
            for i in 0..n {
                let x = -plot.radius_m + (i as f64 + 0.5) * step;
                let y = -plot.radius_m + (j as f64 + 0.5) * step;
                if x.hypot(y) > plot.radius_m {
                    continue;
                }
                c.1 += 1;
                let o = Vec3::new(x as f32, y as f32, 200.0);
                if let Some(hit) = plot.scene.intersect(o, Vec3::NEG_Z, 0.0, 400.0) {
                    let prim = &plot.scene.prims[hit.prim as usize];
                    let z = 200.0 - hit.t as f64;
                    if matches!(prim.material, Material::Leaf | Material::Bark)
                        && z - plot.scene.terrain.height(x, y) > 2.0
                    {
                        c.0 += 1;
                    }
                }
            }
            c
        })
        .collect::<Vec<_>>()
        .into_iter()
        .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    covered as f64 / total.max(1) as f64
}
