//! Registration accuracy table on synthetic plots (`sylva synth`), one row per seed: the
//! recovered `sfm_to_lidar` of stage `register` against the generator's truth.
//!
//! `cargo run --profile test --example register_diag -- PRESET SEEDS [auto|analyse]`, e.g.
//! `-- tiny 1-5` or `-- stand 1-5 auto` (`light-stand` for the light stand of the tests) (which also prints the automatic coarse alignment's
//! own errors). `analyse` prints where the SfM points lie on the LiDAR's classes, why points
//! get no surface patch, and the surface refinement started from the true pose with its
//! standard errors (`REG_DIAG_LOG=1` shows its iterations). `REG_DIAG_POINTS3D` and
//! `REG_DIAG_LIDAR_POINTS` override the preset's SfM and LiDAR point counts. Plots are cached under `$REG_DIAG_DIR` (default
//! `/tmp/sylva-register-diag`); `REG_PARAMS` may hold a JSON object of register parameters.

use std::path::PathBuf;
use std::time::Instant;

use glam::{DMat3, DQuat, DVec3};
use sylva::geom::Similarity;
use sylva::pipeline::{self, PipelineParams, Stage, StageInputs};
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams};

#[path = "support/truth.rs"]
mod truth;
use truth::{errors, seeds, stage_log, truth_of};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let log = stage_log("REG_DIAG_LOG");
    // "light-stand": the lighter stand of tests/register.rs (30 photos of 320×180, 800 k LiDAR
    // points, 5000 SfM points).
    let name = args.first().map_or("tiny", String::as_str);
    let light = name == "light-stand";
    let preset = if light {
        Preset::Stand
    } else {
        Preset::from_name(name).ok_or("preset")?
    };
    let seeds = seeds(args.get(1).map(String::as_str))?;
    let automatic = args.get(2).is_some_and(|a| a == "auto");
    let analyse = args.get(2).is_some_and(|a| a == "analyse");
    let root = PathBuf::from(
        std::env::var("REG_DIAG_DIR").unwrap_or_else(|_| "/tmp/sylva-register-diag".into()),
    );
    let mut params = PipelineParams::default();
    if let Ok(json) = std::env::var("REG_PARAMS") {
        params.register = serde_json::from_str(&json)?;
    }
    params.register.automatic = automatic;
    println!(
        "| seed | method | coarse rot ° | coarse scale % | coarse cm | rot ° | scale % | cm | fitness | rmse m | iters | confidence | rot std ° (normal matrix / split half) | s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let (points3d, lidar_points) = (
        env_parse::<usize>("REG_DIAG_POINTS3D"),
        env_parse::<usize>("REG_DIAG_LIDAR_POINTS"),
    );
    let (lidar_noise, sfm_noise) = (
        env_parse::<f64>("REG_DIAG_LIDAR_NOISE_CM"),
        env_parse::<f64>("REG_DIAG_SFM_NOISE_CM"),
    );
    for seed in seeds {
        let mut dir = format!("{name}-{seed}");
        if let Some(n) = points3d {
            dir += &format!("-sfm{n}");
        }
        if let Some(n) = lidar_points {
            dir += &format!("-lidar{n}");
        }
        if let Some(cm) = lidar_noise {
            dir += &format!("-lnoise{cm}");
        }
        if let Some(cm) = sfm_noise {
            dir += &format!("-snoise{cm}");
        }
        let out = root.join(dir);
        if !out.join("truth.json").exists() {
            let mut p = SynthParams::new(preset);
            p.seed = seed;
            p.points3d = points3d;
            p.lidar_points = lidar_points;
            if let Some(cm) = lidar_noise {
                p.noise_cm = cm;
            }
            if let Some(cm) = sfm_noise {
                p.sfm_noise_cm = cm;
            }
            if light {
                p.images = Some(30);
                p.width = Some(320);
                p.height = Some(180);
                p.lidar_points = Some(800_000);
                p.points3d = Some(5_000);
            }
            sylva::synth::generate(&p, &out, &NoProgress)?;
        }
        let work = out.join("work");
        let inputs = StageInputs {
            lidar: out.join("lidar.laz"),
            colmap: Some(out.join("colmap")),
            photos: None,
            control_points: (!automatic).then(|| out.join("control_points.csv")),
            field_dbh: None,
        };
        if !work.join("ingest").exists() {
            pipeline::execute_stage(Stage::Ingest, &inputs, &work, &params, &NoProgress)?;
        }
        if analyse {
            analyse_seed(&out, &params.register)?;
            continue;
        }
        if automatic {
            coarse_only(&out)?;
        }
        let t0 = Instant::now();
        let result = pipeline::execute_stage(Stage::Register, &inputs, &work, &params, log);
        let secs = t0.elapsed().as_secs_f64();
        let (truth_sim, centre) = truth_of(&out)?;
        let report = match result {
            Ok(o) => o.report,
            Err(e) => {
                println!("| {seed} | refused: {e} |");
                continue;
            }
        };
        let get = |k: &str| pipeline::register::similarity_from_json(&report[k]).ok_or("report");
        let offset = DVec3::from_array(serde_json::from_value(report["lidar_offset"].clone())?);
        let mut coarse = get("coarse")?;
        coarse.translation += offset;
        if let Some(cands) = report["candidates"].as_array() {
            for (k, c) in cands.iter().enumerate() {
                let sim = |key: &str| {
                    pipeline::register::similarity_from_json(&c[key]).map(|mut s| {
                        s.translation += offset;
                        errors(&s, &truth_sim, centre)
                    })
                };
                if let (Some(a), Some(b)) = (sim("coarse"), sim("final")) {
                    println!(
                        "  candidate {k}: coarse {:.2}° {:.2}% {:.2} m -> ICP {:.3}° {:.3}% {:.3} m; on-cloud {:.3}, elevated {:.3} of {}",
                        a.0,
                        a.1 * 100.0,
                        a.2,
                        b.0,
                        b.1 * 100.0,
                        b.2,
                        c["on_cloud"].as_f64().unwrap_or(f64::NAN),
                        c["elevated_on_cloud"].as_f64().unwrap_or(f64::NAN),
                        c["elevated_points"]
                    );
                }
            }
        }
        let (cr, cs, ct) = errors(&coarse, &truth_sim, centre);
        let (r, s, tr) = errors(&get("sfm_to_lidar")?, &truth_sim, centre);
        println!(
            "| {seed} | {} | {cr:.4} | {:.4} | {:.2} | {r:.4} | {:.4} | {:.2} | {:.3} | {:.4} | {} | {:.2} | {:.4} / {:.4} | {secs:.1} |",
            report["method"].as_str().unwrap_or("?"),
            cs * 100.0,
            ct * 100.0,
            s * 100.0,
            tr * 100.0,
            report["fitness"].as_f64().unwrap_or(f64::NAN),
            report["rmse_m"].as_f64().unwrap_or(f64::NAN),
            report["icp_iterations"],
            report["confidence"].as_f64().unwrap_or(f64::NAN),
            norm3(&report["uncertainty"]["normal_matrix"]["rotation_deg"]),
            norm3(&report["uncertainty"]["split_half"]["std_rotation_deg"]),
        );
    }
    Ok(())
}

