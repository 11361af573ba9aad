//! Shared helpers of the GPU tests: a context or a skip, random scenes, comparisons.

#![allow(dead_code)]

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use sylva::splat::camera::Camera;
use sylva::splat::gpu::buffers::storage_from;
use sylva::splat::gpu::{AtomicMode, Frame, GpuContext, GpuGrads, GpuSplats, Renderer};
use sylva::splat::model::{Gaussian, Gaussians, SH_FLOATS};

/// A GPU context, or `None` (with the reason printed) when this machine has no adapter.
pub fn context() -> Option<GpuContext> {
    context_with(None)
}

/// As [`context`], forcing an atomic strategy.
pub fn context_with(mode: Option<AtomicMode>) -> Option<GpuContext> {
    match GpuContext::with_atomic_mode(mode) {
        Ok(c) => Some(c),
        Err(e) => {
            sylva::testing::skip("gpu", &format!("GPU test: {e}"));
            None
        }
    }
}

/// A `width`×`height` camera 4 m from the origin looking at it (z up).
pub fn camera(width: u32, height: u32, fx: f32) -> Camera {
    Camera::look_at(
        [0.4, -4.0, 0.3],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        width,
        height,
        fx,
    )
}

/// `n` random anisotropic, rotated Gaussians within ±`spread` m of the origin (all in front of
/// the camera; a large spread puts some off-screen), SH of `degree` with view-dependent bands.
pub fn scene(seed: u64, n: usize, degree: u32, spread: f32) -> Gaussians {
    let draw = Draw {
        dc: 1.0,
        rest: 0.3,
        mean: [spread; 3],
        log_scale: (-3.0, -1.0),
        opacity: (-1.5, 3.0),
    };
    random_gaussians(seed, n, degree, &draw)
}

/// How [`random_gaussians`] draws each Gaussian: its SH DC terms within ±`dc` and higher bands
/// within ±`rest`, its centre within ±`mean` per axis, its log-scales and opacity logit in the
/// given ranges (and its rotation's components in ±1).
pub struct Draw {
    pub dc: f32,
    pub rest: f32,
    pub mean: [f32; 3],
    pub log_scale: (f32, f32),
    pub opacity: (f32, f32),
}

/// `n` random Gaussians drawn as `draw` says, one after the other from ChaCha8 seeded with
/// `seed`, with SH of `degree`.
pub fn random_gaussians(seed: u64, n: usize, degree: u32, draw: &Draw) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians {
        sh_degree: degree,
        ..Default::default()
    };
    for _ in 0..n {
        let mut sh = [0.0f32; SH_FLOATS];
        for (k, v) in sh.iter_mut().enumerate() {
            let r = if k < 3 { draw.dc } else { draw.rest };
            *v = rng.random_range(-r..r);
        }
        let (scale, opacity) = (draw.log_scale, draw.opacity);
        g.push(Gaussian {
            mean: draw.mean.map(|m| rng.random_range(-m..m)),
            log_scale: [0, 1, 2].map(|_| rng.random_range(scale.0..scale.1)),
            rotation: [0, 1, 2, 3].map(|_| rng.random_range(-1.0f32..1.0)),
            opacity_logit: rng.random_range(opacity.0..opacity.1),
            sh,
            trunk_prob: 0.0,
        });
    }
    g
}

/// Random dL/dimage in [-1, 1].
pub fn random_dl(pixels: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..pixels)
        .map(|_| [0, 1, 2].map(|_| rng.random_range(-1.0f32..1.0)))
        .collect()
}

/// Agreement of `got` with `want`: relative L2 error of the whole vector, and the fraction of
/// entries off by more than `rtol · |want| + atol_frac · max|want|`.
pub fn compare(got: &[f32], want: &[f32], rtol: f32, atol_frac: f32) -> (f32, f32) {
    assert_eq!(got.len(), want.len());
    let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let mut num = 0.0f64;
    let mut den = 0.0f64;
    let mut bad = 0usize;
    for (&g, &w) in got.iter().zip(want) {
        num += ((g - w) as f64).powi(2);
        den += (w as f64).powi(2);
        if (g - w).abs() > rtol * w.abs() + atol_frac * scale {
            bad += 1;
        }
    }
    let rel = if den > 0.0 {
        (num / den).sqrt()
    } else {
        num.sqrt()
    };
    (rel as f32, bad as f32 / got.len().max(1) as f32)
}

/// Camera of [`sub_pixel_grid`] at `k` × 32×24 pixels (k = 1 is half the resolution R =
/// 64×48), focal length 19.2 · k px: 4 m from the origin looking along +y (z up), 4.8 · k px
/// per metre at the origin's depth (the CPU tests' `sub_pixel_grid_camera`).
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
/// [`sub_pixel_grid_camera`]`(1)`, 3.4 px or more apart (the CPU tests' `sub_pixel_grid`).
pub fn sub_pixel_grid(seed: u64) -> Gaussians {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut g = Gaussians::default();
    for ix in 0..5 {
        for iz in 0..4 {
            let mut sh = [0.0f32; SH_FLOATS];
            for v in sh.iter_mut().take(3) {
                *v = 0.5 / sylva::splat::model::SH_C0;
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

/// The backward pass of `frame` (rendered from `splats`) for the dL/dimage `dl`: the gradients,
/// on the GPU.
pub fn gpu_grads(
    ctx: &GpuContext,
    renderer: &Renderer,
    (splats, frame): (&GpuSplats, &Frame),
    dl: &[[f32; 3]],
) -> GpuGrads {
    let dl_buf = storage_from(ctx, "dl", dl).expect("buffer");
    let grads = GpuGrads::new(ctx, splats.count).expect("grads");
    renderer
        .backward(ctx, splats, frame, &dl_buf, &grads)
        .expect("backward");
    grads
}
