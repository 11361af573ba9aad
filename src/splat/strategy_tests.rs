//! Tests of [`DefaultStrategy`] on small hand-made models.

use super::*;
use crate::splat::model::SH_FLOATS;

/// Scene extent used by every test: clone below 0.01 m, world-size prune above 0.1 m.
const EXTENT: f32 = 1.0;
/// First step at which the default schedule densifies.
const DENSIFY_STEP: u32 = 600;

fn gaussian(x: f32, sigma: f32, opacity: f32, trunk: f32) -> Gaussian {
    let mut g = Gaussian::isotropic([x, 0.0, 0.0], sigma, [0.5; 3], opacity);
    g.trunk_prob = trunk;
    g
}

fn model(list: &[Gaussian]) -> Gaussians {
    let mut m = Gaussians::default();
    for g in list {
        m.push(*g);
    }
    m
}

/// Feeds one view where Gaussian i has pixel gradient `grads[i]` along x (image 2×2 so that the
/// NDC scaling is 1) and screen radius `radius`.
fn feed(s: &mut DefaultStrategy, step: u32, grads: &[f32], radius: f32) {
    let g2: Vec<[f32; 2]> = grads.iter().map(|&g| [g, 0.0]).collect();
    let radii = vec![radius; grads.len()];
    s.after_backward(
        step,
        &ViewStats {
            mean2d_grads: &g2,
            radii: &radii,
            width: 2,
            height: 2,
        },
    );
}

#[test]
fn small_gaussians_with_large_gradients_are_cloned_with_their_trunk_probability() {
    let mut m = model(&[
        gaussian(0.0, 0.005, 0.5, 0.9),
        gaussian(1.0, 0.005, 0.5, 0.1),
    ]);
    let mut adam = AdamState::new(2);
    let mut s = DefaultStrategy::new(&TrainConfig::default());
    feed(&mut s, DENSIFY_STEP, &[1e-3, 1e-5], 3.0);
    let r = s.refine(DENSIFY_STEP, &mut m, &mut adam, EXTENT);
    assert_eq!((r.cloned, r.split, r.pruned, r.after), (1, 0, 0, 3));
    assert_eq!(m.get(2), m.get(0), "the clone is an exact copy, appended");
    assert_eq!(m.trunk_prob, vec![0.9, 0.1, 0.9]);
    assert_eq!(adam.len(), 3);
}

#[test]
fn large_gaussians_are_split_into_two_smaller_children_near_the_parent() {
    let parent = gaussian(0.0, 0.05, 0.5, 0.7);
    let mut m = model(&[parent, gaussian(1.0, 0.05, 0.5, 0.0)]);
    let mut adam = AdamState::new(2);
    let mut s = DefaultStrategy::new(&TrainConfig::default());
    feed(&mut s, DENSIFY_STEP, &[1e-3, 0.0], 3.0);
    let r = s.refine(DENSIFY_STEP, &mut m, &mut adam, EXTENT);
    assert_eq!((r.cloned, r.split, r.pruned, r.after), (0, 1, 0, 3));
    // Survivor first, then the two children.
    assert_eq!(m.means[0], [1.0, 0.0, 0.0]);
    for c in 1..3 {
        assert!((m.log_scales[c][0] - (0.05f32 / 1.6).ln()).abs() < 1e-5);
        assert_eq!(m.trunk_prob[c], 0.7);
        assert_eq!(m.sh[c], parent.sh);
        let d = m.means[c].iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!(d < 0.05 * 5.0, "child {c} sampled {d} m from the parent");
    }
    assert_ne!(m.means[1], m.means[2]);
}

#[test]
fn transparent_and_oversized_gaussians_are_pruned() {
    let cfg = TrainConfig::default();
    let mut m = model(&[
        gaussian(0.0, 0.005, 0.001, 0.0), // transparent
        gaussian(1.0, 0.005, 0.5, 0.0),   // fine
        gaussian(2.0, 0.5, 0.5, 0.0),     // larger than 0.1 · extent
        gaussian(3.0, 0.005, 0.5, 0.0),   // large on screen
    ]);
    let mut adam = AdamState::new(4);
    let mut s = DefaultStrategy::new(&cfg);
    // Before the first reset only opacity prunes.
    feed(&mut s, DENSIFY_STEP, &[0.0; 4], 3.0);
    let r = s.refine(DENSIFY_STEP, &mut m, &mut adam, EXTENT);
    assert_eq!((r.pruned, r.after), (1, 3));
    // After it, world size and screen radius prune too.
    let step = cfg.opacity_reset_interval + cfg.densify_interval;
    let g2 = [[0.0f32; 2]; 3];
    s.after_backward(
        step,
        &ViewStats {
            mean2d_grads: &g2,
            radii: &[3.0, 3.0, 50.0],
            width: 2,
            height: 2,
        },
    );
    let r = s.refine(step, &mut m, &mut adam, EXTENT);
    assert_eq!((r.pruned, r.after), (2, 1));
    assert_eq!(m.means, vec![[1.0, 0.0, 0.0]]);
    assert_eq!(adam.len(), 1);
}

