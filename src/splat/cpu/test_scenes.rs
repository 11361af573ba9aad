//! Random small scenes for the tests (fixed seeds, ChaCha8).

use crate::splat::camera::Camera;
use crate::splat::model::{Gaussian, Gaussians, SH_FLOATS};
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};

/// A 32×24 camera 4 m from the origin looking along +y (z up), fx = fy = 30 px.
pub fn small_camera() -> Camera {
    Camera::look_at(
        [0.3, -4.0, 0.2],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        32,
        24,
        30.0,
    )
}

/// `n` anisotropic, rotated, overlapping Gaussians within ±1.2 m × ±0.8 m of the origin (all
/// well inside the Jacobian clamp), opacities 0.27..0.88, colours away from the 0 clamp, SH of
/// the given degree with view-dependent higher bands.
pub fn random_scene(seed: u64, n: usize, degree: u32) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians {
        sh_degree: degree,
        ..Default::default()
    };
    for _ in 0..n {
        let mut sh = [0.0f32; SH_FLOATS];
        for (k, v) in sh.iter_mut().enumerate() {
            *v = if k < 3 {
                rng.random_range(-0.9..0.9)
            } else {
                rng.random_range(-0.25..0.25)
            };
        }
        g.push(Gaussian {
            mean: [
                rng.random_range(-1.2..1.2),
                rng.random_range(-0.8..0.8),
                rng.random_range(-0.8..0.8),
            ],
            log_scale: [0, 1, 2].map(|_| rng.random_range(-2.3f32..-0.9)),
            rotation: [0, 1, 2, 3].map(|_| rng.random_range(-1.0f32..1.0)),
            opacity_logit: rng.random_range(-1.0..2.0),
            sh,
            trunk_prob: 0.0,
        });
    }
    g
}

/// A target at a distance of 0.05..0.3 (random sign) from `image` in every channel, so the L1
/// term is smooth under small perturbations of the render.
pub fn offset_target(image: &[[f64; 3]], seed: u64) -> Vec<[f64; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    image
        .iter()
        .map(|p| {
            p.map(|v| {
                let d: f64 = rng.random_range(0.05..0.3);
                if rng.random_bool(0.5) { v + d } else { v - d }
            })
        })
        .collect()
}

/// A random image with values in [0, 1], smooth-ish plus noise.
pub fn random_image(width: usize, height: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..width * height)
        .map(|i| {
            let (x, y) = ((i % width) as f64, (i / width) as f64);
            [0.0, 1.0, 2.0].map(|c| {
                let s = 0.5 + 0.3 * ((0.3 + 0.1 * c) * x + 0.2 * y).sin();
                (s + rng.random_range(-0.2..0.2)).clamp(0.0, 1.0)
            })
        })
        .collect()
}
