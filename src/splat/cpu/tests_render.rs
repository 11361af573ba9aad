//! Forward sanity checks of the renderer and checks of the loss.

use crate::splat::camera::{Camera, RenderOptions};
use crate::splat::cpu::loss::{blur, loss_f64, ssim_window};
use crate::splat::cpu::raster::T_MIN;
use crate::splat::cpu::test_scenes::{
    camera_facing_origin, mean_intensity, random_image, random_scene, small_camera, sub_pixel_grid,
    sub_pixel_grid_camera,
};
use crate::splat::cpu::{CpuError, loss_and_grad_f64, render, render_backward, render_with};
use crate::splat::eval::{PSNR_IDENTICAL, psnr, ssim};
use crate::splat::model::{Gaussian, Gaussians};

fn centred_camera() -> Camera {
    // Principal point on a pixel centre so the Gaussian at the origin lands exactly there.
    let mut cam = camera_facing_origin([0.0, -4.0, 0.0], 33, 25, 30.0);
    cam.cx = 16.5;
    cam.cy = 12.5;
    cam
}

fn one(g: Gaussian) -> Gaussians {
    let mut m = Gaussians::default();
    m.push(g);
    m
}

#[test]
fn single_opaque_gaussian_shows_its_colour_at_its_centre() {
    let rgb = [0.9, 0.2, 0.4];
    let model = one(Gaussian::isotropic([0.0, 0.0, 0.0], 0.2, rgb, 0.95));
    let bg = [0.0, 0.0, 1.0];
    let r = render(&model, &centred_camera(), bg).unwrap();
    let c = r.image[12 * 33 + 16];
    for ch in 0..3 {
        let expect = 0.95 * rgb[ch] + 0.05 * bg[ch];
        assert!(
            (c[ch] - expect).abs() < 1e-5,
            "channel {ch}: {} vs {expect}",
            c[ch]
        );
    }
    assert_eq!(r.n_contrib[12 * 33 + 16], 1);
    // Far corner: only background.
    assert_eq!(r.image[0], bg);
    assert_eq!(r.n_contrib[0], 0);
}

#[test]
fn radius_follows_the_eigenvalue_rule() {
    let model = one(Gaussian::isotropic([0.0, 0.0, 0.0], 0.2, [0.5; 3], 0.5));
    let p = render(&model, &centred_camera(), [0.0; 3])
        .unwrap()
        .projected[0];
    let s2 = (30.0f64 * 0.2 / 4.0).powi(2) + 0.3; // isotropic: λ_max = mid + sqrt(0.1)
    let expect = (3.0 * (s2 + 0.1f64.sqrt()).sqrt()).ceil() as u32;
    assert_eq!(p.radius, expect);
    assert!((p.conic[0] - 1.0 / s2).abs() < 1e-6 && p.conic[1].abs() < 1e-9);
    assert!((p.mean2d[0] - 16.5).abs() < 1e-5 && (p.depth - 4.0).abs() < 1e-6);
}

#[test]
fn antialias_scales_the_opacity_by_the_compensation_and_keeps_the_footprint() {
    let (sigma, opacity) = (0.05f32, 0.8f32);
    let model = one(Gaussian::isotropic(
        [0.0, 0.0, 0.0],
        sigma,
        [0.5; 3],
        opacity,
    ));
    let cam = centred_camera();
    let on = RenderOptions { antialias: true };
    let plain = render(&model, &cam, [0.0; 3]).unwrap().projected[0];
    let aa = render_with(&model, &cam, [0.0; 3], on).unwrap().projected[0];
    // Isotropic, 30 px/m · 0.05 m / 4 m: variance v px²; ρ = sqrt(v² / (v + 0.3)²).
    let v = (30.0f64 * f64::from(sigma) / 4.0).powi(2);
    let rho = v / (v + 0.3);
    assert!(
        (aa.opacity - f64::from(opacity) * rho).abs() < 1e-6,
        "{} vs {}",
        aa.opacity,
        f64::from(opacity) * rho
    );
    assert!((plain.opacity - f64::from(opacity)).abs() < 1e-6);
    assert_eq!(
        (aa.conic, aa.radius, aa.mean2d),
        (plain.conic, plain.radius, plain.mean2d)
    );
}

