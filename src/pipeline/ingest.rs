//! Stage `ingest`: read every input once, check it is usable, and keep a normalised copy.
//!
//! The LiDAR file (LAS/LAZ/PLY/XYZ) becomes `ingest/cloud.ply` in local coordinates with its
//! offset in the header, the COLMAP model is checked (supported camera models, every
//! registered image present and decodable at its camera's size) and copied as text to
//! `ingest/sparse/`; a job that gave photos instead has them listed and their headers read
//! (at least 3, every one readable), and stage `sfm` makes the model. Optional control points and field DBH tables are parsed. The cloud's
//! CRS (the job's `crs`, else the file's declaration) is settled here once and written as
//! `ingest/crs.json`, which every later stage that writes coordinates copies beside them. The
//! photos' EXIF GPS positions, when they carry any, become `ingest/gps.json` (stage `register`
//! starts from them when the CRS is known). Anything
//! unusable fails the stage with a message naming the file and the fault.

use std::collections::BTreeMap;

use glam::DVec3;
use rayon::prelude::*;
use serde_json::json;

use super::{StageContext, StageError};
use crate::io::colmap;
use crate::io::crs::CrsRecord;
use crate::io::gps::{self, GpsFix};
use crate::io::pointcloud::PointCloud;
use crate::io::{photos, ply, pointcloud, tables};
use crate::progress::SubProgress;

/// How many names of missing or broken images an error message lists before "and N more".
const LISTED_NAMES: usize = 5;

fn list(names: &[String]) -> String {
    let mut s = names
        .iter()
        .take(LISTED_NAMES)
        .cloned()
        .collect::<Vec<_>>()
        .join(", ");
    if names.len() > LISTED_NAMES {
        s.push_str(&format!(" and {} more", names.len() - LISTED_NAMES));
    }
    s
}

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let mut warnings: Vec<String> = Vec::new();
    // 1. The point cloud (0 .. 0.5 of the stage).
    let (cloud, crs, (lo, hi)) = ingest_cloud(ctx, &mut warnings)?;
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }
    ctx.progress.set(0.5);

    // 2. The COLMAP project, or the photos stage `sfm` reconstructs (0.5 .. 0.95).
    let (colmap_report, photos_report) = match (&ctx.inputs.photos, &ctx.inputs.colmap) {
        (Some(photos), _) => (
            serde_json::Value::Null,
            ingest_photos(ctx, photos, &mut warnings)?,
        ),
        (None, Some(colmap)) => (
            ingest_colmap(ctx, colmap, &mut warnings)?,
            serde_json::Value::Null,
        ),
        (None, None) => return Err(StageError::Input(super::NO_PHOTOS.into())),
    };

    // 3. Optional tables.
    let control_points = match &ctx.inputs.control_points {
        Some(path) => Some(tables::read_control_points(path)?.len()),
        None => None,
    };
    let field_trees = match &ctx.inputs.field_dbh {
        Some(path) => Some(tables::read_field_dbh(path)?.len()),
        None => None,
    };
    for w in &warnings {
        ctx.progress.log(&format!("warning: {w}"));
    }
    ctx.progress.set(1.0);

    let extent = hi - lo;
    Ok(json!({
        "lidar": {
            "format": cloud.format,
            "points": cloud.len(),
            "offset": [cloud.offset.x, cloud.offset.y, cloud.offset.z],
            "bounds_min": [lo.x, lo.y, lo.z],
            "bounds_max": [hi.x, hi.y, hi.z],
            "extent_m": [extent.x, extent.y, extent.z],
            "has_color": cloud.colors.is_some(),
            "has_intensity": cloud.intensity.is_some(),
            "crs": crs.label,
            "crs_source": crs.source,
        },
        "colmap": colmap_report,
        "photos": photos_report,
        "control_points": control_points,
        "field_trees": field_trees,
        "warnings": warnings,
    }))
}

