//! COLMAP sparse models (cameras, images, points3D) in text and binary form, project
//! discovery in an unpacked upload, and a check of the registered photos.
//!
//! Poses follow COLMAP: `qvec` (w, x, y, z) and `tvec` (metres, model units) map world to
//! camera coordinates. Pixel coordinates of 2-D points are in pixels with the origin at the
//! top-left corner of the top-left pixel. The readers live in `colmap/text.rs` and
//! `colmap/binary.rs`.

mod binary;
mod text;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Serialize;

use super::{IoError, check_cancel, safe_relative_path};
use crate::progress::{Progress, SubProgress};

/// COLMAP camera models, with their COLMAP ids 0..=10.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum CameraModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    Opencv,
    OpencvFisheye,
    FullOpencv,
    Fov,
    SimpleRadialFisheye,
    RadialFisheye,
    ThinPrismFisheye,
}

/// (model, COLMAP name, number of parameters), indexed by model id.
const MODELS: [(CameraModel, &str, usize); 11] = [
    (CameraModel::SimplePinhole, "SIMPLE_PINHOLE", 3),
    (CameraModel::Pinhole, "PINHOLE", 4),
    (CameraModel::SimpleRadial, "SIMPLE_RADIAL", 4),
    (CameraModel::Radial, "RADIAL", 5),
    (CameraModel::Opencv, "OPENCV", 8),
    (CameraModel::OpencvFisheye, "OPENCV_FISHEYE", 8),
    (CameraModel::FullOpencv, "FULL_OPENCV", 12),
    (CameraModel::Fov, "FOV", 5),
    (CameraModel::SimpleRadialFisheye, "SIMPLE_RADIAL_FISHEYE", 4),
    (CameraModel::RadialFisheye, "RADIAL_FISHEYE", 5),
    (CameraModel::ThinPrismFisheye, "THIN_PRISM_FISHEYE", 12),
];

impl CameraModel {
    /// COLMAP model id (0..=10).
    pub fn model_id(self) -> i32 {
        MODELS.iter().position(|m| m.0 == self).unwrap_or(0) as i32
    }
    /// COLMAP model name, e.g. "PINHOLE".
    pub fn name(self) -> &'static str {
        MODELS[self.model_id() as usize].1
    }
    /// Number of intrinsic parameters (focal lengths and principal point in pixels, then
    /// dimensionless distortion coefficients).
    pub fn num_params(self) -> usize {
        MODELS[self.model_id() as usize].2
    }
    pub fn from_name(name: &str) -> Option<Self> {
        MODELS.iter().find(|m| m.1 == name).map(|m| m.0)
    }
    pub fn from_id(id: i32) -> Option<Self> {
        usize::try_from(id)
            .ok()
            .and_then(|i| MODELS.get(i))
            .map(|m| m.0)
    }
    /// True for the models Sylva can undistort.
    pub fn is_supported(self) -> bool {
        matches!(
            self,
            CameraModel::SimplePinhole
                | CameraModel::Pinhole
                | CameraModel::SimpleRadial
                | CameraModel::Radial
                | CameraModel::Opencv
        )
    }
}

/// Intrinsics of one camera; `width`/`height` in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub id: u32,
    pub model: CameraModel,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

impl Camera {
    /// A camera of `model` with its parameters in COLMAP's order; refused (with the reason, for
    /// the reader's error) when their number is not the model's.
    pub fn new(
        id: u32,
        model: CameraModel,
        width: u64,
        height: u64,
        params: Vec<f64>,
    ) -> Result<Camera, String> {
        if params.len() != model.num_params() {
            return Err(format!(
                "{} takes {} parameters, found {}",
                model.name(),
                model.num_params(),
                params.len()
            ));
        }
        Ok(Camera {
            id,
            model,
            width,
            height,
            params,
        })
    }
}

