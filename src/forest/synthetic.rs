//! A synthetic forest plot with known truth, for tests and benchmarks (until the project's
//! plot generator is merged).
//!
//! Terrain with a slope and a gentle wave; trees with DBH 8–60 cm, some leaning up to 10°,
//! slightly elliptical, tapering; main branches; crowns of small leaf discs; a few bushes.
//! Stems and branches are scanned like a rotating handheld LiDAR from a few viewpoints:
//! rays on rings of constant elevation (`ring_step_deg`) and azimuth steps
//! (`azimuth_step_deg`) are cast at each stem, occluded by the other stems, with Gaussian
//! range noise along the ray. Ground, leaves and bushes are sampled directly (they do not
//! occlude; a simplification).

use glam::{DVec3, Vec2, Vec3};

use crate::io::pointcloud::{CloudFormat, PointCloud};
use crate::rng::SplitMix64;

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotSpec {
    /// Edge of the square plot, metres.
    pub size_m: f32,
    pub n_trees: usize,
    pub seed: u64,
    /// Scanner positions as fractions of the plot edge (height 1.5 m above ground).
    pub viewpoints: Vec<[f32; 2]>,
    /// Range noise (1 sigma), metres.
    pub noise_m: f32,
    pub ring_step_deg: f32,
    pub azimuth_step_deg: f32,
    /// Ground sample spacing, metres.
    pub ground_spacing_m: f32,
    /// Shoots (clumps of 20 leaf discs, sigma 3 cm) per tree.
    pub leaf_discs: usize,
    /// Local origin added as the cloud's offset (a projected CRS, metres).
    pub offset: DVec3,
}

impl Default for PlotSpec {
    fn default() -> Self {
        Self {
            size_m: 20.0,
            n_trees: 14,
            seed: 7,
            viewpoints: vec![
                [0.25, 0.3],
                [0.75, 0.25],
                [0.3, 0.75],
                [0.7, 0.7],
                [0.5, 0.48],
            ],
            noise_m: 0.01,
            ring_step_deg: 2.0,
            azimuth_step_deg: 0.1,
            ground_spacing_m: 0.06,
            leaf_discs: 150,
            offset: DVec3::new(512_000.0, 5_400_000.0, 300.0),
        }
    }
}

/// One generated tree (local coordinates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthTree {
    /// Where the axis meets the terrain.
    pub base: Vec3,
    /// Unit axis (up).
    pub axis: Vec3,
    pub dbh_cm: f32,
    pub height_m: f32,
    /// Relative difference of the cross-section's semi-axes from the mean radius.
    pub ellipticity: f32,
}

/// A generated plot with its truth.
#[derive(Debug, Clone)]
pub struct SyntheticPlot {
    pub cloud: PointCloud,
    pub trees: Vec<TruthTree>,
    pub is_ground: Vec<bool>,
    /// True for stem and main-branch points.
    pub is_trunk: Vec<bool>,
}

/// Terrain height (local metres): a 10% slope in x, 5% in y and a 0.3 m wave.
pub fn terrain_height(x: f32, y: f32) -> f32 {
    0.1 * x + 0.05 * y + 0.3 * (0.25 * x).sin() * (0.2 * y).cos()
}

