//! Terrain: a planar slope plus smooth value-noise relief, sampled on a regular grid and
//! traced as triangles. [`Terrain::height`] interpolates exactly the traced triangles, so a
//! stem base placed at `height(x, y)` sits on the surface the rays see.

use glam::Vec3;

use super::rng::{Stream, fbm2};
use super::scene::{Material, Prim, srgb_to_linear};
use super::shapes::{Shape, Triangle};

/// Grid spacing of the terrain mesh, metres (fine enough that the relief, with wavelengths of
/// 3 m and more, is smooth at this scale).
pub const TERRAIN_CELL_M: f64 = 0.25;

/// A heightfield on a regular grid in the scene frame.
#[derive(Debug, Clone)]
pub struct Terrain {
    /// South-west corner (x, y), metres.
    origin: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    /// Heights, row-major (`j * nx + i`), metres.
    z: Vec<f64>,
    /// Gradient of the planar part (dz/dx, dz/dy).
    pub slope: [f64; 2],
    grass: [u8; 3],
    soil: [u8; 3],
}

impl Terrain {
    /// A square terrain of half-width `half` metres around the origin. Slope 0–8 % (or
    /// `grade`, a fraction, when given) in a random direction, relief amplitude `relief`
    /// metres.
    pub fn generate(
        rng: &mut Stream,
        half: f64,
        relief: f64,
        noise_seed: u32,
        grade: Option<f64>,
    ) -> Terrain {
        let drawn = rng.range(0.0, 0.08);
        let grade = grade.unwrap_or(drawn);
        let dir = rng.range(0.0, std::f64::consts::TAU);
        let slope = [grade * dir.cos(), grade * dir.sin()];
        let n = (2.0 * half / TERRAIN_CELL_M).ceil() as usize + 1;
        let origin = [-half, -half];
        let mut z = Vec::with_capacity(n * n);
        for j in 0..n {
            for i in 0..n {
                let x = origin[0] + i as f64 * TERRAIN_CELL_M;
                let y = origin[1] + j as f64 * TERRAIN_CELL_M;
                let broad = fbm2(noise_seed, (x / 9.0) as f32, (y / 9.0) as f32) as f64 - 0.5;
                let fine = fbm2(noise_seed ^ 0x3c, (x / 3.0) as f32, (y / 3.0) as f32) as f64 - 0.5;
                z.push(slope[0] * x + slope[1] * y + relief * (broad + 0.25 * fine));
            }
        }
        // Grass and soil tints vary a little per plot.
        let g = rng.range(-12.0, 12.0);
        let grass = [(88.0 + g) as u8, (112.0 + g) as u8, 52];
        let soil = [118, (94.0 + g * 0.5) as u8, 70];
        let mut t = Terrain {
            origin,
            cell: TERRAIN_CELL_M,
            nx: n,
            ny: n,
            z,
            slope,
            grass,
            soil,
        };
        // Put the plot centre at height 0.
        let z0 = t.height(0.0, 0.0);
        t.z.iter_mut().for_each(|v| *v -= z0);
        t
    }

    fn at(&self, i: usize, j: usize) -> f64 {
        self.z[j.min(self.ny - 1) * self.nx + i.min(self.nx - 1)]
    }

    /// Ground height at (x, y), metres: the triangle the point lies in, interpolated.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let fx = ((x - self.origin[0]) / self.cell).clamp(0.0, (self.nx - 1) as f64 - 1e-9);
        let fy = ((y - self.origin[1]) / self.cell).clamp(0.0, (self.ny - 1) as f64 - 1e-9);
        let (i, j) = (fx.floor() as usize, fy.floor() as usize);
        let (u, v) = (fx - i as f64, fy - j as f64);
        let (z00, z10, z01, z11) = (
            self.at(i, j),
            self.at(i + 1, j),
            self.at(i, j + 1),
            self.at(i + 1, j + 1),
        );
        if u + v <= 1.0 {
            z00 + (z10 - z00) * u + (z01 - z00) * v
        } else {
            z11 + (z01 - z11) * (1.0 - u) + (z10 - z11) * (1.0 - v)
        }
    }

    /// Half-width of the square covered, metres.
    pub fn half_width(&self) -> f64 {
        -self.origin[0]
    }

    /// Linear colour of bare soil patches.
    pub fn soil_tint(&self) -> Vec3 {
        srgb_to_linear(self.soil)
    }

    /// Two triangles per cell, split along the (i, j)–(i+1, j+1) anti-diagonal as in
    /// [`Terrain::height`].
    pub fn triangles(&self) -> Vec<Prim> {
        let mut out = Vec::with_capacity(2 * (self.nx - 1) * (self.ny - 1));
        let p = |i: usize, j: usize| {
            Vec3::new(
                (self.origin[0] + i as f64 * self.cell) as f32,
                (self.origin[1] + j as f64 * self.cell) as f32,
                self.at(i, j) as f32,
            )
        };
        for j in 0..self.ny - 1 {
            for i in 0..self.nx - 1 {
                let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i, j + 1), p(i + 1, j + 1));
                for (v0, v1, v2) in [(a, b, c), (d, c, b)] {
                    out.push(Prim {
                        shape: Shape::Triangle(Triangle {
                            v0,
                            e1: v1 - v0,
                            e2: v2 - v0,
                        }),
                        material: Material::Ground,
                        tint: self.grass,
                        owner: 0,
                    });
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::shapes::Interval;

    #[test]
    fn height_matches_traced_triangles() {
        let mut rng = Stream::new(1, 0, 0);
        let t = Terrain::generate(&mut rng, 5.0, 0.4, 9, None);
        assert!(t.height(0.0, 0.0).abs() < 1e-12);
        let tris = t.triangles();
        for k in 0..40 {
            let (x, y) = (-4.0 + k as f64 * 0.197, 3.0 - k as f64 * 0.151);
            let o = Vec3::new(x as f32, y as f32, 50.0);
            let hit = tris
                .iter()
                .filter_map(|p| {
                    p.shape
                        .intersect(o, Vec3::NEG_Z, Interval { min: 0.0, max: 1e9 })
                })
                .min_by(f32::total_cmp)
                .map(|tt| 50.0 - tt as f64);
            let h = hit.unwrap_or(f64::NAN);
            assert!(
                (h - t.height(x, y)).abs() < 1e-4,
                "{h} vs {}",
                t.height(x, y)
            );
        }
    }
}
