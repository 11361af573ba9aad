//! Inventory outputs: trees.csv (one row per tree, fixed header) and trees.geojson (a
//! FeatureCollection of Points with the row as properties, in the cloud's own CRS).

use std::path::Path;

use super::inventory::TreeRow;
use crate::io::IoError;

/// The exact header of trees.csv. `n_points`, `rms_mm`, `arc_coverage` and `quality` are
/// the LiDAR fit's; `gs_quality` (last, so readers of the older header keep their columns)
/// is the Gaussian fit's quality flag.
pub const TREES_CSV_HEADER: &str =
    "tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm,n_points,rms_mm,arc_coverage,quality,gs_quality";

/// trees.csv as text: the header, then one line per tree; `dbh_gs_cm` and `gs_quality` are
/// empty when absent. Coordinates with millimetre precision, DBH to 0.01 cm, RMS to 0.01 mm.
pub fn trees_csv(rows: &[TreeRow]) -> String {
    let mut s = String::with_capacity(64 * (rows.len() + 1));
    s.push_str(TREES_CSV_HEADER);
    s.push('\n');
    for r in rows {
        let gs = r.dbh_gs_cm.map(|v| format!("{v:.2}")).unwrap_or_default();
        let gs_quality = r.gs_quality.map(|q| q.as_str()).unwrap_or_default();
        s.push_str(&format!(
            "{},{:.3},{:.3},{:.3},{:.2},{},{},{:.2},{:.3},{},{}\n",
            r.tree_id,
            r.x,
            r.y,
            r.ground_z,
            r.dbh_lidar_cm,
            gs,
            r.n_points,
            r.rms_mm,
            r.arc_coverage,
            csv_field(&r.quality),
            gs_quality
        ));
    }
    s
}

/// Quotes a field holding a comma, quote or line break.
fn csv_field(v: &str) -> String {
    if v.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", v.replace('"', "\"\""))
    } else {
        v.to_string()
    }
}

/// trees.geojson as a JSON value: Point geometries at (x, y, ground_z), every row field as a
/// property (`dbh_gs_cm` and `gs_quality` null when absent).
pub fn trees_geojson(rows: &[TreeRow]) -> serde_json::Value {
    let features: Vec<serde_json::Value> = rows
        .iter()
        .map(|r| {
            serde_json::json!({
                "type": "Feature",
                "geometry": { "type": "Point", "coordinates": [r.x, r.y, r.ground_z] },
                "properties": r,
            })
        })
        .collect();
    serde_json::json!({ "type": "FeatureCollection", "features": features })
}

/// Writes trees.csv to `path`.
pub fn write_trees_csv(path: &Path, rows: &[TreeRow]) -> Result<(), IoError> {
    std::fs::write(path, trees_csv(rows)).map_err(|e| IoError::io(path, e))
}

/// Writes trees.geojson to `path` (pretty-printed).
pub fn write_trees_geojson(path: &Path, rows: &[TreeRow]) -> Result<(), IoError> {
    let text = serde_json::to_string_pretty(&trees_geojson(rows))
        .map_err(|e| IoError::format(path, format!("cannot encode GeoJSON: {e}")))?;
    std::fs::write(path, text).map_err(|e| IoError::io(path, e))
}
