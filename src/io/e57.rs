//! E57 (ASTM E2807) point clouds through the `e57` crate.
//!
//! Every scan in the file is read with its pose applied, so several scans of a plot merge
//! into one cloud in the file's common frame. Spherical-only scans are converted to
//! Cartesian; points the scanner marked invalid (no return) are skipped and counted.
//! Colours are normalised by the file's colour limits to 8-bit, intensity to 16-bit.

use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::pointcloud::{CloudBuilder, CloudFormat, PointCloud};
use super::{IoError, PROGRESS_STEP, check_cancel};
use crate::progress::Progress;

/// What the header and XML of an E57 file say.
#[derive(Debug, Clone, Serialize)]
pub struct E57Info {
    /// Number of scans (Data3D entries).
    pub scans: usize,
    /// Sum of the scans' declared record counts.
    pub declared_points: u64,
    pub has_color: bool,
    pub has_intensity: bool,
}

/// A real I/O failure stays `Io` (disk full is a 507, not the user's fault); anything else —
/// a truncated or inconsistent file — is a `Format` error naming the file.
fn e57_err(path: &Path, e: e57::Error) -> IoError {
    if let e57::Error::Read {
        source: Some(src), ..
    } = &e
        && let Some(io) = src.downcast_ref::<std::io::Error>()
        && !matches!(
            io.kind(),
            std::io::ErrorKind::UnexpectedEof | std::io::ErrorKind::InvalidData
        )
    {
        return IoError::io(path, std::io::Error::new(io.kind(), io.to_string()));
    }
    IoError::format(path, format!("E57: {e}"))
}

/// Reads the header and scan list without decoding points.
pub fn inspect_e57(path: &Path) -> Result<E57Info, IoError> {
    let reader = e57::E57Reader::from_file(path).map_err(|e| e57_err(path, e))?;
    let scans = reader.pointclouds();
    Ok(E57Info {
        scans: scans.len(),
        declared_points: scans.iter().map(|s| s.records).sum(),
        has_color: scans.iter().any(|s| s.has_color()),
        has_intensity: scans.iter().any(|s| s.has_intensity()),
    })
}

