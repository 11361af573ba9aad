//! Stage `sfm`: a COLMAP model from the job's photos (docs/method.md, Stage 0), laid out as
//! an uploaded project's is, so every later stage reads it the same way.
//!
//! With a COLMAP project among the inputs there is nothing to do and the report says so. With
//! photos, [`crate::sfm::reconstruct`] runs COLMAP's feature extraction, matching and mapper;
//! this stage picks the matching from the photos (exhaustive for small sets, spatial by EXIF
//! GPS or sequential by name for large ones), keeps the mapper's largest model, checks it as
//! stage `ingest` checks an uploaded one, and writes it as text to `sfm/sparse/` with
//! COLMAP's log beside it. The report names the photos that did not register and why (their
//! features and verified matches, read from COLMAP's database); when fewer than
//! `min_registered_share` of the photos register, the stage fails with that list.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::json;

use super::params::{SfmMatching, SfmParams};
use super::{Stage, StageContext, StageError};
use crate::io::colmap::{self, CameraModel, ColmapModel};
use crate::io::photos;
use crate::progress::Progress;
use crate::sfm::{self, Matching, SfmError, SfmOptions};

/// Fewer features than this and a photo's failure is put down to its features (COLMAP's
/// mapper needs 15 verified matches per pair; a photo with under 100 features rarely has
/// them).
const FEW_FEATURES: u64 = 100;

/// How many unregistered photos a failure lists before "and N more".
const LISTED: usize = 10;

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let Some(photos_root) = &ctx.inputs.photos else {
        return match &ctx.inputs.colmap {
            Some(_) => Ok(json!({
                "ran": false,
                "source": "colmap",
                "detail": "the job gave a COLMAP project; nothing to reconstruct",
            })),
            None => Err(StageError::Input(super::NO_PHOTOS.into())),
        };
    };
    let gps = gps_count(ctx)?;
    reconstruct_photos(
        &sfm::colmap_program(),
        photos_root,
        gps,
        &ctx.params.sfm,
        ctx.out_dir,
        ctx.progress,
    )
}

