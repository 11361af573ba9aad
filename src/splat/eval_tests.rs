//! Tests of the metrics and report files.

use super::*;
use crate::rng::SplitMix64;

fn noise(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut r = SplitMix64::new(seed);
    (0..n)
        .map(|_| std::array::from_fn(|_| r.uniform() as f32))
        .collect()
}

/// SSIM with the 2-D window applied directly (no separability), zero padding.
fn ssim_direct(a: &[[f32; 3]], b: &[[f32; 3]], w: usize, h: usize) -> f64 {
    let g = crate::splat::cpu::loss::ssim_window();
    let mut total = 0.0;
    for c in 0..3 {
        for y in 0..h as isize {
            for x in 0..w as isize {
                let (mut mx, mut my, mut sxx, mut syy, mut sxy) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
                for dy in -5..=5isize {
                    for dx in -5..=5isize {
                        let (i, j) = (x + dx, y + dy);
                        if i < 0 || j < 0 || i >= w as isize || j >= h as isize {
                            continue;
                        }
                        let k = g[(dx + 5) as usize] * g[(dy + 5) as usize];
                        let (p, q) = (
                            a[j as usize * w + i as usize][c] as f64,
                            b[j as usize * w + i as usize][c] as f64,
                        );
                        (mx, my, sxx, syy, sxy) = (
                            mx + k * p,
                            my + k * q,
                            sxx + k * p * p,
                            syy + k * q * q,
                            sxy + k * p * q,
                        );
                    }
                }
                let (c1, c2) = (1e-4, 9e-4);
                total += (2.0 * mx * my + c1) * (2.0 * (sxy - mx * my) + c2)
                    / ((mx * mx + my * my + c1) * (sxx - mx * mx + syy - my * my + c2));
            }
        }
    }
    total / (3 * w * h) as f64
}

#[test]
fn psnr_of_a_uniform_error_of_a_tenth_is_twenty_db() {
    let a = vec![[0.5f32; 3]; 12];
    let b = vec![[0.6f32; 3]; 12];
    assert!((psnr(&a, &b, 4, 3).expect("sizes match") - 20.0).abs() < 1e-3);
    assert_eq!(psnr(&a, &a, 4, 3).expect("sizes match"), PSNR_IDENTICAL);
    assert!(matches!(
        psnr(&a, &b, 5, 3),
        Err(EvalError::SizeMismatch { .. })
    ));
}

#[test]
fn ssim_matches_a_direct_two_dimensional_window_with_zero_padding() {
    let (w, h) = (23, 17);
    let a = noise(w * h, 1);
    let b: Vec<[f32; 3]> = a
        .iter()
        .zip(noise(w * h, 2))
        .map(|(p, q)| std::array::from_fn(|c| 0.7 * p[c] + 0.3 * q[c]))
        .collect();
    let fast = ssim(&a, &b, w as u32, h as u32).expect("sizes match") as f64;
    let slow = ssim_direct(&a, &b, w, h);
    assert!(
        (fast - slow).abs() < 1e-4,
        "separable {fast} vs direct {slow}"
    );
    assert!(fast < 0.95);
    assert!((ssim(&a, &a, w as u32, h as u32).expect("sizes match") - 1.0).abs() < 1e-5);
}

#[test]
fn report_averages_views_and_serialises() {
    let truth = crate::splat::packed_image::PackedImage::filled(4, 4, [128, 128, 128, 255]);
    let render = vec![[128.0 / 255.0 + 0.01; 3]; 16];
    let v = ViewMetrics::measure("a.jpg", &render, &truth, EvalRegion::Full).expect("sizes match");
    assert!((v.psnr - 40.0).abs() < 0.01);
    let r = EvalReport::from_views(vec![
        v.clone(),
        ViewMetrics {
            name: "b.jpg".into(),
            psnr: 20.0,
            ssim: 0.5,
            lpips: Some(0.4),
        },
    ]);
    assert!((r.psnr - 30.0).abs() < 0.01);
    // LPIPS is averaged only when every view has it (4×4 is below its smallest image).
    assert_eq!(v.lpips, None);
    assert_eq!(r.lpips, None);
    let both = EvalReport::from_views(
        [0.2, 0.4]
            .iter()
            .map(|&l| ViewMetrics {
                lpips: Some(l),
                ..v.clone()
            })
            .collect(),
    );
    assert!((both.lpips.expect("every view has LPIPS") - 0.3).abs() < 1e-6);
    let json = serde_json::to_string(&r).expect("serialise");
    assert!(json.contains("\"views\"") && json.contains("\"b.jpg\""));
    assert_eq!(serde_json::from_str::<EvalReport>(&json).expect("parse"), r);
}

