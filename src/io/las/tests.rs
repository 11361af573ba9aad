//! Tests of the LAS/LAZ reader and writer.

use super::*;
use crate::io::pointcloud::{inspect_point_cloud, read_point_cloud};
use crate::io::real_data;
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
    for (file, expect, color) in [
        ("TreeLS_extdata/pine.laz", 73_851, false),
        ("PyTLidar_trees/tree_1.las", 90_239, false),
        ("lidR_extdata/dbh.laz", 1_369, false),
    ] {
        let Some(path) = real_data(file) else {
            continue;
        };
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
    if let Some(path) = real_data("PyTLidar_trees/tree_1.las") {
        let tree = read_las(&path, &NoProgress).unwrap();
        assert!(tree.intensity.is_some());
        assert_eq!(inspect_las(&path).unwrap().point_format, 6);
    }
}

/// Re-encodes an uncompressed LAS 1.2 file as LAZ, through laz-rs's own compressor:
/// variable-size chunks of the given point counts (`Ok`) or fixed chunks (`Err(points per
/// chunk)`; the `las` writer always uses 50,000).
fn recompress(las: &[u8], chunks: Result<&[usize], u32>) -> Vec<u8> {
    let u16_at = |o: usize| u16::from_le_bytes([las[o], las[o + 1]]);
    let u32_at = |o: usize| u32::from_le_bytes([las[o], las[o + 1], las[o + 2], las[o + 3]]);
    let start = u32_at(96) as usize;
    let fmt = las[104] & 0x3f;
    let rec_len = u16_at(105);
    let base = Format::new(fmt).unwrap().len();
    let builder = laz::LazVlrBuilder::default()
        .with_point_format(fmt, rec_len - base)
        .unwrap();
    let vlr = match chunks {
        Ok(_) => builder.with_variable_chunk_size(),
        Err(chunk) => builder.with_fixed_chunk_size(chunk),
    }
    .build();
    let mut data = Vec::new();
    vlr.write_to(&mut data).unwrap();
    let mut out = las[..start].to_vec();
    out[104] |= 0x80;
    out[100..104].copy_from_slice(&(u32_at(100) + 1).to_le_bytes());
    out[96..100].copy_from_slice(&(start as u32 + 54 + data.len() as u32).to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    let mut user = [0u8; 16];
    user[..14].copy_from_slice(b"laszip encoded");
    out.extend_from_slice(&user);
    out.extend_from_slice(&22204u16.to_le_bytes());
    out.extend_from_slice(&(data.len() as u16).to_le_bytes());
    out.extend_from_slice(&[0u8; 32]);
    out.extend_from_slice(&data);
    let mut cursor = std::io::Cursor::new(out);
    cursor.set_position(cursor.get_ref().len() as u64);
    let mut c = laz::LasZipCompressor::new(cursor, vlr).unwrap();
    match chunks {
        Ok(sizes) => {
            let mut rest = &las[start..];
            for &k in sizes {
                let (chunk, r) = rest.split_at(k * usize::from(rec_len));
                c.compress_many(chunk).unwrap();
                c.finish_current_chunk().unwrap();
                rest = r;
            }
            assert!(rest.is_empty(), "chunk sizes must cover every point");
        }
        Err(_) => c.compress_many(&las[start..]).unwrap(),
    }
    c.done().unwrap();
    c.into_inner().into_inner()
}

/// A cloud of `n` points on a slanted sheet, colour and intensity varying per point.
fn big_sample(n: usize) -> PointCloud {
    PointCloud {
        offset: DVec3::new(431_200.0, 5_300_100.0, 212.0),
        positions: (0..n)
            .map(|i| {
                let f = i as f32;
                Vec3::new((f * 0.37) % 61.0, (f * 0.011) % 47.0, (f * 0.003) % 9.0)
            })
            .collect(),
        colors: Some(
            (0..n)
                .map(|i| [(i % 251) as u8, (i / 7 % 256) as u8, 255 - (i % 13) as u8])
                .collect(),
        ),
        intensity: Some((0..n).map(|i| (i * 37 % 65_536) as u16).collect()),
        format: CloudFormat::Las,
    }
}

/// `cloud` as the LAZ file `dir/name` with the chunk layout `chunks` ([`recompress`]), from
/// its uncompressed LAS `dir/src.las`.
fn laz_file(
    dir: &Path,
    name: &str,
    cloud: &PointCloud,
    chunks: Result<&[usize], u32>,
) -> std::path::PathBuf {
    let las = dir.join("src.las");
    write_las(&las, cloud, false).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, recompress(&std::fs::read(&las).unwrap(), chunks)).unwrap();
    path
}

