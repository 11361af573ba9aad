//! Finite-difference checks of the full chain model → render → loss (f64 internally).

use crate::splat::camera::{Camera, RenderOptions};
use crate::splat::cpu::project::{ProjectedGrad, project, project_backward};
use crate::splat::cpu::test_scenes::{offset_target, random_scene, small_camera};
use crate::splat::cpu::{ParamGrad, loss_and_grad_f64, render, render_backward_f64, render_with};
use crate::splat::model::Gaussians;

const BG: [f32; 3] = [0.1, 0.3, 0.2];
const OFF: RenderOptions = RenderOptions { antialias: false };
const AA: RenderOptions = RenderOptions { antialias: true };

/// Per-pixel weights of the depth term of [`loss_of`] (a smooth linear loss on the rendered
/// expected depth, 1/m), or none.
type DepthWeights<'a> = Option<&'a [f64]>;

fn depth_weights(n: usize) -> Vec<f64> {
    (0..n).map(|p| 0.05 * (p as f64 * 0.7).sin()).collect()
}

fn loss_of(
    model: &Gaussians,
    cam: &Camera,
    opts: RenderOptions,
    target: &[[f64; 3]],
    depth: DepthWeights,
) -> f64 {
    let r = render_with(model, cam, BG, opts).unwrap();
    let photo = loss_and_grad_f64(r.image_f64(), target, cam.width, cam.height)
        .unwrap()
        .0
        .loss;
    photo
        + depth.map_or(0.0, |w| {
            w.iter().zip(r.depth_f64()).map(|(w, d)| w * d).sum::<f64>()
        })
}

/// A parameter group: reads/writes one scalar `k` of Gaussian `i`, and picks its analytic grad.
struct Group {
    name: &'static str,
    dims: usize,
    get: fn(&mut Gaussians, usize, usize) -> &mut f32,
    grad: fn(&ParamGrad, usize) -> f64,
}

/// Central difference on the f32 parameter with the exact step actually taken.
#[allow(clippy::too_many_arguments)]
fn fd(
    model: &mut Gaussians,
    cam: &Camera,
    opts: RenderOptions,
    target: &[[f64; 3]],
    p: &Group,
    i: usize,
    k: usize,
    h: f32,
    depth: DepthWeights,
) -> f64 {
    let x0 = *(p.get)(model, i, k);
    let (xp, xm) = (x0 + h, x0 - h);
    *(p.get)(model, i, k) = xp;
    let lp = loss_of(model, cam, opts, target, depth);
    *(p.get)(model, i, k) = xm;
    let lm = loss_of(model, cam, opts, target, depth);
    *(p.get)(model, i, k) = x0;
    (lp - lm) / (f64::from(xp) - f64::from(xm))
}

/// Compares every component of `group` for the first `max_gaussians` Gaussians. Components
/// where the loss is not smooth at the FD scale (a pixel crossing the 1/255 alpha cut or a tile
/// boundary: FD with steps h, h/4 and h/16 never agree) are skipped; at most 2 % may be.
fn check_group(model: &Gaussians, group: &Group, max_gaussians: usize, opts: RenderOptions) {
    check_group_with(model, group, max_gaussians, opts, false);
}

