//! A training set from a COLMAP project: every registered photo decoded once, undistorted to a
//! pinhole camera, downscaled, and split into training and held-out views (every 8th by name);
//! plus the sparse points (for vanilla initialisation) and the scene extent that scales the
//! position learning rate and the densification thresholds.
//!
//! A sparse model may carry no point colours: COLMAP's mapper with `extract_colors=false` writes
//! every point as (0, 0, 0), as the real `nerfpl_tree` model does. Black points start every
//! Gaussian at the clamp of the colour (`max(raw + 0.5, 0)` at exactly 0), a whole scene
//! renders black and training cannot recover it. Such points are coloured from the photos
//! instead, as the LiDAR anchors are: the median of their visible projections into the
//! training views ([`crate::splat::init::photometric_colours`]).

use std::path::Path;

use rayon::prelude::*;

use super::cameras::{View, load_view, split_train_test};
use super::exposure::ExposureSlot;
use super::packed_image::PackedImage;
use super::photo::keep_compressed;
use crate::io::IoError;
use crate::io::colmap::{self, ColmapModel};
use crate::progress::Progress;

/// Why a dataset could not be built; the message names the file and the fault.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("{0}")]
    Invalid(String),
    #[error("cancelled")]
    Cancelled,
}

/// Training and held-out views with what initialisation needs.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub train: Vec<View>,
    pub test: Vec<View>,
    /// Sparse points (metres, the model's frame) and their colours.
    pub points: Vec<[f32; 3]>,
    pub colours: Vec<[u8; 3]>,
    /// Where `colours` came from.
    pub colour_source: PointColours,
    /// Radius of the camera centres around their mean × 1.1, metres (the reference's
    /// `cameras_extent`, which scales the position learning rate and densification).
    pub extent: f32,
}

/// Where the sparse points' colours come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PointColours {
    /// The model's own colours (`points3D` RGB).
    Model,
    /// The model had none (every point (0, 0, 0)): the median of each point's visible
    /// projections into the training photos.
    Photos,
}

/// True when a sparse model carries no colours: it has points and every one is (0, 0, 0),
/// which is what COLMAP writes with `extract_colors=false`.
pub fn uncoloured(colours: &[[u8; 3]]) -> bool {
    !colours.is_empty() && colours.iter().all(|c| *c == [0; 3])
}

/// How a dataset holds its photos in host memory (stage `train`'s report, `memory.host_photos`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct HostPhotos {
    /// Photos held compressed ([`crate::splat::photo`]).
    pub compressed: usize,
    /// Photos held decoded.
    pub decoded: usize,
    /// Host memory they take, bytes.
    pub bytes: u64,
    /// What they would take decoded, bytes (4 a pixel).
    pub decoded_bytes: u64,
}

impl Dataset {
    /// How the photos are held in host memory.
    pub fn host_photos(&self) -> HostPhotos {
        let mut h = HostPhotos {
            compressed: 0,
            decoded: 0,
            bytes: 0,
            decoded_bytes: 0,
        };
        for v in self.all_views() {
            if v.image.is_compressed() {
                h.compressed += 1;
            } else {
                h.decoded += 1;
            }
            h.bytes += v.image.host_bytes() as u64;
            h.decoded_bytes += 4 * u64::from(v.image.width) * u64::from(v.image.height);
        }
        h
    }

    /// Every view, training first.
    pub fn all_views(&self) -> impl Iterator<Item = &View> {
        self.train.iter().chain(&self.test)
    }

    /// The views training steps draw from, each with the exposure it trains: without
    /// `exposure` the training views alone; with it every view, its slot its place in
    /// [`Dataset::all_views`], and the held-out views train only their left halves
    /// (docs/splatting.md "Exposure"; the reference trainer's `train_test_exp`).
    pub fn step_views(&self, exposure: bool) -> Vec<(&View, Option<ExposureSlot>)> {
        if !exposure {
            return self.train.iter().map(|v| (v, None)).collect();
        }
        self.all_views()
            .enumerate()
            .map(|(index, v)| {
                let left_half = index >= self.train.len();
                (v, Some(ExposureSlot { index, left_half }))
            })
            .collect()
    }
}