/// The environment variable `key` parsed as `T` (None when unset or unparsable).
fn env_parse<T: std::str::FromStr>(key: &str) -> Option<T> {
    std::env::var(key).ok().and_then(|v| v.parse().ok())
}

/// Norm of a JSON array of three numbers (NaN when absent).
fn norm3(v: &serde_json::Value) -> f64 {
    v.as_array().map_or(f64::NAN, |a| {
        a.iter()
            .map(|x| x.as_f64().unwrap_or(f64::NAN).powi(2))
            .sum::<f64>()
            .sqrt()
    })
}

/// The automatic coarse alignment alone against the truth (printed before the stage's row).
fn coarse_only(out: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let cloud =
        sylva::io::pointcloud::read_point_cloud(&out.join("work/ingest/cloud.ply"), &NoProgress)?;
    let model = sylva::io::colmap::read_model(&out.join("work/ingest/sparse"), &NoProgress)?;
    let (truth, centre) = truth_of(out)?;
    let sfm: Vec<DVec3> = model.points.iter().map(|q| q.xyz).collect();
    let rays = pipeline::register::camera_rays(&model);
    if let Ok(up) = sylva::geom::coarse::up_from_cameras(&rays) {
        let true_up = truth.rotation.transpose() * DVec3::Z;
        println!(
            "  up from the cameras: {:.2}° from the true up",
            up.angle_between(true_up).to_degrees()
        );
    }
    match sylva::geom::coarse::align_candidates(
        &sfm,
        &rays,
        &cloud.positions,
        &Default::default(),
        &NoProgress,
    ) {
        Ok(cands) => {
            for (k, c) in cands.iter().enumerate() {
                let est = Similarity {
                    translation: c.transform.translation + cloud.offset,
                    ..c.transform
                };
                let (r, s, t) = errors(&est, &truth, centre);
                println!(
                    "  coarse candidate {k}: rot {r:.2}°, scale {:.2}%, {:.2} m at the centre; confidence {:.2}, score {:.3}, runner-up {:.3}",
                    s * 100.0,
                    t,
                    c.confidence,
                    c.score,
                    c.runner_up
                );
            }
        }
        Err(e) => println!("  coarse alone: {e}"),
    }
    Ok(())
}