/// Reads every scan of an E57 file into one cloud (poses applied).
pub fn read_e57(path: &Path, progress: &dyn Progress) -> Result<PointCloud, IoError> {
    let mut reader = e57::E57Reader::from_file(path).map_err(|e| e57_err(path, e))?;
    let scans = reader.pointclouds();
    if scans.is_empty() {
        return Err(IoError::format(path, "E57 file holds no point cloud"));
    }
    let total: u64 = scans.iter().map(|s| s.records).sum();
    let want_color = scans.iter().all(|s| s.has_color());
    let want_intensity = scans.iter().all(|s| s.has_intensity());
    let mut builder = CloudBuilder::new(path, None, total);
    let mut colors = Vec::new();
    let mut intensity = Vec::new();
    let mut seen = 0u64;
    let mut invalid = 0u64;
    for scan in &scans {
        let mut iter = reader
            .pointcloud_simple(scan)
            .map_err(|e| e57_err(path, e))?;
        iter.spherical_to_cartesian(true);
        iter.apply_pose(true);
        iter.normalize_color(true);
        iter.normalize_intensity(true);
        for point in iter {
            let point = point.map_err(|e| e57_err(path, e))?;
            seen += 1;
            if seen.is_multiple_of(PROGRESS_STEP as u64) {
                check_cancel(progress)?;
                progress.set(seen as f64 / total.max(1) as f64);
            }
            let e57::CartesianCoordinate::Valid { x, y, z } = point.cartesian else {
                invalid += 1;
                continue;
            };
            builder.push(DVec3::new(x, y, z))?;
            if want_color {
                let c = point.color.unwrap_or(e57::Color {
                    red: 0.0,
                    green: 0.0,
                    blue: 0.0,
                });
                let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
                colors.push([q(c.red), q(c.green), q(c.blue)]);
            }
            if want_intensity {
                let v = point.intensity.unwrap_or(0.0).clamp(0.0, 1.0);
                intensity.push((v * 65535.0).round() as u16);
            }
        }
    }
    if seen != total {
        return Err(IoError::format(
            path,
            format!("E57 declares {total} points but holds {seen}"),
        ));
    }
    if builder.count() == 0 {
        return Err(IoError::format(
            path,
            format!("E57 holds no valid point ({invalid} without a return)"),
        ));
    }
    let (offset, positions) = builder.finish();
    progress.set(1.0);
    Ok(PointCloud {
        offset,
        positions,
        colors: want_color.then_some(colors),
        intensity: want_intensity.then_some(intensity),
        format: CloudFormat::E57,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;
    use e57::{E57Writer, Record, RecordDataType, RecordName, RecordValue};

    fn write_scan(path: &Path, points: &[[f64; 3]], with_color: bool) {
        let mut w = E57Writer::from_file(path, "sylva-test").expect("writer");
        let double = || RecordDataType::Double {
            min: None,
            max: None,
        };
        let mut proto = vec![
            Record {
                name: RecordName::CartesianX,
                data_type: double(),
            },
            Record {
                name: RecordName::CartesianY,
                data_type: double(),
            },
            Record {
                name: RecordName::CartesianZ,
                data_type: double(),
            },
        ];
        if with_color {
            for name in [
                RecordName::ColorRed,
                RecordName::ColorGreen,
                RecordName::ColorBlue,
            ] {
                proto.push(Record {
                    name,
                    data_type: RecordDataType::Integer { min: 0, max: 255 },
                });
            }
        }
        let mut pc = w.add_pointcloud("scan-1", proto).expect("pointcloud");
        for (i, p) in points.iter().enumerate() {
            let mut v = vec![
                RecordValue::Double(p[0]),
                RecordValue::Double(p[1]),
                RecordValue::Double(p[2]),
            ];
            if with_color {
                v.extend([
                    RecordValue::Integer(255),
                    RecordValue::Integer((i % 256) as i64),
                    RecordValue::Integer(0),
                ]);
            }
            pc.add_point(v).expect("point");
        }
        pc.finalize().expect("finalize scan");
        w.finalize().expect("finalize file");
    }

    #[test]
    fn e57_round_trip_keeps_georeferenced_coordinates_and_colour() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("scan.e57");
        let pts: Vec<[f64; 3]> = (0..1000)
            .map(|i| {
                [
                    500_000.0 + i as f64 * 0.01,
                    4_000_000.0 + (i % 7) as f64,
                    100.5,
                ]
            })
            .collect();
        write_scan(&path, &pts, true);
        let info = inspect_e57(&path).expect("inspect");
        assert_eq!(info.scans, 1);
        assert_eq!(info.declared_points, 1000);
        let cloud = read_e57(&path, &NoProgress).expect("read");
        assert_eq!(cloud.len(), 1000);
        assert_eq!(cloud.format, CloudFormat::E57);
        for (i, p) in pts.iter().enumerate() {
            assert!((cloud.world(i) - DVec3::from_array(*p)).length() < 1e-4);
        }
        let colors = cloud.colors.expect("colour");
        assert_eq!(colors[3], [255, 3, 0]);
    }

    #[test]
    fn truncated_e57_is_a_format_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("scan.e57");
        let pts: Vec<[f64; 3]> = (0..5000).map(|i| [i as f64, 0.0, 1.0]).collect();
        write_scan(&path, &pts, false);
        let bytes = std::fs::read(&path).expect("read");
        std::fs::write(&path, &bytes[..bytes.len() / 3]).expect("write");
        let err = read_e57(&path, &NoProgress).expect_err("truncated");
        assert!(matches!(err, IoError::Format { .. }), "{err}");
    }
}
