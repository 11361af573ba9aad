//! Random small scenes and photo sets for the tests (fixed seeds, ChaCha8).
//!
//! One file for the library's unit tests and the GPU integration tests: `tests/gpu/main.rs`
//! includes it as its module `test_scenes` (naming the library `crate::splat` and
//! `crate::rng` there), so the GPU kernels are checked on the very scenes the CPU tests draw.

use crate::rng::SplitMix64;
use crate::splat::camera::Camera;
use crate::splat::cameras::View;
use crate::splat::cpu;
use crate::splat::dataset::Dataset;
use crate::splat::eval::{EvalRegion, ViewMetrics, from_rgb8};
use crate::splat::model::{Gaussian, Gaussians, SH_FLOATS};
use crate::splat::packed_image::{PackedImage, pack};
use crate::splat::trainer::TrainOutcome;
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};

/// A `width`×`height` camera at `eye` looking at the origin (z up), fx = fy = `fx` px.
pub fn camera_facing_origin(eye: [f32; 3], width: u32, height: u32, fx: f32) -> Camera {
    Camera::look_at(eye, [0.0; 3], [0.0, 0.0, 1.0], width, height, fx)
}

/// A 32×24 camera 4 m from the origin looking along +y (z up), fx = fy = 30 px.
pub fn small_camera() -> Camera {
    camera_facing_origin([0.3, -4.0, 0.2], 32, 24, 30.0)
}

