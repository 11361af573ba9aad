//! What is true of a synthetic plot, written next to the data: truth.json, field_dbh.csv,
//! control_points.csv and labels.bin.
//!
//! All positions are in the LiDAR file's own coordinates (scene frame plus the
//! georeferenced-like offset), metres. `sfm_to_world` maps SfM coordinates to those
//! coordinates: x_lidar = scale · R x_sfm + t, R given as rows.

use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::SynthError;
use super::colmap_export::Similarity;
use super::layout::{Plot, Stone};
use super::rng::{Stream, domain};
use crate::io::IoError;

/// Label classes of labels.bin.
pub const LABEL_NAMES: [&str; 4] = ["ground", "wood", "leaf", "other"];

/// One tree in truth.json.
#[derive(Debug, Serialize)]
pub struct TreeRecord {
    pub id: usize,
    /// Stem base (where the axis meets the ground), LiDAR coordinates.
    pub x: f64,
    pub y: f64,
    pub z: f64,
    /// Tape DBH: girth / pi of the section perpendicular to the axis, 1.3 m along the axis.
    pub dbh_cm: f64,
    pub height_m: f64,
    /// "broadleaf" or "leafless".
    pub kind: &'static str,
    pub species: &'static str,
    /// Unit stem axis (x, y, z).
    pub axis: [f64; 3],
    /// Axis point at breast height (1.3 m along the axis), LiDAR coordinates.
    pub breast_height_point: [f64; 3],
    pub lean_deg: f64,
    /// Semi-axes of the breast-height section (major, minor), metres.
    pub section_semi_axes_m: [f64; 2],
    /// Unit direction of the major semi-axis.
    pub section_major_axis: [f64; 3],
    /// The generator's nominal crown reach, metres.
    pub crown_radius_m: f64,
    pub crown_base_m: f64,
    /// Crown projection: the convex hull of the tree's primitives seen from above, m², and the
    /// diameter of the circle of that area, metres (what an inventory measures as crown).
    pub crown_area_m2: f64,
    pub crown_diameter_m: f64,
}

