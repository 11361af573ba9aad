//! Shared helpers of the GPU tests: a context or a skip, random scenes, comparisons.

#![allow(dead_code)]

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use sylva::splat::camera::Camera;
use sylva::splat::gpu::buffers::storage_from;
use sylva::splat::gpu::{AtomicMode, Frame, GpuContext, GpuGrads, GpuSplats, Renderer};
use sylva::splat::model::Gaussians;

pub use crate::test_scenes::{
    Draw, mean_intensity, random_gaussians, sub_pixel_grid, sub_pixel_grid_camera,
};

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
    crate::test_scenes::camera_facing_origin([0.4, -4.0, 0.3], width, height, fx)
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
        .backward(ctx, splats, frame, &dl_buf, &grads, false)
        .expect("backward");
    grads
}