/// Reads the LiDAR file, warns when its extent does not look like metres, settles its CRS
/// (the job's `crs` over the file's declaration, [`crate::io::crs::resolve`]) and writes
/// `cloud.ply` and `crs.json`. Returns the cloud, its CRS and its bounds (file coordinates,
/// metres).
fn ingest_cloud(
    ctx: &StageContext<'_>,
    warnings: &mut Vec<String>,
) -> Result<(PointCloud, CrsRecord, (DVec3, DVec3)), StageError> {
    let p = &ctx.params.ingest;
    let lidar_name = ctx
        .inputs
        .lidar
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "lidar".into());
    ctx.progress
        .log(&format!("reading point cloud {lidar_name}"));
    let cloud =
        pointcloud::read_point_cloud(&ctx.inputs.lidar, &SubProgress::new(ctx.progress, 0.0, 0.4))?;
    if cloud.is_empty() {
        return Err(StageError::Input(format!(
            "{lidar_name}: the point cloud has no points"
        )));
    }
    let (lo, hi) = cloud
        .bounds()
        .ok_or_else(|| StageError::Input(format!("{lidar_name}: no finite bounds")))?;
    let extent = hi - lo;
    let diagonal = extent.length();
    if diagonal > p.max_plausible_extent_m {
        warnings.push(format!(
            "{lidar_name}: the cloud spans {diagonal:.0} units; a forest plot spans tens of \
             metres, so the file may not be in metres (millimetres or centimetres?)"
        ));
    }
    if diagonal < 0.5 {
        warnings.push(format!(
            "{lidar_name}: the cloud spans only {diagonal:.3} units; is it in metres?"
        ));
    }
    ctx.progress.log(&format!(
        "{} points, extent {:.1} × {:.1} × {:.1} m",
        cloud.len(),
        extent.x,
        extent.y,
        extent.z
    ));
    let declared = pointcloud::declared_crs(&ctx.inputs.lidar)?;
    let crs = crate::io::crs::resolve(ctx.params.crs.as_deref(), declared)
        .map_err(|e| StageError::Input(format!("{lidar_name}: {e}")))?;
    match &crs.label {
        Some(label) => ctx.progress.log(&format!("CRS {label}")),
        None => ctx.progress.log("CRS unknown"),
    }
    for note in &crs.notes {
        warnings.push(format!("{lidar_name}: {note}"));
    }
    crate::forest::write_crs(ctx.out_dir, &crs)?;
    let cloud_path = ctx.out_dir.join(super::INGEST_CLOUD);
    ply::write_ply(&cloud_path, &cloud, &[])?;
    Ok((cloud, crs, (lo, hi)))
}

/// Reads the COLMAP project, refuses what later stages cannot use (no registered image, an
/// unsupported camera, with `decode_images` a missing, broken or mis-sized photo), reads the
/// photos' GPS positions into `gps.json` and copies the model as text to `sparse/`. Returns
/// the report's `colmap`.
fn ingest_colmap(
    ctx: &StageContext<'_>,
    colmap_dir: &std::path::Path,
    warnings: &mut Vec<String>,
) -> Result<serde_json::Value, StageError> {
    let project = colmap::find_project(colmap_dir)?;
    let model = colmap::read_model(
        &project.sparse_dir,
        &SubProgress::new(ctx.progress, 0.5, 0.1),
    )?;
    if model.images.is_empty() {
        return Err(StageError::Input(
            "COLMAP model: no registered images".into(),
        ));
    }
    model
        .check_cameras()
        .map_err(|e| StageError::Input(format!("COLMAP cameras: {e}")))?;
    let Some(images_dir) = project.images_dir.as_ref() else {
        return Err(StageError::Input(
            "COLMAP project: no images/ folder beside the sparse model".into(),
        ));
    };
    let check = if ctx.params.ingest.decode_images {
        let check =
            colmap::validate_images(&project, &model, &SubProgress::new(ctx.progress, 0.6, 0.35))?;
        refuse_unusable_photos(&check)?;
        Some(check)
    } else {
        None
    };
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }
    let names: Vec<String> = model.images.values().map(|im| im.name.clone()).collect();
    let gps = read_gps(images_dir, &names, warnings);
    write_gps(ctx, &gps)?;
    let sparse_out = ctx.out_dir.join("sparse");
    std::fs::create_dir_all(&sparse_out).map_err(|e| crate::io::IoError::io(&sparse_out, e))?;
    colmap::write_text(&model, &sparse_out)?;
    if model.points.len() < 100 {
        warnings.push(format!(
            "COLMAP model has only {} 3-D points; registration needs more",
            model.points.len()
        ));
    }
    let mut report = colmap::summary(&project, &model);
    report["images_checked"] = json!(check.as_ref().map(|c| c.images_found));
    report["images_with_gps"] = json!(gps.len());
    Ok(report)
}

