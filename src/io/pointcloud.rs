//! The one point-cloud type of Sylva, format detection and the reader entry points.
//!
//! Positions are kept as `f32` relative to a per-file local origin (`offset`, `f64`), so a
//! cloud with georeferenced coordinates (hundreds of kilometres from the origin) keeps
//! sub-millimetre precision over a few kilometres of extent while using 12 bytes per point.

use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

use super::{IoError, PROGRESS_STEP, file_len};
use crate::progress::Progress;

/// The file format a cloud was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CloudFormat {
    Las,
    Laz,
    Ply,
    Xyz,
    E57,
}

/// A point cloud with optional per-point colour and intensity.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud {
    /// Local origin in the file's own coordinates (metres, f64): positions are file coords
    /// minus this.
    pub offset: DVec3,
    /// Point positions relative to `offset`, metres.
    pub positions: Vec<Vec3>,
    /// 8-bit sRGB colour per point (16-bit sources are scaled down by 257 when any channel
    /// exceeds 255).
    pub colors: Option<Vec<[u8; 3]>>,
    /// Raw intensity per point (sensor units, 0..=65535).
    pub intensity: Option<Vec<u16>>,
    /// The format the cloud was read from.
    pub format: CloudFormat,
}

impl PointCloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when the cloud holds no point.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Axis-aligned bounds `(min, max)` in file coordinates (metres); `None` when empty.
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        let first = *self.positions.first()?;
        let (lo, hi) = self
            .positions
            .iter()
            .fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        Some((self.offset + lo.as_dvec3(), self.offset + hi.as_dvec3()))
    }

    /// Position of point `i` in file coordinates (metres). Panics when `i >= len()`.
    pub fn world(&self, i: usize) -> DVec3 {
        self.offset + self.positions[i].as_dvec3()
    }
}

/// Converts 16-bit colour channels to 8-bit: divided by 257 when any channel exceeds 255
/// (a true 16-bit source), kept as is otherwise (8-bit values stored in 16-bit fields).
pub(crate) fn colors_to_u8(colors: &[[u16; 3]]) -> Vec<[u8; 3]> {
    let wide = colors.iter().flatten().any(|&c| c > 255);
    colors
        .iter()
        .map(|c| {
            c.map(|v| {
                if wide {
                    ((u32::from(v) + 128) / 257).min(255) as u8
                } else {
                    v as u8
                }
            })
        })
        .collect()
}

/// Collects positions of one file and chooses its local origin.
///
/// The origin is chosen once per file from the first chunk of [`PROGRESS_STEP`] points (or
/// all points, when fewer): if a `hint` box (the LAS header bounds) contains every point of
/// that chunk (within 1 m), its minimum corner is used, otherwise the chunk's minimum corner.
/// Either is rounded down to whole metres. A `fixed` origin (a PLY `sylva_offset` comment) is
/// used as is.
pub(crate) struct CloudBuilder {
    path: PathBuf,
    hint: Option<(DVec3, DVec3)>,
    offset: Option<DVec3>,
    pending: Vec<DVec3>,
    positions: Vec<Vec3>,
    count: u64,
}

impl CloudBuilder {
    /// A builder that chooses the origin itself, optionally guided by header bounds (metres).
    pub(crate) fn new(path: &Path, hint: Option<(DVec3, DVec3)>, capacity: u64) -> Self {
        let hint = hint.filter(|(lo, hi)| lo.is_finite() && hi.is_finite() && lo.cmple(*hi).all());
        CloudBuilder {
            path: path.to_path_buf(),
            hint,
            offset: None,
            pending: Vec::new(),
            positions: Vec::with_capacity(capacity.min(1 << 24) as usize),
            count: 0,
        }
    }

    /// A builder whose origin is given by the file (metres).
    pub(crate) fn with_offset(path: &Path, offset: DVec3, capacity: u64) -> Self {
        let mut b = CloudBuilder::new(path, None, capacity);
        b.offset = Some(offset);
        b
    }

    /// Number of points pushed so far.
    pub(crate) fn count(&self) -> u64 {
        self.count
    }

    /// Adds a point in file coordinates (metres).
    pub(crate) fn push(&mut self, p: DVec3) -> Result<(), IoError> {
        if !p.is_finite() {
            return Err(self.non_finite());
        }
        self.count += 1;
        match self.offset {
            Some(o) => self.positions.push((p - o).as_vec3()),
            None => {
                self.pending.push(p);
                if self.pending.len() >= PROGRESS_STEP {
                    self.settle();
                }
            }
        }
        Ok(())
    }

    /// Adds a point already relative to a fixed origin (metres). Only valid after
    /// [`CloudBuilder::with_offset`].
    pub(crate) fn push_local(&mut self, p: Vec3) -> Result<(), IoError> {
        if !p.is_finite() {
            return Err(self.non_finite());
        }
        match self.offset {
            Some(_) => {
                self.count += 1;
                self.positions.push(p);
                Ok(())
            }
            None => self.push(p.as_dvec3()),
        }
    }

