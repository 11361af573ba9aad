//! Tests of COLMAP camera conversion, undistortion and the train/test split.

use super::*;
use crate::splat::packed_image::unpack;

const W: u32 = 96;
const H: u32 = 64;

/// [`load_view`] of photo "a.jpg" from a `width`×`height` PINHOLE camera with intrinsics
/// `params` at the world origin, unrotated.
fn pinhole_view(
    params: &[f64; 4],
    width: u32,
    height: u32,
    image: &PackedImage,
    long_side: Option<u32>,
) -> Result<View, CameraError> {
    let identity = [1.0, 0.0, 0.0, 0.0];
    load_view(
        "a.jpg", "PINHOLE", params, width, height, identity, [0.0; 3], image, long_side,
    )
}

fn opencv() -> CameraModel {
    CameraModel::from_colmap(
        "OPENCV",
        &[80.0, 80.0, 48.0, 32.0, -0.25, 0.06, 0.002, -0.001],
    )
    .expect("8 params")
}

/// Checkerboard of 0.2 normalised units (16 px) per square on the ideal image plane.
fn checker(u: f64, v: f64) -> f64 {
    let k = (u / 0.2).floor() as i64 + (v / 0.2).floor() as i64;
    if k.rem_euclid(2) == 0 { 255.0 } else { 0.0 }
}

/// Inverts `distort` by fixed-point iteration (COLMAP's `IterativeUndistortion` idea).
fn undistort_point(m: &CameraModel, ud: f64, vd: f64) -> (f64, f64) {
    let (mut u, mut v) = (ud, vd);
    for _ in 0..100 {
        let (du, dv) = m.distort(u, v);
        u += ud - du;
        v += vd - dv;
    }
    (u, v)
}

/// Renders the checkerboard with 4×4 supersampling; `distorted` renders what the real (distorted)
/// camera sees, otherwise the ideal pinhole view.
fn render(m: &CameraModel, distorted: bool) -> PackedImage {
    let [fx, fy, cx, cy] = m.intrinsics();
    let mut img = PackedImage::filled(W, H, [0, 0, 0, 255]);
    for j in 0..H {
        for i in 0..W {
            let mut acc = 0.0;
            for s in 0..16 {
                let x = i as f64 + (s % 4) as f64 * 0.25 + 0.125;
                let y = j as f64 + (s / 4) as f64 * 0.25 + 0.125;
                let (mut u, mut v) = ((x - cx) / fx, (y - cy) / fy);
                if distorted {
                    (u, v) = undistort_point(m, u, v);
                }
                acc += checker(u, v) / 16.0;
            }
            let g = acc.round() as u8;
            img.pixels[(j * W + i) as usize] = pack([g, g, g, 255]);
        }
    }
    img
}

/// Mean absolute grey difference in [0, 1] over pixels valid (alpha 255) in `a`.
fn mean_diff(a: &PackedImage, b: &PackedImage) -> f64 {
    let pairs: Vec<(u32, u32)> = a
        .pixels
        .iter()
        .copied()
        .zip(b.pixels.iter().copied())
        .collect();
    let valid: Vec<_> = pairs.iter().filter(|(p, _)| unpack(*p)[3] == 255).collect();
    assert!(
        valid.len() > pairs.len() * 9 / 10,
        "most pixels map inside the input"
    );
    valid
        .iter()
        .map(|(p, q)| (unpack(*p)[0] as f64 - unpack(*q)[0] as f64).abs() / 255.0)
        .sum::<f64>()
        / valid.len() as f64
}