impl TruthTree {
    fn radius_at(&self, s: f32) -> f32 {
        let r = self.dbh_cm / 200.0;
        (r * (1.0 - 0.7 * (s - 1.3) / (self.height_m - 1.3))).max(0.015)
    }
    /// Frame (e1, e2) perpendicular to the axis; the ellipse's major axis is e1.
    fn frame(&self) -> (Vec3, Vec3) {
        let e1 = self.axis.cross(Vec3::Z).normalize_or(Vec3::X);
        (e1, self.axis.cross(e1))
    }
    /// First hit of the ray `o + t d` (t > 0) with the trunk below 0.8 of its height.
    fn hit(&self, o: Vec3, d: Vec3) -> Option<f32> {
        let (e1, e2) = self.frame();
        let rel = o - self.base;
        let (a1, a2) = (1.0 + self.ellipticity, 1.0 - self.ellipticity);
        let (ou, ow) = (rel.dot(e1) / a1, rel.dot(e2) / a2);
        let (du, dw) = (d.dot(e1) / a1, d.dot(e2) / a2);
        let mut r = self.radius_at(1.3);
        let mut t = None;
        for _ in 0..3 {
            let a = du * du + dw * dw;
            let b = 2.0 * (ou * du + ow * dw);
            let c = ou * ou + ow * ow - r * r;
            let disc = b * b - 4.0 * a * c;
            if a < 1e-12 || disc < 0.0 {
                return None;
            }
            let t0 = (-b - disc.sqrt()) / (2.0 * a);
            if t0 <= 0.0 {
                return None;
            }
            let s = (rel + d * t0).dot(self.axis);
            if !(0.0..=0.8 * self.height_m).contains(&s) {
                return None;
            }
            r = self.radius_at(s);
            t = Some(t0);
        }
        t
    }
}

