//! Deterministic random streams and smooth procedural noise.
//!
//! Every random decision of the generator draws from a [`Stream`]: a ChaCha8 generator keyed
//! by (seed, domain, index). Parallel loops give each item (a tree, a block of LiDAR rays, an
//! image) its own stream, so the result does not depend on how rayon schedules the work, and
//! ChaCha's output is the same on every platform. Smooth noise (terrain relief, bark and soil
//! texture) is a hash-based value noise that needs no state at all.

use glam::{DVec3, Vec3};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};

/// Independent stream families; the numbers only need to differ.
pub mod domain {
    pub const LAYOUT: u64 = 1;
    pub const TREE: u64 = 2;
    pub const LIDAR: u64 = 3;
    pub const FLIGHT: u64 = 4;
    pub const KEYPOINTS: u64 = 5;
    pub const SFM: u64 = 6;
    pub const CONTROL: u64 = 7;
    pub const SHRUB: u64 = 8;
    pub const TRACK: u64 = 9;
    pub const GPS: u64 = 10;
    pub const HIDDEN: u64 = 11;
}

/// One deterministic random stream.
pub struct Stream(ChaCha8Rng);

impl Stream {
    /// The stream of item `index` in family `domain` for the user's `seed`.
    pub fn new(seed: u64, domain: u64, index: u64) -> Self {
        let mut key = [0u8; 32];
        key[..8].copy_from_slice(&seed.to_le_bytes());
        key[8..16].copy_from_slice(&domain.to_le_bytes());
        key[16..24].copy_from_slice(&index.to_le_bytes());
        key[24..].copy_from_slice(b"sylvasyn");
        Stream(ChaCha8Rng::from_seed(key))
    }

    /// Uniform in [0, 1), 53 bits.
    pub fn uniform(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Uniform integer in [0, n); 0 when n == 0.
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            return 0;
        }
        ((self.uniform() * n as f64) as usize).min(n - 1)
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.uniform() < p
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Uniform direction on the unit sphere.
    pub fn unit_vector(&mut self) -> DVec3 {
        let z = self.range(-1.0, 1.0);
        let phi = self.range(0.0, std::f64::consts::TAU);
        let s = (1.0 - z * z).max(0.0).sqrt();
        DVec3::new(s * phi.cos(), s * phi.sin(), z)
    }

    /// Uniform point in the unit ball.
    pub fn in_ball(&mut self) -> DVec3 {
        self.unit_vector() * self.uniform().cbrt()
    }
}

/// 32-bit integer hash (a variant of the "lowbias32" mixer).
fn hash(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^ (x >> 16)
}

fn lattice(seed: u32, i: i32, j: i32, k: i32) -> f32 {
    let h = hash(seed ^ hash((i as u32) ^ hash((j as u32) ^ hash(k as u32))));
    (h >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Smooth value noise in [0, 1] with unit lattice spacing.
pub fn noise3(seed: u32, p: Vec3) -> f32 {
    let f = p.floor();
    let (i, j, k) = (f.x as i32, f.y as i32, f.z as i32);
    let t = p - f;
    let (u, v, w) = (smooth(t.x), smooth(t.y), smooth(t.z));
    let lerp = |a: f32, b: f32, s: f32| a + (b - a) * s;
    let l = |di, dj, dk| lattice(seed, i + di, j + dj, k + dk);
    let x00 = lerp(l(0, 0, 0), l(1, 0, 0), u);
    let x10 = lerp(l(0, 1, 0), l(1, 1, 0), u);
    let x01 = lerp(l(0, 0, 1), l(1, 0, 1), u);
    let x11 = lerp(l(0, 1, 1), l(1, 1, 1), u);
    lerp(lerp(x00, x10, v), lerp(x01, x11, v), w)
}

/// Two octaves of [`noise3`] in the plane z = 0, in [0, 1].
pub fn fbm2(seed: u32, x: f32, y: f32) -> f32 {
    0.65 * noise3(seed, Vec3::new(x, y, 0.0))
        + 0.35 * noise3(seed ^ 0x9e37, Vec3::new(2.03 * x, 2.03 * y, 0.5))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_repeat_and_differ() {
        let a: Vec<f64> = (0..4).map(|_| Stream::new(7, 1, 2).uniform()).collect();
        assert!(a.windows(2).all(|w| w[0] == w[1]));
        let mut s = Stream::new(7, 1, 2);
        let mut t = Stream::new(7, 1, 3);
        assert_ne!(s.uniform(), t.uniform());
    }

    #[test]
    fn noise_is_bounded_and_continuous() {
        for i in 0..200 {
            let p = Vec3::new(i as f32 * 0.173, i as f32 * 0.071, 0.3);
            let n = noise3(3, p);
            assert!((0.0..=1.0).contains(&n));
            let m = noise3(3, p + Vec3::splat(1e-4));
            assert!((n - m).abs() < 1e-2);
        }
    }
}