/// The `labels` entry of truth.json.
#[derive(Debug, Serialize)]
pub struct LabelsRecord {
    pub file: &'static str,
    pub encoding: &'static str,
    pub classes: [&'static str; 4],
    pub counts: [usize; 4],
}

/// A control point pair (SfM frame, LiDAR coordinates).
#[derive(Debug, Clone, Serialize)]
pub struct ControlPair {
    pub name: String,
    pub sfm: [f64; 3],
    pub lidar: [f64; 3],
}

/// The whole truth.json.
#[derive(Debug, Serialize)]
pub struct Truth {
    pub generator: &'static str,
    pub format_version: u32,
    pub preset: &'static str,
    pub seed: u64,
    /// Offset added to scene coordinates to get LiDAR file coordinates, metres.
    pub geo_offset: [f64; 3],
    pub sfm_to_world: Similarity,
    pub world_to_sfm: Similarity,
    pub trees: Vec<TreeRecord>,
    pub stones: Vec<[f64; 3]>,
    pub control_points: Vec<ControlPair>,
    pub test_images: Vec<String>,
    pub labels: LabelsRecord,
    pub plot_radius_m: f64,
    pub plot_center: [f64; 3],
    pub canopy_closure: f64,
    pub lidar: serde_json::Value,
    pub camera: serde_json::Value,
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), SynthError> {
    std::fs::write(path, bytes).map_err(|e| SynthError::Io(IoError::io(path, e)))
}

/// Tree records in LiDAR coordinates.
pub fn tree_records(plot: &Plot, offset: DVec3) -> Vec<TreeRecord> {
    plot.trees
        .iter()
        .map(|t| {
            let base = t.base + offset;
            TreeRecord {
                id: t.id,
                x: base.x,
                y: base.y,
                z: base.z,
                dbh_cm: t.dbh_m * 100.0,
                height_m: t.height_m,
                kind: if t.leafless { "leafless" } else { "broadleaf" },
                species: t.species,
                axis: t.axis.to_array(),
                breast_height_point: (t.axis_point(1.3) + offset).to_array(),
                lean_deg: t.lean_deg,
                section_semi_axes_m: t.semi_axes_m,
                section_major_axis: t.major_axis.to_array(),
                crown_radius_m: t.crown_radius_m,
                crown_base_m: t.crown_base_m,
                crown_area_m2: t.crown_area_m2,
                crown_diameter_m: 2.0 * (t.crown_area_m2 / std::f64::consts::PI).sqrt(),
            }
        })
        .collect()
}

/// Control points on stem bases and stone tops: the SfM side is the true point mapped to the
/// SfM frame plus picking noise (`noise_m`, metres before scaling), the LiDAR side the true
/// point plus half that noise.
pub fn control_points(
    plot: &Plot,
    offset: DVec3,
    world_to_sfm: &Similarity,
    noise_m: f64,
    seed: u64,
) -> Vec<ControlPair> {
    let mut rng = Stream::new(seed, domain::CONTROL, 0);
    let stems = plot
        .trees
        .iter()
        .map(|t| (format!("stem_base_{}", t.id), t.base));
    let stones = plot
        .stones
        .iter()
        .map(|s: &Stone| (format!("stone_top_{}", s.id), s.top));
    stems
        .chain(stones)
        .map(|(name, p)| {
            let mut n = || DVec3::new(rng.normal(), rng.normal(), rng.normal());
            let sfm = world_to_sfm.apply(p + n() * noise_m);
            let lidar = p + offset + n() * (0.5 * noise_m);
            ControlPair {
                name,
                sfm: sfm.to_array(),
                lidar: lidar.to_array(),
            }
        })
        .collect()
}

/// Writes field_dbh.csv (`tree_id,x,y,dbh_cm`).
pub fn write_field_dbh(path: &Path, trees: &[TreeRecord]) -> Result<(), SynthError> {
    let rows = trees.iter().map(|t| {
        vec![
            t.id.to_string(),
            format!("{:.4}", t.x),
            format!("{:.4}", t.y),
            format!("{:.4}", t.dbh_cm),
        ]
    });
    write_csv(path, &["tree_id", "x", "y", "dbh_cm"], rows)
}

/// Writes a CSV table with the `csv` crate (fields quoted where they need it).
fn write_csv(
    path: &Path,
    header: &[&str],
    rows: impl Iterator<Item = Vec<String>>,
) -> Result<(), SynthError> {
    let fail = |e: csv::Error| SynthError::Io(IoError::io(path, std::io::Error::other(e)));
    let mut w = csv::Writer::from_writer(Vec::new());
    w.write_record(header).map_err(fail)?;
    for r in rows {
        w.write_record(&r).map_err(fail)?;
    }
    let bytes = w
        .into_inner()
        .map_err(|e| SynthError::Io(IoError::io(path, std::io::Error::other(e.to_string()))))?;
    write(path, &bytes)
}

/// Writes control_points.csv (`name,sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z`).
pub fn write_control_points(path: &Path, pairs: &[ControlPair]) -> Result<(), SynthError> {
    let rows = pairs.iter().map(|p| {
        let [a, b, c] = p.sfm;
        let [x, y, z] = p.lidar;
        vec![
            p.name.clone(),
            a.to_string(),
            b.to_string(),
            c.to_string(),
            format!("{x:.4}"),
            format!("{y:.4}"),
            format!("{z:.4}"),
        ]
    });
    write_csv(
        path,
        &[
            "name", "sfm_x", "sfm_y", "sfm_z", "lidar_x", "lidar_y", "lidar_z",
        ],
        rows,
    )
}

/// Writes labels.bin: one byte per LiDAR point in file order.
pub fn write_labels(path: &Path, labels: &[u8]) -> Result<(), SynthError> {
    write(path, labels)
}

/// Writes truth.json (pretty-printed).
pub fn write_truth(path: &Path, truth: &Truth) -> Result<(), SynthError> {
    let mut text = serde_json::to_string_pretty(truth).map_err(SynthError::Json)?;
    text.push('\n');
    write(path, text.as_bytes())
}

/// Every 8th image sorted by name, starting with the first (docs/method.md, Evaluation).
pub fn test_images(names: &[String]) -> Vec<String> {
    let mut sorted = names.to_vec();
    sorted.sort();
    sorted.into_iter().step_by(8).collect()
}