/// The fused reader's cloud, which must exist (the file is one it handles).
fn fused(path: &Path) -> PointCloud {
    let info = inspect_las(path).unwrap();
    fused::read_laz_fused(path, &info, &NoProgress)
        .unwrap()
        .expect("the fused reader takes this file")
}

fn crate_path(path: &Path) -> PointCloud {
    read_las_sequential(path, &inspect_las(path).unwrap(), &NoProgress).unwrap()
}

fn assert_identical(a: &PointCloud, b: &PointCloud, what: &str) {
    assert_eq!(a.offset, b.offset, "{what}");
    assert_eq!(a.len(), b.len(), "{what}");
    assert!(a.positions == b.positions, "{what}: positions differ");
    assert_eq!(a.colors, b.colors, "{what}");
    assert_eq!(a.intensity, b.intensity, "{what}");
    assert_eq!(a.format, b.format, "{what}");
}

#[test]
fn fused_laz_reader_matches_the_las_crate_on_small_partial_chunks() {
    let dir = tempfile::tempdir().unwrap();
    let truth = big_sample(70_500);
    // 70,500 points in chunks of 5,000: 15 chunks, the last one holding 500.
    let path = laz_file(dir.path(), "c5000.laz", &truth, Err(5_000));
    let a = fused(&path);
    assert_identical(&a, &crate_path(&path), "chunks of 5,000");
    assert_identical(&a, &read_las(&path, &NoProgress).unwrap(), "read_las");
    assert_eq!(a.offset, truth.offset);
    assert_close(&truth, &a);
}

#[test]
fn fused_laz_reader_matches_the_las_crate_on_variable_size_chunks() {
    let dir = tempfile::tempdir().unwrap();
    let truth = big_sample(66_500);
    // Point counts come from the chunk table; the origin rule's first 65,536 points end
    // inside the last chunk.
    let sizes = [7_000, 13, 30_000, 1, 29_486];
    let path = laz_file(dir.path(), "var.laz", &truth, Ok(&sizes));
    let a = fused(&path);
    assert_identical(&a, &crate_path(&path), "variable-size chunks");
    assert_close(&truth, &a);
}

/// A LAS writer of `version` and point format `fmt` at millimetre scale, x and y offset by
/// `origin` (metres).
fn las_writer(
    path: &Path,
    version: (u8, u8),
    fmt: Format,
    origin: (f64, f64),
) -> ::las::Writer<BufWriter<File>> {
    let mut b = Builder::from(version);
    b.point_format = fmt;
    let t = |offset: f64| Transform {
        scale: 0.001,
        offset,
    };
    b.transforms = Vector {
        x: t(origin.0),
        y: t(origin.1),
        z: t(0.0),
    };
    ::las::Writer::new(
        BufWriter::new(File::create(path).unwrap()),
        b.into_header().unwrap(),
    )
    .unwrap()
}