/// Loads the registered model `model` with photos from `images_dir`. `long_side` (pixels)
/// downscales every photo so its longer side is at most that; `test_every` holds out every
/// n-th photo by name (0 keeps all for training). When the decoded photos would take more
/// than `host_photo_mb` MiB, each is kept compressed as soon as it is loaded
/// ([`crate::splat::photo`]), so they never all stand decoded at once.
pub fn load(
    model: &ColmapModel,
    images_dir: &Path,
    long_side: Option<u32>,
    test_every: usize,
    host_photo_mb: u64,
    progress: &dyn Progress,
) -> Result<Dataset, DatasetError> {
    let images: Vec<&colmap::Image> = model.images.values().collect();
    if images.is_empty() {
        return Err(DatasetError::Invalid(
            "the COLMAP model has no registered images".into(),
        ));
    }
    let pixels: u64 = images
        .iter()
        .filter_map(|img| model.cameras.get(&img.camera_id))
        .map(|c| loaded_pixels(c.width, c.height, long_side))
        .sum();
    let compress = keep_compressed(pixels, host_photo_mb);
    if compress {
        progress.log(&format!(
            "{} photos take {:.0} MiB decoded, more than the {host_photo_mb} MiB allowed (params.train.host_photo_mb): keeping them compressed on the host",
            images.len(),
            (pixels * 4) as f64 / f64::from(1 << 20)
        ));
    }
    let done = std::sync::atomic::AtomicUsize::new(0);
    let views: Vec<Result<View, DatasetError>> = images
        .par_iter()
        .map(|img| {
            if progress.is_cancelled() {
                return Err(DatasetError::Cancelled);
            }
            let v = load_one(model, img, images_dir, long_side).and_then(|mut v| {
                if compress {
                    v.image = v
                        .image
                        .compressed()
                        .map_err(|e| DatasetError::Invalid(format!("{}: {e}", v.name)))?;
                }
                Ok(v)
            });
            let k = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.set(k as f64 / images.len() as f64);
            v
        })
        .collect();
    let views: Vec<View> = views.into_iter().collect::<Result<_, _>>()?;
    let names: Vec<&str> = views.iter().map(|v| v.name.as_str()).collect();
    let split = split_train_test(&names, test_every);
    // The photos move into their side, in the split's order: never two copies of them (at
    // the paper's 857 photos of 1920×1080 a copy is 7.1 GB).
    let centres: Vec<[f32; 3]> = views.iter().map(|v| v.camera.centre()).collect();
    let mut slots: Vec<Option<View>> = views.into_iter().map(Some).collect();
    let mut pick = |idx: &[usize]| -> Vec<View> {
        idx.iter()
            .filter_map(|&i| slots.get_mut(i).and_then(Option::take))
            .collect()
    };
    let (train, test) = (pick(&split.train), pick(&split.test));
    if train.is_empty() {
        return Err(DatasetError::Invalid(format!(
            "no training views: {} photos with every {test_every}th held out",
            centres.len()
        )));
    }
    let n = centres.len() as f32;
    let mean = centres.iter().fold([0.0f32; 3], |a, c| {
        [a[0] + c[0] / n, a[1] + c[1] / n, a[2] + c[2] / n]
    });
    let radius = centres
        .iter()
        .map(|c| {
            ((c[0] - mean[0]).powi(2) + (c[1] - mean[1]).powi(2) + (c[2] - mean[2]).powi(2)).sqrt()
        })
        .fold(0.0f32, f32::max);
    let points: Vec<[f32; 3]> = model
        .points
        .iter()
        .map(|p| p.xyz.as_vec3().to_array())
        .collect();
    let mut colours: Vec<[u8; 3]> = model.points.iter().map(|p| p.rgb).collect();
    let colour_source = if uncoloured(&colours) {
        progress.log(&format!(
            "the sparse model's {} points carry no colour (all black): colouring them from the photos",
            points.len()
        ));
        colours = colours_from_photos(&points, &train);
        PointColours::Photos
    } else {
        PointColours::Model
    };
    let data = Dataset {
        train,
        test,
        points,
        colours,
        colour_source,
        // A single camera has no spread; fall back to 1 m rather than a zero learning rate.
        extent: if radius > 0.0 { radius * 1.1 } else { 1.0 },
    };
    if compress {
        let h = data.host_photos();
        progress.log(&format!(
            "{} photos held compressed in {:.0} MiB ({:.0} % of decoded)",
            h.compressed,
            h.bytes as f64 / f64::from(1 << 20),
            100.0 * h.bytes as f64 / h.decoded_bytes.max(1) as f64
        ));
    }
    Ok(data)
}

