//! Content inspection of a finished upload: is this file what its kind says, and usable?
//!
//! Runs when a client completes an upload, so a broken file is refused with reasons (HTTP 422)
//! before any job is queued on it. A COLMAP or photos archive is extracted here, safely, once;
//! jobs read the extracted folder.

use std::path::Path;

use serde_json::json;

use crate::io::archive::{self, ExtractLimits};
use crate::io::{IoError, colmap, photos, pointcloud, tables};
use crate::progress::Progress;

pub use crate::stage::UploadKind;

/// Why an upload is unusable.
#[derive(Debug, thiserror::Error)]
pub enum InspectError {
    /// The content is not usable; the message names the file and the fault.
    #[error("{0}")]
    Unusable(String),
    #[error(transparent)]
    Io(IoError),
    #[error("cancelled")]
    Cancelled,
}

impl From<IoError> for InspectError {
    fn from(e: IoError) -> Self {
        match e {
            IoError::Format { .. } => InspectError::Unusable(e.to_string()),
            IoError::Cancelled => InspectError::Cancelled,
            other => InspectError::Io(other),
        }
    }
}

/// Inspects `blob` (named `filename` by the client) as an upload of `kind`; for an archive,
/// extracts it into `unpack_dir`. Returns what was found, for the upload's `inspection`.
pub fn inspect_upload(
    kind: UploadKind,
    filename: &str,
    blob: &Path,
    unpack_dir: &Path,
    limits: &ExtractLimits,
    progress: &dyn Progress,
) -> Result<serde_json::Value, InspectError> {
    let named = |e: InspectError| match e {
        // Server paths never reach the client: the blob's path goes, and paths inside the
        // extracted archive become paths relative to the archive.
        InspectError::Unusable(m) => InspectError::Unusable(format!(
            "{filename}: {}",
            m.strip_prefix(&format!("{}: ", blob.display()))
                .unwrap_or(&m)
                .replace(&format!("{}/", unpack_dir.display()), "")
                .replace(&unpack_dir.display().to_string(), "the archive")
        )),
        other => other,
    };
    let result = match kind {
        UploadKind::Lidar => pointcloud::inspect_point_cloud(blob)
            .map_err(InspectError::from)
            .map(|s| {
                let warnings: Vec<String> = units_warning(filename, &s).into_iter().collect();
                json!({ "point_cloud": s, "warnings": warnings })
            }),
        UploadKind::Colmap => inspect_colmap(blob, unpack_dir, limits, progress),
        UploadKind::Photos => inspect_photos(blob, unpack_dir, limits, progress),
        UploadKind::ControlPoints => tables::read_control_points(blob)
            .map_err(InspectError::from)
            .map(|v| json!({ "control_points": v.len() })),
        UploadKind::FieldDbh => tables::read_field_dbh(blob)
            .map_err(InspectError::from)
            .map(|v| json!({ "field_trees": v.len() })),
    };
    result.map_err(named)
}

/// A warning when the cloud's extent, as far as the header (LAS, LAZ) or the first lines
/// (XYZ) tell, is too large for a plot in metres: a cloud in millimetres or centimetres. The
/// limit is the ingest stage's `max_plausible_extent_m` default (5000 m); ingest checks again
/// on every point.
fn units_warning(filename: &str, s: &pointcloud::CloudSummary) -> Option<String> {
    use crate::io::pointcloud::SummaryDetails;
    let limit = crate::pipeline::params::IngestParams::default().max_plausible_extent_m;
    let (lo, hi) = match &s.details {
        SummaryDetails::Las(l) => (l.bounds_min, l.bounds_max),
        SummaryDetails::Xyz(x) => {
            let pts: Vec<[f64; 3]> = x
                .first_lines
                .iter()
                .filter_map(|l| {
                    let v: Vec<f64> = l
                        .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
                        .filter(|t| !t.is_empty())
                        .take(3)
                        .map(str::parse)
                        .collect::<Result<_, _>>()
                        .ok()?;
                    (v.len() == 3).then(|| [v[0], v[1], v[2]])
                })
                .collect();
            if pts.len() < 2 {
                return None;
            }
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            for p in &pts {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            (lo, hi)
        }
        _ => return None,
    };
    let diagonal = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    (diagonal.is_finite() && diagonal > limit).then(|| {
        format!(
            "{filename}: the cloud spans {diagonal:.0} units; a forest plot spans tens of \
             metres, so the file may not be in metres (millimetres or centimetres?). Sylva \
             reads coordinates as metres."
        )
    })
}

/// Extracts an archive upload into `unpack_dir` (emptied first), returning its summary.
fn extract(
    blob: &Path,
    unpack_dir: &Path,
    limits: &ExtractLimits,
    progress: &dyn Progress,
) -> Result<serde_json::Value, InspectError> {
    if unpack_dir.exists() {
        std::fs::remove_dir_all(unpack_dir)
            .map_err(|e| InspectError::Io(IoError::io(unpack_dir, e)))?;
    }
    let summary =
        archive::extract_archive(blob, unpack_dir, limits, progress).map_err(|e| match e {
            archive::ArchiveError::File(IoError::Cancelled) => InspectError::Cancelled,
            archive::ArchiveError::File(e) => InspectError::Io(e),
            other => InspectError::Unusable(format!("archive: {other}")),
        })?;
    Ok(json!(summary))
}

/// A `photos` upload: an archive of at least 3 photos, each with a readable header.
fn inspect_photos(
    blob: &Path,
    unpack_dir: &Path,
    limits: &ExtractLimits,
    progress: &dyn Progress,
) -> Result<serde_json::Value, InspectError> {
    let summary = extract(blob, unpack_dir, limits, progress)?;
    let set = photos::usable_photos(unpack_dir)?;
    Ok(json!({
        "archive": summary,
        "photos": { "photos": set.names.len(), "sizes": photos::sizes_json(&set.check) },
    }))
}

fn inspect_colmap(
    blob: &Path,
    unpack_dir: &Path,
    limits: &ExtractLimits,
    progress: &dyn Progress,
) -> Result<serde_json::Value, InspectError> {
    let summary = extract(blob, unpack_dir, limits, progress)?;
    let project = colmap::find_project(unpack_dir)?;
    let model = colmap::read_model(&project.sparse_dir, progress)?;
    let images_dir = project.images_dir.as_ref().ok_or_else(|| {
        InspectError::Unusable("no images/ folder beside the sparse model".into())
    })?;
    let missing: Vec<&str> = model
        .images
        .values()
        .filter(|im| !colmap::image_path(images_dir, &im.name).is_some_and(|p| p.is_file()))
        .map(|im| im.name.as_str())
        .collect();
    if !missing.is_empty() {
        let shown: Vec<&str> = missing.iter().take(5).copied().collect();
        return Err(InspectError::Unusable(format!(
            "{} registered image(s) missing from images/: {}{}",
            missing.len(),
            shown.join(", "),
            if missing.len() > 5 { ", …" } else { "" }
        )));
    }
    model.check_cameras().map_err(InspectError::Unusable)?;
    Ok(json!({
        "archive": summary,
        "colmap": colmap::summary(&project, &model),
    }))
}