/// A COLMAP model, made by `program` ([`sfm::colmap_program`] outside tests), of the photos
/// under `photos_root` (of which `gps` carry an EXIF position), written as text to
/// `<out_dir>/sparse/` with COLMAP's log as `<out_dir>/colmap.log`; returns the report.
/// Stage `sfm` and `sylva train --photos` both run it.
pub fn reconstruct_photos(
    program: &Path,
    photos_root: &Path,
    gps: usize,
    p: &SfmParams,
    out_dir: &Path,
    progress: &dyn Progress,
) -> Result<serde_json::Value, StageError> {
    check_params(p)?;
    let set = photos::usable_photos(photos_root)?;
    let (photos_dir, names) = (&set.dir, &set.names);
    let sizes = set.check.size_counts();
    let matching = choose_matching(p, names.len(), gps);
    let version = sfm::check_program(program).map_err(map_err)?;
    progress.log(&format!(
        "{} photos ({} with GPS); {} matching; {version}",
        names.len(),
        gps,
        matching.name()
    ));
    let opts = SfmOptions {
        program: program.to_path_buf(),
        photos_dir: photos_dir.clone(),
        photos: names.len(),
        camera_model: p.camera_model.clone(),
        single_camera: p.single_camera && sizes.len() == 1,
        max_image_size: p.max_image_size,
        matching,
        spatial_neighbours: p.spatial_neighbours,
        sequential_overlap: p.sequential_overlap,
        min_model_size: p.min_model_photos.max(2),
        threads: p.threads as usize,
        use_gpu: p.use_gpu,
        time_limit: Some(Duration::from_secs_f64(p.time_limit_min * 60.0)),
    };
    let work = out_dir.join("colmap");
    std::fs::create_dir_all(&work).map_err(|e| crate::io::IoError::io(&work, e))?;
    let log = out_dir.join("colmap.log");
    let outcome = sfm::reconstruct(&opts, &work, &log, progress);
    let database = work.join("database.db");
    let run = match outcome {
        Ok(run) => run,
        Err(SfmError::Failed { step: "mapper", .. }) => {
            let why = unregistered_reasons(&database, names, &BTreeSet::new());
            return Err(StageError::Input(format!(
                "COLMAP's mapper built no model from the {} photos: no pair of photos had \
                 enough matches and parallax to start one. {}",
                names.len(),
                listed(&why)
            )));
        }
        Err(e) => return Err(map_err(e)),
    };
    let (model, models) = largest_model(&run.sparse_root)?;
    let Some(model) = model else {
        let why = unregistered_reasons(&database, names, &BTreeSet::new());
        return Err(StageError::Input(format!(
            "COLMAP's mapper left no model of at least {} photos. {}",
            opts.min_model_size,
            listed(&why)
        )));
    };
    model
        .check_cameras()
        .map_err(|e| StageError::Input(format!("COLMAP cameras: {e}")))?;
    let registered: BTreeSet<String> = model.images.values().map(|im| im.name.clone()).collect();
    let why = unregistered_reasons(&database, names, &registered);
    let share = registered.len() as f64 / names.len() as f64;
    if share < p.min_registered_share {
        return Err(StageError::Input(format!(
            "only {} of {} photos registered ({:.0}% < {:.0}%, params.sfm.min_registered_share). \
             {}",
            registered.len(),
            names.len(),
            share * 100.0,
            p.min_registered_share * 100.0,
            listed(&why)
        )));
    }
    let mut warnings = Vec::new();
    if !why.is_empty() {
        warnings.push(format!(
            "{} of {} photos did not register and are left out: {}",
            why.len(),
            names.len(),
            why.iter()
                .take(LISTED)
                .map(|(n, w)| format!("{n} ({w})"))
                .collect::<Vec<_>>()
                .join("; ")
        ));
    }
    if models > 1 {
        warnings.push(format!(
            "the mapper made {models} separate models; the largest ({} photos) is kept",
            registered.len()
        ));
    }
    for w in &warnings {
        progress.log(&format!("warning: {w}"));
    }
    let sparse = out_dir.join("sparse");
    std::fs::create_dir_all(&sparse).map_err(|e| crate::io::IoError::io(&sparse, e))?;
    colmap::write_text(&model, &sparse)?;
    if p.keep_database {
        let kept = out_dir.join("database.db");
        std::fs::rename(&database, &kept).map_err(|e| crate::io::IoError::io(&kept, e))?;
    }
    // The binary models and (unless kept) the database are COLMAP's working files.
    std::fs::remove_dir_all(&work).map_err(|e| crate::io::IoError::io(&work, e))?;
    let error = mean_reprojection_error(&model);
    progress.log(&format!(
        "{} of {} photos registered, {} points, mean reprojection error {:.2} px",
        registered.len(),
        names.len(),
        model.points.len(),
        error
    ));
    progress.set(1.0);
    let unregistered: Vec<serde_json::Value> = why
        .iter()
        .map(|(n, w)| json!({ "name": n, "why": w }))
        .collect();
    Ok(json!({
        "ran": true,
        "source": "photos",
        "colmap": version,
        "photos": names.len(),
        "photos_with_gps": gps,
        "photo_sizes": photos::sizes_json(&set.check),
        "camera_model": p.camera_model,
        "single_camera": opts.single_camera,
        "max_image_size": p.max_image_size,
        "matching": matching.name(),
        "registered": registered.len(),
        "unregistered": unregistered,
        "models": models,
        "points3d": model.points.len(),
        "mean_reprojection_error_px": error,
        "steps": run.steps,
        "warnings": warnings,
    }))
}

