//! Inventory outputs: trees.csv (one row per tree, fixed header), trees.geojson (RFC 7946: a
//! FeatureCollection of Points in WGS84 longitude/latitude, with the row as properties), and
//! the `crs.json` sidecar that says which CRS the rows' x, y are in.

use std::path::Path;

use super::inventory::TreeRow;
use crate::io::IoError;
use crate::io::crs::{CRS_FILE, CrsError, CrsRecord};

/// The exact header of trees.csv. `n_points`, `rms_mm`, `arc_coverage` and `quality` are
/// the LiDAR fit's; `gs_quality` is the Gaussian fit's quality flag; then the tree's size
/// (`forest::crowns`) and its allometry (`forest::allometry`, from the LiDAR DBH). Columns
/// are only ever added at the end, so readers of an older header keep theirs.
pub const TREES_CSV_HEADER: &str = "tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm,n_points,rms_mm,\
arc_coverage,quality,gs_quality,height_m,crown_base_m,crown_area_m2,crown_diameter_m,\
basal_area_m2,volume_m3,agb_kg,carbon_kg,height_quality,crown_gap_m";

/// trees.csv as text: the header, then one line per tree; a field without a value (no
/// Gaussian DBH, no height) is empty. Coordinates and heights with millimetre precision, DBH
/// to 0.01 cm, RMS to 0.01 mm, areas to 0.01 m² (basal area 1e-5 m²), volume to 1e-4 m³,
/// biomass and carbon to 0.1 kg.
/// Written with the `csv` crate, which quotes a field only where it must (a comma, quote or
/// line break in it), so `io::tables` and any CSV reader read it back.
pub fn trees_csv(rows: &[TreeRow]) -> String {
    let mut w = csv::WriterBuilder::new().from_writer(Vec::with_capacity(64 * (rows.len() + 1)));
    // Writing to a Vec cannot fail but for a record of the wrong length, which the fixed
    // header and the fixed fields below rule out.
    let _ = w.write_record(TREES_CSV_HEADER.split(','));
    for r in rows {
        let opt =
            |v: Option<f64>, digits: usize| v.map(|v| format!("{v:.digits$}")).unwrap_or_default();
        let gs_quality = r.gs_quality.map(|q| q.as_str()).unwrap_or_default();
        let _ = w.write_record([
            r.tree_id.to_string(),
            format!("{:.3}", r.x),
            format!("{:.3}", r.y),
            format!("{:.3}", r.ground_z),
            format!("{:.2}", r.dbh_lidar_cm),
            opt(r.dbh_gs_cm, 2),
            r.n_points.to_string(),
            format!("{:.2}", r.rms_mm),
            format!("{:.3}", r.arc_coverage),
            r.quality.to_string(),
            gs_quality.to_string(),
            opt(r.height_m, 3),
            opt(r.crown_base_m, 3),
            opt(r.crown_area_m2, 2),
            opt(r.crown_diameter_m, 3),
            opt(r.basal_area_m2, 5),
            opt(r.volume_m3, 4),
            opt(r.agb_kg, 1),
            opt(r.carbon_kg, 1),
            r.height_quality
                .map(|q| q.as_str().to_string())
                .unwrap_or_default(),
            opt(r.crown_gap_m, 2),
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

/// Writes `value` to `path` as pretty-printed JSON; `what` names it in an error.
fn write_json<T: serde::Serialize>(path: &Path, value: &T, what: &str) -> Result<(), IoError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| IoError::format(path, format!("cannot encode {what}: {e}")))?;
    std::fs::write(path, text).map_err(|e| IoError::io(path, e))
}

/// Reads JSON from `path`; `None` when there is no such file; `what` names it in an error.
fn read_json<T: serde::de::DeserializeOwned>(
    path: &Path,
    what: &str,
) -> Result<Option<T>, IoError> {
    match std::fs::read(path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| IoError::format(path, format!("not {what}: {e}"))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(IoError::io(path, e)),
    }
}

/// Writes trees.geojson to `path` (pretty-printed).
pub fn write_trees_geojson(path: &Path, rows: &[TreeRow], crs: &CrsRecord) -> Result<(), IoError> {
    let value = trees_geojson(rows, crs).map_err(|e| IoError::format(path, e.to_string()))?;
    write_json(path, &value, "GeoJSON")
}

/// Writes the CRS sidecar `crs.json` into `dir` (pretty-printed [`CrsRecord`]).
pub fn write_crs(dir: &Path, crs: &CrsRecord) -> Result<(), IoError> {
    write_json(&dir.join(CRS_FILE), crs, "the CRS")
}

/// Reads the CRS sidecar of `dir`; a folder written before sidecars existed has none and
/// reads as an unknown CRS.
pub fn read_crs(dir: &Path) -> Result<CrsRecord, IoError> {
    Ok(
        read_json(&dir.join(CRS_FILE), "a CRS record")?.unwrap_or_else(|| {
            CrsRecord::unknown("this output predates CRS records, so its CRS is unknown")
        }),
    )
}

/// The file name of the plot summary every inventory folder holds.
pub const PLOT_FILE: &str = "plot.json";

/// plot.json: the stand figures and the footprint they were measured on (file coordinates,
/// the hull's vertices, closed), so that a later stage can sum the same plot again.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlotFile {
    #[serde(flatten)]
    pub summary: super::summary::PlotSummary,
    pub footprint: Vec<[f64; 2]>,
}

impl PlotFile {
    /// The record of `summary` on `footprint`.
    pub fn new(summary: super::summary::PlotSummary, footprint: &geo::Polygon<f64>) -> Self {
        Self {
            summary,
            footprint: footprint
                .exterior()
                .points()
                .map(|p| [p.x(), p.y()])
                .collect(),
        }
    }

    /// The footprint as a polygon.
    pub fn footprint(&self) -> geo::Polygon<f64> {
        let ring: geo::LineString<f64> = self.footprint.iter().map(|v| (v[0], v[1])).collect();
        geo::Polygon::new(ring, Vec::new())
    }

    /// Writes plot.json into `dir`.
    pub fn write(&self, dir: &Path) -> Result<(), IoError> {
        write_json(&dir.join(PLOT_FILE), self, "the plot")
    }

    /// Reads plot.json from `dir`; `None` where a stage wrote none (one that predates plot
    /// summaries).
    pub fn read(dir: &Path) -> Result<Option<Self>, IoError> {
        read_json(&dir.join(PLOT_FILE), "a plot summary")
    }
}

/// trees.gpkg: the stems as points (layer `trees`, every trees.csv column) and the crowns as
/// polygons (layer `crowns`: the convex hull of each tree's points, with its tree id, area
/// and diameter), in the cloud's own CRS. `crowns` are in the local frame of `offset` (file
/// coordinates = local + offset), one per row; a tree whose hull has no area has no crown
/// feature.
pub fn write_trees_gpkg(
    path: &Path,
    rows: &[TreeRow],
    crowns: &[super::crowns::TreeCrown],
    offset: glam::DVec3,
    crs: &CrsRecord,
) -> Result<(), IoError> {
    use crate::io::gpkg::{ColumnType, Layer, Value, write_gpkg};
    let columns: Vec<(String, ColumnType)> = TREES_CSV_HEADER
        .split(',')
        .map(|name| {
            let t = match name {
                "tree_id" | "n_points" => ColumnType::Integer,
                "quality" | "gs_quality" | "height_quality" => ColumnType::Text,
                _ => ColumnType::Real,
            };
            (name.to_string(), t)
        })
        .collect();
    let features = rows
        .iter()
        .map(|r| {
            let json = serde_json::to_value(r).unwrap_or_default();
            let values = columns
                .iter()
                .map(|(name, t)| match (&json[name.as_str()], t) {
                    (serde_json::Value::Null, _) => Value::Null,
                    (v, ColumnType::Integer) => v.as_i64().map_or(Value::Null, Value::Integer),
                    (v, ColumnType::Real) => v.as_f64().map_or(Value::Null, Value::Real),
                    (v, ColumnType::Text) => {
                        Value::Text(v.as_str().map_or_else(|| v.to_string(), str::to_string))
                    }
                })
                .collect();
            (geo::Geometry::Point(geo::Point::new(r.x, r.y)), values)
        })
        .collect();
    let trees = Layer {
        name: "trees".into(),
        geometry_type: "POINT",
        columns,
        features,
    };
    let crown_features = rows
        .iter()
        .zip(crowns)
        .filter(|(_, c)| c.hull.len() >= 3)
        .map(|(r, c)| {
            let ring: geo::LineString<f64> = c
                .hull
                .iter()
                .map(|v| (f64::from(v[0]) + offset.x, f64::from(v[1]) + offset.y))
                .collect();
            let polygon = geo::Geometry::Polygon(geo::Polygon::new(ring, Vec::new()));
            let values = vec![
                Value::Integer(i64::from(r.tree_id)),
                Value::Real(c.crown_area_m2),
                Value::Real(c.crown_diameter_m),
                r.height_m.map_or(Value::Null, Value::Real),
            ];
            (polygon, values)
        })
        .collect();
    let crown_layer = Layer {
        name: "crowns".into(),
        geometry_type: "POLYGON",
        columns: vec![
            ("tree_id".into(), ColumnType::Integer),
            ("crown_area_m2".into(), ColumnType::Real),
            ("crown_diameter_m".into(), ColumnType::Real),
            ("height_m".into(), ColumnType::Real),
        ],
        features: crown_features,
    };
    write_gpkg(path, crs, &[trees, crown_layer])
}
