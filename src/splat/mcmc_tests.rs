use super::*;
use crate::splat::config::{StrategyKind, TrainConfig};
use crate::splat::cpu;
use crate::splat::cpu::test_scenes::{camera_facing_origin, random_scene};
use crate::splat::model::Gaussian;

fn terms() -> StepTerms {
    StepTerms {
        noise_lr: 5e5,
        opacity_reg: 0.01,
        scale_reg: 0.01,
        seed: 11,
        bound_min_prob: Some(0.5),
    }
}

#[test]
fn one_copy_is_the_gaussian_itself_and_n_copies_keep_its_opacity() {
    let (o1, f1) = relocated(0.6, 1, 0.005);
    assert!(
        (o1 - 0.6).abs() < 1e-6 && (f1 - 1.0).abs() < 1e-6,
        "{o1} {f1}"
    );
    for n in 2..6 {
        for o in [0.1f32, 0.5, 0.9] {
            let (on, f) = relocated(o, n, 0.005);
            // n layers of opacity o' in front of each other let through (1 − o')^n.
            let through = (1.0 - on).powi(n as i32);
            assert!((1.0 - through - o).abs() < 1e-5, "n {n} o {o} o' {on}");
            assert!(on < o && f > 0.0 && f.is_finite(), "n {n} o {o}: {on} {f}");
        }
    }
}

/// The paper's claim behind the formula: the copies, stacked on the original, render what it
/// rendered — far closer than copies that keep the original's opacity and scale.
#[test]
fn relocated_copies_render_like_the_original() {
    let cam = camera_facing_origin([0.0, -3.0, 0.0], 48, 48, 60.0);
    let g = Gaussian::isotropic([0.0; 3], 0.2, [0.8, 0.5, 0.3], 0.7);
    let render = |m: &Gaussians| cpu::render(m, &cam, [0.0; 3]).expect("render").image;
    let mut one = Gaussians::default();
    one.push(g);
    let reference = render(&one);
    let diff = |m: &Gaussians| {
        let img = render(m);
        img.iter()
            .zip(&reference)
            .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs()).sum::<f32>())
            .sum::<f32>()
            / reference.len() as f32
    };
    let n = 3;
    let (o, f) = relocated(0.7, n, 0.005);
    let mut copies = Gaussians::default();
    let mut naive = Gaussians::default();
    for _ in 0..n {
        let mut c = g;
        c.opacity_logit = logit(o);
        c.log_scale = c.log_scale.map(|s| s + f.ln());
        copies.push(c);
        naive.push(g);
    }
    let (d_copies, d_naive) = (diff(&copies), diff(&naive));
    assert!(
        d_copies < 0.2 * d_naive && d_copies < 0.01,
        "mean |Δ| per pixel: relocated copies {d_copies}, naive copies {d_naive}"
    );
}

fn scene_with_dead() -> Gaussians {
    let mut g = random_scene(3, 40, 0);
    for i in 0..40 {
        if i % 4 == 0 {
            g.opacity_logits[i] = -8.0; // opacity 3e-4: dead
        }
        if i % 5 == 1 {
            g.trunk_prob[i] = 0.9; // bound trunk surfel
        }
    }
    g
}

fn strategy(cap: usize) -> McmcStrategy {
    let mut cfg = TrainConfig {
        strategy: StrategyKind::Mcmc,
        max_gaussians: Some(cap),
        ..TrainConfig::default()
    }
    .scaled_to(1000);
    cfg.bind.enabled = true;
    McmcStrategy::new(&cfg).expect("strategy")
}

#[test]
fn refinement_relocates_the_dead_grows_to_the_cap_and_keeps_moments_aligned() {
    let mut g = scene_with_dead();
    let mut adam = AdamState::new(g.len());
    adam.opacity_logits.m.fill(1.0);
    let before = g.clone();
    let mut s = strategy(41);
    assert!(s.wants_refine(100) && !s.wants_refine(101) && !s.wants_refine(10));
    let r = s.refine(100, &mut g, &mut adam, 1.0);
    // 5 % of 40 is 2, but the cap allows 1.
    assert_eq!((r.before, r.after, r.relocated, r.cloned), (40, 41, 10, 1));
    assert_eq!(adam.len(), 41);
    assert!(g.is_consistent());
    let opac: Vec<f32> = g.opacity_logits.iter().map(|&l| sigmoid(l)).collect();
    assert!(opac.iter().all(|&o| o > 0.005), "a dead Gaussian is left");
    let mut moved = 0;
    for i in 0..40 {
        let unchanged = g.get(i) == before.get(i);
        // Untouched Gaussians keep their moments; touched ones start again from zero.
        let m = adam.opacity_logits.m[i];
        assert!(
            (unchanged && m == 1.0) || (!unchanged && m == 0.0),
            "Gaussian {i}: unchanged {unchanged}, moment {m}"
        );
        moved += usize::from(!unchanged);
        // A bound surfel is never the source of a copy: its parameters do not change unless it
        // was dead itself.
        if before.trunk_prob[i] >= 0.5 && before.opacity_logits[i] > -8.0 {
            assert!(unchanged, "bound Gaussian {i} was relocated onto");
        }
    }
    assert!(moved >= 10);
    // Every relocated Gaussian sits exactly on a live one.
    for i in (0..40).step_by(4) {
        assert!(
            (0..41).any(|j| j != i && g.means[j] == g.means[i]),
            "relocated {i} is on no other Gaussian"
        );
    }
    // At the cap, nothing grows; there is nothing dead to move.
    let r = s.refine(200, &mut g, &mut adam, 1.0);
    assert_eq!((r.after, r.relocated, r.cloned), (41, 0, 0));
}

