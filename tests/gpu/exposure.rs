//! The exposure kernels (`exposure.wgsl`) against their CPU twin, and the GPU trainer learning
//! known per-photo exposures (docs/splatting.md "Exposure").

use crate::common;
use crate::test_scenes::{
    check_learned_exposures, grey_blobs, jitter_exposures, random_scene, ring_dataset,
};

use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use sylva::splat::backend::Backend;
use sylva::splat::config::TrainConfig;
use sylva::splat::cpu::exposure as cpu_exposure;
use sylva::splat::exposure::{EXPOSURE_FLOATS, ExposureSlot, ExposureState};
use sylva::splat::gpu::buffers::{read_buffer, storage_from, storage_zeroed};
use sylva::splat::gpu::exposure::{ExposureScratch, GpuExposure};
use sylva::splat::gpu::{GpuBackend, GpuContext};
use sylva::splat::packed_image::{PackedImage, pack};

/// `n` transforms away from the identity: gains 0.7–1.3, cross terms and offsets ±0.05.
fn random_state(n: usize, seed: u64) -> ExposureState {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut s = ExposureState::new(n);
    for e in &mut s.params {
        for r in 0..3 {
            for k in 0..4 {
                e[4 * r + k] = if k == r {
                    rng.random_range(0.7f32..1.3)
                } else {
                    rng.random_range(-0.05f32..0.05)
                };
            }
        }
    }
    s
}

fn f64s(img: &[[f32; 3]]) -> Vec<[f64; 3]> {
    img.iter().map(|p| p.map(f64::from)).collect()
}

#[test]
fn exposure_kernels_match_the_cpu_twin() {
    let Some(ctx) = common::context() else { return };
    // An odd width (the right half starts at column 18) and 1073 pixels: four full workgroups
    // of 256 and a partial one.
    let (w, h) = (37u32, 29u32);
    let n = (w * h) as usize;
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let rendered: Vec<[f32; 3]> = (0..n)
        .map(|_| [0, 1, 2].map(|_| rng.random_range(0.0f32..1.0)))
        .collect();
    let target = PackedImage {
        width: w,
        height: h,
        pixels: (0..n)
            .map(|_| pack([0, 1, 2, 3].map(|_| rng.random::<u8>())))
            .collect(),
    };
    let dl_out = common::random_dl(n, 4);
    let state = random_state(3, 2);
    let ex = GpuExposure::from_state(&ctx, &state).expect("exposures");
    let scratch = ExposureScratch::new(&ctx, n).expect("scratch");
    let rendered_buf = storage_from(&ctx, "rendered", &rendered).expect("upload");
    let target_buf = storage_from(&ctx, "target", &target.pixels).expect("upload");
    let dl_drgb = storage_zeroed(&ctx, "dl_drgb", n as u64 * 12).expect("buffer");
    ctx.queue
        .write_buffer(&scratch.dl_out, 0, bytemuck::cast_slice(&dl_out));
    let target64 = f64s(&target.to_rgb_f32());
    for slot in [
        ExposureSlot {
            index: 1,
            left_half: false,
        },
        ExposureSlot {
            index: 2,
            left_half: true,
        },
    ] {
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        ex.encode_apply(
            &ctx,
            &mut enc,
            &rendered_buf,
            Some(&target_buf),
            &scratch,
            w,
            h,
            slot,
        )
        .expect("apply");
        ex.encode_backward(
            &ctx,
            &mut enc,
            &rendered_buf,
            &scratch,
            &dl_drgb,
            w,
            h,
            slot,
        )
        .expect("backward");
        ctx.queue.submit([enc.finish()]);
        let got_out: Vec<[f32; 3]> = read_buffer(&ctx, &scratch.exposed, n).expect("read");
        let got_drgb: Vec<[f32; 3]> = read_buffer(&ctx, &dl_drgb, n).expect("read");
        let got_grads: Vec<f32> = read_buffer(&ctx, &ex.grads, 3 * EXPOSURE_FLOATS).expect("read");

        let e = state.params[slot.index].map(f64::from);
        let right = slot.left_half.then_some(target64.as_slice());
        let want_out = cpu_exposure::apply(&f64s(&rendered), &e, w as usize, right);
        let (want_drgb, want_de) = cpu_exposure::backward(
            &f64s(&rendered),
            &e,
            &f64s(&dl_out),
            w as usize,
            slot.left_half,
        );
        for i in 0..n {
            for c in 0..3 {
                let (a, b) = (f64::from(got_out[i][c]), want_out[i][c]);
                assert!(
                    (a - b).abs() <= 1e-6,
                    "{slot:?} pixel {i} ch {c}: out {a} vs {b}"
                );
                let (a, b) = (f64::from(got_drgb[i][c]), want_drgb[i][c]);
                assert!(
                    (a - b).abs() <= 1e-6,
                    "{slot:?} pixel {i} ch {c}: dL/drgb {a} vs {b}"
                );
            }
        }
        let scale = want_de.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 1.0, "{slot:?}: gradient sums vanish ({scale})");
        for (k, &g) in got_grads.iter().enumerate() {
            let want = if k / EXPOSURE_FLOATS == slot.index {
                want_de[k % EXPOSURE_FLOATS]
            } else {
                0.0
            };
            assert!(
                (f64::from(g) - want).abs() <= 1e-5 * scale,
                "{slot:?} dL/de[{k}]: {g} vs {want}"
            );
        }
    }
}