    fn non_finite(&self) -> IoError {
        IoError::format(
            &self.path,
            format!("point {} has a non-finite coordinate", self.count),
        )
    }

    fn settle(&mut self) {
        let Some(first) = self.pending.first().copied() else {
            self.offset = Some(DVec3::ZERO);
            return;
        };
        let (lo, hi) = self
            .pending
            .iter()
            .fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
        let corner = match self.hint {
            Some((hlo, hhi))
                if (hlo - DVec3::ONE).cmple(lo).all() && hi.cmple(hhi + DVec3::ONE).all() =>
            {
                hlo
            }
            _ => lo,
        };
        let offset = corner.floor();
        self.offset = Some(offset);
        for p in std::mem::take(&mut self.pending) {
            self.positions.push((p - offset).as_vec3());
        }
    }

    /// The origin (metres) and the positions relative to it.
    pub(crate) fn finish(mut self) -> (DVec3, Vec<Vec3>) {
        if self.offset.is_none() {
            self.settle();
        }
        (self.offset.unwrap_or(DVec3::ZERO), self.positions)
    }
}

/// Detects the format of a point-cloud file: magic bytes first ("LASF": LAS, or LAZ when the
/// point-format byte has the compression bit; "ply" + newline: PLY), then the extension
/// (`.las`, `.laz`, `.ply`, `.xyz`, `.txt`, `.csv`, `.pts`).
pub fn detect_format(path: &Path) -> Result<CloudFormat, IoError> {
    let mut head = Vec::with_capacity(128);
    File::open(path)
        .and_then(|f| f.take(128).read_to_end(&mut head))
        .map_err(|e| IoError::io(path, e))?;
    if head.is_empty() {
        return Err(IoError::format(path, "file is empty"));
    }
    if head.starts_with(b"LASF") {
        return match head.get(104) {
            Some(b) if b & 0x80 != 0 => Ok(CloudFormat::Laz),
            Some(_) => Ok(CloudFormat::Las),
            None => Err(IoError::format(path, "LAS header is truncated")),
        };
    }
    if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
        return Ok(CloudFormat::Ply);
    }
    if head.starts_with(b"ASTM-E57") {
        return Ok(CloudFormat::E57);
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    match ext.as_str() {
        "las" | "laz" => Err(IoError::format(
            path,
            "not a LAS/LAZ file (no LASF signature)",
        )),
        "ply" => Err(IoError::format(
            path,
            "not a PLY file (no 'ply' magic line)",
        )),
        "xyz" | "txt" | "csv" | "pts" => Ok(CloudFormat::Xyz),
        "e57" => Err(IoError::format(
            path,
            "not an E57 file (no ASTM-E57 signature)",
        )),
        _ => Err(IoError::format(
            path,
            "unrecognised point-cloud format (expected LAS, LAZ, PLY, E57 or XYZ text)",
        )),
    }
}

/// Reads a whole point cloud, detecting its format with [`detect_format`].
pub fn read_point_cloud(path: &Path, progress: &dyn Progress) -> Result<PointCloud, IoError> {
    match detect_format(path)? {
        CloudFormat::Las | CloudFormat::Laz => super::las::read_las(path, progress),
        CloudFormat::Ply => super::ply::read_ply(path, progress),
        CloudFormat::Xyz => super::xyz::read_xyz(path, progress),
        CloudFormat::E57 => super::e57::read_e57(path, progress),
    }
}

/// The CRS a point-cloud file declares, read from its header only: LAS/LAZ projection
/// records (OGC WKT or GeoTIFF keys, [`super::crs`]); PLY, XYZ text and E57 files carry none
/// that Sylva reads, so they give `Ok(None)`. The outer error is the file's (unreadable,
/// not a cloud); the inner one a declaration that is there but cannot be used.
pub fn declared_crs(
    path: &Path,
) -> Result<Result<Option<super::crs::Crs>, super::crs::CrsError>, IoError> {
    match detect_format(path)? {
        CloudFormat::Las | CloudFormat::Laz => super::las::read_crs(path),
        CloudFormat::Ply | CloudFormat::Xyz | CloudFormat::E57 => Ok(Ok(None)),
    }
}

/// What a header says about a point cloud, read without decoding the points.
#[derive(Debug, Clone, Serialize)]
pub struct CloudSummary {
    /// Detected format.
    pub format: CloudFormat,
    /// File size, bytes.
    pub file_bytes: u64,
    /// Point count declared by the header (`None` for XYZ text, which has no header).
    pub declared_points: Option<u64>,
    /// Format-specific details.
    pub details: SummaryDetails,
}