/// Pixels of a `width` × `height` photo once downscaled to `long_side` (an upper bound: the
/// downscale rounds each side).
fn loaded_pixels(width: u64, height: u64, long_side: Option<u32>) -> u64 {
    let long = width.max(height).max(1);
    let scale = match long_side {
        Some(l) if u64::from(l) < long => u64::from(l) as f64 / long as f64,
        _ => 1.0,
    };
    ((width as f64 * scale).ceil() * (height as f64 * scale).ceil()) as u64
}

/// Each point's median colour over the training views where it is visible; mid-grey where it
/// is seen in none (grey, not black, keeps the colour off the clamp).
pub fn colours_from_photos(points: &[[f32; 3]], views: &[View]) -> Vec<[u8; 3]> {
    let anchors: Vec<crate::splat::init::Anchor> = points
        .iter()
        .map(|&position| crate::splat::init::Anchor {
            position,
            colour: [128; 3],
            trunk_prob: 0.0,
        })
        .collect();
    crate::splat::init::photometric_colours(&anchors, views, &Default::default())
}

fn load_one(
    model: &ColmapModel,
    img: &colmap::Image,
    images_dir: &Path,
    long_side: Option<u32>,
) -> Result<View, DatasetError> {
    let cam = model.cameras.get(&img.camera_id).ok_or_else(|| {
        DatasetError::Invalid(format!(
            "image {} refers to camera {}, which the model lacks",
            img.name, img.camera_id
        ))
    })?;
    let path = colmap::image_path(images_dir, &img.name)
        .ok_or_else(|| DatasetError::Invalid(format!("image {} has an unsafe path", img.name)))?;
    let decoded = image::open(&path)
        .map_err(|e| DatasetError::Invalid(format!("{}: cannot decode: {e}", path.display())))?
        .to_rgba8();
    let (w, h) = decoded.dimensions();
    let packed = PackedImage::from_rgba8(w, h, decoded.as_raw()).ok_or_else(|| {
        DatasetError::Invalid(format!("{}: inconsistent image buffer", path.display()))
    })?;
    let dims = |v: u64| u32::try_from(v).unwrap_or(u32::MAX);
    load_view(
        &img.name,
        cam.model.name(),
        &cam.params,
        dims(cam.width),
        dims(cam.height),
        img.qvec,
        img.tvec,
        &packed,
        long_side,
    )
    .map_err(|e| DatasetError::Invalid(format!("{}: {e}", img.name)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::camera::Camera;

    #[test]
    fn a_model_without_colours_is_recognised() {
        assert!(uncoloured(&[[0; 3]; 5]));
        assert!(!uncoloured(&[[0, 0, 0], [0, 0, 1]]));
        assert!(!uncoloured(&[]));
    }

    #[test]
    fn uncoloured_points_take_the_colour_of_the_photos_that_see_them() {
        let camera = Camera::look_at([0.0; 3], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], 64, 64, 64.0);
        let view = View {
            name: "v".into(),
            camera,
            image: PackedImage::filled(64, 64, [200, 40, 10, 255]).into(),
        };
        // One point in view, one behind the camera (seen by no photo: mid-grey).
        let c = colours_from_photos(&[[0.1, 0.0, 3.0], [0.0, 0.0, -3.0]], &[view]);
        assert_eq!(c, vec![[200, 40, 10], [128, 128, 128]]);
    }
}