#[test]
fn renders_round_to_8_bit_and_back() {
    let r = to_rgb8(&[[0.0, 0.5, 1.2], [-0.1, 1.0 / 255.0, 0.499 / 255.0]]);
    assert_eq!(r, vec![[0, 128, 255], [0, 1, 0]]);
    assert_eq!(from_rgb8(&r)[0], [0.0, 128.0 / 255.0, 1.0]);
}

#[test]
fn side_by_side_png_has_render_left_and_truth_right() {
    let dir = std::env::temp_dir().join(format!("splat-train-eval-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("view.png");
    save_side_by_side(&path, &[[255, 0, 0]; 6], &[[0, 0, 255]; 6], 3, 2).expect("write png");
    let img = image::open(&path).expect("read back").to_rgb8();
    assert_eq!(img.dimensions(), (6, 2));
    assert_eq!(img.get_pixel(0, 0).0, [255, 0, 0]);
    assert_eq!(img.get_pixel(5, 1).0, [0, 0, 255]);
    std::fs::remove_dir_all(&dir).expect("clean up");
}

#[test]
fn loss_csv_has_a_header_and_one_line_per_record() {
    let r = LossRecord {
        step: 7,
        loss: 0.25,
        l1: 0.2,
        ssim: 0.6,
        geo: 0.125,
        n_gaussians: 1234,
        seconds: 1.5,
        trunk: None,
    };
    let measured = LossRecord {
        trunk: Some(crate::splat::trunk_diag::TrunkDiag {
            s_count: 3,
            s_weight: 1.75,
            slice_count: 40,
            slice_in_s: Some(0.25),
            geo_photo_grad_ratio: None,
            surface_offset_mm: Some(-1.5),
            surface_abs_mm: Some(4.0),
        }),
        ..r
    };
    let mut out = Vec::new();
    write_loss_csv(&mut out, &[r, measured]).expect("write to memory");
    let text = String::from_utf8(out).expect("utf-8");
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines,
        [
            "step,loss,l1,ssim,n_gaussians,seconds,geo,s_count,s_weight,slice_count,slice_in_s,geo_photo_grad_ratio,surface_offset_mm,surface_abs_mm",
            "7,0.25,0.2,0.6,1234,1.500,0.125,,,,,,,",
            "7,0.25,0.2,0.6,1234,1.500,0.125,3,1.7500,40,0.2500,,-1.5000,4.0000"
        ]
    );
}

#[test]
fn right_half_metrics_see_only_columns_from_half_the_width() {
    // 5×2: columns 2, 3, 4 are the right half. The render is wrong in columns 0 and 1 only.
    let truth = crate::splat::packed_image::PackedImage::filled(5, 2, [51, 102, 153, 255]);
    let t = truth.to_rgb_f32();
    let mut render = t.clone();
    for y in 0..2 {
        for x in 0..2 {
            render[y * 5 + x] = [1.0, 0.0, 0.0];
        }
    }
    let full = ViewMetrics::measure("a", &render, &truth, EvalRegion::Full).expect("ok");
    let right = ViewMetrics::measure("a", &render, &truth, EvalRegion::RightHalf).expect("ok");
    assert!(full.psnr < 20.0, "full {}", full.psnr);
    assert_eq!(right.psnr, PSNR_IDENTICAL);
    // One wrong pixel in column 2 (the first right-half column) is seen.
    render[2] = [1.0, 0.0, 0.0];
    let right = ViewMetrics::measure("a", &render, &truth, EvalRegion::RightHalf).expect("ok");
    assert!(right.psnr < 20.0, "right {}", right.psnr);
    let (half, w) = right_half(&[0, 1, 2, 3, 4, 5, 6, 7, 8, 9], 5, 2);
    assert_eq!((half, w), (vec![2, 3, 4, 7, 8, 9], 3));
    let r = EvalReport::from_views_in(vec![right], EvalRegion::RightHalf);
    let json = serde_json::to_string(&r).expect("serialise");
    assert!(json.contains("\"region\":\"right_half\""), "{json}");
    // Reports written before the field existed read as full-image ones.
    let old: EvalReport =
        serde_json::from_str(r#"{"psnr": 20.0, "ssim": 0.5, "views": []}"#).expect("parse");
    assert_eq!(old.region, EvalRegion::Full);
}
