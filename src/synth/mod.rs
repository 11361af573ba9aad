//! `sylva synth`: a deterministic synthetic forest plot with everything the pipeline needs and
//! everything it should recover.
//!
//! One seed drives a scene (terrain, stones, shrubs, trees of [`presets`]), a handheld SLAM
//! LiDAR scan of it ([`lidar`]), a UAV image set rendered from the same scene with a COLMAP
//! model in a random SfM frame ([`camera`], [`colmap_export`]), and the truth ([`truth`]):
//! the SfM→LiDAR similarity, stem positions and tape DBH, control point pairs, per-point
//! wood/leaf/ground labels and the held-out test views. The same parameters give
//! byte-identical files on the same platform: parallel work is split into items with their
//! own random streams and collected in order.
//!
//! Output layout under `out/`: `lidar.laz`, `labels.bin`, `colmap/images/`,
//! `colmap/sparse/0/` (text, or binary), `control_points.csv`, `field_dbh.csv`, `truth.json`.
//!
//! [`lidar_plot`] gives the scene's LiDAR side alone, in memory (the scan, its labels and the
//! trees' truth, no photos and no files): the generated plot of the forest room's tests and
//! of `examples/inventory_bench.rs`.

pub mod bvh;
pub mod camera;
pub mod colmap_export;
pub mod layout;
pub mod lidar;
pub mod params;
pub mod presets;
pub mod rng;
pub mod scene;
pub mod shapes;
pub mod terrain;
pub mod trees;
pub mod truth;

#[cfg(test)]
mod tests;

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use glam::DVec3;
use image::ImageEncoder;
use rayon::prelude::*;

use crate::io::IoError;
use crate::io::colmap::{ColmapModel, write_binary, write_text};
use crate::io::crs::Crs;
use crate::io::gps::{self, GpsFix};
use crate::io::las::write_las_with_crs;
use crate::io::pointcloud::{CloudFormat, PointCloud};
use crate::progress::{Progress, SubProgress};

pub use params::{PhaseTiming, SynthError, SynthParams, SynthSummary};
pub use presets::Preset;

use camera::{Intrinsics, Lighting, View};
use colmap_export::{Candidate, ExportParams, Similarity};
use layout::{LayoutParams, Plot};

/// In-memory products, for tests.
#[cfg_attr(not(test), allow(dead_code))]
pub(crate) struct Artifacts {
    pub plot: Plot,
    pub views: Vec<View>,
    pub intrinsics: Intrinsics,
    pub model: ColmapModel,
}

/// Generates the plot into `out` (created if needed). See the module doc for the layout.
pub fn generate(
    params: &SynthParams,
    out: &Path,
    progress: &dyn Progress,
) -> Result<SynthSummary, SynthError> {
    run(params, out, progress).map(|(s, _)| s)
}