/// Small Gaussians (0.25–0.6 px at half resolution, 1–2.4 px at twice) rendered at R/2, R and
/// 2R: the mean intensity of the image is the total light over the image area, which does not
/// depend on the resolution. With the 2-D Mip filter it stays within 3 % (what is left: the
/// tails under the 1/255 alpha cut, a larger share of a dimmer Gaussian); with the dilation
/// alone the sub-pixel Gaussians grow to the filter's size as bright, and half resolution is
/// more than 25 % brighter than twice.
#[test]
fn antialias_keeps_the_total_light_across_resolutions() {
    let model = sub_pixel_grid(31);
    let light = |opts: RenderOptions| -> Vec<f64> {
        [1u32, 2, 4]
            .map(|k| {
                let r = render_with(&model, &sub_pixel_grid_camera(k), [0.0; 3], opts).unwrap();
                mean_intensity(&r.image)
            })
            .to_vec()
    };
    let on = light(RenderOptions { antialias: true });
    let off = light(RenderOptions::default());
    eprintln!("mean intensity at R/2, R, 2R: filter on {on:?}, off {off:?}");
    let spread =
        on.iter().cloned().fold(0.0, f64::max) / on.iter().cloned().fold(f64::INFINITY, f64::min);
    assert!(on[0] > 0.0 && spread < 1.03, "filter on: {on:?}");
    assert!(off[0] / off[2] > 1.25, "filter off: {off:?}");
}

#[test]
fn transmittance_and_contributors_are_consistent() {
    let model = random_scene(11, 40, 2);
    let cam = small_camera();
    let black = render(&model, &cam, [0.0; 3]).unwrap();
    let white = render(&model, &cam, [1.0; 3]).unwrap();
    assert!(
        black.n_contrib.iter().any(|&n| n >= 3),
        "scene should overlap"
    );
    assert!(
        black.n_contrib.contains(&0),
        "scene should leave background"
    );
    for p in 0..black.image.len() {
        let t = f64::from(black.final_t[p]);
        assert!((T_MIN..=1.0).contains(&t));
        assert!((t == 1.0) == (black.n_contrib[p] == 0));
        for ch in 0..3 {
            let d = f64::from(white.image[p][ch] - black.image[p][ch]);
            assert!(
                (d - t).abs() < 1e-6,
                "pixel {p}: background weight {d} vs T {t}"
            );
        }
        assert!(black.n_contrib[p] as usize <= black.depth_order.len());
    }
}

#[test]
fn front_gaussian_wins_regardless_of_index_order() {
    let near = Gaussian::isotropic([0.0, -1.0, 0.0], 0.3, [1.0, 0.0, 0.0], 0.99);
    let far = Gaussian::isotropic([0.0, 1.0, 0.0], 0.3, [0.0, 1.0, 0.0], 0.99);
    for pair in [[near, far], [far, near]] {
        let mut m = Gaussians::default();
        pair.into_iter().for_each(|g| m.push(g));
        let c = render(&m, &centred_camera(), [0.0; 3]).unwrap().image[12 * 33 + 16];
        assert!(c[0] > 0.98 && c[1] < 0.01, "{c:?}");
    }
}

#[test]
fn gaussians_behind_the_near_plane_or_off_screen_are_culled() {
    let cam = centred_camera(); // camera at y = -4 looking along +y
    let behind = Gaussian::isotropic([0.0, -5.0, 0.0], 0.2, [1.0; 3], 0.9);
    let too_near = Gaussian::isotropic([0.0, -3.995, 0.0], 0.001, [1.0; 3], 0.9);
    let just_in = Gaussian::isotropic([0.0, -3.98, 0.0], 0.0001, [1.0; 3], 0.9);
    let aside = Gaussian::isotropic([50.0, 0.0, 0.0], 0.2, [1.0; 3], 0.9);
    let mut m = Gaussians::default();
    [behind, too_near, just_in, aside]
        .into_iter()
        .for_each(|g| m.push(g));
    let r = render(&m, &cam, [0.2; 3]).unwrap();
    let vis: Vec<bool> = r.projected.iter().map(|p| p.visible).collect();
    assert_eq!(vis, [false, false, true, false]);
    assert_eq!(r.depth_order, [2]);
    let (g, stat) = render_backward(&m, &r, &vec![[1.0; 3]; r.image.len()], None).unwrap();
    assert_eq!(g.means[0], [0.0; 3]);
    assert_eq!(stat[0], 0.0);
}

