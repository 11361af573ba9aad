//! GeoPackage output (OGC 12-128r18, GeoPackage 1.3): one SQLite file with feature tables that
//! GIS tools (QGIS, GDAL/OGR, ArcGIS) open directly, in the data's own CRS.
//!
//! The file is written with the SQLite Sylva already links (sqlx's bundled SQLite) and the
//! geometries as GeoPackage binary blobs: the `GP` header (version 0, little-endian, with the
//! geometry's envelope) then standard WKB from the `wkb` crate. A layer is a list of features:
//! a geometry (points or polygons, x and y in the CRS) and attribute columns.

use std::path::Path;

use geo::{BoundingRect, Geometry};
use sqlx::{ConnectOptions, Connection};

use super::IoError;
use super::crs::CrsRecord;

/// An attribute value of a feature.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Integer(i64),
    Real(f64),
    Text(String),
    Null,
}

/// The SQLite type of an attribute column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColumnType {
    Integer,
    Real,
    Text,
}

impl ColumnType {
    fn sql(self) -> &'static str {
        match self {
            ColumnType::Integer => "INTEGER",
            ColumnType::Real => "REAL",
            ColumnType::Text => "TEXT",
        }
    }
}

/// One feature table.
#[derive(Debug, Clone)]
pub struct Layer {
    /// Table name (letters, digits and underscores).
    pub name: String,
    /// `POINT` or `POLYGON` (the GeoPackage geometry type name).
    pub geometry_type: &'static str,
    /// Attribute columns (names as table names).
    pub columns: Vec<(String, ColumnType)>,
    /// Geometry and attribute values (one per column) of each feature.
    pub features: Vec<(Geometry<f64>, Vec<Value>)>,
}

/// The srs_id, organisation, code and WKT definition a GeoPackage records for `crs`: its EPSG
/// code when it has one, else a private id; an unknown CRS is GeoPackage's "undefined
/// Cartesian" -1.
fn srs(crs: &CrsRecord) -> (i64, &'static str, i64, String, String) {
    match &crs.crs {
        Some(c) => {
            let definition = if c.definition.contains('[') {
                c.definition.clone()
            } else {
                "undefined".to_string()
            };
            match c.epsg {
                Some(code) => (
                    i64::from(code),
                    "EPSG",
                    i64::from(code),
                    definition,
                    c.label(),
                ),
                None => (100_000, "NONE", 100_000, definition, c.label()),
            }
        }
        None => (
            -1,
            "NONE",
            -1,
            "undefined".into(),
            "undefined Cartesian".into(),
        ),
    }
}

fn check_name(name: &str) -> Result<(), String> {
    let ok = !name.is_empty()
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !name.starts_with(|c: char| c.is_ascii_digit());
    if ok {
        Ok(())
    } else {
        Err(format!("{name:?} is not a valid table or column name"))
    }
}

/// GeoPackage binary: header (magic, version 0, flags: little-endian with an [minx, maxx,
/// miny, maxy] envelope), srs_id, envelope, then little-endian WKB.
fn geometry_blob(g: &Geometry<f64>, srs_id: i64) -> Result<Vec<u8>, String> {
    let mut out = vec![b'G', b'P', 0, 0b0000_0011];
    let srs = i32::try_from(srs_id).map_err(|_| format!("srs_id {srs_id} out of range"))?;
    out.extend_from_slice(&srs.to_le_bytes());
    let rect = g
        .bounding_rect()
        .ok_or_else(|| "an empty geometry has no envelope".to_string())?;
    for v in [rect.min().x, rect.max().x, rect.min().y, rect.max().y] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let options = wkb::writer::WriteOptions {
        endianness: wkb::Endianness::LittleEndian,
    };
    wkb::writer::write_geometry(&mut out, g, &options).map_err(|e| e.to_string())?;
    Ok(out)
}

/// Writes `layers` into a new GeoPackage at `path` (replacing a file there), all in `crs`.
pub fn write_gpkg(path: &Path, crs: &CrsRecord, layers: &[Layer]) -> Result<(), IoError> {
    let fail = |why: String| IoError::format(path, why);
    for l in layers {
        check_name(&l.name).map_err(fail)?;
        for (c, _) in &l.columns {
            check_name(c).map_err(fail)?;
        }
        if l.features.iter().any(|(_, v)| v.len() != l.columns.len()) {
            return Err(fail(format!(
                "layer {}: a feature's values do not match its columns",
                l.name
            )));
        }
    }
    match std::fs::remove_file(path) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(IoError::io(path, e)),
    }
    let write = write_async(path, crs, layers);
    let result = match tokio::runtime::Handle::try_current() {
        // A blocking thread of a runtime (stages run there) can wait on it.
        Ok(handle) => tokio::task::block_in_place(|| handle.block_on(write)),
        Err(_) => tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .map_err(|e| IoError::io(path, e))?
            .block_on(write),
    };
    result.map_err(|e| fail(format!("cannot write the GeoPackage: {e}")))
}