pub(crate) fn run(
    params: &SynthParams,
    out: &Path,
    progress: &dyn Progress,
) -> Result<(SynthSummary, Artifacts), SynthError> {
    params::check(params)?;
    let cfg = params.preset.config();
    let n_images = params.images.unwrap_or(cfg.images);
    let (width, height) = (
        params.width.unwrap_or(cfg.width),
        params.height.unwrap_or(cfg.height),
    );
    let offset = DVec3::from_array(params.geo_offset);
    let mkdir =
        |p: &Path| std::fs::create_dir_all(p).map_err(|e| SynthError::Io(IoError::io(p, e)));
    let images_dir = out.join("colmap").join("images");
    let sparse_dir = out.join("colmap").join("sparse").join("0");
    mkdir(&images_dir)?;
    mkdir(&sparse_dir)?;
    let cancelled = || {
        if progress.is_cancelled() {
            Err(SynthError::Cancelled)
        } else {
            Ok(())
        }
    };
    let mut timings = Vec::new();
    let mut clock = Instant::now();
    let mut lap = |name: &'static str, timings: &mut Vec<PhaseTiming>| {
        timings.push(PhaseTiming {
            phase: name,
            seconds: clock.elapsed().as_secs_f64(),
        });
        clock = Instant::now();
    };

    // 1. Scene.
    progress.log("synth: building the scene");
    let mut plot = layout::build_plot(&layout_params(params));
    let closure = layout::canopy_closure(&plot);
    lap("scene", &mut timings);
    cancelled()?;

    // 2. LiDAR (of the plot without its leaves for a leaf-off scan).
    progress.log("synth: scanning");
    let scan = scan_plot(params, &mut plot, &SubProgress::new(progress, 0.0, 0.4))?;
    lap("lidar", &mut timings);
    let n_points = scan.positions.len();
    let mut label_counts = [0usize; 4];
    scan.labels
        .iter()
        .for_each(|&l| label_counts[(l as usize).min(3)] += 1);
    truth::write_labels(&out.join("labels.bin"), &scan.labels)?;
    let cloud = PointCloud {
        offset,
        positions: scan.positions,
        colors: scan.colors,
        intensity: Some(scan.intensity),
        format: CloudFormat::Laz,
    };
    let crs = match params.gps_noise_m {
        Some(_) => {
            Some(Crs::from_epsg(GPS_EPSG).map_err(|e| SynthError::InvalidParams(e.to_string()))?)
        }
        None => None,
    };
    write_las_with_crs(&out.join("lidar.laz"), &cloud, true, crs.as_ref())?;
    drop(cloud);
    lap("laz", &mut timings);
    cancelled()?;

    // 3. Images.
    progress.log("synth: rendering images");
    let ext = if params.png { "png" } else { "jpg" };
    let views = camera::plan_flight(&plot, cfg.flight, n_images, params.seed, ext);
    let intr = Intrinsics::new(width, height, params.pinhole);
    let light = Lighting::from_seed(params.seed);
    let target_points = params.points3d.unwrap_or(cfg.points3d);
    let per_image = (2 * target_points).div_ceil(views.len().max(1)).max(8);
    let done = AtomicUsize::new(0);
    let img_progress = SubProgress::new(progress, 0.4, 0.5);
    let cands: Vec<Vec<Candidate>> = views
        .par_iter()
        .enumerate()
        .map(|(k, v)| {
            if progress.is_cancelled() {
                return Err(SynthError::Cancelled);
            }
            let pixels = camera::render(&plot.scene, &light, &intr, v, params.samples_per_pixel);
            let path = images_dir.join(&v.name);
            let exif = match (params.gps_noise_m, &crs) {
                (Some(sigma), Some(crs)) => Some(gps_exif(v, k, sigma, offset, crs, params.seed)?),
                _ => None,
            };
            encode(&path, &pixels, width, height, params.png, exif)?;
            let c = colmap_export::candidates(
                &plot.scene,
                &intr,
                v,
                k,
                per_image,
                &pixels,
                params.seed,
            );
            let n = done.fetch_add(1, Ordering::Relaxed) + 1;
            img_progress.set(n as f64 / views.len() as f64);
            Ok(c)
        })
        .collect::<Result<_, _>>()?;
    lap("images", &mut timings);

    // 4. SfM model.
    progress.log("synth: building the COLMAP model");
    let mut world_to_sfm =
        Similarity::random(&mut rng::Stream::new(params.seed, rng::domain::SFM, 0));
    if let Some(s) = params.sfm_scale {
        world_to_sfm.scale = s;
    }
    let cands: Vec<Candidate> = cands.into_iter().flatten().collect();
    let export = ExportParams {
        points3d: target_points,
        noise_m: params.sfm_noise_cm / 100.0,
        seed: params.seed,
    };
    let model =
        colmap_export::build_model(&plot.scene, &intr, &views, &cands, &world_to_sfm, &export);
    if params.binary {
        write_binary(&model, &sparse_dir)?;
    } else {
        write_text(&model, &sparse_dir)?;
    }
    lap("sfm", &mut timings);
    cancelled()?;

    // 5. Truth.
    // sfm → LiDAR file coordinates: the inverse of (scene → SfM), then + offset.
    let inv = world_to_sfm.inverse();
    let sfm_to_world = Similarity {
        translation: (DVec3::from_array(inv.translation) + offset).to_array(),
        ..inv
    };
    let file_to_sfm = sfm_to_world.inverse();
    let trees = truth::tree_records(&plot, offset);
    let pairs = truth::control_points(
        &plot,
        offset,
        &world_to_sfm,
        params.sfm_noise_cm / 100.0,
        params.seed,
    );
    truth::write_field_dbh(&out.join("field_dbh.csv"), &trees)?;
    truth::write_control_points(&out.join("control_points.csv"), &pairs)?;
    let names: Vec<String> = views.iter().map(|v| v.name.clone()).collect();
    let n_pairs = pairs.len();
    let record = truth::Truth {
        generator: "sylva synth",
        format_version: 1,
        preset: params.preset.name(),
        seed: params.seed,
        geo_offset: params.geo_offset,
        sfm_to_world,
        world_to_sfm: file_to_sfm,
        trees,
        stones: plot
            .stones
            .iter()
            .map(|s| (s.top + offset).to_array())
            .collect(),
        control_points: pairs,
        test_images: truth::test_images(&names),
        labels: truth::LabelsRecord {
            file: "labels.bin",
            encoding: "one u8 per LiDAR point, in lidar.laz order",
            classes: truth::LABEL_NAMES,
            counts: label_counts,
        },
        plot_radius_m: plot.radius_m,
        plot_center: offset.to_array(),
        canopy_closure: closure,
        lidar: serde_json::json!({
            "file": "lidar.laz",
            "points": n_points,
            "rays_cast": scan.rays_cast,
            "noise_cm": params.noise_cm,
            "max_range_m": params.max_range_m,
            "trajectory_length_m": scan.trajectory_length_m,
            "laps": scan.laps,
            "scanner": "16 beams at -15..15 deg, spin axis tilted 45 deg, mount turning at 0.5 Hz, 1.35 m above ground, walked at 0.8 m/s; firings subsampled uniformly in time",
        }),
        camera: serde_json::json!({
            "model": intr.model.name(),
            "params": intr.params(),
            "width": width,
            "height": height,
            "images": n_images,
            "flight": cfg.flight,
            "sun_direction": light.sun_dir.to_array(),
            "sfm_noise_cm": params.sfm_noise_cm,
        }),
    };
    truth::write_truth(&out.join("truth.json"), &record)?;
    lap("truth", &mut timings);
    progress.set(1.0);

    let summary = SynthSummary {
        preset: params.preset.name(),
        seed: params.seed,
        trees: plot.trees.len(),
        stones: plot.stones.len(),
        shrubs: plot.shrubs,
        primitives: plot.scene.prims.len(),
        lidar_points: n_points,
        lidar_rays: scan.rays_cast,
        images: views.len(),
        width,
        height,
        points3d: model.points.len(),
        control_points: n_pairs,
        canopy_closure: closure,
        timings,
    };
    Ok((
        summary,
        Artifacts {
            plot,
            views,
            intrinsics: intr,
            model,
        },
    ))
}