#[test]
fn undistorting_a_distorted_checkerboard_recovers_the_pinhole_view() {
    let m = opencv();
    let ideal = render(&m, false);
    let seen = render(&m, true);
    let fixed = undistort(&seen, &m);
    let before = mean_diff(&seen, &ideal);
    let after = mean_diff(&fixed, &ideal);
    // Bilinear resampling blurs the square edges; on average the error stays small ...
    assert!(
        after < 0.045,
        "undistorted differs by {after} (before {before})"
    );
    assert!(after < before / 4.0, "before {before}, after {after}");
    // ... and away from the edges the geometry is exact: pixels whose ideal 3×3 neighbourhood is
    // uniform must come back with that value.
    let grey =
        |img: &PackedImage, i: u32, j: u32| unpack(img.pixels[(j * W + i) as usize])[0] as i32;
    let (mut interior, mut wrong) = (0, 0);
    for j in 1..H - 1 {
        for i in 1..W - 1 {
            let g = grey(&ideal, i, j);
            let uniform = (0..9).all(|k| grey(&ideal, i + k % 3 - 1, j + k / 3 - 1) == g);
            if uniform && unpack(fixed.pixels[(j * W + i) as usize])[3] == 255 {
                interior += 1;
                wrong += ((grey(&fixed, i, j) - g).abs() > 8) as usize;
            }
        }
    }
    assert!(
        interior > 2000 && wrong * 100 < interior,
        "{wrong} of {interior} interior pixels wrong"
    );
}

#[test]
fn a_world_point_projects_where_the_colmap_pose_puts_it() {
    // 90° about z: x_cam = (−y, x, z) + t.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let m = CameraModel::from_colmap("SIMPLE_PINHOLE", &[100.0, 50.0, 40.0]).expect("3 params");
    let cam = camera_from_colmap(&m, 100, 80, [h, 0.0, 0.0, h], [0.1, 0.2, 5.0]);
    let p = cam.to_camera([1.0, 2.0, 3.0]);
    for (got, want) in p.iter().zip([-1.9, 1.2, 8.0]) {
        assert!((got - want).abs() < 1e-5, "{p:?}");
    }
    let px = cam.fx * p[0] / p[2] + cam.cx;
    let py = cam.fy * p[1] / p[2] + cam.cy;
    assert!(
        (px - (50.0 - 100.0 * 1.9 / 8.0)).abs() < 1e-4
            && (py - (40.0 + 100.0 * 1.2 / 8.0)).abs() < 1e-4
    );
    let c = cam.to_camera(cam.centre());
    assert!(c.iter().all(|v| v.abs() < 1e-5));
}

#[test]
fn unsupported_models_and_wrong_parameter_counts_are_explained() {
    let err = CameraModel::from_colmap("FISHEYE", &[1.0]).expect_err("unsupported");
    assert!(err.to_string().contains("FISHEYE") && err.to_string().contains("OPENCV"));
    assert_eq!(
        CameraModel::from_colmap("PINHOLE", &[1.0, 2.0]),
        Err(CameraError::WrongParamCount {
            model: "PINHOLE",
            expected: 4,
            got: 2
        })
    );
    let img = PackedImage::filled(10, 10, [0; 4]);
    let err = pinhole_view(&[10.0, 10.0, 5.0, 5.0], 20, 10, &img, None);
    assert!(matches!(err, Err(CameraError::SizeMismatch { .. })));
}

#[test]
fn downscaling_to_a_long_side_scales_the_intrinsics() {
    let m = CameraModel::from_colmap("PINHOLE", &[100.0, 90.0, 50.0, 30.0]).expect("4 params");
    let img = PackedImage::filled(100, 60, [10, 20, 30, 255]);
    let v = pinhole_view(&[100.0, 90.0, 50.0, 30.0], 100, 60, &img, Some(50)).expect("valid view");
    assert_eq!((v.image.width, v.image.height), (50, 30));
    assert_eq!(
        (v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy),
        (50.0, 45.0, 25.0, 15.0)
    );
    assert_eq!(
        v.image.image().expect("decoded").get(7, 7),
        [10, 20, 30, 255]
    );
    assert!(!m.is_distorted());
}

#[test]
fn every_eighth_image_by_name_is_held_out() {
    let names: Vec<String> = (0..17).rev().map(|i| format!("img_{i:03}.jpg")).collect();
    let split = split_train_test(&names, 8);
    let test: Vec<&str> = split.test.iter().map(|&i| names[i].as_str()).collect();
    assert_eq!(test, ["img_000.jpg", "img_008.jpg", "img_016.jpg"]);
    assert_eq!(split.train.len(), 14);
    assert_eq!(names[split.train[0]], "img_001.jpg");
    assert!(split_train_test(&names, 0).test.is_empty());
}