/// Adds record `id` of a model file's `what` (camera, image), refusing an id the file gave
/// before (the refusal, for the reader's error).
fn insert_new<T>(
    records: &mut BTreeMap<u32, T>,
    what: &str,
    id: u32,
    record: T,
) -> Result<(), String> {
    match records.entry(id) {
        std::collections::btree_map::Entry::Vacant(e) => {
            e.insert(record);
            Ok(())
        }
        std::collections::btree_map::Entry::Occupied(_) => Err(format!("duplicate {what} {id}")),
    }
}

/// One registered photo and its pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub id: u32,
    /// Rotation world→camera as a unit quaternion (w, x, y, z).
    pub qvec: [f64; 4],
    /// Translation world→camera (model units).
    pub tvec: [f64; 3],
    pub camera_id: u32,
    /// File name relative to the images folder (may contain subfolders).
    pub name: String,
    pub points2d: Vec<Point2D>,
}

/// A keypoint in an image (pixels) and the 3-D point it observes, if any (-1 in files).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point2D {
    pub xy: [f64; 2],
    pub point3d_id: Option<u64>,
}

/// A triangulated point: position (model units), colour, mean reprojection error (pixels)
/// and track of (image id, index of the 2-D point in that image).
#[derive(Debug, Clone, PartialEq)]
pub struct Point3D {
    pub id: u64,
    pub xyz: DVec3,
    pub rgb: [u8; 3],
    pub error: f64,
    pub track: Vec<(u32, u32)>,
}

/// A whole sparse model.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, Camera>,
    pub images: BTreeMap<u32, Image>,
    pub points: Vec<Point3D>,
}

impl ColmapModel {
    /// Refuses cameras Sylva cannot undistort, naming each (at most five, then how many more)
    /// and the models it can: the one check the upload's inspection and stage `ingest` share.
    pub fn check_cameras(&self) -> Result<(), String> {
        let unsupported: Vec<String> = self
            .cameras
            .values()
            .filter(|c| !c.model.is_supported())
            .map(|c| format!("camera {} uses {}", c.id, c.model.name()))
            .collect();
        if unsupported.is_empty() {
            return Ok(());
        }
        let mut named = unsupported[..unsupported.len().min(5)].join(", ");
        if unsupported.len() > 5 {
            named.push_str(&format!(" and {} more", unsupported.len() - 5));
        }
        let supported: Vec<&str> = MODELS
            .iter()
            .filter(|m| m.0.is_supported())
            .map(|m| m.1)
            .collect();
        Err(format!(
            "unsupported camera model ({named}); supported: {}",
            supported.join(", ")
        ))
    }
}

/// What a report says of a project's model: its format, camera count and models (sorted,
/// once each), registered images and 3-D points. The upload's inspection gives it as is,
/// stage `ingest` adds what it checked beside it.
pub fn summary(project: &ColmapProject, model: &ColmapModel) -> serde_json::Value {
    let mut models: Vec<&str> = model.cameras.values().map(|c| c.model.name()).collect();
    models.sort_unstable();
    models.dedup();
    serde_json::json!({
        "format": if project.binary { "binary" } else { "text" },
        "cameras": model.cameras.len(),
        "camera_models": models,
        "images_registered": model.images.len(),
        "points3d": model.points.len(),
    })
}

/// Where a COLMAP project lies inside an unpacked upload.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ColmapProject {
    /// Folder with cameras/images/points3D (.bin or .txt).
    pub sparse_dir: PathBuf,
    /// Folder with the photos, when there is one.
    pub images_dir: Option<PathBuf>,
    /// True when the model is binary (cameras.bin exists).
    pub binary: bool,
}

fn has_model(dir: &Path) -> bool {
    dir.join("cameras.bin").is_file() || dir.join("cameras.txt").is_file()
}