/// The layout's inputs from the parameters.
fn layout_params(params: &SynthParams) -> LayoutParams {
    LayoutParams {
        config: params.preset.config(),
        seed: params.seed,
        trees: params.trees,
        leafless: params.leafless,
        stem_dbh_cm: params.stem_dbh_cm.clone(),
        slope_pct: params.slope_pct,
        hidden_stem_m: params.hidden_stem_m,
        crown_interlock: params.crown_interlock,
    }
}

/// The scanner's settings from the parameters (beam dropout 1 % at normal incidence and short
/// range).
fn lidar_params(params: &SynthParams) -> lidar::LidarParams {
    lidar::LidarParams {
        points: params
            .lidar_points
            .unwrap_or(params.preset.config().lidar_points),
        noise_m: params.noise_cm / 100.0,
        max_range_m: params.max_range_m as f32,
        dropout: 0.01,
        rgb: params.lidar_rgb,
    }
}
/// A LiDAR-only plot in memory: the scene of [`generate`] and its handheld scan, without
/// photos, SfM model or files. The cloud is the one `generate` writes to `lidar.laz` for the
/// same parameters (before the LAS format's millimetre quantisation); `labels` is
/// `labels.bin` (one [`scene::Label`] per point, as u8) and `trees` the truth of every tree.
pub struct LidarPlot {
    /// The scan: positions in the scene frame (metres, origin at the plot centre), `offset`
    /// the parameters' `geo_offset`, intensity, and colour when `lidar_rgb` is set.
    pub cloud: PointCloud,
    /// One label per point: 0 ground, 1 wood (stems and branches), 2 leaf, 3 other (stones,
    /// shrubs).
    pub labels: Vec<u8>,
    /// One tree per point: the id of the tree the return hit (1-based, as
    /// [`trees::TreeTruth::id`]), 0 for ground, stones and shrubs. The truth of a tree
    /// segmentation.
    pub tree_of_point: Vec<u16>,
    /// What is true of each tree (scene frame: add `cloud.offset` for file coordinates).
    pub trees: Vec<trees::TreeTruth>,
    /// Radius of the plot disc around the origin, metres.
    pub radius_m: f64,
}

/// Builds the scene of `params` and scans it (phases 1 and 2 of [`generate`]); the photo
/// settings (`images`, `width`, `height`, `points3d`, ...) are not used. For tests and
/// benchmarks of the LiDAR side, which then need neither the renderer's time nor a folder.
pub fn lidar_plot(params: &SynthParams, progress: &dyn Progress) -> Result<LidarPlot, SynthError> {
    params::check(params)?;
    let mut plot = layout::build_plot(&layout_params(params));
    if progress.is_cancelled() {
        return Err(SynthError::Cancelled);
    }
    let scan = scan_plot(params, &mut plot, progress)?;
    progress.set(1.0);
    Ok(LidarPlot {
        cloud: PointCloud {
            offset: DVec3::from_array(params.geo_offset),
            positions: scan.positions,
            colors: scan.colors,
            intensity: Some(scan.intensity),
            format: CloudFormat::Laz,
        },
        labels: scan.labels,
        tree_of_point: scan.owners,
        trees: plot.trees,
        radius_m: plot.radius_m,
    })
}