fn gauss(rng: &mut SplitMix64) -> f32 {
    let u1 = rng.uniform().max(1e-12);
    let u2 = rng.uniform();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

fn range(rng: &mut SplitMix64, lo: f32, hi: f32) -> f32 {
    lo + (hi - lo) * rng.uniform() as f32
}

/// Generates the plot described by `spec`.
pub fn synthetic_plot(spec: &PlotSpec) -> SyntheticPlot {
    let mut rng = SplitMix64::new(spec.seed);
    let size = spec.size_m;
    // Trees at least 2.5 m apart, 1.5 m inside the edge.
    let mut trees: Vec<TruthTree> = Vec::new();
    let mut attempts = 0;
    while trees.len() < spec.n_trees && attempts < 10_000 {
        attempts += 1;
        let xy = Vec2::new(
            range(&mut rng, 1.5, size - 1.5),
            range(&mut rng, 1.5, size - 1.5),
        );
        let vp_clear = spec
            .viewpoints
            .iter()
            .all(|v| (Vec2::new(v[0], v[1]) * size).distance(xy) > 1.5);
        if !vp_clear || trees.iter().any(|t| t.base.truncate().distance(xy) < 2.5) {
            continue;
        }
        let k = trees.len();
        let lean = if k.is_multiple_of(3) {
            range(&mut rng, 3.0, 10.0)
        } else {
            range(&mut rng, 0.0, 2.0)
        };
        let az = range(&mut rng, 0.0, std::f32::consts::TAU);
        let (sl, cl) = lean.to_radians().sin_cos();
        let dbh = if k == 0 {
            8.0
        } else if k == 1 {
            60.0
        } else {
            range(&mut rng, 8.0, 60.0)
        };
        trees.push(TruthTree {
            base: Vec3::new(xy.x, xy.y, terrain_height(xy.x, xy.y)),
            axis: Vec3::new(sl * az.cos(), sl * az.sin(), cl),
            dbh_cm: dbh,
            height_m: 10.0 + dbh / 4.0 + range(&mut rng, 0.0, 4.0),
            ellipticity: range(&mut rng, 0.0, 0.04),
        });
    }
    let (mut pts, mut ground, mut trunk) = (Vec::new(), Vec::new(), Vec::new());
    let mut push = |p: Vec3, g: bool, t: bool| {
        pts.push(p);
        ground.push(g);
        trunk.push(t);
    };
    // Stems: scanned from each viewpoint.
    let views: Vec<Vec3> = spec
        .viewpoints
        .iter()
        .map(|v| {
            let (x, y) = (v[0] * size, v[1] * size);
            Vec3::new(x, y, terrain_height(x, y) + 1.5)
        })
        .collect();
    for o in &views {
        for (ti, tree) in trees.iter().enumerate() {
            let rel = tree.base.truncate() - o.truncate();
            let dist = rel.length();
            let half = ((tree.dbh_cm / 100.0 + 0.05) / dist).asin().to_degrees() + 3.0;
            let az0 = rel.y.atan2(rel.x).to_degrees();
            let top = tree.base.z + 0.8 * tree.height_m - o.z;
            let (el_lo, el_hi) = (
                (tree.base.z - 0.2 - o.z).atan2(dist + 1.0),
                top.atan2(dist - 1.0),
            );
            let (el_lo, el_hi) = (el_lo.to_degrees().max(-80.0), el_hi.to_degrees().min(80.0));
            let mut el = (el_lo / spec.ring_step_deg).floor() * spec.ring_step_deg;
            while el <= el_hi {
                let mut az = ((az0 - half) / spec.azimuth_step_deg).floor() * spec.azimuth_step_deg;
                while az <= az0 + half {
                    let (se, ce) = el.to_radians().sin_cos();
                    let (sa, ca) = az.to_radians().sin_cos();
                    let d = Vec3::new(ce * ca, ce * sa, se);
                    if let Some(t) = tree.hit(*o, d) {
                        let blocked = trees
                            .iter()
                            .enumerate()
                            .any(|(j, u)| j != ti && u.hit(*o, d).is_some_and(|tu| tu < t));
                        let gz = terrain_height(o.x + d.x * t, o.y + d.y * t);
                        if !blocked && o.z + d.z * t > gz {
                            let noisy = t + spec.noise_m * gauss(&mut rng);
                            push(*o + d * noisy, false, true);
                        }
                    }
                    az += spec.azimuth_step_deg;
                }
                el += spec.ring_step_deg;
            }
        }
    }

    // Main branches: 4 per tree, sampled along their length on rings.
    for tree in &trees {
        for b in 0..4 {
            let s0 = tree.height_m * range(&mut rng, 0.45, 0.75);
            let start = tree.base + tree.axis * s0;
            let az = range(&mut rng, 0.0, std::f32::consts::TAU) + b as f32;
            let dir = Vec3::new(az.cos(), az.sin(), range(&mut rng, 0.4, 1.2)).normalize();
            let (len, rb) = (range(&mut rng, 1.0, 2.5), range(&mut rng, 0.02, 0.04));
            let (e1, e2) = (
                dir.any_orthonormal_vector(),
                dir.any_orthonormal_vector().cross(dir),
            );
            let n = (len / 0.01) as usize;
            for k in 0..n {
                let a = range(&mut rng, 0.0, std::f32::consts::TAU);
                let p = start + dir * (k as f32 * 0.01) + (e1 * a.cos() + e2 * a.sin()) * rb;
                push(
                    p + Vec3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng))
                        * spec.noise_m
                        * 0.5,
                    false,
                    true,
                );
            }
        }
    }
    // Leaves: small discs (radius 1.5–2.5 cm, 5 points, 20 per shoot) in a crown ellipsoid; bushes likewise.
    let disc = |rng: &mut SplitMix64, c: Vec3, push: &mut dyn FnMut(Vec3, bool, bool)| {
        let nrm = Vec3::new(gauss(rng), gauss(rng), gauss(rng)).normalize_or(Vec3::Z);
        let (e1, e2) = (
            nrm.any_orthonormal_vector(),
            nrm.cross(nrm.any_orthonormal_vector()),
        );
        let r = range(rng, 0.015, 0.025);
        for _ in 0..5 {
            let (a, q) = (
                range(rng, 0.0, std::f32::consts::TAU),
                rng.uniform().sqrt() as f32 * r,
            );
            let p = c + (e1 * a.cos() + e2 * a.sin()) * q + nrm * spec.noise_m * gauss(rng);
            push(p, false, false);
        }
    };
    for tree in &trees {
        let centre = tree.base + tree.axis * (0.7 * tree.height_m);
        let (rh, rv) = (1.0 + tree.dbh_cm / 25.0, 0.3 * tree.height_m);
        for _ in 0..spec.leaf_discs {
            let v = loop {
                let v = Vec3::new(
                    range(&mut rng, -1.0, 1.0),
                    range(&mut rng, -1.0, 1.0),
                    range(&mut rng, -1.0, 1.0),
                );
                if v.length_squared() <= 1.0 && v.truncate().length() > 0.15 {
                    break v;
                }
            };
            // A shoot: a Gaussian clump of discs (sigma 3 cm).
            let shoot = centre + Vec3::new(v.x * rh, v.y * rh, v.z * rv);
            for _ in 0..20 {
                let o = Vec3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.03;
                disc(&mut rng, shoot + o, &mut push);
            }
        }
    }
    for b in 0..3 {
        let xy = Vec2::new(
            range(&mut rng, 2.0, size - 2.0),
            range(&mut rng, 2.0, size - 2.0),
        );
        if trees.iter().any(|t| t.base.truncate().distance(xy) < 1.2) {
            continue;
        }
        let centre = Vec3::new(
            xy.x,
            xy.y,
            terrain_height(xy.x, xy.y) + 0.7 + 0.1 * b as f32,
        );
        for _ in 0..300 {
            let v = Vec3::new(
                range(&mut rng, -1.0, 1.0),
                range(&mut rng, -1.0, 1.0),
                range(&mut rng, -1.0, 1.0),
            );
            if v.length_squared() <= 1.0 {
                disc(&mut rng, centre + v * 0.6, &mut push);
            }
        }
    }
    // Ground: a jittered grid with noise, not inside stems.
    let n = (size / spec.ground_spacing_m) as usize;
    for i in 0..n {
        for j in 0..n {
            let x = (i as f32 + rng.uniform() as f32) * spec.ground_spacing_m;
            let y = (j as f32 + rng.uniform() as f32) * spec.ground_spacing_m;
            if trees
                .iter()
                .any(|t| t.base.truncate().distance(Vec2::new(x, y)) < t.dbh_cm / 200.0)
            {
                continue;
            }
            push(
                Vec3::new(x, y, terrain_height(x, y) + spec.noise_m * gauss(&mut rng)),
                true,
                false,
            );
        }
    }

    SyntheticPlot {
        cloud: PointCloud {
            offset: spec.offset,
            positions: pts,
            colors: None,
            intensity: None,
            format: CloudFormat::Las,
        },
        trees,
        is_ground: ground,
        is_trunk: trunk,
    }
}