/// Writes `gps.json` when any photo has a position.
fn write_gps(ctx: &StageContext<'_>, gps: &BTreeMap<String, GpsFix>) -> Result<(), StageError> {
    if !gps.is_empty() {
        let path = ctx.out_dir.join(GPS_FILE);
        let text = serde_json::to_vec_pretty(gps).map_err(|e| StageError::Input(e.to_string()))?;
        std::fs::write(&path, text).map_err(|e| crate::io::IoError::io(&path, e))?;
    }
    Ok(())
}

/// Finds the photos of a job that gave photos instead of a COLMAP project, refuses a set
/// stage `sfm` cannot use (fewer than 3 photos, a photo whose header cannot be read), and
/// reads their GPS positions into `gps.json`. Returns the report's `photos`.
fn ingest_photos(
    ctx: &StageContext<'_>,
    root: &std::path::Path,
    warnings: &mut Vec<String>,
) -> Result<serde_json::Value, StageError> {
    let set = photos::usable_photos(root)?;
    let (dir, names) = (&set.dir, &set.names);
    ctx.progress.log(&format!("{} photos", names.len()));
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }
    let gps = read_gps(dir, names, warnings);
    write_gps(ctx, &gps)?;
    let sizes = set.check.size_counts().len();
    if sizes > 1 {
        warnings.push(format!(
            "photos: {sizes} different sizes; each size gets its own camera in stage sfm"
        ));
    }
    Ok(json!({
        "photos": names.len(),
        "sizes": photos::sizes_json(&set.check),
        "images_with_gps": gps.len(),
    }))
}

/// Refuses photos the check found missing, undecodable or not at their camera's size,
/// naming the first few of them.
fn refuse_unusable_photos(check: &colmap::ImageCheck) -> Result<(), StageError> {
    if !check.missing.is_empty() {
        return Err(StageError::Input(format!(
            "COLMAP images: {} registered image(s) missing from images/: {}",
            check.missing.len(),
            list(&check.missing)
        )));
    }
    let broken: Vec<String> = check
        .undecodable
        .iter()
        .map(|u| format!("{} ({})", u.name, u.fault))
        .chain(check.size_mismatch.iter().map(|m| {
            format!(
                "{} is {}×{} px but its camera says {}×{}",
                m.name, m.found[0], m.found[1], m.expected[0], m.expected[1]
            )
        }))
        .collect();
    if !broken.is_empty() {
        return Err(StageError::Input(format!(
            "COLMAP images: {} image(s) unusable: {}",
            broken.len(),
            list(&broken)
        )));
    }
    Ok(())
}

/// Stage `ingest`'s record of the photos' GPS positions (EXIF): image name → WGS84 fix.
/// Written only when at least one registered photo has one; stage `register` starts from it.
pub const GPS_FILE: &str = "gps.json";

/// The EXIF GPS position of every photo in `names` that has one, by name. A photo whose
/// EXIF is malformed adds a warning and no position.
fn read_gps(
    images_dir: &std::path::Path,
    names: &[String],
    warnings: &mut Vec<String>,
) -> BTreeMap<String, GpsFix> {
    let read: Vec<(String, Result<Option<GpsFix>, String>)> = names
        .par_iter()
        .filter_map(|name| {
            let path = colmap::image_path(images_dir, name)?;
            Some((name.clone(), gps::read_fix(&path)))
        })
        .collect();
    let mut bad = Vec::new();
    let mut out = BTreeMap::new();
    for (name, r) in read {
        match r {
            Ok(Some(fix)) => {
                out.insert(name, fix);
            }
            Ok(None) => {}
            Err(e) => bad.push(format!("{name} ({e})")),
        }
    }
    if !bad.is_empty() {
        warnings.push(format!(
            "{} photo(s) carry unreadable GPS tags and are used without a position: {}",
            bad.len(),
            list(&bad)
        ));
    }
    out
}