/// Scans `plot` with the handheld LiDAR of `params`, of the plot without its leaves for a
/// leaf-off scan (the leaves are back in `plot` after), and keeps the returns of the covered
/// share ([`SynthParams::lidar_coverage`]).
fn scan_plot(
    params: &SynthParams,
    plot: &mut layout::Plot,
    progress: &dyn Progress,
) -> Result<lidar::LidarScan, SynthError> {
    let leafy = params.lidar_leaf_off.then(|| {
        let bare = plot.scene.without_leaves();
        std::mem::replace(&mut plot.scene, bare)
    });
    let scan = lidar::scan(plot, &lidar_params(params), params.seed, progress);
    if let Some(scene) = leafy {
        plot.scene = scene;
    }
    Ok(cover(scan?, params.lidar_coverage))
}

/// The CRS the LiDAR file declares when the photos carry GPS positions: UTM zone 32N, in
/// which the default `geo_offset` (500 000 E, 4 000 000 N) lies at about 9° E, 36.1° N.
pub const GPS_EPSG: u32 = 32632;

/// The EXIF block of view `k`'s GPS position: its true centre in file coordinates plus
/// Gaussian noise (`sigma` metres horizontally, 1.5 `sigma` vertically), in WGS84.
fn gps_exif(
    v: &View,
    k: usize,
    sigma: f64,
    offset: DVec3,
    crs: &Crs,
    seed: u64,
) -> Result<Vec<u8>, SynthError> {
    let mut rng = rng::Stream::new(seed, rng::domain::GPS, k as u64);
    let noise = DVec3::new(rng.normal(), rng.normal(), 1.5 * rng.normal()) * sigma;
    let p = v.center + offset + noise;
    let mut lonlat = [(p.x, p.y)];
    crs.to_wgs84(&mut lonlat)
        .map_err(|e| SynthError::InvalidParams(e.to_string()))?;
    let fix = GpsFix {
        lon: lonlat[0].0,
        lat: lonlat[0].1,
        alt: Some(p.z),
    };
    gps::exif_block(&fix).map_err(SynthError::InvalidParams)
}

/// Keeps the returns whose x lies in the first `coverage` share of the scan's x extent (all
/// of them without a coverage).
fn cover(mut scan: lidar::LidarScan, coverage: Option<f64>) -> lidar::LidarScan {
    let Some(c) = coverage.filter(|c| *c < 1.0) else {
        return scan;
    };
    let (lo, hi) = scan
        .positions
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
    let cut = lo + (hi - lo) * c as f32;
    let keep: Vec<bool> = scan.positions.iter().map(|p| p.x <= cut).collect();
    fn kept<T>(v: Vec<T>, keep: &[bool]) -> Vec<T> {
        v.into_iter()
            .zip(keep)
            .filter(|(_, k)| **k)
            .map(|(x, _)| x)
            .collect()
    }
    scan.positions = kept(scan.positions, &keep);
    scan.labels = kept(scan.labels, &keep);
    scan.owners = kept(scan.owners, &keep);
    scan.intensity = kept(scan.intensity, &keep);
    scan.colors = scan.colors.map(|c| kept(c, &keep));
    scan
}

/// Writes one image as JPEG (quality 92, with `exif` when given) or PNG.
fn encode(
    path: &Path,
    rgb: &[u8],
    w: u32,
    h: u32,
    png: bool,
    exif: Option<Vec<u8>>,
) -> Result<(), SynthError> {
    let file = File::create(path).map_err(|e| SynthError::Io(IoError::io(path, e)))?;
    let mut out = BufWriter::new(file);
    let res = if png {
        image::codecs::png::PngEncoder::new(&mut out).write_image(
            rgb,
            w,
            h,
            image::ExtendedColorType::Rgb8,
        )
    } else {
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 92);
        if let Some(exif) = exif {
            // The JPEG encoder takes EXIF (only formats without EXIF refuse it).
            let _ = enc.set_exif_metadata(exif);
        }
        enc.write_image(rgb, w, h, image::ExtendedColorType::Rgb8)
    };
    res.map_err(|source| SynthError::Image {
        path: path.to_path_buf(),
        source,
    })?;
    std::io::Write::flush(&mut out).map_err(|e| SynthError::Io(IoError::io(path, e)))
}
