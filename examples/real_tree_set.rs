//! Makes `tests/data/real_tree/`: the small real-photo job CI runs end to end (issue 39).
//!
//! `cargo run --release --example real_tree_set -- SRC OUT`, with SRC the upstream
//! `nerfpl_tree/tree` folder (../shared/data/real_photos/nerfpl_tree/tree: 18 phone photos of
//! one real trunk, PNG 600×800, and its COLMAP model). It writes to OUT:
//!
//! - `photos/*.jpg`: the 18 photos as JPEG (quality 80), each with an EXIF GPS position: its
//!   camera centre in the upstream model, moved into the cloud's frame below, as an RTK
//!   receiver would give it (no noise added);
//! - `cloud.laz`: the upstream model's 3-D points in that frame, standing in for the LiDAR
//!   scan, with its CRS (EPSG:32615, UTM 15 N);
//! - `truth.json`: the similarity from the upstream model's frame to the cloud's.
//!
//! The frame: "up" is the mean of the cameras' up vectors (the photos were taken upright),
//! the scale puts the cameras' median distance from the points' median at 3 m (the upstream
//! model has no metric scale), and the origin lies at 500 123 E, 5 187 456 N, 200 m.
//! Stage `sfm` makes its own model of the photos, in a frame of its own; stage `register`
//! finds it from the GPS tags, as for a georeferenced drone flight.

use std::path::PathBuf;

use glam::{DMat3, DVec3, Vec3};
use image::ImageEncoder;
use sylva::geom::register::camera_ray;
use sylva::io::colmap;
use sylva::io::crs::Crs;
use sylva::io::gps::{self, GpsFix};
use sylva::io::pointcloud::{CloudFormat, PointCloud};
use sylva::progress::NoProgress;

/// Where the cloud's frame puts the upstream model's origin (UTM 15 N, metres).
const ORIGIN: DVec3 = DVec3::new(500_123.0, 5_187_456.0, 200.0);
/// Median camera distance from the points' median after scaling, metres.
const CAMERA_DISTANCE_M: f64 = 3.0;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [src, out] = args.as_slice() else {
        return Err("usage: real_tree_set SRC OUT".into());
    };
    let (src, out) = (PathBuf::from(src), PathBuf::from(out));
    let project = colmap::find_project(&src)?;
    let model = colmap::read_model(&project.sparse_dir, &NoProgress)?;
    let images = project.images_dir.ok_or("no images/ folder")?;

    // Up: the mean of the cameras' up vectors (camera y points down the image).
    let mut up = DVec3::ZERO;
    let mut centres = Vec::new();
    for im in model.images.values() {
        let q = glam::DQuat::from_xyzw(im.qvec[1], im.qvec[2], im.qvec[3], im.qvec[0]);
        let world_from_cam = DMat3::from_quat(q).transpose();
        up -= world_from_cam * DVec3::Y;
        centres.push((im.name.clone(), camera_ray(im.qvec, im.tvec).0));
    }
    let up = up.normalize();
    let level = DMat3::from_quat(glam::DQuat::from_rotation_arc(up, DVec3::Z));
    // The points' median, and the cameras' median distance from it.
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let pts: Vec<DVec3> = model.points.iter().map(|p| p.xyz).collect();
    let centre = DVec3::new(
        median(pts.iter().map(|p| p.x).collect()),
        median(pts.iter().map(|p| p.y).collect()),
        median(pts.iter().map(|p| p.z).collect()),
    );
    let dist = median(
        centres
            .iter()
            .map(|(_, c)| (*c - centre).length())
            .collect(),
    );
    let scale = CAMERA_DISTANCE_M / dist;
    let to_cloud = |p: DVec3| ORIGIN + level * ((p - centre) * scale);

    let crs = Crs::from_epsg(32615)?;
    std::fs::create_dir_all(out.join("photos"))?;
    for (name, c) in &centres {
        let p = to_cloud(*c);
        let mut lonlat = [(p.x, p.y)];
        crs.to_wgs84(&mut lonlat)?;
        let fix = GpsFix {
            lon: lonlat[0].0,
            lat: lonlat[0].1,
            alt: Some(p.z),
        };
        let rgb = image::open(images.join(name))?.to_rgb8();
        let jpg = out
            .join("photos")
            .join(PathBuf::from(name).with_extension("jpg"));
        let mut file = std::io::BufWriter::new(std::fs::File::create(&jpg)?);
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut file, 80);
        enc.set_exif_metadata(gps::exif_block(&fix)?)?;
        enc.write_image(
            rgb.as_raw(),
            rgb.width(),
            rgb.height(),
            image::ExtendedColorType::Rgb8,
        )?;
    }
    let positions: Vec<Vec3> = pts
        .iter()
        .map(|p| (to_cloud(*p) - ORIGIN).as_vec3())
        .collect();
    let cloud = PointCloud {
        offset: ORIGIN,
        positions,
        colors: None,
        intensity: None,
        format: CloudFormat::Las,
    };
    sylva::io::las::write_las_with_crs(&out.join("cloud.laz"), &cloud, true, Some(&crs))?;
    let truth = serde_json::json!({
        "source": "RayanBabar/NeRF_PL_TCNN @ 438fda1bce04f226e25d2232f8ee30661eee3efd, tree/",
        "scale": scale,
        "level_rotation_rows": level.transpose().to_cols_array_2d(),
        "model_centre": [centre.x, centre.y, centre.z],
        "origin": [ORIGIN.x, ORIGIN.y, ORIGIN.z],
        "crs": "EPSG:32615",
        "points": cloud.positions.len(),
        "photos": centres.len(),
    });
    std::fs::write(out.join("truth.json"), serde_json::to_vec_pretty(&truth)?)?;
    println!(
        "{} photos, {} points, scale {scale:.4} into {}",
        centres.len(),
        cloud.positions.len(),
        out.display()
    );
    Ok(())
}