fn check_params(p: &SfmParams) -> Result<(), StageError> {
    let bad =
        |field: &str, why: String| Err(StageError::Input(format!("params.sfm.{field}: {why}")));
    match CameraModel::from_name(&p.camera_model) {
        Some(m) if m.is_supported() => {}
        _ => {
            return bad(
                "camera_model",
                format!(
                    "{:?} is not a camera model Sylva undistorts; use SIMPLE_PINHOLE, PINHOLE, \
                     SIMPLE_RADIAL, RADIAL or OPENCV",
                    p.camera_model
                ),
            );
        }
    }
    if p.max_image_size < 100 {
        return bad(
            "max_image_size",
            format!(
                "{} px is too small for SIFT; use at least 100",
                p.max_image_size
            ),
        );
    }
    if !(0.0..=1.0).contains(&p.min_registered_share) {
        return bad(
            "min_registered_share",
            format!("{} is not a share in [0, 1]", p.min_registered_share),
        );
    }
    if !(p.time_limit_min.is_finite() && p.time_limit_min > 0.0) {
        return bad(
            "time_limit_min",
            format!("{} is not a positive number of minutes", p.time_limit_min),
        );
    }
    if p.spatial_neighbours == 0 || p.sequential_overlap == 0 {
        return bad(
            "spatial_neighbours",
            "spatial_neighbours and sequential_overlap must be at least 1".into(),
        );
    }
    Ok(())
}

/// The matching `auto` picks, or the one asked for.
pub fn choose_matching(p: &SfmParams, photos: usize, with_gps: usize) -> Matching {
    match p.matching {
        SfmMatching::Exhaustive => Matching::Exhaustive,
        SfmMatching::Spatial => Matching::Spatial,
        SfmMatching::Sequential => Matching::Sequential,
        SfmMatching::Auto if photos <= p.exhaustive_max_photos as usize => Matching::Exhaustive,
        SfmMatching::Auto if 2 * with_gps >= photos => Matching::Spatial,
        SfmMatching::Auto => Matching::Sequential,
    }
}

/// How many photos stage `ingest` found EXIF GPS positions in.
fn gps_count(ctx: &StageContext<'_>) -> Result<usize, StageError> {
    let ingest = ctx.output_of(Stage::Ingest, Stage::Sfm)?;
    let path = ingest.join(super::ingest::GPS_FILE);
    if !path.is_file() {
        return Ok(0);
    }
    let text = std::fs::read(&path).map_err(|e| crate::io::IoError::io(&path, e))?;
    let fixes: BTreeMap<String, serde_json::Value> = serde_json::from_slice(&text)
        .map_err(|e| crate::io::IoError::format(&path, e.to_string()))?;
    Ok(fixes.len())
}

fn map_err(e: SfmError) -> StageError {
    match e {
        SfmError::NotInstalled { .. } => StageError::Unavailable(e.to_string()),
        SfmError::Cancelled => StageError::Cancelled,
        SfmError::Io { path, source } => StageError::Io(crate::io::IoError::Io { path, source }),
        SfmError::TimedOut { .. } => StageError::Input(format!(
            "{e}; raise params.sfm.time_limit_min, or lower params.sfm.max_image_size or use \
             fewer photos"
        )),
        SfmError::Failed { .. } => StageError::Input(e.to_string()),
    }
}

/// Every model the mapper left (`sparse/0`, `sparse/1`, …), returning the one with the most
/// photos and how many there were.
fn largest_model(root: &Path) -> Result<(Option<ColmapModel>, usize), StageError> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
        .map_err(|e| crate::io::IoError::io(root, e))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.join("cameras.bin").is_file() || p.join("cameras.txt").is_file())
        .collect();
    dirs.sort();
    let mut best: Option<ColmapModel> = None;
    for d in &dirs {
        let m = colmap::read_model(d, &crate::progress::NoProgress)?;
        if best
            .as_ref()
            .is_none_or(|b| m.images.len() > b.images.len())
        {
            best = Some(m);
        }
    }
    Ok((best, dirs.len()))
}