/// [`check_group`], with the depth term of [`loss_of`] added when `with_depth`.
fn check_group_with(
    model: &Gaussians,
    group: &Group,
    max_gaussians: usize,
    opts: RenderOptions,
    with_depth: bool,
) {
    let cam = small_camera();
    let r = render_with(model, &cam, BG, opts).unwrap();
    let target = offset_target(r.image_f64(), 99);
    let (_, dl_dimg) = loss_and_grad_f64(r.image_f64(), &target, cam.width, cam.height).unwrap();
    let weights = depth_weights(r.image.len());
    let depth = with_depth.then_some(&weights[..]);
    let (grads, _) = render_backward_f64(model, &r, &dl_dimg, depth).unwrap();
    let mut m = model.clone();
    let mut rows = Vec::new();
    for (i, grad) in grads.iter().enumerate().take(max_gaussians) {
        for k in 0..group.dims {
            let f1 = fd(&mut m, &cam, opts, &target, group, i, k, 1e-4, depth);
            let f2 = fd(&mut m, &cam, opts, &target, group, i, k, 2.5e-5, depth);
            rows.push((i, k, (group.grad)(grad, k), f1, f2));
            if (f1 - f2).abs() > 0.05 * f2.abs() {
                // Possibly a discontinuity inside the larger step: refine once.
                let f3 = fd(&mut m, &cam, opts, &target, group, i, k, 6e-6, depth);
                if let Some(last) = rows.last_mut() {
                    (last.3, last.4) = (f2, f3);
                }
            }
        }
    }
    let scale = rows.iter().map(|r| r.4.abs()).fold(0.0, f64::max);
    assert!(
        scale > 1e-7,
        "{}: gradients vanish, the test would be vacuous",
        group.name
    );
    let (mut skipped, mut nonzero) = (0, 0);
    for &(i, k, an, f1, f2) in &rows {
        if (f1 - f2).abs() > 1e-3 * scale + 0.05 * f2.abs() {
            skipped += 1;
            continue;
        }
        nonzero += usize::from(f2.abs() > 1e-3 * scale);
        let tol = 1e-3 * f2.abs() + 1e-5 * scale;
        assert!(
            (an - f2).abs() <= tol,
            "{} gaussian {i} comp {k}: analytic {an:e} fd {f2:e} (scale {scale:e})",
            group.name
        );
    }
    assert!(
        skipped * 50 <= rows.len(),
        "{}: {skipped} of {} components not smooth",
        group.name,
        rows.len()
    );
    assert!(
        nonzero * 4 >= rows.len(),
        "{}: too few non-zero gradients ({nonzero})",
        group.name
    );
}

fn means() -> Group {
    Group {
        name: "means",
        dims: 3,
        get: |m, i, k| &mut m.means[i][k],
        grad: |g, k| g.mean[k],
    }
}

fn log_scales() -> Group {
    Group {
        name: "log_scales",
        dims: 3,
        get: |m, i, k| &mut m.log_scales[i][k],
        grad: |g, k| g.log_scale[k],
    }
}

fn rotations() -> Group {
    Group {
        name: "rotations",
        dims: 4,
        get: |m, i, k| &mut m.rotations[i][k],
        grad: |g, k| g.rotation[k],
    }
}

fn opacity_logits() -> Group {
    Group {
        name: "opacity",
        dims: 1,
        get: |m, i, _| &mut m.opacity_logits[i],
        grad: |g, _| g.opacity_logit,
    }
}

#[test]
fn fd_means() {
    check_group(&random_scene(1, 30, 3), &means(), 30, OFF);
}

#[test]
fn fd_log_scales() {
    check_group(&random_scene(2, 30, 0), &log_scales(), 30, OFF);
}

#[test]
fn fd_rotations() {
    check_group(&random_scene(3, 30, 1), &rotations(), 30, OFF);
}

#[test]
fn fd_opacity_logits() {
    check_group(&random_scene(4, 40, 2), &opacity_logits(), 40, OFF);
}

#[test]
fn fd_sh_degree3_view_dependent() {
    let g = Group {
        name: "sh",
        dims: 48,
        get: |m, i, k| &mut m.sh[i][k],
        grad: |g, k| g.sh[k],
    };
    check_group(&random_scene(5, 25, 3), &g, 6, OFF);
}

/// [`random_scene`] with every axis `e^-0.7` ≈ half as long (0.05–0.2 m, 0.4–1.5 px on
/// [`small_camera`]): most Gaussians near or below a pixel, where the compensation ρ of the
/// 2-D Mip filter is far from 1 (about 0.35–0.9).
fn small_scene(seed: u64, n: usize, degree: u32) -> Gaussians {
    let mut m = random_scene(seed, n, degree);
    for s in &mut m.log_scales {
        *s = s.map(|v| v - 0.7);
    }
    m
}

#[test]
fn fd_means_antialias() {
    check_group(&small_scene(21, 30, 3), &means(), 30, AA);
}

#[test]
fn fd_log_scales_antialias() {
    check_group(&small_scene(22, 30, 0), &log_scales(), 30, AA);
}

#[test]
fn fd_rotations_antialias() {
    check_group(&small_scene(23, 30, 1), &rotations(), 30, AA);
}