/// Finds a project under `root`: the model in `sparse/0`, `sparse` or `root` itself (the first
/// holding cameras.bin or cameras.txt), photos in `root/images`. When `root` holds nothing but
/// one folder (archives often wrap everything in one), that folder is searched instead.
pub fn find_project(root: &Path) -> Result<ColmapProject, IoError> {
    let mut base = root.to_path_buf();
    for _ in 0..2 {
        for sparse in [
            base.join("sparse").join("0"),
            base.join("sparse"),
            base.clone(),
        ] {
            if has_model(&sparse) {
                let images = base.join("images");
                return Ok(ColmapProject {
                    binary: sparse.join("cameras.bin").is_file(),
                    sparse_dir: sparse,
                    images_dir: images.is_dir().then_some(images),
                });
            }
        }
        let entries: Vec<PathBuf> = std::fs::read_dir(&base)
            .map_err(|e| IoError::io(&base, e))?
            .filter_map(Result::ok)
            .filter(|e| {
                let n = e.file_name();
                let n = n.to_string_lossy();
                !n.starts_with('.') && n != "__MACOSX"
            })
            .map(|e| e.path())
            .collect();
        match entries.as_slice() {
            [only] if only.is_dir() => base = only.clone(),
            _ => break,
        }
    }
    Err(IoError::format(
        root,
        "no COLMAP model found (looked for sparse/0, sparse and the folder itself)",
    ))
}

/// Reads a model from `sparse_dir`: binary when cameras.bin exists, else text. All three files
/// are required, every image must reference an existing camera.
pub fn read_model(sparse_dir: &Path, progress: &dyn Progress) -> Result<ColmapModel, IoError> {
    let bin = sparse_dir.join("cameras.bin").is_file();
    let ext = if bin { "bin" } else { "txt" };
    let file = |stem: &str| -> Result<PathBuf, IoError> {
        let p = sparse_dir.join(format!("{stem}.{ext}"));
        if p.is_file() {
            Ok(p)
        } else {
            Err(IoError::format(&p, "required COLMAP file is missing"))
        }
    };
    let (cams, imgs, pts) = (file("cameras")?, file("images")?, file("points3D")?);
    let images_progress = SubProgress::new(progress, 0.0, 0.5);
    let points_progress = SubProgress::new(progress, 0.5, 0.5);
    let model = if bin {
        ColmapModel {
            cameras: binary::read_cameras(&cams)?,
            images: binary::read_images(&imgs, &images_progress)?,
            points: binary::read_points(&pts, &points_progress)?,
        }
    } else {
        ColmapModel {
            cameras: text::read_cameras(&cams)?,
            images: text::read_images(&imgs, &images_progress)?,
            points: text::read_points(&pts, &points_progress)?,
        }
    };
    if let Some(img) = model
        .images
        .values()
        .find(|i| !model.cameras.contains_key(&i.camera_id))
    {
        return Err(IoError::format(
            &imgs,
            format!(
                "image {} references missing camera {}",
                img.id, img.camera_id
            ),
        ));
    }
    progress.set(1.0);
    Ok(model)
}

/// Refuses models that could not be read back: wrong parameter counts, image names that are
/// empty or hold a line break or NUL.
fn check_writable(model: &ColmapModel, dir: &Path) -> Result<(), IoError> {
    for c in model.cameras.values() {
        if c.params.len() != c.model.num_params() {
            let (n, m) = (c.model.num_params(), c.params.len());
            let fault = format!(
                "camera {}: {} takes {n} parameters, has {m}",
                c.id,
                c.model.name()
            );
            return Err(IoError::format(dir, fault));
        }
    }
    if let Some(i) = model
        .images
        .values()
        .find(|i| i.name.is_empty() || i.name.contains(['\n', '\r', '\0']))
    {
        return Err(IoError::format(
            dir,
            format!("image {} has an unwritable name {:?}", i.id, i.name),
        ));
    }
    Ok(())
}