#[test]
fn background_gaussians_are_large_by_design_and_only_opacity_prunes_them() {
    let cfg = TrainConfig::default();
    let sky = crate::splat::init::BACKGROUND_PROB;
    let mut m = model(&[
        gaussian(0.0, 0.5, 0.5, sky),   // wide and large on screen: kept
        gaussian(1.0, 0.5, 0.001, sky), // transparent: pruned
        gaussian(2.0, 0.5, 0.5, 0.0),   // wide, not background: pruned
    ]);
    let mut adam = AdamState::new(3);
    let mut s = DefaultStrategy::new(&cfg);
    let step = cfg.opacity_reset_interval + cfg.densify_interval;
    feed(&mut s, step, &[0.0; 3], 50.0);
    let r = s.refine(step, &mut m, &mut adam, EXTENT);
    assert_eq!((r.pruned, r.after), (2, 1));
    assert_eq!(m.means, vec![[0.0, 0.0, 0.0]]);
}

#[test]
fn adam_moments_follow_their_gaussians_and_new_ones_start_at_zero() {
    // 0: cloned, 1: pruned, 2: split, 3: untouched.
    let mut m = model(&[
        gaussian(0.0, 0.005, 0.5, 0.0),
        gaussian(1.0, 0.005, 0.001, 0.0),
        gaussian(2.0, 0.05, 0.5, 0.0),
        gaussian(3.0, 0.005, 0.5, 0.0),
    ]);
    let mut adam = AdamState::new(4);
    for i in 0..4 {
        adam.means.m[i * 3] = 10.0 + i as f32;
        adam.sh.v[i * SH_FLOATS] = 20.0 + i as f32;
        adam.opacity_logits.m[i] = 30.0 + i as f32;
    }
    let mut s = DefaultStrategy::new(&TrainConfig::default());
    feed(&mut s, DENSIFY_STEP, &[1e-3, 0.0, 1e-3, 0.0], 3.0);
    let r = s.refine(DENSIFY_STEP, &mut m, &mut adam, EXTENT);
    assert_eq!((r.cloned, r.split, r.pruned, r.after), (1, 1, 1, 5));
    assert_eq!(m.means[0][0], 0.0);
    assert_eq!(m.means[1][0], 3.0);
    assert_eq!(adam.len(), m.len());
    assert_eq!(&adam.means.m[0..6], &[10.0, 0.0, 0.0, 13.0, 0.0, 0.0]);
    assert_eq!(adam.sh.v[SH_FLOATS], 23.0);
    assert_eq!(adam.opacity_logits.m, vec![30.0, 33.0, 0.0, 0.0, 0.0]);
    assert!(adam.means.m[6..].iter().all(|&v| v == 0.0));
}

#[test]
fn the_cap_limits_growth_to_the_highest_gradients() {
    let list: Vec<Gaussian> = (0..10)
        .map(|i| gaussian(i as f32, 0.005, 0.5, i as f32 / 10.0))
        .collect();
    let mut m = model(&list);
    let mut adam = AdamState::new(10);
    let cfg = TrainConfig {
        max_gaussians: Some(13),
        ..TrainConfig::default()
    };
    let mut s = DefaultStrategy::new(&cfg);
    let grads: Vec<f32> = (0..10).map(|i| 1e-3 * (1.0 + i as f32)).collect();
    feed(&mut s, DENSIFY_STEP, &grads, 3.0);
    let r = s.refine(DENSIFY_STEP, &mut m, &mut adam, EXTENT);
    assert_eq!((r.cloned, r.after), (3, 13));
    assert_eq!(
        &m.trunk_prob[10..],
        &[0.7, 0.8, 0.9],
        "the three steepest were cloned"
    );
    // At the cap nothing more grows.
    feed(&mut s, DENSIFY_STEP + 100, &[1e-2; 13], 3.0);
    let r = s.refine(DENSIFY_STEP + 100, &mut m, &mut adam, EXTENT);
    assert_eq!((r.cloned, r.split, r.after), (0, 0, 13));
}

#[test]
fn opacities_are_reset_on_schedule_only_while_densifying() {
    let cfg = TrainConfig::default();
    let mut m = model(&[
        gaussian(0.0, 0.005, 0.9, 0.0),
        gaussian(1.0, 0.005, 0.006, 0.0),
    ]);
    let mut adam = AdamState::new(2);
    adam.opacity_logits.m = vec![1.0, 1.0];
    let mut s = DefaultStrategy::new(&cfg);
    let low = m.opacity_logits[1];
    assert!(!s.refine(2999, &mut m, &mut adam, EXTENT).opacity_reset);
    assert!(s.refine(3000, &mut m, &mut adam, EXTENT).opacity_reset);
    assert!((sigmoid(m.opacity_logits[0]) - 0.01).abs() < 1e-6);
    assert_eq!(
        m.opacity_logits[1], low,
        "min(current, 0.01) keeps lower opacities"
    );
    assert_eq!(adam.opacity_logits.m, vec![0.0, 0.0]);
    assert!(
        !s.refine(cfg.densify_until, &mut m, &mut adam, EXTENT)
            .opacity_reset
    );
}

#[test]
fn nothing_changes_outside_the_densification_schedule() {
    let mut m = model(&[gaussian(0.0, 0.005, 0.5, 0.0)]);
    let mut adam = AdamState::new(1);
    let mut s = DefaultStrategy::new(&TrainConfig::default());
    for step in [100, 500, 601, 15_000, 15_100] {
        feed(&mut s, step, &[1.0], 3.0);
        let r = s.refine(step, &mut m, &mut adam, EXTENT);
        assert_eq!((r.before, r.after), (1, 1), "step {step}");
    }
}