#[test]
fn inconsistent_inputs_are_errors() {
    let mut m = random_scene(1, 3, 0);
    let cam = small_camera();
    let r = render(&m, &cam, [0.0; 3]).unwrap();
    assert_eq!(
        render_backward(&m, &r, &[[0.0; 3]; 5], None).unwrap_err(),
        CpuError::ImageSize {
            expected: 768,
            got: 5
        }
    );
    m.opacity_logits.pop();
    assert_eq!(
        render(&m, &cam, [0.0; 3]).unwrap_err(),
        CpuError::InconsistentModel
    );
}

#[test]
fn render_64x64_with_500_gaussians_gives_gradients() {
    let model = random_scene(12, 500, 3);
    let cam = camera_facing_origin([0.3, -4.0, 0.2], 64, 64, 50.0);
    let r = render(&model, &cam, [0.0; 3]).unwrap();
    let (_, stat) = render_backward(&model, &r, &vec![[0.1; 3]; r.image.len()], None).unwrap();
    assert!(stat.iter().any(|&s| s > 0.0));
}

#[test]
fn blur_matches_a_direct_2d_window_sum() {
    let (w, h) = (13, 9);
    let img: Vec<f64> = random_image(w, h, 3).iter().map(|p| p[1]).collect();
    let win = ssim_window();
    assert!((win.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    let b = blur(&img, w, h);
    for (x, y) in [(0, 0), (6, 4), (12, 8), (3, 7)] {
        let mut s = 0.0;
        for (dy, wy) in win.iter().enumerate() {
            for (dx, wx) in win.iter().enumerate() {
                let (xx, yy) = (x as isize + dx as isize - 5, y as isize + dy as isize - 5);
                if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                    s += wx * wy * img[yy as usize * w + xx as usize];
                }
            }
        }
        assert!((s - b[y * w + x]).abs() < 1e-12);
    }
}

#[test]
fn loss_of_identical_images_and_known_ssim() {
    let (w, h) = (20, 15);
    let a = random_image(w, h, 4);
    let (v, _) = loss_f64(&a, &a, w, h, false);
    assert!(v.loss.abs() < 1e-12 && (v.ssim - 1.0).abs() < 1e-12 && v.l1 == 0.0);
    let a32: Vec<[f32; 3]> = a.iter().map(|p| p.map(|x| x as f32)).collect();
    let (wu, hu) = (w as u32, h as u32);
    assert_eq!(psnr(&a32, &a32, wu, hu).unwrap(), PSNR_IDENTICAL);
    let shifted: Vec<[f32; 3]> = a32.iter().map(|p| p.map(|x| x + 0.1)).collect();
    assert!((psnr(&a32, &shifted, wu, hu).unwrap() - 20.0).abs() < 1e-4);
    // SSIM is symmetric, 1 only for identical images, and a contrast change lowers it.
    let b32: Vec<[f32; 3]> = a32.iter().map(|p| p.map(|x| 0.5 * x + 0.25)).collect();
    let (s_ab, s_ba) = (
        ssim(&a32, &b32, w as u32, h as u32).unwrap(),
        ssim(&b32, &a32, w as u32, h as u32).unwrap(),
    );
    assert!(
        (s_ab - s_ba).abs() < 1e-6 && s_ab < 0.99 && s_ab > 0.5,
        "{s_ab}"
    );
}

#[test]
fn loss_backward_matches_finite_differences() {
    let (w, h) = (23, 17);
    let x = random_image(w, h, 5);
    let y = random_image(w, h, 6);
    let (v, g) = loss_and_grad_f64(&x, &y, w as u32, h as u32).unwrap();
    assert!(v.ssim < 0.9 && v.l1 > 0.05);
    let scale = g
        .iter()
        .flat_map(|p| p.iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    for p in (0..w * h).step_by(7) {
        for c in 0..3 {
            let step = 1e-6;
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[p][c] += step;
            xm[p][c] -= step;
            let fd = (loss_f64(&xp, &y, w, h, false).0.loss
                - loss_f64(&xm, &y, w, h, false).0.loss)
                / (2.0 * step);
            assert!(
                (fd - g[p][c]).abs() < 1e-4 * scale,
                "pixel {p} ch {c}: {fd} vs {}",
                g[p][c]
            );
        }
    }
}
