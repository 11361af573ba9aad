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
