//! Tests of the Adam optimiser and its reindexing.

use super::*;
use crate::splat::model::Gaussian;

fn model(n: usize) -> Gaussians {
    let mut g = Gaussians::default();
    for i in 0..n {
        g.push(Gaussian::isotropic(
            [i as f32, 0.0, 0.0],
            0.1,
            [0.5; 3],
            0.5,
        ));
    }
    g
}

#[test]
fn position_rate_decays_exponentially_from_init_to_final() {
    let cfg = TrainConfig::default();
    assert!((lr_position(&cfg, 0, 2.0) - 3.2e-4).abs() < 1e-9);
    assert!((lr_position(&cfg, 30_000, 2.0) - 3.2e-6).abs() < 1e-10);
    // Halfway is the geometric mean.
    assert!((lr_position(&cfg, 15_000, 1.0) - 1.6e-5).abs() < 1e-9);
}

#[test]
fn first_step_moves_each_parameter_by_its_learning_rate() {
    let mut g = model(2);
    let mut grads = GaussianGrads::zeros(2);
    grads.means[0] = [1.0, -2.0, 0.0];
    grads.sh[1][0] = 0.3;
    grads.sh[1][5] = -0.3;
    let mut adam = AdamState::new(2);
    let lr = LearningRates::at(&TrainConfig::default(), 0, 1.0);
    adam.step(&mut g, &grads, &lr).expect("lengths agree");
    // With bias correction the first Adam step is lr · sign(g).
    assert!((g.means[0][0] - (0.0 - 1.6e-4)).abs() < 1e-7);
    assert!((g.means[0][1] - 1.6e-4).abs() < 1e-7);
    assert_eq!(g.means[0][2], 0.0);
    assert!((g.sh[1][0] - (model(2).sh[1][0] - 2.5e-3)).abs() < 1e-6);
    assert!((g.sh[1][5] - 1.25e-4).abs() < 1e-7);
}

#[test]
fn remap_gathers_moments_and_zeroes_new_gaussians() {
    let mut adam = AdamState::new(3);
    for i in 0..3 {
        adam.means.m[i * 3] = i as f32 + 1.0;
        adam.sh.v[i * SH_FLOATS + 47] = 10.0 * (i as f32 + 1.0);
    }
    adam.remap(&[Some(2), None, Some(0)]);
    assert_eq!(adam.len(), 3);
    assert_eq!(adam.means.m[0], 3.0);
    assert_eq!(adam.means.m[3], 0.0);
    assert_eq!(adam.means.m[6], 1.0);
    assert_eq!(adam.sh.v[2 * SH_FLOATS + 47], 10.0);
    adam.extend_zeros(2);
    assert_eq!(adam.len(), 5);
    assert_eq!(adam.sh.m.len(), 5 * SH_FLOATS);
    adam.retain_mask(&[false, true, true, false, false]);
    assert_eq!(adam.len(), 2);
    assert_eq!(adam.means.m[3], 1.0);
}

#[test]
fn mismatched_lengths_are_refused() {
    let mut g = model(3);
    let mut adam = AdamState::new(2);
    let lr = LearningRates::at(&TrainConfig::default(), 0, 1.0);
    let err = adam.step(&mut g, &GaussianGrads::zeros(3), &lr);
    assert!(matches!(
        err,
        Err(AdamError::LengthMismatch { model: 3, .. })
    ));
}