#[test]
fn fused_laz_reader_matches_the_las_crate_on_layered_format_7() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f7.laz");
    let mut fmt = Format::new(7).unwrap();
    fmt.is_compressed = true;
    let mut w = las_writer(&path, (1, 4), fmt, (640_000.0, 4_100_000.0));
    // 120,000 points: chunks of 50,000, the last one partial; GPS time and classification
    // vary so that the skipped layers hold data.
    let n = 120_000;
    for i in 0..n {
        let f = f64::from(i);
        w.write_point(Point {
            x: 640_000.0 + (f * 0.013) % 80.0,
            y: 4_100_000.0 + (f * 0.0007) % 90.0,
            z: 300.0 + (f * 0.29) % 25.0,
            intensity: (i % 4_000) as u16,
            gps_time: Some(f * 0.5),
            classification: ::las::point::Classification::new((i % 10) as u8).unwrap(),
            color: Some(Color::new(
                (i % 65_536) as u16,
                (i * 3 % 65_536) as u16,
                (i * 7 % 65_536) as u16,
            )),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
    let a = fused(&path);
    assert_eq!(a.len(), n as usize);
    assert!(a.colors.is_some() && a.intensity.is_some());
    assert_identical(&a, &crate_path(&path), "point format 7");
    assert_matches_laz_rs(&a, &path, "point format 7");
}

#[test]
fn fused_laz_reader_matches_the_las_crate_on_real_files() {
    for file in [
        "TreeLS_extdata/pine.laz",
        "TreeLS_extdata/pine_plot.laz",
        "TreeLS_extdata/spruce.laz",
        "lidR_extdata/Megaplot.laz",
        "lidR_extdata/MixedConifer.laz",
        "lidR_extdata/Topography.laz",
        "lidR_extdata/dbh.laz",
    ] {
        let Some(path) = real_data(file) else {
            continue;
        };
        let a = fused(&path);
        assert_identical(&a, &crate_path(&path), file);
        assert_matches_laz_rs(&a, &path, file);
    }
}

/// `cloud` against the same file read point by point through the `las` crate (laz-rs's own
/// decoders, GPS time included): an independent reference for both of Sylva's LAZ paths.
fn assert_matches_laz_rs(cloud: &PointCloud, path: &Path, what: &str) {
    let all = ::las::Reader::from_path(path).unwrap().read_all().unwrap();
    let mut rgb = Vec::new();
    let mut n = 0;
    for (i, p) in all.points().enumerate() {
        let p = p.unwrap();
        let d = (cloud.world(i) - DVec3::new(p.x, p.y, p.z))
            .abs()
            .max_element();
        assert!(d < 1e-4, "{what}: point {i} off by {d} m");
        if let Some(int) = &cloud.intensity {
            assert_eq!(int[i], p.intensity, "{what}: intensity of point {i}");
        }
        rgb.extend(p.color.map(|c| [c.red, c.green, c.blue]));
        n += 1;
    }
    assert_eq!(n, cloud.len(), "{what}");
    // 16-bit colour becomes 8-bit by one rule for the whole cloud.
    let want = (!rgb.is_empty()).then(|| colors_to_u8(&rgb));
    assert!(cloud.colors == want, "{what}: colours differ");
}

#[test]
fn fused_laz_reader_leaves_wrong_header_bounds_to_the_las_crate() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("b.laz");
    write_las(&path, &big_sample(2_000), true).unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[179..227].fill(0); // max/min x, y, z = 0: a valid box that misses every point
    std::fs::write(&path, &bytes).unwrap();
    let info = inspect_las(&path).unwrap();
    assert!(
        fused::read_laz_fused(&path, &info, &NoProgress)
            .unwrap()
            .is_none()
    );
    let c = read_las(&path, &NoProgress).unwrap();
    assert_eq!(c.offset, DVec3::new(431_200.0, 5_300_100.0, 212.0));
    assert_close(&big_sample(2_000), &c);
}

#[test]
fn truncated_laz_is_a_format_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = laz_file(dir.path(), "t.laz", &big_sample(20_000), Err(2_000));
    let full = std::fs::read(&path).unwrap();
    // Cut in the middle: the chunk table at the end is gone.
    std::fs::write(&path, &full[..full.len() / 2]).unwrap();
    let e = read_las(&path, &NoProgress).unwrap_err();
    assert!(matches!(e, IoError::Format { .. }), "{e}");
    assert!(e.to_string().contains("truncated"), "{e}");
    // Chunk bytes missing but the table intact: cut 20,000 bytes from the point data and
    // move the table offset back by as much.
    let start = u32::from_le_bytes(full[96..100].try_into().unwrap()) as usize;
    let table = i64::from_le_bytes(full[start..start + 8].try_into().unwrap());
    let mut cut = full[..start + 8].to_vec();
    cut[start..start + 8].copy_from_slice(&(table - 20_000).to_le_bytes());
    cut.extend_from_slice(&full[start + 8 + 20_000..]);
    std::fs::write(&path, &cut).unwrap();
    let e = read_las(&path, &NoProgress).unwrap_err();
    assert!(matches!(e, IoError::Format { .. }), "{e}");
    assert!(e.to_string().contains("truncated"), "{e}");
}

