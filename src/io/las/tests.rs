//! Tests of the LAS/LAZ reader and writer.

use super::*;
use crate::io::pointcloud::{inspect_point_cloud, read_point_cloud};
use crate::io::real_data_dir;
use crate::progress::NoProgress;
use glam::Vec3;

fn sample(colors: bool) -> PointCloud {
    let n = 1000;
    PointCloud {
        offset: DVec3::new(512_000.0, 6_100_000.0, 90.0),
        positions: (0..n)
            .map(|i| Vec3::new(i as f32 * 0.013, (i % 37) as f32 * 0.25, (i % 11) as f32))
            .collect(),
        colors: colors.then(|| (0..n).map(|i| [i as u8, 255 - i as u8, 7]).collect()),
        intensity: Some((0..n).map(|i| i as u16 * 3).collect()),
        format: CloudFormat::Las,
    }
}

fn assert_close(a: &PointCloud, b: &PointCloud) {
    assert_eq!(a.len(), b.len());
    for i in 0..a.len() {
        assert!(
            (a.world(i) - b.world(i)).abs().max_element() < 0.0011,
            "point {i}"
        );
    }
    assert_eq!(a.colors, b.colors);
    assert_eq!(a.intensity, b.intensity);
}

#[test]
fn las_and_laz_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    for (name, compress, colors) in [
        ("a.las", false, true),
        ("b.laz", true, true),
        ("c.las", false, false),
    ] {
        let cloud = sample(colors);
        let path = dir.path().join(name);
        write_las(&path, &cloud, compress).unwrap();
        let back = read_point_cloud(&path, &NoProgress).unwrap();
        assert_eq!(
            back.format,
            if compress {
                CloudFormat::Laz
            } else {
                CloudFormat::Las
            }
        );
        assert_eq!(back.offset, cloud.offset);
        assert_close(&cloud, &back);
        let info = inspect_las(&path).unwrap();
        assert_eq!(info.declared_points, 1000);
        assert_eq!(info.has_color, colors);
    }
}

#[test]
fn las14_point_format_7_reads_colour_and_extended_count() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f7.las");
    let mut b = Builder::from((1, 4));
    b.point_format = Format::new(7).unwrap();
    let mut w = ::las::Writer::new(
        BufWriter::new(File::create(&path).unwrap()),
        b.into_header().unwrap(),
    )
    .unwrap();
    for i in 0..5 {
        let p = Point {
            x: 10.0 + f64::from(i),
            y: 20.0,
            z: 1.5,
            intensity: 100,
            gps_time: Some(0.0),
            color: Some(Color::new(65535, 0, 32896)),
            ..Default::default()
        };
        w.write_point(p).unwrap();
    }
    w.close().unwrap();
    let c = read_las(&path, &NoProgress).unwrap();
    assert_eq!(c.len(), 5);
    assert_eq!(c.colors.as_ref().unwrap()[0], [255, 0, 128]);
    assert_eq!(inspect_las(&path).unwrap().point_format, 7);
}

#[test]
fn truncated_las_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.las");
    write_las(&path, &sample(false), false).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 7]).unwrap();
    let e = inspect_point_cloud(&path).unwrap_err().to_string();
    assert!(
        e.contains("declares 1000 points but the file holds 999"),
        "{e}"
    );
    assert!(matches!(
        read_point_cloud(&path, &NoProgress),
        Err(IoError::Format { .. })
    ));
}

#[test]
fn wrong_declared_count_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    for (name, compress, declared) in [("w.las", false, 900u32), ("w.laz", true, 60_000)] {
        let path = dir.path().join(name);
        write_las(&path, &sample(false), compress).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[107..111].copy_from_slice(&declared.to_le_bytes()); // legacy point count
        std::fs::write(&path, &bytes).unwrap();
        let e = read_las(&path, &NoProgress).unwrap_err().to_string();
        assert!(
            e.contains(&format!("header declares {declared} points")),
            "{e}"
        );
    }
}

#[test]
fn real_las_and_laz_files_read_fully() {
    let Some(dir) = real_data_dir() else {
        println!("skipping: real data not found (set SYLVA_REAL_DATA)");
        return;
    };
    for (file, expect, color) in [
        ("TreeLS_extdata/pine.laz", 73_851, false),
        ("PyTLidar_trees/tree_1.las", 90_239, false),
        ("lidR_extdata/dbh.laz", 1_369, false),
    ] {
        let path = dir.join(file);
        let info = inspect_point_cloud(&path).unwrap();
        assert_eq!(info.declared_points, Some(expect), "{file}");
        let c = read_point_cloud(&path, &NoProgress).unwrap();
        assert_eq!(c.len() as u64, expect, "{file}");
        assert_eq!(c.colors.is_some(), color, "{file}");
        let (lo, hi) = c.bounds().unwrap();
        assert!(
            lo.is_finite() && hi.is_finite() && lo.cmple(hi).all(),
            "{file}"
        );
        // Local coordinates stay small: the origin sits at the data.
        let far = c
            .positions
            .iter()
            .map(|p| p.abs().max_element())
            .fold(0.0, f32::max);
        assert!(far < 1000.0, "{file}: local extent {far}");
    }
    let tree = read_las(&dir.join("PyTLidar_trees/tree_1.las"), &NoProgress).unwrap();
    assert!(tree.intensity.is_some());
    assert_eq!(
        inspect_las(&dir.join("PyTLidar_trees/tree_1.las"))
            .unwrap()
            .point_format,
        6
    );
}
