//! COPC 1.0 (Cloud Optimized Point Cloud: a LAZ 1.4 file whose chunks are the nodes of an
//! octree, copc.io) of a labelled cloud, with its CRS, for PDAL, QGIS, Potree and web viewers.
//!
//! Written through the `copc-writer` crate (0.9, roteiro-gis/copc-rust): it takes points from
//! a source trait, so Sylva's columns stream into it without a LAS file in between, writes the
//! WKT CRS record LAS 1.4 asks for and Extra Bytes records, and builds the octree, its levels
//! of detail and the hierarchy itself. `copc-rs` (0.5) was the other candidate; it takes
//! `las::Point`s of las 0.9 one by one and its README calls writing a work in progress. Both
//! are built on an older `las` than Sylva's own (0.10 here, beside 0.11), which costs a
//! second build of that crate and nothing at run time.
//!
//! Each point carries: x, y, z in the file's own coordinates (the cloud's offset added back;
//! LAS scale 1 mm), its RGB where the cloud has colour (16-bit, the 8-bit value times 257), its
//! intensity, its class (ASPRS: 2 ground, 5 high vegetation for leaf; 64, the first
//! user-definable class, for wood; 1 unassigned), and an Extra Bytes field `tree_id` (u32, 0 =
//! no tree).

use std::path::Path;

use copc_core::{Bounds, Result as CopcResult};
use copc_writer::{CopcPointFields, CopcPointSource, CopcWriterParams};

use super::IoError;
use super::pointcloud::PointCloud;

/// ASPRS class of ground points.
pub const CLASS_GROUND: u8 = 2;
/// ASPRS class "high vegetation", for leaf points.
pub const CLASS_LEAF: u8 = 5;
/// The first user-definable class (LAS 1.4 R15, table 17), for wood points.
pub const CLASS_WOOD: u8 = 64;
/// ASPRS class "unassigned".
pub const CLASS_UNASSIGNED: u8 = 1;

/// A cloud's points with their classes and tree ids, as [`write_copc`] takes them.
pub struct LabelledCloud<'a> {
    pub cloud: &'a PointCloud,
    /// One ASPRS class a point.
    pub classes: Vec<u8>,
    /// One tree id a point (0: none).
    pub trees: Vec<u32>,
    /// The Extra Bytes record describing `tree_id`.
    vlrs: Vec<las010::Vlr>,
}

/// The Extra Bytes record (LAS 1.4 R15 §2.6.2, record 4 of `LASF_Spec`) of one u32 field named
/// `tree_id`: a 192-byte descriptor.
fn tree_id_descriptor() -> las010::Vlr {
    let mut d = vec![0u8; 192];
    d[2] = 6; // data type 6: unsigned long (u32)
    d[3] = 0; // options: no no_data, min, max, scale or offset
    let name = b"tree_id";
    d[4..4 + name.len()].copy_from_slice(name);
    let description = b"tree of the inventory, 0 = none";
    d[160..160 + description.len()].copy_from_slice(description);
    las010::Vlr {
        user_id: "LASF_Spec".into(),
        record_id: 4,
        description: "Extra Bytes".into(),
        data: d,
    }
}

impl<'a> LabelledCloud<'a> {
    /// `cloud` with one class and one tree id a point; `None` when the lengths differ.
    pub fn new(cloud: &'a PointCloud, classes: Vec<u8>, trees: Vec<u32>) -> Option<Self> {
        (classes.len() == cloud.len() && trees.len() == cloud.len()).then(|| LabelledCloud {
            cloud,
            classes,
            trees,
            vlrs: vec![tree_id_descriptor()],
        })
    }

    fn xyz_f64(&self, i: usize) -> (f64, f64, f64) {
        let p = self.cloud.positions[i];
        let o = self.cloud.offset;
        (
            o.x + f64::from(p.x),
            o.y + f64::from(p.y),
            o.z + f64::from(p.z),
        )
    }
}

impl CopcPointSource for LabelledCloud<'_> {
    fn len(&self) -> usize {
        self.cloud.len()
    }

    fn xyz(&self, index: usize) -> CopcResult<(f64, f64, f64)> {
        Ok(self.xyz_f64(index))
    }

    fn fields_into(&self, index: usize, out: &mut CopcPointFields) -> CopcResult<()> {
        let (x, y, z) = self.xyz_f64(index);
        out.x = x;
        out.y = y;
        out.z = z;
        out.intensity = self
            .cloud
            .intensity
            .as_ref()
            .and_then(|v| v.get(index).copied())
            .unwrap_or(0);
        out.return_number = 1;
        out.number_of_returns = 1;
        out.classification = self.classes[index];
        if let Some(c) = self.cloud.colors.as_ref().and_then(|c| c.get(index)) {
            (out.red, out.green, out.blue) = (
                u16::from(c[0]) * 257,
                u16::from(c[1]) * 257,
                u16::from(c[2]) * 257,
            );
        }
        out.extra_bytes.clear();
        out.extra_bytes
            .extend_from_slice(&self.trees[index].to_le_bytes());
        Ok(())
    }

    fn extra_byte_count(&self) -> u16 {
        4
    }

    fn extra_bytes_vlrs(&self) -> &[las010::Vlr] {
        &self.vlrs
    }
}

/// The WKT a COPC file declares for `crs`: the EPSG registry's for a code, the definition
/// when it is WKT; `None` for a CRS known only as a PROJ string (the file then carries an empty
/// WKT record, as LAS 1.4 allows).
pub fn wkt_of(crs: &super::crs::Crs) -> Option<String> {
    if let Some(def) = crs.epsg.and_then(|c| crs_definitions::from_code(c as u16)) {
        return Some(def.wkt.to_string());
    }
    crs.definition.contains('[').then(|| crs.definition.clone())
}

/// Writes `points` to `path` as COPC 1.0, declaring `wkt` as its CRS.
pub fn write_copc(
    path: &Path,
    points: &LabelledCloud<'_>,
    wkt: Option<String>,
) -> Result<(), IoError> {
    if points.cloud.is_empty() {
        return Err(IoError::format(
            path,
            "no points to write as COPC".to_string(),
        ));
    }
    let mut lo = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    let mut hi = (f64::NEG_INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for i in 0..points.cloud.len() {
        let (x, y, z) = points.xyz_f64(i);
        lo = (lo.0.min(x), lo.1.min(y), lo.2.min(z));
        hi = (hi.0.max(x), hi.1.max(y), hi.2.max(z));
    }
    let mut meta = copc_writer::CopcWriteMetadata::default();
    meta.wkt_crs = wkt;
    meta.system_identifier = Some("sylva".into());
    meta.generating_software = Some(concat!("sylva ", env!("CARGO_PKG_VERSION")).into());
    copc_writer::write_source(
        path,
        points,
        points.cloud.colors.is_some(),
        Bounds::new(lo, hi),
        &CopcWriterParams::default(),
        &meta,
    )
    .map_err(|e| IoError::format(path, format!("cannot write COPC: {e}")))?;
    // The writer renames a private temporary file into place; readable as every output is.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o644))
            .map_err(|e| IoError::io(path, e))?;
    }
    Ok(())
}