async fn write_async(path: &Path, crs: &CrsRecord, layers: &[Layer]) -> Result<(), String> {
    let err = |e: sqlx::Error| e.to_string();
    let mut db = sqlx::sqlite::SqliteConnectOptions::new()
        .filename(path)
        .create_if_missing(true)
        .connect()
        .await
        .map_err(err)?;
    let mut tx = db.begin().await.map_err(err)?;
    // "GPKG" as the application id; 10300 = version 1.3.0.
    for sql in [
        "PRAGMA application_id = 1196444487",
        "PRAGMA user_version = 10300",
        "CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER PRIMARY KEY, \
         organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, \
         definition TEXT NOT NULL, description TEXT)",
        "CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, \
         data_type TEXT NOT NULL, identifier TEXT UNIQUE, description TEXT DEFAULT '', \
         last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')), \
         min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER, \
         CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id))",
        "CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, \
         column_name TEXT NOT NULL, geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, \
         z TINYINT NOT NULL, m TINYINT NOT NULL, \
         CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name), \
         CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name), \
         CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id))",
    ] {
        sqlx::query(sql).execute(&mut *tx).await.map_err(err)?;
    }
    // The three rows every GeoPackage holds, then the data's own CRS.
    let wgs84 = crs_definitions::EPSG_4326.wkt;
    let mut systems = vec![
        (
            4326,
            "WGS 84 geodetic",
            "EPSG",
            4326,
            wgs84.to_string(),
            "longitude/latitude",
        ),
        (
            -1,
            "Undefined Cartesian SRS",
            "NONE",
            -1,
            "undefined".into(),
            "undefined Cartesian",
        ),
        (
            0,
            "Undefined geographic SRS",
            "NONE",
            0,
            "undefined".into(),
            "undefined geographic",
        ),
    ];
    let (srs_id, org, code, definition, label) = srs(crs);
    if !matches!(srs_id, -1 | 0 | 4326) {
        systems.push((
            srs_id,
            "the cloud's CRS",
            org,
            code,
            definition,
            label.as_str(),
        ));
    }
    for (id, name, org, code, def, description) in systems {
        sqlx::query(
            "INSERT INTO gpkg_spatial_ref_sys (srs_name, srs_id, organization, \
             organization_coordsys_id, definition, description) VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(name)
        .bind(id)
        .bind(org)
        .bind(code)
        .bind(def)
        .bind(description)
        .execute(&mut *tx)
        .await
        .map_err(err)?;
    }
    for layer in layers {
        let columns: String = layer
            .columns
            .iter()
            .map(|(name, t)| format!(", {name} {}", t.sql()))
            .collect();
        let create = format!(
            "CREATE TABLE {} (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom {}{columns})",
            layer.name, layer.geometry_type
        );
        // Names are checked by `check_name` (letters, digits, underscores) before this point.
        sqlx::query(sqlx::AssertSqlSafe(create))
            .execute(&mut *tx)
            .await
            .map_err(err)?;
        let mut bounds: Option<geo::Rect<f64>> = None;
        let names: String = layer
            .columns
            .iter()
            .map(|(n, _)| format!(", {n}"))
            .collect();
        let marks: String = (0..layer.columns.len())
            .map(|i| format!(", ${}", i + 2))
            .collect();
        let insert = format!(
            "INSERT INTO {} (geom{names}) VALUES ($1{marks})",
            layer.name
        );
        for (geometry, values) in &layer.features {
            if let Some(r) = geometry.bounding_rect() {
                bounds = Some(match bounds {
                    None => r,
                    Some(b) => geo::Rect::new(
                        (b.min().x.min(r.min().x), b.min().y.min(r.min().y)),
                        (b.max().x.max(r.max().x), b.max().y.max(r.max().y)),
                    ),
                });
            }
            let mut q = sqlx::query(sqlx::AssertSqlSafe(insert.as_str()))
                .bind(geometry_blob(geometry, srs_id)?);
            for v in values {
                q = match v {
                    Value::Integer(i) => q.bind(*i),
                    Value::Real(f) => q.bind(*f),
                    Value::Text(s) => q.bind(s.clone()),
                    Value::Null => q.bind(Option::<f64>::None),
                };
            }
            q.execute(&mut *tx).await.map_err(err)?;
        }
        let (min, max) = bounds.map_or((None, None), |b| (Some(b.min()), Some(b.max())));
        sqlx::query(
            "INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, \
             max_y, srs_id) VALUES ($1, 'features', $1, $2, $3, $4, $5, $6)",
        )
        .bind(&layer.name)
        .bind(min.map(|c| c.x))
        .bind(min.map(|c| c.y))
        .bind(max.map(|c| c.x))
        .bind(max.map(|c| c.y))
        .bind(srs_id)
        .execute(&mut *tx)
        .await
        .map_err(err)?;
        sqlx::query(
            "INSERT INTO gpkg_geometry_columns (table_name, column_name, geometry_type_name, \
             srs_id, z, m) VALUES ($1, 'geom', $2, $3, 0, 0)",
        )
        .bind(&layer.name)
        .bind(layer.geometry_type)
        .bind(srs_id)
        .execute(&mut *tx)
        .await
        .map_err(err)?;
    }
    tx.commit().await.map_err(err)?;
    db.close().await.map_err(err)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_blob_carries_the_header_envelope_and_wkb() {
        let g = Geometry::Point(geo::Point::new(2.0, 4.0));
        let blob = geometry_blob(&g, 32649).expect("blob");
        assert_eq!(&blob[..4], &[b'G', b'P', 0, 3]);
        assert_eq!(
            i32::from_le_bytes([blob[4], blob[5], blob[6], blob[7]]),
            32649
        );
        // Envelope (2, 2, 4, 4), then WKB: little-endian byte, type 1, x, y.
        let f = |i: usize| f64::from_le_bytes(blob[i..i + 8].try_into().unwrap_or([0; 8]));
        assert_eq!((f(8), f(16), f(24), f(32)), (2.0, 2.0, 4.0, 4.0));
        assert_eq!(&blob[40..45], &[1, 1, 0, 0, 0]);
        assert_eq!((f(45), f(53)), (2.0, 4.0));
        assert!(check_name("trees").is_ok() && check_name("x; DROP").is_err());
    }
}