/// Mean reprojection error of the model's points, pixels (COLMAP's per-point error, each
/// point weighted by its track length as COLMAP's own mean is).
pub fn mean_reprojection_error(model: &ColmapModel) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for p in &model.points {
        let w = p.track.len().max(1);
        sum += p.error * w as f64;
        n += w;
    }
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// Why each photo outside `registered` did not register, from COLMAP's database: its
/// features and how many other photos it has verified matches with.
fn unregistered_reasons(
    database: &Path,
    names: &[String],
    registered: &BTreeSet<String>,
) -> Vec<(String, String)> {
    let stats = database_stats(database).unwrap_or_default();
    names
        .iter()
        .filter(|n| !registered.contains(*n))
        .map(|n| {
            let why = match stats.get(n) {
                None => "COLMAP read no features from it".to_string(),
                Some((f, _)) if *f < FEW_FEATURES => format!(
                    "only {f} features: blurred, over- or under-exposed, or of a featureless \
                     surface such as water or sky"
                ),
                Some((f, 0)) => {
                    format!("{f} features, but verified matches with no other photo: no overlap")
                }
                Some((f, m)) => format!(
                    "{f} features and verified matches with {m} other photo(s), but too little \
                     overlap or parallax with the model to place it"
                ),
            };
            (n.clone(), why)
        })
        .collect()
}

/// Per photo name: (features, other photos with at least 15 verified matches), read from
/// COLMAP's SQLite database (its `images`, `keypoints` and `two_view_geometries` tables;
/// a pair's id is `id1 · 2147483647 + id2`). `None` when it cannot be read.
fn database_stats(database: &Path) -> Option<BTreeMap<String, (u64, u64)>> {
    if !database.is_file() {
        return None;
    }
    let url = format!("sqlite://{}?mode=ro", database.display());
    // A fresh thread, so that the runtime below never nests in the worker's own.
    std::thread::scope(|s| {
        s.spawn(|| {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .ok()?;
            rt.block_on(async {
                use sqlx::Row;
                let mut conn = <sqlx::SqliteConnection as sqlx::Connection>::connect(&url)
                    .await
                    .ok()?;
                let rows = sqlx::query(
                    "SELECT i.name, COALESCE(k.rows, 0) AS features, \
                     (SELECT COUNT(*) FROM two_view_geometries g WHERE g.rows >= 15 AND \
                      (g.pair_id / 2147483647 = i.image_id OR g.pair_id % 2147483647 = i.image_id)) \
                      AS matched \
                     FROM images i LEFT JOIN keypoints k ON k.image_id = i.image_id",
                )
                .fetch_all(&mut conn)
                .await
                .ok()?;
                let mut out = BTreeMap::new();
                for r in rows {
                    let name: String = r.try_get("name").ok()?;
                    let f: i64 = r.try_get("features").ok()?;
                    let m: i64 = r.try_get("matched").ok()?;
                    out.insert(name, (f.max(0) as u64, m.max(0) as u64));
                }
                Some(out)
            })
        })
        .join()
        .ok()
        .flatten()
    })
}

