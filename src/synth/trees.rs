//! One tree as primitives: a straight, possibly leaning stem of chained elliptical cone
//! segments with butt flare and taper, arching tapered branches in two orders, and leaf
//! clusters of small oriented discs at the branch ends.
//!
//! Breast height is 1.3 m measured along the stem axis from the point where the axis meets
//! the ground (the forestry convention for leaning stems). The stem profile is linear between
//! 0.8 m and 2.0 m, so the 1.2–1.4 m slice is centred on the true breast-height section, and
//! DBH is the girth of that section (an ellipse perpendicular to the axis) divided by pi.

use glam::DVec3;
use serde::Serialize;

use super::presets::Species;
use super::rng::Stream;
use super::scene::{Material, Prim};
use super::shapes::{Cone, Disc, Shape};

/// Drawn parameters of one tree (scene frame, metres).
#[derive(Debug, Clone)]
pub struct TreeSpec {
    /// 1-based id.
    pub id: usize,
    /// Where the stem axis meets the ground.
    pub base: DVec3,
    pub dbh_m: f64,
    /// Nominal height from the height curve (the generated tree's height is measured).
    pub height_m: f64,
    pub crown_radius_m: f64,
    pub crown_base_m: f64,
    pub lean_deg: f64,
    pub lean_azimuth_deg: f64,
    /// Minor/major axis ratio of the stem cross-section, [0.95, 1].
    pub ellipse_ratio: f64,
    pub ellipse_azimuth_deg: f64,
    pub leafless: bool,
}

/// What is true of a generated tree (scene frame).
#[derive(Debug, Clone, Serialize)]
pub struct TreeTruth {
    pub id: usize,
    pub base: DVec3,
    /// Unit stem axis.
    pub axis: DVec3,
    /// Major cross-section direction (unit, perpendicular to `axis`).
    pub major_axis: DVec3,
    pub dbh_m: f64,
    /// Semi-axes of the breast-height section, metres.
    pub semi_axes_m: [f64; 2],
    /// Top of the tree above the base, metres (from the primitives' bounds).
    pub height_m: f64,
    /// The generator's nominal crown reach, metres (the lowest primary branches' reach).
    pub crown_radius_m: f64,
    pub crown_base_m: f64,
    /// Crown projection area: the convex hull of the tree's primitives seen from above (their
    /// bounds' corners), m².
    pub crown_area_m2: f64,
    pub lean_deg: f64,
    pub leafless: bool,
    pub species: &'static str,
    /// The band of heights along the axis above the base, metres, in which the scan saw none
    /// of this tree ([`super::SynthParams::hidden_stem_m`]); absent when nothing is hidden.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hidden_m: Option<[f64; 2]>,
}

impl TreeTruth {
    /// The stem axis point `s` metres along the axis from the base.
    pub fn axis_point(&self, s: f64) -> DVec3 {
        self.base + self.axis * s
    }
}

/// Perimeter of an ellipse with semi-axes a, b (Ramanujan's second approximation, relative
/// error below 1e-9 for the near-circular sections used here).
pub fn ellipse_perimeter(a: f64, b: f64) -> f64 {
    let h = ((a - b) / (a + b)).powi(2);
    std::f64::consts::PI * (a + b) * (1.0 + 3.0 * h / (10.0 + (4.0 - 3.0 * h).sqrt()))
}

/// Any unit vector perpendicular to unit `d`.
fn perpendicular(d: DVec3) -> DVec3 {
    let h = if d.z.abs() < 0.9 { DVec3::Z } else { DVec3::X };
    (h - d * h.dot(d)).normalize()
}

struct Builder<'a> {
    prims: Vec<Prim>,
    owner: u16,
    bark: [u8; 3],
    species: &'a Species,
}

