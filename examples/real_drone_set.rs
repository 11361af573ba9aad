//! Makes `tests/data/real_drone/`: the small real-photo job CI runs end to end (issue 39),
//! from the Brighton Beach drone flight (pierotofy/drone_dataset_brighton_beach, BSD-2-Clause).
//!
//! `cargo run --release --example real_drone_set -- SRC OUT [LONGEST_SIDE_PX] [VOXEL_M]`, with
//! SRC the upstream folder (../shared/data/real_photos/brighton_beach: 18 nadir photos, JPEG
//! 4000 × 2250 with EXIF GPS, and `model.laz`, OpenDroneMap's photogrammetric cloud of the
//! same flight, EPSG:32615). It writes to OUT:
//!
//! - `photos/*.JPG`: every photo scaled to LONGEST_SIDE_PX (default 800) on its longest side
//!   (Lanczos), JPEG quality 85, with the photo's own EXIF tags for its camera, focal length,
//!   time and GPS position (its maker note and thumbnail, 50 kB a photo, are left out);
//! - `cloud.laz`: `model.laz` thinned to one point per VOXEL_M (default 0.1 m) voxel (the
//!   centroid and mean colour of its points), with the same CRS.
//!
//! Both are the real data, only smaller: the GPS tags are the drone's, the cloud is the
//! photogrammetry of the same flight.

use std::path::{Path, PathBuf};

use image::ImageEncoder;
use sylva::io::pointcloud::{self, PointCloud};
use sylva::progress::NoProgress;

/// The EXIF tags kept: the camera (COLMAP's focal-length prior reads them) and the GPS
/// position. The rest (a 50 kB maker note and thumbnail per photo) is dropped.
const KEPT: [exif::Tag; 13] = [
    exif::Tag::Make,
    exif::Tag::Model,
    exif::Tag::FocalLength,
    exif::Tag::FocalLengthIn35mmFilm,
    exif::Tag::DateTimeOriginal,
    exif::Tag::GPSVersionID,
    exif::Tag::GPSLatitudeRef,
    exif::Tag::GPSLatitude,
    exif::Tag::GPSLongitudeRef,
    exif::Tag::GPSLongitude,
    exif::Tag::GPSAltitudeRef,
    exif::Tag::GPSAltitude,
    exif::Tag::GPSMapDatum,
];

/// A slim EXIF block (TIFF bytes) of the [`KEPT`] tags of a JPEG's own EXIF.
fn exif_of(jpeg: &[u8]) -> Result<Vec<u8>, Box<dyn std::error::Error>> {
    let exif = exif::Reader::new().read_from_container(&mut std::io::Cursor::new(jpeg))?;
    let mut writer = exif::experimental::Writer::new();
    let fields: Vec<&exif::Field> = exif
        .fields()
        .filter(|f| f.ifd_num == exif::In::PRIMARY && KEPT.contains(&f.tag))
        .collect();
    for f in &fields {
        writer.push_field(f);
    }
    let mut out = std::io::Cursor::new(Vec::new());
    writer.write(&mut out, exif.little_endian())?;
    Ok(out.into_inner())
}

fn photos(src: &Path, out: &Path, longest: u32) -> Result<usize, Box<dyn std::error::Error>> {
    let dir = sylva::io::photos::find_photos_dir(src)?;
    let names = sylva::io::photos::list_photos(&dir)?;
    std::fs::create_dir_all(out)?;
    for name in &names {
        let bytes = std::fs::read(dir.join(name))?;
        let exif = exif_of(&bytes).map_err(|e| format!("{name}: {e}"))?;
        let img = image::load_from_memory(&bytes)?;
        let small = img.resize(longest, longest, image::imageops::FilterType::Lanczos3);
        let rgb = small.to_rgb8();
        let mut file = std::io::BufWriter::new(std::fs::File::create(out.join(name))?);
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut file, 85);
        enc.set_exif_metadata(exif)?;
        enc.write_image(
            rgb.as_raw(),
            rgb.width(),
            rgb.height(),
            image::ExtendedColorType::Rgb8,
        )?;
    }
    Ok(names.len())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (src, out) = match args.as_slice() {
        [s, o, ..] => (PathBuf::from(s), PathBuf::from(o)),
        _ => return Err("usage: real_drone_set SRC OUT [LONGEST_SIDE_PX] [VOXEL_M]".into()),
    };
    let longest: u32 = args.get(2).map_or(Ok(800), |v| v.parse())?;
    let voxel: f32 = args.get(3).map_or(Ok(0.1), |v| v.parse())?;
    let n = photos(&src.join("images"), &out.join("photos"), longest)?;

    let laz = src.join("model.laz");
    let cloud = pointcloud::read_point_cloud(&laz, &NoProgress)?;
    let crs = pointcloud::declared_crs(&laz)??.ok_or("model.laz declares no CRS")?;
    let thin = sylva::geom::voxel_downsample(
        &cloud.positions,
        cloud.colors.as_deref(),
        voxel,
        &NoProgress,
    )?;
    let small = PointCloud {
        offset: cloud.offset,
        positions: thin.positions,
        colors: thin.colours,
        intensity: None,
        format: cloud.format,
    };
    sylva::io::las::write_las_with_crs(&out.join("cloud.laz"), &small, true, Some(&crs))?;
    println!(
        "{n} photos at {longest} px; {} of {} points at {voxel} m voxels",
        small.positions.len(),
        cloud.positions.len()
    );
    Ok(())
}