/// Where the SfM points lie on the LiDAR's classes at the true pose, and where the
/// refinement drifts from the true pose with each subset of them.
fn analyse_seed(
    out: &std::path::Path,
    p: &sylva::pipeline::params::RegisterParams,
) -> Result<(), Box<dyn std::error::Error>> {
    use glam::Vec3;
    let cloud =
        sylva::io::pointcloud::read_point_cloud(&out.join("work/ingest/cloud.ply"), &NoProgress)?;
    let labels = std::fs::read(out.join("labels.bin"))?;
    let model = sylva::io::colmap::read_model(&out.join("work/ingest/sparse"), &NoProgress)?;
    let (truth, centre) = truth_of(out)?;
    let local = Similarity {
        translation: truth.translation - cloud.offset,
        ..truth
    };
    let c_local = centre - cloud.offset;
    let source: Vec<Vec3> = model
        .points
        .iter()
        .map(|q| local.apply(q.xyz).as_vec3())
        .collect();
    let index = sylva::geom::PointIndex::new(&cloud.positions)?;
    let mut by_label = vec![Vec::new(); 4];
    let mut lab = Vec::with_capacity(source.len());
    for q in &source {
        let m = index.nearest(*q).ok_or("nearest")?;
        let l = labels.get(m.index as usize).copied().unwrap_or(3) as usize;
        by_label[l.min(3)].push((m.dist2 as f64).sqrt());
        lab.push(l);
    }
    for (l, d) in by_label.iter_mut().enumerate() {
        d.sort_by(f64::total_cmp);
        let med = d.get(d.len() / 2).copied().unwrap_or(f64::NAN);
        print!("label {l}: {} pts, median nn {:.3} m; ", d.len(), med);
    }
    println!();
    let thin = sylva::geom::voxel_downsample(
        &cloud.positions,
        None,
        p.refine_voxel_m as f32,
        &NoProgress,
    )?
    .positions;
    let tindex = sylva::geom::PointIndex::new(&thin)?;
    let sp = sylva::pipeline::register::surface_params(p);
    let cps = sylva::io::tables::read_control_points(&out.join("control_points.csv"))?;
    let cp_sfm: Vec<DVec3> = cps.iter().map(|c| c.sfm).collect();
    let cp_lidar: Vec<DVec3> = cps.iter().map(|c| c.lidar - cloud.offset).collect();
    let mut why = [[0usize; 6]; 4];
    for (q, l) in source.iter().zip(&lab) {
        let k = sylva::geom::surface::patch_status(&thin, &tindex, q.as_dvec3(), &sp);
        why[(*l).min(3)][k as usize] += 1;
    }
    println!("  patch status by label (ok, few, line, off-centre, singular, rms): {why:?}");
    let sfm_local: Vec<DVec3> = model.points.iter().map(|q| q.xyz).collect();
    let radius: Vec<f64> = source
        .iter()
        .map(|q| (q.as_dvec3() - c_local).truncate().length())
        .collect();
    // Subsets: the labels kept (ground, wood, leaf, other), the control points as extra
    // observations, and the range of horizontal distances from the plot centre (metres).
    const ALL: [bool; 4] = [true; 4];
    const GROUND: [bool; 4] = [true, false, false, false];
    let any = (0.0, f64::INFINITY);
    for (name, keep, with_cp, within) in [
        ("all", ALL, false, any),
        ("all + control points", ALL, true, any),
        ("ground+wood+other", [true, true, false, true], false, any),
        ("ground", GROUND, false, any),
        ("ground within 5 m", GROUND, false, (0.0, 5.0)),
        ("ground beyond 5 m", GROUND, false, (5.0, f64::INFINITY)),
        ("all within 5 m", ALL, false, (0.0, 5.0)),
    ] {
        let w: Vec<f64> = lab
            .iter()
            .zip(&radius)
            .map(|(l, r)| f64::from(u8::from(keep[*l] && (within.0..within.1).contains(r))))
            .collect();
        match sylva::geom::surface::refine_on_surface(
            &sfm_local,
            Some(&w),
            &thin,
            &tindex,
            &local,
            with_cp.then_some(sylva::geom::surface::PairPrior {
                sfm: &cp_sfm,
                lidar: &cp_lidar,
                sigma_m: p.control_point_sigma_m,
            }),
            &sp,
            stage_log("REG_DIAG_LOG"),
        ) {
            Ok(r) => {
                let t = local.inverse().then(&r.transform);
                let (er, es, et) = errors(&t, &Similarity::IDENTITY, c_local);
                println!(
                    "  surface refine from truth on {name}: rot {er:.4}°, scale {:.4}%, {:.2} cm, used {} ({:.2}), rmse {:.4}, iters {}, std rot {:.4?}° scale {:.4}%",
                    es * 100.0,
                    et * 100.0,
                    r.used,
                    r.fitness,
                    r.rmse_m,
                    r.iterations,
                    r.std_rotation_deg,
                    r.std_scale * 100.0
                );
            }
            Err(e) => println!("  {name}: {e}"),
        }
    }
    // Monte Carlo: REG_DIAG_MC refinements from the truth on all points, each with extra
    // isotropic SfM noise of REG_DIAG_MC_CM centimetres (default 1), to compare the spread
    // of the estimates with the refinement's own standard errors.
    let runs = env_parse::<u64>("REG_DIAG_MC").unwrap_or(0);
    let cm = env_parse::<f64>("REG_DIAG_MC_CM").unwrap_or(1.0);
    // Start off the truth by REG_DIAG_MC_START_DEG about the vertical through the plot
    // centre, alternating in sign, as a coarse alignment would.
    let start_deg = env_parse::<f64>("REG_DIAG_MC_START_DEG").unwrap_or(0.0);
    let sigma = cm / 100.0 / truth.scale;
    let mut yaw = Vec::new();
    let mut std_yaw = Vec::new();
    for k in 0..runs {
        let mut rng = sylva::synth::rng::Stream::new(k, 0x6d63, 0);
        let noisy: Vec<DVec3> = sfm_local
            .iter()
            .map(|q| *q + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * sigma)
            .collect();
        let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
        let turn = DMat3::from_rotation_z((sign * start_deg).to_radians());
        let start = Similarity {
            rotation: turn * local.rotation,
            translation: c_local + turn * (local.translation - c_local),
            ..local
        };
        let r = sylva::geom::surface::refine_on_surface(
            &noisy,
            None,
            &thin,
            &tindex,
            &start,
            None,
            &sp,
            &NoProgress,
        )?;
        let t = local.inverse().then(&r.transform);
        let (er, es, _) = errors(&t, &Similarity::IDENTITY, c_local);
        // Signed rotation about the vertical (degrees).
        let z = DQuat::from_mat3(&t.rotation)
            .to_scaled_axis()
            .z
            .to_degrees();
        println!(
            "  mc {k}: rot {er:.4}°, yaw {z:+.4}°, scale {:+.4}%, std yaw {:.4}°",
            es * 100.0,
            r.std_rotation_deg[2]
        );
        yaw.push(z);
        std_yaw.push(r.std_rotation_deg[2]);
    }
    if runs > 1 {
        let n = yaw.len() as f64;
        let mean = yaw.iter().sum::<f64>() / n;
        let sd = (yaw.iter().map(|y| (y - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let rep = std_yaw.iter().sum::<f64>() / n;
        println!("  mc yaw: mean {mean:+.4}°, spread {sd:.4}°, reported std {rep:.4}°");
    }
    Ok(())
}