#[test]
fn fd_opacity_logits_antialias() {
    check_group(&small_scene(24, 40, 2), &opacity_logits(), 40, AA);
}

/// The blended opacity `sigmoid(logit) · ρ(Σ2D)` of the projection alone against central
/// differences in every parameter it depends on (no rasteriser, so no alpha cut-offs): the
/// gradient of the compensation through Σ2D → J, Σ → means, scales and rotations.
#[test]
fn fd_projection_compensated_opacity() {
    let model = small_scene(25, 40, 1);
    let cam = small_camera();
    let unit = ProjectedGrad {
        opacity: 1.0,
        ..ProjectedGrad::default()
    };
    let (mut checked, mut below_half) = (0, 0);
    for i in 0..model.len() {
        let p = project(&model, i, &cam, AA);
        if !p.visible {
            continue;
        }
        let plain = project(&model, i, &cam, OFF);
        let rho = p.opacity / plain.opacity;
        assert!(rho > 0.0 && rho < 1.0, "gaussian {i}: rho {rho}");
        below_half += usize::from(rho < 0.5);
        let an = project_backward(&model, i, &cam, AA, &unit);
        for group in [means(), log_scales(), rotations(), opacity_logits()] {
            for k in 0..group.dims {
                let mut m = model.clone();
                let x0 = *(group.get)(&mut m, i, k);
                let h = 1e-3 * x0.abs().max(0.1);
                let (xp, xm) = (x0 + h, x0 - h);
                *(group.get)(&mut m, i, k) = xp;
                let op = project(&m, i, &cam, AA).opacity;
                *(group.get)(&mut m, i, k) = xm;
                let om = project(&m, i, &cam, AA).opacity;
                let fd = (op - om) / (f64::from(xp) - f64::from(xm));
                let a = (group.grad)(&an, k);
                assert!(
                    (a - fd).abs() <= 1e-4 * fd.abs() + 1e-6,
                    "{} gaussian {i} comp {k}: analytic {a:e} fd {fd:e}",
                    group.name
                );
                checked += 1;
            }
        }
    }
    assert!(checked >= 200, "only {checked} components checked");
    assert!(
        below_half >= 3,
        "only {below_half} Gaussians with rho < 0.5"
    );
}

#[test]
fn sh_above_active_degree_gets_zero_gradient() {
    let model = random_scene(6, 20, 1);
    let cam = small_camera();
    let r = render(&model, &cam, BG).unwrap();
    let dl: Vec<[f64; 3]> = vec![[1.0, -0.5, 0.25]; r.image.len()];
    let (grads, _) = render_backward_f64(&model, &r, &dl, None).unwrap();
    assert!(
        grads
            .iter()
            .any(|g| g.sh[3..12].iter().any(|v| v.abs() > 1e-6))
    );
    assert!(grads.iter().all(|g| g.sh[12..].iter().all(|&v| v == 0.0)));
}

/// The rendered depth's gradient reaches the means (through z and the alphas), the shapes and
/// the opacities.
#[test]
fn fd_with_a_depth_loss() {
    check_group_with(&random_scene(7, 30, 0), &means(), 30, OFF, true);
    check_group_with(&random_scene(8, 30, 0), &log_scales(), 30, OFF, true);
    check_group_with(&random_scene(9, 40, 0), &opacity_logits(), 40, OFF, true);
    check_group_with(&random_scene(7, 30, 0), &means(), 30, AA, true);
}

/// The depth term changes the gradients (so [`fd_with_a_depth_loss`] tests something).
#[test]
fn a_depth_loss_changes_the_gradients() {
    let model = random_scene(7, 30, 0);
    let cam = small_camera();
    let r = render(&model, &cam, BG).unwrap();
    let dl: Vec<[f64; 3]> = vec![[0.0; 3]; r.image.len()];
    let w = depth_weights(r.image.len());
    let (g0, _) = render_backward_f64(&model, &r, &dl, None).unwrap();
    let (g1, _) = render_backward_f64(&model, &r, &dl, Some(&w)).unwrap();
    assert!(g0.iter().all(|g| g.mean == [0.0; 3]));
    assert!(g1.iter().filter(|g| g.mean[1].abs() > 1e-6).count() > 10);
}
