//! The semantic term L_geo on the GPU against its CPU twin: the same candidate set, nearest
//! anchors, target scales, weights, loss and gradients.

use crate::common;

use sylva::splat::gpu::buffers::{read_buffer, storage_zeroed};
use sylva::splat::gpu::semantic::GpuSemantic;
use sylva::splat::gpu::{GpuGrads, GpuSplats};
use sylva::splat::model::sigmoid;
use sylva::splat::semantic::{SemanticConfig, geo_loss_and_grad, geo_targets, test_scene};

#[test]
fn gpu_semantic_term_matches_cpu_twin() {
    let Some(ctx) = common::context() else { return };
    let cfg = SemanticConfig {
        enabled: true,
        ..Default::default()
    };
    let (mut model, anchors) = test_scene(11, 3000);
    // Keep clear of the threshold, where f32 and f64 could disagree on membership of S.
    let targets = geo_targets(&model, &anchors, &cfg);
    for (i, t) in targets.iter().enumerate() {
        let ap = sigmoid(model.opacity_logits[i]) * model.trunk_prob[i];
        let near = |x: f64| (x - 0.5).abs() < 2e-3;
        if near(f64::from(ap)) || (t.weight > 0.0 && near(t.weight)) {
            model.trunk_prob[i] = 0.0;
        }
    }
    let targets = geo_targets(&model, &anchors, &cfg);
    let in_s = targets.iter().filter(|t| t.weight > 0.0).count();
    assert!(in_s > 300, "only {in_s} Gaussians in S");
    let (loss, d_mu, d_s) = geo_loss_and_grad(&model, &targets, anchors.n_pos);

    let n = model.len() as u32;
    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let grads = GpuGrads::new(&ctx, n).expect("grads");
    let loss_out = storage_zeroed(&ctx, "loss out", 16).expect("loss buffer");
    let mut sem = GpuSemantic::new(&ctx, &anchors, &cfg).expect("semantic");
    sem.set_model(&ctx, &model.trunk_prob).expect("model");
    let gamma = 0.5f32;
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    sem.encode(&ctx, &mut enc, &splats, &grads, &loss_out, gamma)
        .expect("encode");
    ctx.queue.submit([enc.finish()]);
    let (rows, sums) = sem.read_back(&ctx).expect("read back");

    let total_w: f64 = targets.iter().map(|t| t.weight).sum();
    for (i, (t, r)) in targets.iter().zip(&rows).enumerate() {
        assert_eq!(t.weight > 0.0, r[4] > 0.0, "membership of S differs at {i}");
        if t.weight == 0.0 {
            continue;
        }
        assert!(
            (f64::from(r[4]) - t.weight).abs() < 1e-4,
            "w {i}: {} vs {}",
            r[4],
            t.weight
        );
        for (got, want) in r[..3].iter().zip(t.anchor) {
            assert!(
                (f64::from(*got) - want).abs() < 1e-6,
                "nearest trunk anchor {i} differs"
            );
        }
        assert!(
            (f64::from(r[3]) - t.log_scale).abs() < 1e-4,
            "s_target {i}: {} vs {}",
            r[3],
            t.log_scale
        );
    }
    assert!(
        (f64::from(sums[0]) - total_w).abs() < 1e-4 * total_w,
        "W {} vs {total_w}",
        sums[0]
    );
    assert!(
        (f64::from(sums[2]) - loss).abs() < 1e-3 * loss,
        "L_geo {} vs {loss}",
        sums[2]
    );
    let out: Vec<f32> = read_buffer(&ctx, &loss_out, 4).expect("loss out");
    assert_eq!(out[3], sums[2], "L_geo reaches the loss read-back");

    let gm: Vec<f32> = read_buffer(&ctx, &grads.means, 3 * n as usize).expect("grad means");
    let gs: Vec<f32> = read_buffer(&ctx, &grads.log_scales, 3 * n as usize).expect("grad scales");
    let scale_m = d_mu.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs())) * f64::from(gamma);
    let scale_s = d_s.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs())) * f64::from(gamma);
    assert!(scale_m > 0.0 && scale_s > 0.0);
    for i in 0..n as usize {
        for a in 0..3 {
            let want_m = f64::from(gamma) * d_mu[i][a];
            let want_s = f64::from(gamma) * d_s[i][a];
            assert!(
                (f64::from(gm[3 * i + a]) - want_m).abs() <= 1e-3 * scale_m,
                "dL/dmu {i} {a}: {} vs {want_m}",
                gm[3 * i + a]
            );
            assert!(
                (f64::from(gs[3 * i + a]) - want_s).abs() <= 1e-3 * scale_s,
                "dL/ds {i} {a}: {} vs {want_s}",
                gs[3 * i + a]
            );
        }
    }
}

