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

/// Camera of [`sub_pixel_grid`] at `k` × 32×24 pixels (k = 1 is half the resolution R =
/// 64×48), focal length 19.2 · k px: 4 m from the origin looking along +y (z up), 4.8 · k px
/// per metre at the origin's depth.
pub fn sub_pixel_grid_camera(k: u32) -> Camera {
    Camera::look_at(
        [0.0, -4.0, 0.0],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        32 * k,
        24 * k,
        19.2 * k as f32,
    )
}

/// 20 white, anisotropic, rotated Gaussians of opacity 0.9 on a 5 × 4 grid 1 m apart in the
/// plane y = 0 (jittered by up to 0.15 m), axes 0.052–0.125 m: 0.25–0.6 px at
/// [`sub_pixel_grid_camera`]`(1)`, 3.4 px or more apart, all well inside the image.
pub fn sub_pixel_grid(seed: u64) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians::default();
    for ix in 0..5 {
        for iz in 0..4 {
            let mut sh = [0.0f32; SH_FLOATS];
            for v in sh.iter_mut().take(3) {
                *v = 0.5 / crate::splat::model::SH_C0;
            }
            g.push(Gaussian {
                mean: [
                    ix as f32 - 2.0 + rng.random_range(-0.15..0.15),
                    rng.random_range(-0.1..0.1),
                    iz as f32 - 1.5 + rng.random_range(-0.15..0.15),
                ],
                log_scale: [0, 1, 2].map(|_| rng.random_range(0.052f32..0.125).ln()),
                rotation: [0, 1, 2, 3].map(|_| rng.random_range(-1.0f32..1.0)),
                opacity_logit: (0.9f32 / 0.1).ln(),
                sh,
                trunk_prob: 0.0,
            });
        }
    }
    g
}

/// Mean over pixels and channels of an RGB image.
pub fn mean_intensity(image: &[[f32; 3]]) -> f64 {
    let sum: f64 = image.iter().flatten().map(|&v| f64::from(v)).sum();
    sum / (3 * image.len().max(1)) as f64
}
