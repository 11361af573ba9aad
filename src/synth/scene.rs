//! The scene both simulators see: primitives with materials, the BVH over them, and the
//! surface appearance (albedo, normal, LiDAR reflectance) at a hit.
//!
//! Frame: metres, z up, origin at the plot centre at about ground level ("scene frame"). The
//! LiDAR file's coordinates are scene coordinates plus the georeferenced-like offset.

use glam::Vec3;

use super::bvh::Bvh;
use super::rng::{fbm2, noise3};
use super::shapes::{Interval, Shape};
use super::terrain::Terrain;

/// Per-point class of the LiDAR labels (`labels.bin`, one byte per point).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Label {
    Ground = 0,
    /// Trunk and branches.
    Wood = 1,
    Leaf = 2,
    /// Stones and shrubs.
    Other = 3,
}

/// What a primitive is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Material {
    Ground,
    Bark,
    Leaf,
    Stone,
    Shrub,
}

impl Material {
    pub fn label(self) -> Label {
        match self {
            Material::Ground => Label::Ground,
            Material::Bark => Label::Wood,
            Material::Leaf => Label::Leaf,
            Material::Stone | Material::Shrub => Label::Other,
        }
    }

    /// Reflectance at the scanner's 905 nm wavelength, [0, 1] (vegetation is bright in the
    /// near infrared; values are typical of published leaf/bark/soil spectra).
    pub fn nir_reflectance(self) -> f32 {
        match self {
            Material::Ground => 0.30,
            Material::Bark => 0.40,
            Material::Leaf => 0.55,
            Material::Stone => 0.35,
            Material::Shrub => 0.50,
        }
    }
}

/// One primitive with its appearance: `tint` is its base colour (sRGB, 8 bit), `owner` the
/// tree index + 1 (0 for none).
#[derive(Debug, Clone, Copy)]
pub struct Prim {
    pub shape: Shape,
    pub material: Material,
    pub tint: [u8; 3],
    pub owner: u16,
}

/// Appearance of the surface at a hit.
#[derive(Debug, Clone, Copy)]
pub struct Surface {
    pub point: Vec3,
    /// Unit normal facing the incoming ray.
    pub normal: Vec3,
    /// Linear albedo in [0, 1].
    pub albedo: Vec3,
    pub material: Material,
    /// |cos| of the incidence angle.
    pub cos_incidence: f32,
}

/// A ray hit: distance along the ray (metres) and primitive index.
#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub t: f32,
    pub prim: u32,
}

/// The whole scene, ready for ray casting.
pub struct Scene {
    pub prims: Vec<Prim>,
    bvh: Bvh,
    pub terrain: Terrain,
    texture_seed: u32,
}

/// sRGB (8 bit) to linear.
pub fn srgb_to_linear(c: [u8; 3]) -> Vec3 {
    let f = |v: u8| {
        let x = v as f32 / 255.0;
        if x <= 0.04045 {
            x / 12.92
        } else {
            ((x + 0.055) / 1.055).powf(2.4)
        }
    };
    Vec3::new(f(c[0]), f(c[1]), f(c[2]))
}

/// Linear to sRGB (8 bit), clamped.
pub fn linear_to_srgb(c: Vec3) -> [u8; 3] {
    let f = |x: f32| {
        let x = x.clamp(0.0, 1.0);
        let s = if x <= 0.003_130_8 {
            12.92 * x
        } else {
            1.055 * x.powf(1.0 / 2.4) - 0.055
        };
        (s * 255.0 + 0.5) as u8
    };
    [f(c.x), f(c.y), f(c.z)]
}

impl Scene {
    /// Builds the BVH and reorders `prims` into its leaf order (deterministic).
    pub fn new(prims: Vec<Prim>, terrain: Terrain, texture_seed: u32) -> Scene {
        let bounds: Vec<(Vec3, Vec3)> = prims.iter().map(|p| p.shape.bounds()).collect();
        let bvh = Bvh::build(&bounds);
        let prims = bvh.order.iter().map(|&i| prims[i as usize]).collect();
        Scene {
            prims,
            bvh,
            terrain,
            texture_seed,
        }
    }

    /// The same scene without its leaves (a leaf-off scan of a leafy plot).
    pub fn without_leaves(&self) -> Scene {
        let prims = self
            .prims
            .iter()
            .filter(|p| p.material != Material::Leaf)
            .copied()
            .collect();
        Scene::new(prims, self.terrain.clone(), self.texture_seed)
    }

    /// Nearest hit along the unit direction `d` in (tmin, tmax).
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        let prims = &self.prims;
        self.bvh
            .intersect(
                o,
                d,
                Interval {
                    min: tmin,
                    max: tmax,
                },
                |p, span| prims[p as usize].shape.intersect(o, d, span),
            )
            .map(|(t, prim)| Hit { t, prim })
    }

    /// True when something lies along `d` in (tmin, tmax).
    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> bool {
        let prims = &self.prims;
        self.bvh.any(
            o,
            d,
            Interval {
                min: tmin,
                max: tmax,
            },
            |p, span| prims[p as usize].shape.intersect(o, d, span).is_some(),
        )
    }

    /// True when the straight segment from `a` to `b` is free, ignoring `margin` metres at
    /// its end (the surface `b` lies on).
    pub fn visible(&self, a: Vec3, b: Vec3, margin: f32) -> bool {
        let v = b - a;
        let len = v.length();
        if len <= margin {
            return true;
        }
        !self.occluded(a, v / len, 0.0, len - margin)
    }

    /// Appearance at a hit of the ray (o, d).
    pub fn surface(&self, o: Vec3, d: Vec3, hit: Hit) -> Surface {
        let prim = &self.prims[hit.prim as usize];
        let point = o + d * hit.t;
        let mut normal = prim.shape.normal(point);
        if normal.dot(d) > 0.0 {
            normal = -normal;
        }
        let base = srgb_to_linear(prim.tint);
        let ts = self.texture_seed;
        let albedo = match (prim.material, &prim.shape) {
            (Material::Bark, Shape::Cone(c)) => {
                // Vertical furrows: noise stretched along the stem, on the unrolled surface.
                let (angle, s) = c.surface_coords(point);
                let r = c.r0 + c.k * (s - c.s0);
                let u = angle * r.max(0.02) * 28.0;
                let furrow = noise3(ts ^ 0xba5c, Vec3::new(u, s * 2.5, prim.owner as f32));
                let fine = noise3(ts ^ 0x51e1, Vec3::new(u * 3.0, s * 9.0, 0.0));
                base * (0.55 + 0.6 * furrow * furrow + 0.25 * fine)
            }
            (Material::Ground, _) => {
                // Grass with patches of soil and leaf litter.
                let n = fbm2(ts ^ 0x6a55, point.x * 0.35, point.y * 0.35);
                let fine = noise3(ts ^ 0x77, point * 6.0);
                let soil = self.terrain.soil_tint();
                let w = ((n - 0.55) * 5.0).clamp(0.0, 1.0);
                (base * (1.0 - w) + soil * w) * (0.75 + 0.5 * fine)
            }
            (Material::Stone, _) => base * (0.7 + 0.6 * noise3(ts ^ 0x5707, point * 9.0)),
            _ => base,
        };
        Surface {
            point,
            normal,
            albedo: albedo.clamp(Vec3::ZERO, Vec3::ONE),
            material: prim.material,
            cos_incidence: normal.dot(-d).clamp(0.0, 1.0),
        }
    }
}