/// `n` anisotropic, rotated, overlapping Gaussians within ±1.2 m × ±0.8 m of the origin (all
/// well inside the Jacobian clamp), opacities 0.27..0.88, colours away from the 0 clamp, SH of
/// the given degree with view-dependent higher bands.
pub fn random_scene(seed: u64, n: usize, degree: u32) -> Gaussians {
    let draw = Draw {
        dc: 0.9,
        rest: 0.25,
        mean: [1.2, 0.8, 0.8],
        log_scale: (-2.3, -0.9),
        opacity: (-1.0, 2.0),
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

/// `n` Gaussians with SH of degree 3, each made by `make` from standard normal draws (`r()`,
/// SplitMix64 seeded with `seed`, one stream for the whole model).
pub fn normal_gaussians(
    n: usize,
    seed: u64,
    mut make: impl FnMut(&mut dyn FnMut() -> f32) -> Gaussian,
) -> Gaussians {
    let mut rng = SplitMix64::new(seed);
    let mut r = move || rng.normal() as f32;
    let mut g = Gaussians {
        sh_degree: 3,
        ..Default::default()
    };
    for _ in 0..n {
        g.push(make(&mut r));
    }
    g
}

/// Grey blobs at jittered positions of the true Gaussians: the start of the training tests.
pub fn grey_blobs(truth: &Gaussians) -> Gaussians {
    let mut init = Gaussians::default();
    for m in &truth.means {
        init.push(Gaussian::isotropic(
            [m[0] + 0.1, m[1] - 0.1, m[2] + 0.05],
            0.15,
            [0.5, 0.5, 0.5],
            0.3,
        ));
    }
    init
}

/// Views of a random scene from a ring of `n_views` cameras 4 m out (40×32, rendered by the
/// CPU reference), every 8th held out.
pub fn ring_dataset(truth: &Gaussians, n_views: usize) -> Dataset {
    ring_dataset_sized(truth, n_views, (40, 32), 36.0)
}

/// [`ring_dataset`] with photos of `size` (width, height) pixels and focal length `fx` pixels.
pub fn ring_dataset_sized(truth: &Gaussians, n_views: usize, size: (u32, u32), fx: f32) -> Dataset {
    let (width, height) = size;
    let mut views = Vec::new();
    for k in 0..n_views {
        let a = k as f32 / n_views as f32 * std::f32::consts::TAU;
        let cam = Camera::look_at(
            [4.0 * a.sin(), -4.0 * a.cos(), 0.6],
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            width,
            height,
            fx,
        );
        let img = cpu::render(truth, &cam, [0.0; 3]).expect("render").image;
        let pixels = img
            .iter()
            .map(|p| {
                let c = p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
                pack([c[0], c[1], c[2], 255])
            })
            .collect();
        views.push(View {
            name: format!("view_{k:02}.png"),
            camera: cam,
            image: PackedImage {
                width,
                height,
                pixels,
            }
            .into(),
        });
    }
    let test = views.iter().step_by(8).cloned().collect();
    let train = views
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 8 != 0)
        .map(|(_, v)| v.clone())
        .collect();
    Dataset {
        train,
        test,
        points: Vec::new(),
        colours: Vec::new(),
        colour_source: crate::splat::dataset::PointColours::Model,
        extent: 4.4,
    }
}

/// Gives every photo of `data` its own exposure: per channel a gain in [0.7, 1.3] and an
/// offset in [−0.05, 0.05], rounded back to 8 bits. Returns the (gain, offset) per view,
/// in [`Dataset::all_views`] order.
pub fn jitter_exposures(data: &mut Dataset, seed: u64) -> Vec<([f64; 3], [f64; 3])> {
    let mut rng = SplitMix64::new(seed);
    let mut truth = Vec::new();
    for v in data.train.iter_mut().chain(data.test.iter_mut()) {
        let gain = [0, 1, 2].map(|_| 0.7 + 0.6 * rng.uniform());
        let offset = [0, 1, 2].map(|_| 0.1 * (rng.uniform() - 0.5));
        let mut img = v.image.image().expect("decoded").into_owned();
        let rgb = img.to_rgb_f32();
        img.pixels = rgb
            .iter()
            .map(|p| {
                let c: [u8; 3] = std::array::from_fn(|k| {
                    let x = gain[k] * f64::from(p[k]) + offset[k];
                    (x.clamp(0.0, 1.0) * 255.0).round() as u8
                });
                pack([c[0], c[1], c[2], 255])
            })
            .collect();
        v.image = img.into();
        truth.push((gain, offset));
    }
    truth
}

/// The bounds of the exposure training tests, for the runs `off` (without compensation) and
/// `on` (with it) on `data`, whose photos [`jitter_exposures`] gave the exposures `truth`:
/// the compensated held-out right halves are over 3 dB better than the uncompensated model's,
/// and per channel the learned gains follow the true ones (correlation above 0.8 across all
/// photos, up to the colour scale the model itself absorbs).
pub fn check_learned_exposures(
    off: &TrainOutcome,
    on: &TrainOutcome,
    data: &Dataset,
    truth: &[([f64; 3], [f64; 3])],
) {
    assert_eq!(on.eval.region, EvalRegion::RightHalf);
    // The uncompensated model on the same right halves.
    let off_right: Vec<f32> = off
        .renders
        .iter()
        .zip(&data.test)
        .map(|((name, img, _, _), v)| {
            let truth = v.image.image().expect("decoded");
            ViewMetrics::measure(name, &from_rgb8(img), &truth, EvalRegion::RightHalf)
                .expect("sizes")
                .psnr
        })
        .collect();
    let off_right = off_right.iter().sum::<f32>() / off_right.len() as f32;
    eprintln!(
        "held-out right halves: {:.2} dB with exposure compensation, {off_right:.2} dB without (baseline {:.2} dB)",
        on.eval.psnr, on.baseline_psnr
    );
    assert!(
        on.eval.psnr > off_right + 3.0,
        "right halves: {} dB compensated vs {off_right} dB",
        on.eval.psnr
    );
    for c in 0..3 {
        let learned: Vec<f64> = on
            .exposures
            .iter()
            .map(|(_, e)| f64::from(e[4 * c + c]))
            .collect();
        let true_gain: Vec<f64> = truth.iter().map(|(g, _)| g[c]).collect();
        let r = correlation(&learned, &true_gain);
        eprintln!("channel {c}: learned vs true gain correlation {r:.3}");
        assert!(r > 0.8, "channel {c}: correlation {r}");
    }
}

/// Pearson correlation of two equally long series.
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
    let va: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
    let vb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
    cov / (va * vb).sqrt().max(1e-300)
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
    camera_facing_origin([0.0, -4.0, 0.0], 32 * k, 24 * k, 19.2 * k as f32)
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