/// Tiles `plot` `nx` × `ny` times; odd columns are mirrored in x and odd rows in y, so the
/// terrain, and every stem, continues across tile edges. Returns the cloud and the trees.
pub fn tile_plot(
    plot: &SyntheticPlot,
    size_m: f32,
    nx: usize,
    ny: usize,
) -> (PointCloud, Vec<TruthTree>) {
    let mut positions = Vec::with_capacity(plot.cloud.len() * nx * ny);
    let mut trees = Vec::new();
    for i in 0..nx {
        for j in 0..ny {
            let map = |p: Vec3| {
                let x = if i % 2 == 1 {
                    (i + 1) as f32 * size_m - p.x
                } else {
                    i as f32 * size_m + p.x
                };
                let y = if j % 2 == 1 {
                    (j + 1) as f32 * size_m - p.y
                } else {
                    j as f32 * size_m + p.y
                };
                Vec3::new(x, y, p.z)
            };
            let flip = Vec3::new(
                if i % 2 == 1 { -1.0 } else { 1.0 },
                if j % 2 == 1 { -1.0 } else { 1.0 },
                1.0,
            );
            positions.extend(plot.cloud.positions.iter().map(|p| map(*p)));
            trees.extend(plot.trees.iter().map(|t| TruthTree {
                base: map(t.base),
                axis: t.axis * flip,
                ..*t
            }));
        }
    }
    let cloud = PointCloud {
        offset: plot.cloud.offset,
        positions,
        colors: None,
        intensity: None,
        format: plot.cloud.format,
    };
    (cloud, trees)
}