#[test]
fn exposure_adam_matches_the_cpu_twin() {
    let Some(ctx) = common::context() else { return };
    let mut cpu = random_state(5, 7);
    let mut ex = GpuExposure::from_state(&ctx, &cpu).expect("exposures");
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for step in 0..6usize {
        let index = (step * 3) % 5;
        let g: [f32; EXPOSURE_FLOATS] = std::array::from_fn(|_| rng.random_range(-0.1f32..0.1));
        let mut all = vec![0.0f32; 5 * EXPOSURE_FLOATS];
        all[index * EXPOSURE_FLOATS..(index + 1) * EXPOSURE_FLOATS].copy_from_slice(&g);
        ctx.queue
            .write_buffer(&ex.grads, 0, bytemuck::cast_slice(&all));
        let lr = 0.01 * 0.9f32.powi(step as i32);
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        ex.encode_adam(&ctx, &mut enc, lr);
        ctx.queue.submit([enc.finish()]);
        cpu.adam_step(index, &g, lr);
    }
    let gpu = ex.download(&ctx).expect("download");
    assert_eq!(gpu.step, 6);
    for (i, (a, b)) in gpu.params.iter().zip(&cpu.params).enumerate() {
        for k in 0..EXPOSURE_FLOATS {
            assert!(
                (a[k] - b[k]).abs() <= 1e-6 * (1.0 + b[k].abs()),
                "image {i} float {k}: {} vs {}",
                a[k],
                b[k]
            );
        }
    }
    let (rel, _) = common::compare(&gpu.m, &cpu.m, 1e-5, 0.0);
    assert!(rel < 1e-5, "first moments: rel {rel}");
    let (rel, _) = common::compare(&gpu.v, &cpu.v, 1e-5, 0.0);
    assert!(rel < 1e-5, "second moments: rel {rel}");
}

/// The GPU trainer on the CPU trainer test's photos with known exposures, held to the same
/// bounds: compensated, the held-out right halves are far better rendered than without, and
/// the learned gains follow the true ones.
#[test]
fn gpu_training_learns_the_photos_exposures() {
    let Some(ctx) = common::context() else { return };
    let truth = random_scene(7, 30, 0);
    let mut data = ring_dataset(&truth, 16);
    let exposures = jitter_exposures(&mut data, 5);
    let init = grey_blobs(&truth);
    let run = |ctx: &GpuContext, exposure: bool| {
        let cfg = TrainConfig {
            steps: 300,
            exposure,
            ..TrainConfig::default()
        }
        .scaled_to(300);
        let mut backend = GpuBackend::with_context(ctx.clone(), [0.0; 3]).expect("backend");
        let mut strategy = sylva::splat::trainer::default_strategy(&cfg);
        let out = sylva::splat::trainer::train(
            &mut backend,
            &data,
            init.clone(),
            &cfg,
            &mut strategy,
            &sylva::progress::NoProgress,
        )
        .expect("train");
        assert_eq!(
            backend.exposures().expect("exposures").len(),
            out.exposures.len()
        );
        out
    };
    let off = run(&ctx, false);
    let on = run(&ctx, true);
    check_learned_exposures(&off, &on, &data, &exposures);
}
