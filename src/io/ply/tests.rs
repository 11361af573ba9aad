//! Tests of the PLY reader and writer.

use super::*;
use crate::io::pointcloud::{inspect_point_cloud, read_point_cloud};
use crate::io::real_data;
use crate::progress::NoProgress;
use glam::Vec3;

const PTS: [[f64; 3]; 3] = [
    [1000.25, 2000.5, 10.0],
    [1001.0, 2003.75, 12.5],
    [999.5, 2001.0, 9.0],
];

/// Writes a PLY with doubles, ushort colour, an ignored float, a list property in the
/// vertex element and a face element before the vertices.
fn write_test_ply(path: &Path, enc: PlyEncoding) {
    let fmt = match enc {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
        PlyEncoding::BinaryBigEndian => "binary_big_endian",
    };
    let mut out = format!(
        "ply\nformat {fmt} 1.0\ncomment test\nelement face 2\nproperty list uchar int vertex_indices\n\
         element vertex 3\nproperty double x\nproperty double y\nproperty double z\n\
         property ushort red\nproperty ushort green\nproperty ushort blue\nproperty float nx\n\
         property list uchar float tags\nproperty float scalar_intensity\nend_header\n"
    )
    .into_bytes();
    let put = |out: &mut Vec<u8>, le: Vec<u8>| {
        let mut b = le;
        if enc == PlyEncoding::BinaryBigEndian {
            b.reverse();
        }
        out.extend(b);
    };
    if enc == PlyEncoding::Ascii {
        out.extend(b"3 0 1 2\n4 0 1 2 0\n");
        for (i, p) in PTS.iter().enumerate() {
            let line = format!(
                "{} {} {} 65535 {} 0 0.5 2 1.5 2.5 {}\n",
                p[0],
                p[1],
                p[2],
                257 * i,
                100 * i
            );
            out.extend(line.into_bytes());
        }
    } else {
        for n in [3u8, 4] {
            out.push(n);
            for k in 0..n {
                put(&mut out, i32::from(k).to_le_bytes().to_vec());
            }
        }
        for (i, p) in PTS.iter().enumerate() {
            for v in p {
                put(&mut out, v.to_le_bytes().to_vec());
            }
            for c in [65535u16, 257 * i as u16, 0] {
                put(&mut out, c.to_le_bytes().to_vec());
            }
            put(&mut out, 0.5f32.to_le_bytes().to_vec());
            out.push(2);
            put(&mut out, 1.5f32.to_le_bytes().to_vec());
            put(&mut out, 2.5f32.to_le_bytes().to_vec());
            put(&mut out, (100.0 * i as f32).to_le_bytes().to_vec());
        }
    }
    std::fs::write(path, out).unwrap();
}

#[test]
fn ascii_and_binary_le_be_read_the_same_points() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let path = dir.path().join("t.ply");
        write_test_ply(&path, enc);
        assert_eq!(inspect_ply(&path).unwrap().encoding, enc);
        let c = read_point_cloud(&path, &NoProgress).unwrap();
        assert_eq!(c.len(), 3, "{enc:?}");
        assert_eq!(c.offset, DVec3::new(999.0, 2000.0, 9.0));
        for (i, p) in PTS.iter().enumerate() {
            assert!(
                (c.world(i) - DVec3::from_array(*p)).length() < 1e-4,
                "{enc:?} {i}"
            );
        }
        assert_eq!(c.colors.as_ref().unwrap()[2], [255, 2, 0]);
        assert_eq!(c.intensity, Some(vec![0, 100, 200]));
    }
}

#[test]
fn write_read_round_trip_keeps_offset_colour_and_fields() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rt.ply");
    let cloud = PointCloud {
        offset: DVec3::new(654_321.0, 5_123_456.0, -12.0),
        positions: vec![Vec3::new(0.001, 2.5, 3.25), Vec3::new(-1.0, 0.0, 7.125)],
        colors: Some(vec![[1, 2, 3], [250, 251, 252]]),
        intensity: Some(vec![7, 65535]),
        format: CloudFormat::Ply,
    };
    let normals = ScalarField {
        name: "nz".into(),
        values: vec![0.5, -1.0],
    };
    write_ply(&path, &cloud, std::slice::from_ref(&normals)).unwrap();
    let (back, fields) = read_ply_with_fields(&path, &NoProgress).unwrap();
    assert_eq!(back, cloud);
    assert_eq!(fields, vec![normals]);
    let bad = ScalarField {
        name: "short".into(),
        values: vec![1.0],
    };
    assert!(write_ply(&path, &cloud, &[bad]).is_err());
}

#[test]
fn inconsistent_header_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.ply");
    write_test_ply(&path, PlyEncoding::BinaryLittleEndian);
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
    assert!(matches!(
        read_ply(&path, &NoProgress),
        Err(IoError::Format { .. })
    ));
    // Fixed-size rows: fewer or more vertex bytes than declared.
    let text = "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    for extra in [12usize, 36] {
        let mut b = text.as_bytes().to_vec();
        b.extend(vec![0u8; extra]);
        std::fs::write(&path, &b).unwrap();
        let e = inspect_point_cloud(&path).unwrap_err().to_string();
        assert!(e.contains("declares 2 vertices"), "{e}");
        assert!(matches!(
            read_ply(&path, &NoProgress),
            Err(IoError::Format { .. })
        ));
    }
    // Missing z.
    std::fs::write(&path, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n").unwrap();
    let e = inspect_ply(&path).unwrap_err().to_string();
    assert!(e.contains("no scalar 'z'"), "{e}");
    // Short ASCII body names the line.
    std::fs::write(&path, "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n1 2\n").unwrap();
    let e = read_ply(&path, &NoProgress).unwrap_err().to_string();
    assert!(e.contains("line 9"), "{e}");
}

#[test]
fn non_finite_vertex_is_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nan.ply");
    std::fs::write(&path, "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\nnan 2 3\n").unwrap();
    let e = read_ply(&path, &NoProgress).unwrap_err().to_string();
    assert!(e.contains("point 1"), "{e}");
}

#[test]
fn real_cloudcompare_ply_reads_fully() {
    let Some(path) = real_data("CSF_sample/sample.ply") else {
        return;
    };
    let info = inspect_ply(&path).unwrap();
    assert_eq!(info.vertex_count, 100_000);
    let c = read_point_cloud(&path, &NoProgress).unwrap();
    assert_eq!(c.len(), 100_000);
    let (lo, hi) = c.bounds().unwrap();
    assert!(lo.is_finite() && hi.is_finite());
    assert!(lo.z > 780.0 && hi.z < 830.0, "{lo} {hi}");
}