/// Writes cameras.txt, images.txt and points3D.txt into `dir` (created if needed).
pub fn write_text(model: &ColmapModel, dir: &Path) -> Result<(), IoError> {
    check_writable(model, dir)?;
    std::fs::create_dir_all(dir).map_err(|e| IoError::io(dir, e))?;
    text::write(model, dir)
}

/// Writes cameras.bin, images.bin and points3D.bin into `dir` (created if needed).
pub fn write_binary(model: &ColmapModel, dir: &Path) -> Result<(), IoError> {
    check_writable(model, dir)?;
    std::fs::create_dir_all(dir).map_err(|e| IoError::io(dir, e))?;
    binary::write(model, dir)
}

/// Result of [`validate_images`].
#[derive(Debug, Clone, Default, Serialize)]
pub struct ImageCheck {
    pub images_registered: usize,
    /// Registered images present in the images folder (decodable or not).
    pub images_found: usize,
    pub missing: Vec<String>,
    pub undecodable: Vec<ImageFault>,
    pub size_mismatch: Vec<SizeMismatch>,
}

/// A photo that exists but does not decode.
#[derive(Debug, Clone, Serialize)]
pub struct ImageFault {
    pub name: String,
    pub fault: String,
}

/// The file of image `name` inside `images_dir`, or `None` when the name would escape it.
pub fn image_path(images_dir: &Path, name: &str) -> Option<std::path::PathBuf> {
    safe_relative_path(name).map(|rel| images_dir.join(rel))
}

/// A photo whose pixel size differs from its camera's.
#[derive(Debug, Clone, Serialize)]
pub struct SizeMismatch {
    pub name: String,
    /// Camera width, height (pixels).
    pub expected: [u64; 2],
    /// Decoded width, height (pixels).
    pub found: [u32; 2],
}

/// Checks that every registered image exists under `project.images_dir`, decodes fully and
/// has its camera's size. Names escaping the folder (`..`, absolute) are a `Format` error;
/// missing or broken photos are listed in the report.
pub fn validate_images(
    project: &ColmapProject,
    model: &ColmapModel,
    progress: &dyn Progress,
) -> Result<ImageCheck, IoError> {
    let mut check = ImageCheck {
        images_registered: model.images.len(),
        ..Default::default()
    };
    let total = model.images.len().max(1) as f64;
    for (k, img) in model.images.values().enumerate() {
        check_cancel(progress)?;
        progress.set(k as f64 / total);
        let rel = safe_relative_path(&img.name).ok_or_else(|| {
            IoError::format(
                &project.sparse_dir,
                format!("image {} has an unsafe name {:?}", img.id, img.name),
            )
        })?;
        let Some(path) = project.images_dir.as_ref().map(|d| d.join(rel)) else {
            check.missing.push(img.name.clone());
            continue;
        };
        if !path.is_file() {
            check.missing.push(img.name.clone());
            continue;
        }
        check.images_found += 1;
        let decoded = image::ImageReader::open(&path)
            .map_err(|e| IoError::io(&path, e))?
            .with_guessed_format()
            .map_err(|e| IoError::io(&path, e))
            .map(|r| r.decode());
        let pixels = match decoded? {
            Ok(p) => p,
            Err(image::ImageError::IoError(e))
                if !matches!(
                    e.kind(),
                    std::io::ErrorKind::UnexpectedEof | std::io::ErrorKind::InvalidData
                ) =>
            {
                return Err(IoError::io(&path, e));
            }
            Err(e) => {
                check.undecodable.push(ImageFault {
                    name: img.name.clone(),
                    fault: e.to_string(),
                });
                continue;
            }
        };
        let expected = model
            .cameras
            .get(&img.camera_id)
            .map_or([0, 0], |c| [c.width, c.height]);
        let found = [pixels.width(), pixels.height()];
        if expected != found.map(u64::from) {
            check.size_mismatch.push(SizeMismatch {
                name: img.name.clone(),
                expected,
                found,
            });
        }
    }
    progress.set(1.0);
    Ok(check)
}

#[cfg(test)]
mod tests;
