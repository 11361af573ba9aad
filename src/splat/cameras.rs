//! COLMAP cameras and poses to the rasteriser's pinhole [`Camera`], and the train/test split.
//!
//! The rasteriser only knows pinhole cameras (docs/splatting.md "Camera"), so distorted COLMAP models
//! are undistorted once at load: every pixel of the output pinhole image (same size, focal
//! lengths and principal point) is mapped through the distortion model and sampled bilinearly
//! from the input. Distortion formulas are COLMAP's (`src/colmap/sensor/models.h`), applied to
//! normalised image coordinates u = (x − cx) / fx, v = (y − cy) / fy with pixel centres at
//! i + 0.5.

use crate::splat::camera::Camera;
use crate::splat::cpu::linalg::quat_to_mat;

pub use crate::splat::camera_models::{CameraError, CameraModel};
use crate::splat::packed_image::{PackedImage, pack};
use crate::splat::photo::Photo;

/// World→camera rotation (row-major) of a COLMAP `qvec` (w, x, y, z), normalised first.
pub fn rotation_from_qvec(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    quat_to_mat(q.map(|v| v / n))
}

/// The pinhole camera of a COLMAP camera and image pose (`qvec` w, x, y, z and `tvec` in
/// metres, world→camera). Distortion terms are dropped: pair it with [`undistort`].
pub fn camera_from_colmap(
    model: &CameraModel,
    width: u32,
    height: u32,
    qvec: [f64; 4],
    tvec: [f64; 3],
) -> Camera {
    let [fx, fy, cx, cy] = model.intrinsics();
    let r = rotation_from_qvec(qvec);
    Camera {
        width,
        height,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
        r: r.map(|row| row.map(|v| v as f32)),
        t: tvec.map(|v| v as f32),
    }
}

/// The pinhole image of a distorted one: same size, focal lengths and principal point; output
/// pixels that map outside the input are transparent black (alpha 0).
pub fn undistort(image: &PackedImage, model: &CameraModel) -> PackedImage {
    if !model.is_distorted() {
        return image.clone();
    }
    let [fx, fy, cx, cy] = model.intrinsics();
    let mut out = PackedImage::filled(image.width, image.height, [0; 4]);
    for j in 0..image.height {
        for i in 0..image.width {
            let u = (i as f64 + 0.5 - cx) / fx;
            let v = (j as f64 + 0.5 - cy) / fy;
            let (ud, vd) = model.distort(u, v);
            if let Some(c) = image.sample_bilinear(ud * fx + cx, vd * fy + cy) {
                out.pixels[(j * image.width + i) as usize] =
                    pack(c.map(|x| x.round().clamp(0.0, 255.0) as u8));
            }
        }
    }
    out
}

/// Downscales `image` so that its long side is at most `long_side` px (area averaging) and
/// adjusts `camera`'s intrinsics to match; no-op when the image is already small enough.
pub fn downscale_to_long_side(
    image: &PackedImage,
    camera: &Camera,
    long_side: u32,
) -> (PackedImage, Camera) {
    let long = image.width.max(image.height);
    if long_side == 0 || long <= long_side {
        return (image.clone(), *camera);
    }
    let s = long_side as f64 / long as f64;
    let w = ((image.width as f64 * s).round() as u32).max(1);
    let h = ((image.height as f64 * s).round() as u32).max(1);
    let (sx, sy) = (
        w as f32 / image.width as f32,
        h as f32 / image.height as f32,
    );
    let mut cam = *camera;
    (cam.width, cam.height) = (w, h);
    (cam.fx, cam.cx, cam.fy, cam.cy) = (cam.fx * sx, cam.cx * sx, cam.fy * sy, cam.cy * sy);
    (image.resize_area(w, h), cam)
}

/// A training or test view: name (COLMAP image name), pinhole camera and its photo (held
/// decoded or compressed, [`crate::splat::photo`]).
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub name: String,
    pub camera: Camera,
    pub image: Photo,
}

/// Builds a [`View`] from a COLMAP camera (model name, params, size), an image pose and the
/// decoded image: checks the size, undistorts, then downscales to `long_side` px if given.
#[allow(clippy::too_many_arguments)]
pub fn load_view(
    name: &str,
    model_name: &str,
    params: &[f64],
    width: u32,
    height: u32,
    qvec: [f64; 4],
    tvec: [f64; 3],
    image: &PackedImage,
    long_side: Option<u32>,
) -> Result<View, CameraError> {
    let model = CameraModel::from_colmap(model_name, params)?;
    if image.width != width || image.height != height {
        return Err(CameraError::SizeMismatch {
            name: name.to_string(),
            got_w: image.width,
            got_h: image.height,
            want_w: width,
            want_h: height,
        });
    }
    let [fx, fy, ..] = model.intrinsics();
    let qn: f64 = qvec.iter().map(|v| v * v).sum();
    if !(fx.is_finite() && fy.is_finite() && fx != 0.0 && fy != 0.0 && qn.is_finite() && qn > 0.0) {
        return Err(CameraError::Degenerate(name.to_string()));
    }
    let camera = camera_from_colmap(&model, width, height, qvec, tvec);
    let pinhole = undistort(image, &model);
    let (image, camera) = match long_side {
        Some(l) => downscale_to_long_side(&pinhole, &camera, l),
        None => (pinhole, camera),
    };
    Ok(View {
        name: name.to_string(),
        camera,
        image: image.into(),
    })
}

/// Indices into a list of images, split for training and testing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrainTestSplit {
    /// Training images, in name order.
    pub train: Vec<usize>,
    /// Held-out images, in name order.
    pub test: Vec<usize>,
}

/// Sorts `names` and holds out every `every`-th (sorted index % every == 0; docs/method.md
/// evaluation, reference `llffhold = 8`); `every == 0` holds out nothing. Returns indices into
/// `names`.
pub fn split_train_test<S: AsRef<str>>(names: &[S], every: usize) -> TrainTestSplit {
    let mut order: Vec<usize> = (0..names.len()).collect();
    order.sort_by(|&a, &b| names[a].as_ref().cmp(names[b].as_ref()));
    let (test, train) = order
        .iter()
        .enumerate()
        .partition::<Vec<_>, _>(|(k, _)| every > 0 && k % every == 0);
    TrainTestSplit {
        train: train.into_iter().map(|(_, &i)| i).collect(),
        test: test.into_iter().map(|(_, &i)| i).collect(),
    }
}

#[cfg(test)]
#[path = "cameras_tests.rs"]
mod tests;