impl Builder<'_> {
    /// A cone segment from `p0` along unit `d` over `len`, radii `r0` → `r1`, section axes
    /// `e1` (scale 1) and `d × e1` (scale `ratio`).
    #[allow(clippy::too_many_arguments)]
    fn segment(
        &mut self,
        p0: DVec3,
        d: DVec3,
        len: f64,
        r0: f64,
        r1: f64,
        e1: DVec3,
        ratio: f64,
        s0: f64,
    ) {
        let e2 = d.cross(e1);
        self.prims.push(Prim {
            shape: Shape::Cone(Cone {
                origin: p0.as_vec3(),
                e1: e1.as_vec3(),
                e2: e2.as_vec3(),
                axis: d.as_vec3(),
                a: 1.0,
                b: ratio as f32,
                r0: r0 as f32,
                k: ((r1 - r0) / len) as f32,
                len: len as f32,
                s0: s0 as f32,
            }),
            material: Material::Bark,
            tint: self.bark,
            owner: self.owner,
        });
    }

    /// A branch of `n` segments bending by `bend` radians of elevation per segment; returns
    /// the points and directions at the ends of its segments.
    #[allow(clippy::too_many_arguments)]
    fn branch(
        &mut self,
        rng: &mut Stream,
        start: DVec3,
        mut dir: DVec3,
        len: f64,
        r0: f64,
        r1: f64,
        n: usize,
        bend: f64,
    ) -> Vec<(DVec3, DVec3)> {
        let mut p = start;
        let mut out = Vec::with_capacity(n);
        let seg = len / n as f64;
        for k in 0..n {
            let (ra, rb) = (
                r0 + (r1 - r0) * k as f64 / n as f64,
                r0 + (r1 - r0) * (k + 1) as f64 / n as f64,
            );
            self.segment(p, dir, seg, ra, rb, perpendicular(dir), 1.0, k as f64 * seg);
            p += dir * seg;
            out.push((p, dir));
            // Bend: lower the elevation, wiggle the azimuth.
            let horiz = DVec3::new(dir.x, dir.y, 0.0);
            let el = dir.z.clamp(-1.0, 1.0).asin() - bend + rng.range(-0.12, 0.12);
            let az = horiz.y.atan2(horiz.x) + rng.range(-0.15, 0.15);
            let el = el.clamp(-0.6, 1.4);
            dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        }
        out
    }

    /// A leaf cluster: discs scattered in a flattened ball around `c`.
    fn cluster(&mut self, rng: &mut Stream, c: DVec3, radius: f64, leaf_tint: [u8; 3]) {
        let shade = rng.range(0.8, 1.15);
        for _ in 0..self.species.cluster_leaves {
            let mut off = rng.in_ball() * radius;
            off.z *= 0.7;
            let normal = (rng.unit_vector() + DVec3::new(0.0, 0.0, 0.9)).normalize_or(DVec3::Z);
            let b = shade * rng.range(0.75, 1.2);
            let jit = |v: u8, rng: &mut Stream| {
                (v as f64 * b * rng.range(0.92, 1.08)).clamp(0.0, 255.0) as u8
            };
            let tint = [
                jit(leaf_tint[0], rng),
                jit(leaf_tint[1], rng),
                jit(leaf_tint[2], rng),
            ];
            self.prims.push(Prim {
                shape: Shape::Disc(Disc {
                    center: (c + off).as_vec3(),
                    normal: normal.as_vec3(),
                    radius: (self.species.leaf_radius_m * rng.range(0.7, 1.3)) as f32,
                }),
                material: Material::Leaf,
                tint,
                owner: self.owner,
            });
        }
    }
}