#[test]
fn mcmc_needs_a_budget() {
    let cfg = TrainConfig {
        strategy: StrategyKind::Mcmc,
        ..TrainConfig::default()
    };
    let err = McmcStrategy::new(&cfg).expect_err("no cap");
    assert!(err.contains("max_gaussians"), "{err}");
}

#[test]
fn hashed_normals_are_standard() {
    let mut sum = [0.0f64; 3];
    let mut sq = [0.0f64; 3];
    let n = 30_000u32;
    for i in 0..n {
        let e = normal3(7, 3, i);
        for k in 0..3 {
            sum[k] += f64::from(e[k]);
            sq[k] += f64::from(e[k]) * f64::from(e[k]);
        }
    }
    for k in 0..3 {
        let mean = sum[k] / f64::from(n);
        let var = sq[k] / f64::from(n) - mean * mean;
        assert!(
            mean.abs() < 0.03 && (var - 1.0).abs() < 0.05,
            "axis {k}: {mean} {var}"
        );
    }
    assert_ne!(normal3(7, 3, 1), normal3(7, 4, 1));
    assert_ne!(normal3(7, 3, 1), normal3(8, 3, 1));
}

#[test]
fn noise_moves_transparent_gaussians_along_their_long_axis_and_spares_the_bound() {
    let mut g = Gaussians::default();
    for i in 0..400 {
        let mut x = Gaussian::isotropic(
            [0.0; 3],
            0.01,
            [0.5; 3],
            if i % 2 == 0 { 0.001 } else { 0.9 },
        );
        x.log_scale = [0.1f32.ln(), 0.01f32.ln(), 0.01f32.ln()]; // long along x
        x.trunk_prob = if i % 4 == 0 { 0.9 } else { 0.0 };
        g.push(x);
    }
    let t = terms();
    let f = flags(&g.trunk_prob, &t);
    let before = g.clone();
    add_noise(&mut g, &f, &t, 1e-4, 1);
    let mut spread = [0.0f64; 3];
    let mut moved_transparent = 0;
    for i in 0..400 {
        let d: Vec<f32> = (0..3).map(|a| g.means[i][a] - before.means[i][a]).collect();
        let norm = d.iter().map(|v| v * v).sum::<f32>().sqrt();
        if i % 4 == 0 {
            assert_eq!(norm, 0.0, "bound Gaussian {i} moved");
        } else if i % 2 == 1 {
            assert!(norm < 1e-6, "opaque Gaussian {i} moved {norm}");
        } else {
            moved_transparent += usize::from(norm > 0.0);
            for a in 0..3 {
                spread[a] += f64::from(d[a] * d[a]);
            }
        }
    }
    assert_eq!(moved_transparent, 100);
    // Σ ε has standard deviation s² along each axis: 100 × larger along the long axis.
    assert!(
        spread[0] > 1000.0 * spread[1] && spread[0] > 1000.0 * spread[2],
        "{spread:?}"
    );
}

#[test]
fn regulariser_gradients_match_finite_differences() {
    let mut g = random_scene(5, 12, 0);
    g.trunk_prob[3] = -1.0; // background: no scale term
    let t = terms();
    let f = flags(&g.trunk_prob, &t);
    let mut go = vec![0.0f32; g.len()];
    let mut gs = vec![[0.0f32; 3]; g.len()];
    regularise_grads(&g, &f, &t, &mut go, &mut gs);
    let h = 1e-3f32;
    for i in 0..g.len() {
        let mut p = g.clone();
        p.opacity_logits[i] += h;
        let mut m = g.clone();
        m.opacity_logits[i] -= h;
        let fd = (regulariser(&p, &f, &t) - regulariser(&m, &f, &t)) / (2.0 * f64::from(h));
        assert!(
            (fd - f64::from(go[i])).abs() < 1e-3 * fd.abs().max(1e-7),
            "opacity {i}: {fd} vs {}",
            go[i]
        );
        for (k, &analytic) in gs[i].iter().enumerate() {
            let mut p = g.clone();
            p.log_scales[i][k] += h;
            let mut m = g.clone();
            m.log_scales[i][k] -= h;
            let fd = (regulariser(&p, &f, &t) - regulariser(&m, &f, &t)) / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(analytic)).abs() < 1e-3 * fd.abs().max(1e-7),
                "scale {i},{k}: {fd} vs {analytic}"
            );
        }
    }
    assert_eq!(gs[3], [0.0; 3]);
}
