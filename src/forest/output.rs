//! Inventory outputs: trees.csv (one row per tree, fixed header), trees.geojson (RFC 7946: a
//! FeatureCollection of Points in WGS84 longitude/latitude, with the row as properties), and
//! the `crs.json` sidecar that says which CRS the rows' x, y are in.

use std::path::Path;

use super::inventory::TreeRow;
use crate::io::IoError;
use crate::io::crs::{CRS_FILE, CrsError, CrsRecord};

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

/// trees.geojson as a JSON value, as RFC 7946 asks: with a known CRS, Point geometries at the
/// stems' WGS84 longitude and latitude in degrees (§4; no altitude, since `ground_z` is in the
/// cloud's own vertical datum, not above the ellipsoid), rounded to 1e-8° (about a millimetre);
/// every row field as a property (`x`, `y`, `ground_z` in the native CRS; `dbh_gs_cm` and
/// `gs_quality` null when absent). With no known CRS the geometries are null (§3.2 allows it)
/// rather than native coordinates posing as degrees. Either way the foreign member
/// `sylva_crs` carries the [`CrsRecord`], so a reader sees which CRS x, y are in, or why none
/// is known.
pub fn trees_geojson(rows: &[TreeRow], crs: &CrsRecord) -> Result<serde_json::Value, CrsError> {
    let mut lonlat: Vec<(f64, f64)> = rows.iter().map(|r| (r.x, r.y)).collect();
    let placed = match &crs.crs {
        Some(c) => {
            c.to_wgs84(&mut lonlat)?;
            true
        }
        None => false,
    };
    let round = |v: f64| (v * 1e8).round() / 1e8;
    let features: Vec<serde_json::Value> = rows
        .iter()
        .zip(&lonlat)
        .map(|(r, &(lon, lat))| {
            let geometry = if placed {
                serde_json::json!({ "type": "Point", "coordinates": [round(lon), round(lat)] })
            } else {
                serde_json::Value::Null
            };
            serde_json::json!({ "type": "Feature", "geometry": geometry, "properties": r })
        })
        .collect();
    Ok(serde_json::json!({
        "type": "FeatureCollection",
        "sylva_crs": crs,
        "features": features,
    }))
}

/// Writes trees.csv to `path`.
pub fn write_trees_csv(path: &Path, rows: &[TreeRow]) -> Result<(), IoError> {
    std::fs::write(path, trees_csv(rows)).map_err(|e| IoError::io(path, e))
}

/// Writes trees.geojson to `path` (pretty-printed).
pub fn write_trees_geojson(path: &Path, rows: &[TreeRow], crs: &CrsRecord) -> Result<(), IoError> {
    let value = trees_geojson(rows, crs).map_err(|e| IoError::format(path, e.to_string()))?;
    let text = serde_json::to_string_pretty(&value)
        .map_err(|e| IoError::format(path, format!("cannot encode GeoJSON: {e}")))?;
    std::fs::write(path, text).map_err(|e| IoError::io(path, e))
}

/// Writes the CRS sidecar `crs.json` into `dir` (pretty-printed [`CrsRecord`]).
pub fn write_crs(dir: &Path, crs: &CrsRecord) -> Result<(), IoError> {
    let path = dir.join(CRS_FILE);
    let text = serde_json::to_string_pretty(crs)
        .map_err(|e| IoError::format(&path, format!("cannot encode the CRS: {e}")))?;
    std::fs::write(&path, text).map_err(|e| IoError::io(&path, e))
}

/// Reads the CRS sidecar of `dir`; a folder written before sidecars existed has none and
/// reads as an unknown CRS.
pub fn read_crs(dir: &Path) -> Result<CrsRecord, IoError> {
    let path = dir.join(CRS_FILE);
    match std::fs::read(&path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map_err(|e| IoError::format(&path, format!("not a CRS record: {e}"))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(CrsRecord::unknown(
            "this output predates CRS records, so its CRS is unknown",
        )),
        Err(e) => Err(IoError::io(&path, e)),
    }
}
