//! Finite-difference checks of the full chain model → render → loss (f64 internally).

use crate::splat::camera::Camera;
use crate::splat::cpu::test_scenes::{offset_target, random_scene, small_camera};
use crate::splat::cpu::{
    ParamGrad, loss_and_grad_f64, render, render_backward_depth_f64, render_backward_f64,
};
use crate::splat::model::Gaussians;

const BG: [f32; 3] = [0.1, 0.3, 0.2];

/// Per-pixel weights of the depth term of [`loss_of`] (a smooth linear loss on the rendered
/// expected depth, 1/m), or none.
type DepthWeights<'a> = Option<&'a [f64]>;

fn depth_weights(n: usize) -> Vec<f64> {
    (0..n).map(|p| 0.05 * (p as f64 * 0.7).sin()).collect()
}

fn loss_of(model: &Gaussians, cam: &Camera, target: &[[f64; 3]], depth: DepthWeights) -> f64 {
    let r = render(model, cam, BG).unwrap();
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
    let lp = loss_of(model, cam, target, depth);
    *(p.get)(model, i, k) = xm;
    let lm = loss_of(model, cam, target, depth);
    *(p.get)(model, i, k) = x0;
    (lp - lm) / (f64::from(xp) - f64::from(xm))
}

/// Compares every component of `group` for the first `max_gaussians` Gaussians. Components
/// where the loss is not smooth at the FD scale (a pixel crossing the 1/255 alpha cut or a tile
/// boundary: FD with steps h, h/4 and h/16 never agree) are skipped; at most 2 % may be.
fn check_group(model: &Gaussians, group: &Group, max_gaussians: usize) {
    check_group_with(model, group, max_gaussians, false);
}

/// [`check_group`], with the depth term of [`loss_of`] added when `with_depth`.
fn check_group_with(model: &Gaussians, group: &Group, max_gaussians: usize, with_depth: bool) {
    let cam = small_camera();
    let r = render(model, &cam, BG).unwrap();
    let target = offset_target(r.image_f64(), 99);
    let (_, dl_dimg) = loss_and_grad_f64(r.image_f64(), &target, cam.width, cam.height).unwrap();
    let weights = depth_weights(r.image.len());
    let depth = with_depth.then_some(&weights[..]);
    let (grads, _) = render_backward_depth_f64(model, &cam, BG, &r, &dl_dimg, depth).unwrap();
    let mut m = model.clone();
    let mut rows = Vec::new();
    for (i, grad) in grads.iter().enumerate().take(max_gaussians) {
        for k in 0..group.dims {
            let f1 = fd(&mut m, &cam, &target, group, i, k, 1e-4, depth);
            let f2 = fd(&mut m, &cam, &target, group, i, k, 2.5e-5, depth);
            rows.push((i, k, (group.grad)(grad, k), f1, f2));
            if (f1 - f2).abs() > 0.05 * f2.abs() {
                // Possibly a discontinuity inside the larger step: refine once.
                let f3 = fd(&mut m, &cam, &target, group, i, k, 6e-6, depth);
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

#[test]
fn fd_means() {
    let g = Group {
        name: "means",
        dims: 3,
        get: |m, i, k| &mut m.means[i][k],
        grad: |g, k| g.mean[k],
    };
    check_group(&random_scene(1, 30, 3), &g, 30);
}

#[test]
fn fd_log_scales() {
    let g = Group {
        name: "log_scales",
        dims: 3,
        get: |m, i, k| &mut m.log_scales[i][k],
        grad: |g, k| g.log_scale[k],
    };
    check_group(&random_scene(2, 30, 0), &g, 30);
}

#[test]
fn fd_rotations() {
    let g = Group {
        name: "rotations",
        dims: 4,
        get: |m, i, k| &mut m.rotations[i][k],
        grad: |g, k| g.rotation[k],
    };
    check_group(&random_scene(3, 30, 1), &g, 30);
}

#[test]
fn fd_opacity_logits() {
    let g = Group {
        name: "opacity",
        dims: 1,
        get: |m, i, _| &mut m.opacity_logits[i],
        grad: |g, _| g.opacity_logit,
    };
    check_group(&random_scene(4, 40, 2), &g, 40);
}

#[test]
fn fd_sh_degree3_view_dependent() {
    let g = Group {
        name: "sh",
        dims: 48,
        get: |m, i, k| &mut m.sh[i][k],
        grad: |g, k| g.sh[k],
    };
    check_group(&random_scene(5, 25, 3), &g, 6);
}

/// The rendered depth's gradient reaches the means (through z and the alphas), the shapes and
/// the opacities.
#[test]
fn fd_with_a_depth_loss() {
    let means = Group {
        name: "means with depth",
        dims: 3,
        get: |m, i, k| &mut m.means[i][k],
        grad: |g, k| g.mean[k],
    };
    check_group_with(&random_scene(7, 30, 0), &means, 30, true);
    let scales = Group {
        name: "log_scales with depth",
        dims: 3,
        get: |m, i, k| &mut m.log_scales[i][k],
        grad: |g, k| g.log_scale[k],
    };
    check_group_with(&random_scene(8, 30, 0), &scales, 30, true);
    let opacity = Group {
        name: "opacity with depth",
        dims: 1,
        get: |m, i, _| &mut m.opacity_logits[i],
        grad: |g, _| g.opacity_logit,
    };
    check_group_with(&random_scene(9, 40, 0), &opacity, 40, true);
}

/// The depth term changes the gradients (so [`fd_with_a_depth_loss`] tests something).
#[test]
fn a_depth_loss_changes_the_gradients() {
    let model = random_scene(7, 30, 0);
    let cam = small_camera();
    let r = render(&model, &cam, BG).unwrap();
    let dl: Vec<[f64; 3]> = vec![[0.0; 3]; r.image.len()];
    let w = depth_weights(r.image.len());
    let (g0, _) = render_backward_f64(&model, &cam, BG, &r, &dl).unwrap();
    let (g1, _) = render_backward_depth_f64(&model, &cam, BG, &r, &dl, Some(&w)).unwrap();
    assert!(g0.iter().all(|g| g.mean == [0.0; 3]));
    assert!(g1.iter().filter(|g| g.mean[1].abs() > 1e-6).count() > 10);
}

#[test]
fn sh_above_active_degree_gets_zero_gradient() {
    let model = random_scene(6, 20, 1);
    let cam = small_camera();
    let r = render(&model, &cam, BG).unwrap();
    let dl: Vec<[f64; 3]> = vec![[1.0, -0.5, 0.25]; r.image.len()];
    let (grads, _) = render_backward_f64(&model, &cam, BG, &r, &dl).unwrap();
    assert!(
        grads
            .iter()
            .any(|g| g.sh[3..12].iter().any(|v| v.abs() > 1e-6))
    );
    assert!(grads.iter().all(|g| g.sh[12..].iter().all(|&v| v == 0.0)));
}