/// Format-specific part of a [`CloudSummary`].
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SummaryDetails {
    Las(super::las::LasInfo),
    Ply(super::ply::PlyInfo),
    Xyz(super::xyz::XyzInfo),
    E57(super::e57::E57Info),
}

/// Reads only the header of a point cloud and checks it against the file size. Rejects an
/// empty file, a truncated uncompressed LAS, a binary PLY whose header disagrees with the
/// file size or a PLY without x/y/z, and XYZ text whose first lines do not parse.
pub fn inspect_point_cloud(path: &Path) -> Result<CloudSummary, IoError> {
    let format = detect_format(path)?;
    let file_bytes = file_len(path)?;
    let (declared_points, details) = match format {
        CloudFormat::Las | CloudFormat::Laz => {
            let info = super::las::inspect_las(path)?;
            (Some(info.declared_points), SummaryDetails::Las(info))
        }
        CloudFormat::Ply => {
            let info = super::ply::inspect_ply(path)?;
            (Some(info.vertex_count), SummaryDetails::Ply(info))
        }
        CloudFormat::Xyz => (None, SummaryDetails::Xyz(super::xyz::inspect_xyz(path)?)),
        CloudFormat::E57 => {
            let info = super::e57::inspect_e57(path)?;
            (Some(info.declared_points), SummaryDetails::E57(info))
        }
    };
    Ok(CloudSummary {
        format,
        file_bytes,
        declared_points,
        details,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;

    #[test]
    fn offset_is_floored_minimum_and_keeps_precision() {
        let mut b = CloudBuilder::new(Path::new("t"), None, 0);
        b.push(DVec3::new(500_000.123_4, 6_000_000.567_8, 101.25))
            .unwrap();
        b.push(DVec3::new(501_000.0, 6_001_000.0, 130.0)).unwrap();
        let (offset, pos) = b.finish();
        assert_eq!(offset, DVec3::new(500_000.0, 6_000_000.0, 101.0));
        let back = offset + pos[0].as_dvec3();
        assert!(
            (back - DVec3::new(500_000.123_4, 6_000_000.567_8, 101.25))
                .abs()
                .max_element()
                < 1e-4
        );
    }

    #[test]
    fn header_hint_is_ignored_when_points_fall_outside() {
        let hint = Some((DVec3::ZERO, DVec3::ZERO));
        let mut b = CloudBuilder::new(Path::new("t"), hint, 0);
        b.push(DVec3::new(1_176_120.5, 2_857_140.5, 3.0)).unwrap();
        assert_eq!(b.finish().0, DVec3::new(1_176_120.0, 2_857_140.0, 3.0));
    }

    #[test]
    fn non_finite_coordinate_names_the_point() {
        let mut b = CloudBuilder::new(Path::new("t"), None, 0);
        b.push(DVec3::ONE).unwrap();
        let e = b.push(DVec3::new(f64::NAN, 0.0, 0.0)).unwrap_err();
        assert!(e.to_string().contains("point 1"), "{e}");
    }

    #[test]
    fn empty_and_unknown_files_are_format_errors() {
        let dir = tempfile::tempdir().unwrap();
        let empty = dir.path().join("a.las");
        std::fs::write(&empty, b"").unwrap();
        assert!(matches!(
            inspect_point_cloud(&empty),
            Err(IoError::Format { .. })
        ));
        assert!(matches!(
            read_point_cloud(&empty, &NoProgress),
            Err(IoError::Format { .. })
        ));
        let odd = dir.path().join("a.bin");
        std::fs::write(&odd, b"hello").unwrap();
        assert!(matches!(detect_format(&odd), Err(IoError::Format { .. })));
        let missing = dir.path().join("missing.las");
        assert!(matches!(detect_format(&missing), Err(IoError::Io { .. })));
    }

    #[test]
    fn colors_scale_down_only_when_sixteen_bit() {
        assert_eq!(colors_to_u8(&[[255, 10, 0]]), vec![[255, 10, 0]]);
        assert_eq!(colors_to_u8(&[[65535, 257, 0]]), vec![[255, 1, 0]]);
    }

    #[test]
    fn bounds_and_world_are_in_file_coordinates() {
        let c = PointCloud {
            offset: DVec3::new(100.0, 200.0, 0.0),
            positions: vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(-1.0, 5.0, 0.0)],
            colors: None,
            intensity: None,
            format: CloudFormat::Xyz,
        };
        assert_eq!(c.len(), 2);
        assert_eq!(c.world(1), DVec3::new(99.0, 205.0, 0.0));
        let (lo, hi) = c.bounds().unwrap();
        assert_eq!(lo, DVec3::new(99.0, 202.0, 0.0));
        assert_eq!(hi, DVec3::new(101.0, 205.0, 3.0));
    }
}
