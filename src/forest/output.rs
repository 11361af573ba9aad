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
/// Written with the `csv` crate, which quotes a field only where it must (a comma, quote or
/// line break in it), so `io::tables` and any CSV reader read it back.
pub fn trees_csv(rows: &[TreeRow]) -> String {
    let mut w = csv::WriterBuilder::new().from_writer(Vec::with_capacity(64 * (rows.len() + 1)));
    // Writing to a Vec cannot fail but for a record of the wrong length, which the fixed
    // header and the fixed fields below rule out.
    let _ = w.write_record(TREES_CSV_HEADER.split(','));
    for r in rows {
        let gs = r.dbh_gs_cm.map(|v| format!("{v:.2}")).unwrap_or_default();
        let gs_quality = r.gs_quality.map(|q| q.as_str()).unwrap_or_default();
        let _ = w.write_record([
            r.tree_id.to_string(),
            format!("{:.3}", r.x),
            format!("{:.3}", r.y),
            format!("{:.3}", r.ground_z),
            format!("{:.2}", r.dbh_lidar_cm),
            gs,
            r.n_points.to_string(),
            format!("{:.2}", r.rms_mm),
            format!("{:.3}", r.arc_coverage),
            r.quality.to_string(),
            gs_quality.to_string(),
        ]);
    }
    let bytes = w.into_inner().unwrap_or_default();
    String::from_utf8(bytes).unwrap_or_default()
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