fn listed(why: &[(String, String)]) -> String {
    if why.is_empty() {
        return String::new();
    }
    let mut s = format!(
        "Photos not registered: {}",
        why.iter()
            .take(LISTED)
            .map(|(n, w)| format!("{n} ({w})"))
            .collect::<Vec<_>>()
            .join("; ")
    );
    if why.len() > LISTED {
        s.push_str(&format!("; and {} more", why.len() - LISTED));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_matching_follows_the_photo_count_and_their_gps() {
        let p = SfmParams::default();
        assert_eq!(choose_matching(&p, 18, 0), Matching::Exhaustive);
        assert_eq!(choose_matching(&p, 60, 0), Matching::Exhaustive);
        assert_eq!(choose_matching(&p, 857, 857), Matching::Spatial);
        assert_eq!(choose_matching(&p, 857, 100), Matching::Sequential);
        let forced = SfmParams {
            matching: SfmMatching::Sequential,
            ..SfmParams::default()
        };
        assert_eq!(choose_matching(&forced, 18, 18), Matching::Sequential);
    }

    fn photos(dir: &Path, n: usize) -> PathBuf {
        let photos = dir.join("photos");
        std::fs::create_dir_all(&photos).expect("mkdir");
        for k in 0..n {
            image::RgbImage::from_pixel(40, 30, image::Rgb([30 * k as u8, 90, 60]))
                .save(photos.join(format!("p{k}.png")))
                .expect("png");
        }
        photos
    }

    /// A stand-in for COLMAP whose mapper leaves a model of one photo, `p0.png`, of four.
    fn one_photo_mapper(dir: &Path) -> PathBuf {
        use std::os::unix::fs::PermissionsExt;
        let script = dir.join("fake-colmap");
        std::fs::write(
            &script,
            r#"#!/bin/sh
if [ "$1" = mapper ]; then
  while [ $# -gt 0 ]; do [ "$1" = --output_path ] && out="$2"; shift; done
  mkdir -p "$out/0"
  echo "1 PINHOLE 40 30 30 30 20 15" > "$out/0/cameras.txt"
  printf '1 1 0 0 0 0 0 0 1 p0.png

' > "$out/0/images.txt"
  : > "$out/0/points3D.txt"
  echo "Registering image #1 (1)"
fi
"#,
        )
        .expect("script");
        std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).expect("chmod");
        script
    }

    #[test]
    fn too_few_registered_photos_fail_the_stage_naming_the_others() {
        let dir = tempfile::tempdir().expect("tmp");
        let photos = photos(dir.path(), 4);
        let program = one_photo_mapper(dir.path());
        let out = dir.path().join("out");
        std::fs::create_dir_all(&out).expect("mkdir");
        let p = SfmParams::default();
        let e = reconstruct_photos(&program, &photos, 0, &p, &out, &crate::progress::NoProgress)
            .expect_err("1 of 4 registered");
        let text = e.to_string();
        assert!(e.is_input_fault(), "{text}");
        assert!(text.contains("only 1 of 4 photos registered"), "{text}");
        for name in ["p1.png", "p2.png", "p3.png"] {
            assert!(text.contains(name), "{name} not named: {text}");
        }
        assert!(!text.contains("p0.png"), "{text}");
        // With a share the user accepts, the model is written and the others are reported.
        let lenient = SfmParams {
            min_registered_share: 0.2,
            ..SfmParams::default()
        };
        let report = reconstruct_photos(
            &program,
            &photos,
            0,
            &lenient,
            &out,
            &crate::progress::NoProgress,
        )
        .expect("accepted");
        assert_eq!(report["registered"], 1);
        assert_eq!(report["unregistered"].as_array().map(Vec::len), Some(3));
        assert!(out.join("sparse").join("images.txt").is_file());
        assert!(
            !out.join("colmap").exists(),
            "COLMAP's working folder is removed"
        );
    }

    #[test]
    fn a_worker_without_colmap_fails_the_stage_as_unavailable_naming_the_package() {
        let dir = tempfile::tempdir().expect("tmp");
        let photos = photos(dir.path(), 3);
        let out = dir.path().join("out");
        std::fs::create_dir_all(&out).expect("mkdir");
        let e = reconstruct_photos(
            &dir.path().join("no-colmap-here"),
            &photos,
            0,
            &SfmParams::default(),
            &out,
            &crate::progress::NoProgress,
        )
        .expect_err("no COLMAP");
        assert!(matches!(e, StageError::Unavailable(_)), "{e}");
        assert!(!e.is_input_fault());
        assert!(e.to_string().contains("apt-get install colmap"), "{e}");
    }

    #[test]
    fn parameters_sylva_cannot_use_are_refused_by_name() {
        let bad = SfmParams {
            camera_model: "OPENCV_FISHEYE".into(),
            ..SfmParams::default()
        };
        let e = check_params(&bad).expect_err("fisheye");
        assert!(e.to_string().contains("params.sfm.camera_model"), "{e}");
        let bad = SfmParams {
            min_registered_share: 1.5,
            ..SfmParams::default()
        };
        assert!(check_params(&bad).is_err());
        assert!(check_params(&SfmParams::default()).is_ok());
    }
}