/// Counts progress calls and cancels after the first.
#[derive(Default)]
struct CancelAfterFirst {
    calls: std::sync::atomic::AtomicUsize,
    last: std::sync::Mutex<f64>,
}

impl Progress for CancelAfterFirst {
    fn set(&self, fraction: f64) {
        self.calls
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if let Ok(mut l) = self.last.lock() {
            *l = l.max(fraction);
        }
    }
    fn is_cancelled(&self) -> bool {
        self.calls.load(std::sync::atomic::Ordering::Relaxed) > 0
    }
}

#[test]
fn fused_laz_reader_reports_progress_and_stops_on_cancel() {
    let dir = tempfile::tempdir().unwrap();
    let path = laz_file(dir.path(), "p.laz", &big_sample(20_000), Err(1_000));
    let p = CancelAfterFirst::default();
    assert!(matches!(read_las(&path, &p), Err(IoError::Cancelled)));
    // 20 chunks; cancelled after the first one finished, so at most one per core more ran.
    let calls = p.calls.load(std::sync::atomic::Ordering::Relaxed);
    assert!(
        (1..=1 + rayon::current_num_threads()).contains(&calls),
        "{calls} chunks ran"
    );
    let last = p.last.lock().map(|l| *l).unwrap_or(0.0);
    assert!(last > 0.0 && last < 1.0, "{last}");
}

