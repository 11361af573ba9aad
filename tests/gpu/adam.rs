//! GPU Adam against its CPU twin over a few steps.

use crate::common;

use rand::{RngExt, SeedableRng};
use sylva::splat::gpu::adam::{AdamRates, EPSILON, GpuAdam, adam_cpu};
use sylva::splat::gpu::{GpuGrads, GpuSplats};
use sylva::splat::model::SH_FLOATS;

#[test]
fn gpu_adam_matches_cpu_twin() {
    let Some(ctx) = common::context() else { return };
    let mut model = common::scene(3, 700, 3, 1.0);
    let n = model.len() as u32;
    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let grads = GpuGrads::new(&ctx, n).expect("grads");
    let mut adam = GpuAdam::new(&ctx, n).expect("adam");
    let rates = AdamRates {
        means: 1.6e-4,
        log_scales: 5e-3,
        rotations: 1e-3,
        opacity: 0.05,
        sh_dc: 2.5e-3,
        sh_rest: 2.5e-3 / 20.0,
    };
    let mut rng = rand::rngs::ChaCha8Rng::seed_from_u64(5);
    let strides = [3usize, 3, 4, 1, SH_FLOATS];
    let mut cpu_params: Vec<Vec<f32>> = vec![
        model.means.iter().flatten().copied().collect(),
        model.log_scales.iter().flatten().copied().collect(),
        model.rotations.iter().flatten().copied().collect(),
        model.opacity_logits.clone(),
        model.sh.iter().flatten().copied().collect(),
    ];
    let mut mom: Vec<(Vec<f32>, Vec<f32>)> = strides
        .iter()
        .map(|s| (vec![0.0; s * n as usize], vec![0.0; s * n as usize]))
        .collect();
    let lr = rates.per_buffer();
    let grad_bufs = grads.buffers();
    for step in 1..=4u32 {
        for k in 0..5 {
            let g: Vec<f32> = (0..cpu_params[k].len())
                .map(|_| {
                    if rng.random_bool(0.1) {
                        0.0
                    } else {
                        rng.random_range(-1e-2f32..1e-2)
                    }
                })
                .collect();
            ctx.queue
                .write_buffer(grad_bufs[k], 0, bytemuck::cast_slice(&g));
            let (m, v) = &mut mom[k];
            adam_cpu(
                &mut cpu_params[k],
                &g,
                m,
                v,
                strides[k],
                lr[k].2 as usize,
                lr[k].0,
                lr[k].1,
                step,
                EPSILON,
            );
        }
        adam.step(&ctx, &splats, &grads, &rates).expect("step");
    }
    splats.download_into(&ctx, &mut model).expect("download");
    let gpu: Vec<Vec<f32>> = vec![
        model.means.iter().flatten().copied().collect(),
        model.log_scales.iter().flatten().copied().collect(),
        model.rotations.iter().flatten().copied().collect(),
        model.opacity_logits.clone(),
        model.sh.iter().flatten().copied().collect(),
    ];
    for k in 0..5 {
        for (i, (a, b)) in gpu[k].iter().zip(&cpu_params[k]).enumerate() {
            assert!(
                (a - b).abs() <= 1e-6 * (1.0 + b.abs()),
                "group {k} float {i}: {a} vs {b}"
            );
        }
    }
    let moments = adam.download_moments(&ctx).expect("moments");
    for k in 0..5 {
        let (rel, _) = common::compare(&moments[k].0, &mom[k].0, 1e-5, 0.0);
        assert!(rel < 1e-5, "first moments of group {k}: rel {rel}");
    }
}