/// Builds the primitives of one tree and what is true of it.
pub fn build_tree(spec: &TreeSpec, species: &Species, rng: &mut Stream) -> (Vec<Prim>, TreeTruth) {
    let lean = spec.lean_deg.to_radians();
    let laz = spec.lean_azimuth_deg.to_radians();
    let axis = DVec3::new(lean.sin() * laz.cos(), lean.sin() * laz.sin(), lean.cos());
    let eaz = spec.ellipse_azimuth_deg.to_radians();
    let h = DVec3::new(eaz.cos(), eaz.sin(), 0.0);
    let e1 = (h - axis * h.dot(axis)).normalize();
    let ratio = spec.ellipse_ratio;
    // Semi-axes (r, ratio r) with girth pi * DBH.
    let r_bh = std::f64::consts::PI * spec.dbh_m / ellipse_perimeter(1.0, ratio);
    let jitter =
        |rng: &mut Stream, v: u8| (v as f64 * rng.range(0.85, 1.15)).clamp(0.0, 255.0) as u8;
    let bark = [
        jitter(rng, species.bark[0]),
        jitter(rng, species.bark[1]),
        jitter(rng, species.bark[2]),
    ];
    let leaf_tint = [
        jitter(rng, species.leaf[0]),
        jitter(rng, species.leaf[1]),
        jitter(rng, species.leaf[2]),
    ];
    let mut b = Builder {
        prims: Vec::new(),
        owner: spec.id as u16,
        bark,
        species,
    };

    // Stem profile: (axial distance m, radius as a multiple of r_bh).
    let taper = rng.range(0.012, 0.02);
    let s_top = 0.8 * spec.height_m / lean.cos();
    let top_frac = 0.22;
    let mut knots = vec![
        (-0.4, 1.22),
        (0.0, 1.15),
        (0.8, 1.0 + 0.5 * taper),
        (2.0, 1.0 - 0.7 * taper),
    ];
    let n_upper = ((s_top - 2.0) / 1.5).ceil().max(1.0) as usize;
    for k in 1..=n_upper {
        let f = k as f64 / n_upper as f64;
        knots.push((
            2.0 + f * (s_top - 2.0),
            (1.0 - 0.7 * taper) * (1.0 - f) + top_frac * f,
        ));
    }
    for w in knots.windows(2) {
        let (s0, f0) = w[0];
        let (s1, f1) = w[1];
        b.segment(
            spec.base + axis * s0,
            axis,
            s1 - s0,
            f0 * r_bh,
            f1 * r_bh,
            e1,
            ratio,
            s0,
        );
    }
    let stem_radius = |s: f64| {
        knots
            .windows(2)
            .find(|w| s <= w[1].0)
            .map_or(top_frac, |w| {
                w[0].1 + (w[1].1 - w[0].1) * (s - w[0].0) / (w[1].0 - w[0].0)
            })
            * r_bh
    };

    // Leader: continues the stem to the nominal height.
    let top = spec.base + axis * s_top;
    let leader_len = (spec.height_m - top.z + spec.base.z - species.cluster_radius_m).max(0.5);
    let ends = b.branch(
        rng,
        top,
        DVec3::Z,
        leader_len,
        top_frac * r_bh,
        0.008,
        2,
        0.0,
    );
    if !spec.leafless
        && let Some(&(p, _)) = ends.last()
    {
        b.cluster(rng, p, species.cluster_radius_m, leaf_tint);
    }

    // Primary branches spiral up the crown (golden angle), longer below.
    let rc = spec.crown_radius_m;
    let s_cb = spec.crown_base_m / lean.cos();
    let n_primary = (5.0 + 2.2 * rc).round().clamp(6.0, 24.0) as usize;
    let phase = rng.range(0.0, std::f64::consts::TAU);
    for i in 0..n_primary {
        let frac = ((i as f64 + 0.5 + rng.range(-0.2, 0.2)) / n_primary as f64).clamp(0.0, 1.0);
        let s = s_cb + frac * (s_top - s_cb) * 0.97;
        let az = phase + i as f64 * 2.399_963 + rng.range(-0.3, 0.3);
        let el = (25.0 + 35.0 * frac + rng.range(-10.0, 10.0)).to_radians();
        let reach = rc * (1.0 - 0.55 * frac) * rng.range(0.8, 1.05);
        let len = reach / (el.cos() * 0.85).max(0.3);
        let r0 = (0.6 * stem_radius(s))
            .min(r_bh * (0.2 + 0.3 * reach / rc))
            .max(0.015);
        let dir = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let bend = rng.range(0.12, 0.25);
        let ends = b.branch(rng, spec.base + axis * s, dir, len, r0, 0.01, 3, bend);
        if !spec.leafless
            && let Some(&(p, _)) = ends.last()
        {
            b.cluster(rng, p, species.cluster_radius_m, leaf_tint);
        }
        // Secondary branches from the outer two thirds of the primary.
        let n_sec = (1.0 + len / 1.1).round().clamp(2.0, 7.0) as usize;
        for k in 0..n_sec {
            let f = 0.3 + 0.65 * (k as f64 + 0.5) / n_sec as f64;
            let seg = ((f * 3.0) as usize).min(2);
            let (p_end, d) = ends.get(seg).copied().unwrap_or((spec.base, DVec3::Z));
            let back = (seg as f64 + 1.0 - f * 3.0) * len / 3.0;
            let start = p_end - d * back;
            let side = if k % 2 == 0 { 1.0 } else { -1.0 };
            let saz = d.y.atan2(d.x) + side * rng.range(0.6, 1.15);
            let sel = d.z.asin() + rng.range(0.0, 0.45);
            let sdir = DVec3::new(sel.cos() * saz.cos(), sel.cos() * saz.sin(), sel.sin());
            let slen = len * rng.range(0.3, 0.5) * (1.0 - 0.4 * f);
            let sr0 = (0.6 * (r0 + (0.01 - r0) * f)).max(0.008);
            let sends = b.branch(rng, start, sdir, slen, sr0, 0.006, 2, 0.1);
            for (n, &(p, d2)) in sends.iter().enumerate() {
                if spec.leafless {
                    // Twigs instead of leaves.
                    for _ in 0..2 {
                        let tdir = (d2 + rng.unit_vector() * 0.8).normalize_or(d2);
                        let tlen = rng.range(0.3, 0.6);
                        b.branch(rng, p, tdir, tlen, 0.006, 0.003, 1, 0.0);
                    }
                } else {
                    b.cluster(rng, p, species.cluster_radius_m, leaf_tint);
                    if n + 1 == sends.len() {
                        // A second, offset cluster fills the outer crown.
                        let q = p
                            + d2 * (0.6 * species.cluster_radius_m)
                            + rng.unit_vector() * (0.3 * species.cluster_radius_m);
                        b.cluster(rng, q, species.cluster_radius_m, leaf_tint);
                    }
                }
            }
        }
    }

    let top_z = b
        .prims
        .iter()
        .map(|p| p.shape.bounds().1.z)
        .fold(f32::NEG_INFINITY, f32::max) as f64;
    let corners: geo::MultiPoint<f64> = b
        .prims
        .iter()
        .flat_map(|p| {
            let (lo, hi) = p.shape.bounds();
            [(lo.x, lo.y), (lo.x, hi.y), (hi.x, lo.y), (hi.x, hi.y)]
                .map(|(x, y)| geo::Point::new(f64::from(x), f64::from(y)))
        })
        .collect();
    let crown_area_m2 = geo::Area::unsigned_area(&geo::ConvexHull::convex_hull(&corners));
    let truth = TreeTruth {
        id: spec.id,
        base: spec.base,
        axis,
        major_axis: e1,
        dbh_m: spec.dbh_m,
        semi_axes_m: [r_bh, r_bh * ratio],
        height_m: top_z - spec.base.z,
        crown_radius_m: rc,
        crown_base_m: spec.crown_base_m,
        crown_area_m2,
        lean_deg: spec.lean_deg,
        leafless: spec.leafless,
        species: species.name,
        hidden_m: None,
    };
    (b.prims, truth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ellipse_perimeter_is_exact_for_circles_and_close_for_ellipses() {
        assert!((ellipse_perimeter(1.0, 1.0) - std::f64::consts::TAU).abs() < 1e-12);
        // Numerical integration of an ellipse 1 x 0.9.
        let n = 200_000;
        let p: f64 = (0..n)
            .map(|i| {
                let t = (i as f64 + 0.5) / n as f64 * std::f64::consts::TAU;
                (t.sin().powi(2) + (0.9 * t.cos()).powi(2)).sqrt() * std::f64::consts::TAU
                    / n as f64
            })
            .sum();
        assert!((ellipse_perimeter(1.0, 0.9) - p).abs() < 1e-8);
    }
}