/// A 3-point LAS 1.2 file whose header carries `vlrs`.
fn las_with_vlrs(path: &Path, vlrs: Vec<::las::Vlr>) {
    let mut builder = ::las::Builder::from((1, 2));
    builder.vlrs = vlrs;
    let t = |offset: f64| ::las::Transform {
        scale: 0.001,
        offset,
    };
    builder.transforms = ::las::Vector {
        x: t(500_000.0),
        y: t(3_000_000.0),
        z: t(0.0),
    };
    let header = builder.into_header().unwrap();
    let mut w = ::las::Writer::from_path(path, header).unwrap();
    for i in 0..3 {
        w.write_point(::las::Point {
            x: 500_000.0 + f64::from(i),
            y: 3_000_000.0,
            z: 10.0,
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

fn projection_vlr(record_id: u16, data: Vec<u8>) -> ::las::Vlr {
    ::las::Vlr {
        user_id: "LASF_Projection".into(),
        record_id,
        description: String::new(),
        data,
    }
}

#[test]
fn inspection_names_the_crs_the_projection_records_declare() {
    let dir = tempfile::tempdir().unwrap();
    let keys = |code: u16| -> Vec<u8> {
        [1u16, 1, 0, 2, 1024, 0, 1, 1, 3072, 0, 1, code]
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .collect()
    };
    let utm = dir.path().join("utm.las");
    las_with_vlrs(&utm, vec![projection_vlr(34735, keys(32649))]);
    let info = inspect_las(&utm).unwrap();
    assert_eq!(info.crs.as_deref(), Some("EPSG:32649"));
    assert_eq!(info.crs_problem, None);

    let wkt = dir.path().join("wkt.las");
    let text = crate::io::crs::Crs::from_epsg(25832).unwrap().definition;
    las_with_vlrs(&wkt, vec![projection_vlr(2112, text.into_bytes())]);
    assert_eq!(
        inspect_las(&wkt).unwrap().crs.as_deref(),
        Some("EPSG:25832")
    );

    let none = dir.path().join("none.las");
    las_with_vlrs(&none, Vec::new());
    let info = inspect_las(&none).unwrap();
    assert_eq!((info.crs, info.crs_problem), (None, None));

    // A user-defined CRS spelled out key by key is not read; the file is still accepted.
    let custom = dir.path().join("custom.las");
    las_with_vlrs(&custom, vec![projection_vlr(34735, keys(32767))]);
    let info = inspect_las(&custom).unwrap();
    assert_eq!(info.crs, None);
    assert!(
        info.crs_problem.as_deref().unwrap_or("").contains("--crs"),
        "{info:?}"
    );
}

/// What Sylva writes, it reads back: a CRS with an EPSG code as GeoTIFF keys, and none as
/// none; a PROJ string, which LAS cannot hold, is refused.
#[test]
fn a_written_crs_is_declared_and_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let utm = crate::io::crs::Crs::from_epsg(32649).unwrap();
    let path = dir.path().join("utm.laz");
    write_las_with_crs(&path, &sample(false), true, Some(&utm)).unwrap();
    assert_eq!(read_crs(&path).unwrap().unwrap(), Some(utm));
    assert_eq!(
        inspect_las(&path).unwrap().crs.as_deref(),
        Some("EPSG:32649")
    );
    let custom = crate::io::crs::Crs::parse("+proj=utm +zone=33 +datum=WGS84 +units=m").unwrap();
    let path = dir.path().join("custom.las");
    let err = write_las_with_crs(&path, &sample(false), false, Some(&custom)).unwrap_err();
    assert!(err.to_string().contains("EPSG:<code> or WKT"), "{err}");
    let path = dir.path().join("none.las");
    write_las(&path, &sample(false), false).unwrap();
    assert_eq!(read_crs(&path).unwrap().unwrap(), None);
}

/// `n` GPS times that reach every branch of the GPS-time decoder: runs of repeats, steady
/// steps, multiples of the step from −12 to 600 (every integer-decoder context), two and four
/// interleaved sequences far apart (switches by 1, 2 and 3), five (more than the decoder
/// keeps: new sequences) and random jumps.
fn gps_times(n: usize) -> Vec<f64> {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut seqs = [1.0e3, 4.0e5, 2.5e8, 7.7e6, 9.9e8];
    let dt = 1e-5;
    (0..n)
        .map(|i| match (i / 2_500) % 7 {
            0 => seqs[0] + (i / 7) as f64 * dt,
            1 => {
                seqs[0] += dt;
                seqs[0]
            }
            2 => {
                // A step of 1e-8 s keeps 600 of them within 32 bits of the time's f64 bits.
                seqs[0] += ((next() % 613) as f64 - 12.0) * 1e-8;
                seqs[0]
            }
            3 => {
                let s = i % 2 * 2;
                seqs[s] += dt;
                seqs[s]
            }
            4 => {
                let s = (next() % 4) as usize;
                seqs[s] += dt * (1 + next() % 3) as f64;
                seqs[s]
            }
            5 => {
                let s = i % 5;
                seqs[s] += dt;
                seqs[s]
            }
            _ => (next() % 1_000_000_000) as f64 * 1e-3,
        })
        .collect()
}

/// An uncompressed LAS 1.2 file of point format `fmt` (1 or 3) whose points carry
/// [`gps_times`].
fn las_with_gps(path: &Path, fmt: u8, n: usize) {
    let mut w = las_writer(
        path,
        (1, 2),
        Format::new(fmt).unwrap(),
        (500_000.0, 6_000_000.0),
    );
    for (i, gps) in gps_times(n).into_iter().enumerate() {
        let f = i as f64;
        w.write_point(Point {
            x: 500_000.0 + (f * 0.017) % 70.0,
            y: 6_000_000.0 + (f * 0.0009) % 60.0,
            z: 100.0 + (f * 0.31) % 30.0,
            intensity: (i * 7 % 5_000) as u16,
            gps_time: Some(gps),
            color: (fmt == 3).then(|| Color::new(i as u16, (i * 5) as u16, 9)),
            ..Default::default()
        })
        .unwrap();
    }
    w.close().unwrap();
}

/// Every record of a point-wise LAZ file as laz-rs's own decoder gives it (all fields, GPS
/// time included): the reference for Sylva's decoder.
fn laz_rs_records(bytes: &[u8]) -> Vec<u8> {
    let start = u32::from_le_bytes(bytes[96..100].try_into().unwrap()) as u64;
    let rec_len = u16::from_le_bytes([bytes[105], bytes[106]]) as usize;
    let n = u32::from_le_bytes(bytes[107..111].try_into().unwrap()) as usize;
    let vlr = laszip_vlr(bytes);
    let mut src = std::io::Cursor::new(bytes);
    src.set_position(start);
    let mut d = laz::LasZipDecompressor::new(src, laz::LazVlr::from_buffer(vlr).unwrap()).unwrap();
    let mut out = vec![0u8; n * rec_len];
    d.decompress_many(&mut out).unwrap();
    out
}

/// The LASzip VLR's body in a LAS 1.2 file (the first VLR, as [`recompress`] writes it).
fn laszip_vlr(bytes: &[u8]) -> &[u8] {
    let at = bytes
        .windows(14)
        .position(|w| w == b"laszip encoded")
        .expect("LASzip VLR")
        - 2;
    let len = u16::from_le_bytes([bytes[at + 20], bytes[at + 21]]) as usize;
    &bytes[at + 54..at + 54 + len]
}

#[test]
fn sylvas_gps_time_decoder_matches_laz_rs_on_every_branch() {
    let dir = tempfile::tempdir().unwrap();
    let n = 40_000;
    for fmt in [1u8, 3] {
        let las = dir.path().join(format!("f{fmt}.las"));
        las_with_gps(&las, fmt, n);
        let raw = std::fs::read(&las).unwrap();
        for (what, chunks) in [
            ("fixed chunks of 3,000", Err(3_000)),
            ("variable chunks", Ok(&[9_000usize, 1, 17_000, 13_999][..])),
        ] {
            let bytes = recompress(&raw, chunks);
            let path = dir.path().join(format!("f{fmt}.laz"));
            std::fs::write(&path, &bytes).unwrap();
            let truth = laz_rs_records(&bytes);
            let rec_len = truth.len() / n;
            // Every time made it through (the file holds the times written).
            let times: Vec<f64> = truth
                .chunks_exact(rec_len)
                .map(|r| f64::from_le_bytes(r[20..28].try_into().unwrap()))
                .collect();
            assert!(times == gps_times(n), "{what}: laz-rs round trip");
            let start = u32::from_le_bytes(bytes[96..100].try_into().unwrap()) as u64;
            // The sequential reader, in batches that cross chunk boundaries.
            let mut seq = pointwise::LazRecords::open(
                &path,
                laszip_vlr(&bytes),
                start,
                (n as u64, rec_len),
                fmt == 3,
            )
            .unwrap();
            let (mut got, mut buf) = (Vec::new(), Vec::new());
            while seq.fill(4_321, &mut buf).unwrap() > 0 {
                got.extend_from_slice(&buf);
            }
            assert!(
                got == truth,
                "format {fmt}, {what}: sequential records differ"
            );
            // The fused reader's chunk decoder, chunk by chunk from the table.
            let vlr = laz::LazVlr::from_buffer(laszip_vlr(&bytes)).unwrap();
            let mut src = std::io::Cursor::new(&bytes[..]);
            src.set_position(start);
            let table = laz::laszip::ChunkTable::read_from(&mut src, &vlr).unwrap();
            let (mut at, mut first) = (start as usize + 8, 0usize);
            let mut chunked = vec![0u8; truth.len()];
            for (k, e) in table.as_ref().iter().enumerate() {
                let points = if vlr.uses_variable_size_chunks() {
                    e.point_count as usize
                } else {
                    (n - first).min(3_000)
                };
                let end = at + e.byte_count as usize;
                pointwise::decode_pointwise_chunk(
                    &bytes[at..end],
                    vlr.items(),
                    &mut chunked[first * rec_len..(first + points) * rec_len],
                )
                .unwrap_or_else(|e| panic!("format {fmt}, {what}, chunk {k}: {e}"));
                (at, first) = (end, first + points);
            }
            assert_eq!(first, n);
            assert!(
                chunked == truth,
                "format {fmt}, {what}: chunk records differ"
            );
            // And the whole reader.
            let cloud = read_las(&path, &NoProgress).unwrap();
            assert_eq!(cloud.len(), n);
        }
    }
}

/// A GPS-time stream of one raw first time and then `symbols` of the zero-difference model,
/// as a LASzip encoder would write them (one 8-byte field per record).
fn gps_stream(symbols: &[u32]) -> Vec<u8> {
    let mut out = 1234.5f64.to_le_bytes().to_vec();
    let mut enc = laz::encoders::ArithmeticEncoder::new(Vec::new());
    let mut zero_diff = laz::models::ArithmeticModelBuilder::new(6).build();
    for &s in symbols {
        enc.encode_symbol(&mut zero_diff, s).unwrap();
    }
    enc.done().unwrap();
    out.extend_from_slice(&enc.into_inner());
    out
}

#[test]
fn a_gps_time_stream_that_switches_sequence_without_end_is_refused() {
    let item = laz::LazItemRecordBuilder::new()
        .add_item(laz::LazItemType::GpsTime)
        .build();
    assert_eq!(item[0].version(), 2);
    let decode = |symbols: &[u32], points: usize| {
        let mut out = vec![0u8; 8 * points];
        pointwise::decode_pointwise_chunk(&gps_stream(symbols), &item, &mut out).map(|()| out)
    };
    // Symbol 0 repeats the time; 3–5 switch by 1–3 sequences (every slot holds 0.0 but the
    // first). One switch then a repeat: the second point is the other sequence's time, 0.
    let out = decode(&[0, 3, 0], 3).unwrap();
    let t = |k: usize| f64::from_le_bytes(out[8 * k..8 * k + 8].try_into().unwrap());
    assert_eq!((t(0), t(1), t(2)), (1234.5, 1234.5, 0.0));
    // MAX_SWITCHES switches for one point are decoded; one more is refused, not recursed.
    let k = pointwise::MAX_SWITCHES as usize;
    assert!(decode(&[[3].repeat(k), vec![0]].concat(), 2).is_ok());
    let e = decode(&[4].repeat(100_000), 2).unwrap_err();
    assert!(e.contains("corrupt GPS time"), "{e}");
}

/// The inputs that overflowed laz-rs's recursive GPS-time decoder (issue 43) are refused
/// with an error, on a thread with a 256 KiB stack (an eighth of a worker thread's).
#[test]
fn fuzzed_gps_time_streams_are_refused_on_a_small_stack() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/regressions/laz");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name().is_some_and(|n| {
                let n = n.to_string_lossy();
                n.starts_with("gps-recursion") || n.starts_with("layered-pointwise-items")
            })
        })
        .collect();
    files.sort();
    assert_eq!(files.len(), 20, "the 20 kept inputs");
    let scratch = tempfile::tempdir().unwrap();
    let errors = std::thread::Builder::new()
        .stack_size(256 << 10)
        .spawn(move || {
            files
                .iter()
                .map(|f| {
                    let path = scratch.path().join("in.laz");
                    std::fs::copy(f, &path).unwrap();
                    match read_las(&path, &NoProgress) {
                        Ok(c) => panic!("{} read as {} points", f.display(), c.len()),
                        Err(e) => e.to_string(),
                    }
                })
                .collect::<Vec<_>>()
        })
        .unwrap()
        .join()
        .unwrap();
    let gps = errors
        .iter()
        .filter(|e| e.contains("corrupt GPS time"))
        .count();
    assert!(gps > 0, "{errors:#?}");
    // Layered compression declared over point-wise items (which would reach laz-rs's
    // recursive decoder by another door) is refused before decoding.
    let layered = errors
        .iter()
        .filter(|e| e.contains("declares layered compression"))
        .count();
    assert_eq!(layered, 2, "{errors:#?}");
}