#[test]
fn gpu_semantic_term_is_silent_without_trunk_gaussians() {
    let Some(ctx) = common::context() else { return };
    let cfg = SemanticConfig::default();
    let (mut model, anchors) = test_scene(2, 500);
    model.trunk_prob.iter_mut().for_each(|p| *p = 0.0);
    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let grads = GpuGrads::new(&ctx, model.len() as u32).expect("grads");
    let loss_out = storage_zeroed(&ctx, "loss out", 16).expect("loss buffer");
    let mut sem = GpuSemantic::new(&ctx, &anchors, &cfg).expect("semantic");
    sem.set_model(&ctx, &model.trunk_prob).expect("model");
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    sem.encode(&ctx, &mut enc, &splats, &grads, &loss_out, 0.02)
        .expect("encode");
    ctx.queue.submit([enc.finish()]);
    let (_, sums) = sem.read_back(&ctx).expect("read back");
    assert_eq!(sums[0], 0.0);
    assert_eq!(sums[2], 0.0);
    let gm: Vec<f32> = read_buffer(&ctx, &grads.means, 3 * model.len()).expect("grad means");
    assert!(gm.iter().all(|&g| g == 0.0));
}

/// Sylva's binding on the GPU against its CPU twin (`splat::bind::project`): the same nearest
/// trunk anchor, offset clamp, rotation onto the normal and normal-scale cap, for Gaussians
/// thrown up to 6 cm off the trunk with random rotations; leaf Gaussians untouched.
#[test]
fn gpu_trunk_binding_matches_cpu_twin() {
    use rand::rngs::ChaCha8Rng;
    use rand::{RngExt, SeedableRng};
    use sylva::splat::bind::{BindConfig, project};
    use sylva::splat::semantic::AnchorIndex;
    let Some(ctx) = common::context() else { return };
    let (mut model, anchors) = test_scene(6, 3000);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for i in 0..model.len() {
        for a in 0..3 {
            model.means[i][a] += rng.random_range(-0.06f32..0.06);
        }
        model.rotations[i] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
        model.log_scales[i][2] = rng.random_range(-6.0f32..-2.0);
    }
    let cfg = BindConfig {
        enabled: true,
        ..Default::default()
    };
    let mut cpu = model.clone();
    let index = AnchorIndex::new(&anchors).expect("index");
    let bound = project(&mut cpu, &index, &cfg);
    assert!(bound > 1000, "{bound} bound");

    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let mut sem = GpuSemantic::new(&ctx, &anchors, &SemanticConfig::default()).expect("semantic");
    sem.set_model(&ctx, &model.trunk_prob).expect("model");
    sem.set_bind(&cfg).expect("bind");
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    sem.encode_bind(&ctx, &mut enc, &splats).expect("encode");
    ctx.queue.submit([enc.finish()]);
    let mut gpu = model.clone();
    splats.download_into(&ctx, &mut gpu).expect("download");
    let mut moved = 0;
    for i in 0..model.len() {
        if model.trunk_prob[i] < cfg.min_trunk_prob {
            assert_eq!(gpu.means[i], model.means[i], "leaf Gaussian {i} moved");
            assert_eq!(gpu.rotations[i], model.rotations[i]);
            continue;
        }
        moved += usize::from(cpu.means[i] != model.means[i]);
        for a in 0..3 {
            assert!(
                (gpu.means[i][a] - cpu.means[i][a]).abs() < 1e-5,
                "mean {i}: {:?} vs {:?}",
                gpu.means[i],
                cpu.means[i]
            );
            assert!((gpu.log_scales[i][a] - cpu.log_scales[i][a]).abs() < 1e-6);
        }
        // q and -q are the same rotation.
        let dot: f32 = (0..4)
            .map(|k| gpu.rotations[i][k] * cpu.rotations[i][k])
            .sum();
        assert!(dot.abs() > 1.0 - 1e-5, "rotation {i}: {dot}");
    }
    assert!(
        moved > 500,
        "only {moved} trunk Gaussians needed the projection"
    );
}
