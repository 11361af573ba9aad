//! Stage `register`: the similarity that maps the SfM frame onto the LiDAR frame
//! (docs/method.md Stage 1), and the COLMAP model moved into the LiDAR frame.
//!
//! The stage orchestrates: it reads its inputs, maps [`RegisterParams`] onto the geometry's
//! parameters, calls the registration science of [`crate::geom`] (mainly
//! [`crate::geom::register`]), applies its gates and writes the model and the report.
//!
//! Coarse: from control point pairs (Umeyama, residual per pair) or, without them, the
//! automatic alignment of [`crate::geom::coarse`], verified by
//! [`geom::register::verify_candidates`]. Fine: ICP of the SfM points onto the
//! LiDAR cloud thinned to `target_voxel_m`, estimating scale too; then the surface
//! refinement of [`crate::geom::surface`] (similarity Gauss-Newton of the SfM points onto
//! quadric patches of the LiDAR surface, the control points as extra observations), whose
//! standard errors the report gives as `uncertainty`: per parameter the larger of the
//! normal-matrix error and the spread over split halves of the SfM points (both are in the
//! report too, as `normal_matrix` and `split_half`). Everything runs in the
//! LiDAR cloud's local frame (file coordinates minus the ingest offset) so f32 positions stay
//! precise; the report gives `sfm_to_lidar` in the file's own coordinates.

use std::path::Path;

use glam::{DMat3, DVec3};
use serde_json::json;

use super::params::RegisterParams;
use super::{Stage, StageContext, StageError};
use crate::geom::register::{
    AUTOMATIC_MAX_STD_ROTATION_DEG, AUTOMATIC_MAX_STD_SCALE, AUTOMATIC_REFINE_PASSES, CandidateRun,
    SurfaceTarget, icp_from, refine_on_surface, verify_candidates,
};
use crate::geom::{self, IcpMethod, IcpParams, RobustKernel, Similarity, VoxelParams};
use crate::io::colmap::{self, ColmapModel};
use crate::io::pointcloud::PointCloud;
use crate::io::{IoError, tables};
use crate::progress::SubProgress;

/// A similarity as the report writes it: scale, row-major rotation, translation.
pub fn similarity_json(s: &Similarity) -> serde_json::Value {
    let r = s.rotation.transpose().to_cols_array_2d(); // rows of the rotation
    json!({
        "scale": s.scale,
        "rotation": r,
        "translation": [s.translation.x, s.translation.y, s.translation.z],
    })
}

/// Reads a similarity written by [`similarity_json`].
pub fn similarity_from_json(v: &serde_json::Value) -> Option<Similarity> {
    let scale = v["scale"].as_f64()?;
    let mut rows = [[0.0; 3]; 3];
    for (i, row) in rows.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = v["rotation"][i][j].as_f64()?;
        }
    }
    let t = &v["translation"];
    Some(Similarity {
        scale,
        rotation: DMat3::from_cols_array_2d(&rows).transpose(),
        translation: DVec3::new(t[0].as_f64()?, t[1].as_f64()?, t[2].as_f64()?),
    })
}

/// Moves a COLMAP model by `s` (x' = s R x + t): points move, camera centres move
/// (C' = s R C + t), camera rotations turn (R_cw' = R_cw Rᵀ); intrinsics are unchanged
/// ([`geom::register::transform_pose`]).
pub fn transform_model(model: &ColmapModel, s: &Similarity) -> ColmapModel {
    let mut out = model.clone();
    for im in out.images.values_mut() {
        (im.qvec, im.tvec) = geom::register::transform_pose(im.qvec, im.tvec, s);
    }
    for p in &mut out.points {
        p.xyz = s.apply(p.xyz);
    }
    out
}

/// Camera centre (world) and viewing direction (world) of every registered image
/// ([`geom::register::camera_ray`]).
pub fn camera_rays(model: &ColmapModel) -> Vec<(DVec3, DVec3)> {
    model
        .images
        .values()
        .map(|im| geom::register::camera_ray(im.qvec, im.tvec))
        .collect()
}

/// The report's `candidates`: every automatic candidate's coarse and final similarity and
/// scores.
fn candidates_json(runs: &[CandidateRun]) -> serde_json::Value {
    json!(
        runs.iter()
            .map(|r| json!({
                "coarse": similarity_json(&r.coarse),
                "final": similarity_json(&r.refined),
                "on_cloud": r.on_cloud,
                "elevated_on_cloud": r.elevated_on_cloud,
                "elevated_points": r.elevated_points,
                "icp_fitness": r.fine.fitness,
            }))
            .collect::<Vec<_>>()
    )
}

/// The candidates an automatic alignment weighed, for a refusal: how many, and the best five
/// by score (share of SfM points on the LiDAR cloud after ICP, plus the share of those standing
/// above the ground), each with its rotation and scale.
fn weighed(runs: &[CandidateRun]) -> String {
    let mut order: Vec<&CandidateRun> = runs.iter().collect();
    let score = |r: &CandidateRun| r.on_cloud + r.elevated_on_cloud;
    order.sort_by(|a, b| score(b).total_cmp(&score(a)));
    let best: Vec<String> = order
        .iter()
        .take(5)
        .map(|r| {
            format!(
                "on cloud {:.2}, elevated {:.2} (rotation {:.1}°, scale {:.3})",
                r.on_cloud,
                r.elevated_on_cloud,
                r.refined.rotation_angle_deg(),
                r.refined.scale
            )
        })
        .collect();
    format!(
        "Candidates weighed: {}; best: {}",
        runs.len(),
        if best.is_empty() {
            "none".to_string()
        } else {
            best.join("; ")
        }
    )
}

fn load_inputs(ctx: &StageContext<'_>) -> Result<(PointCloud, ColmapModel), StageError> {
    let ingest = ctx.output_of(Stage::Ingest, Stage::Register)?;
    let cloud = ctx.read_ingest_cloud(&ingest, 0.1)?;
    let model = colmap::read_model(&ingest.join("sparse"), &crate::progress::NoProgress)?;
    Ok((cloud, model))
}

/// What a refusal of the automatic alignment asks for.
const SUPPLY_CONTROL_POINTS: &str =
    "supply control points (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)";

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let automatic = ctx.inputs.control_points.is_none() && ctx.params.register.automatic;
    match align(ctx) {
        // Every refusal of the automatic alignment says what to supply, also one from deep in
        // the geometry (a degenerate surface fit, too few points on the cloud).
        Err(StageError::Input(why)) if automatic && !why.contains("control points") => {
            Err(StageError::Input(format!(
                "automatic registration failed: {why}; {SUPPLY_CONTROL_POINTS}"
            )))
        }
        other => other,
    }
}

fn align(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let p = &ctx.params.register;
    let (cloud, model) = load_inputs(ctx)?;
    if model.points.len() < 10 {
        return Err(StageError::Input(format!(
            "COLMAP model has {} 3-D points; registration needs at least 10",
            model.points.len()
        )));
    }
    let offset = cloud.offset;
    let sfm: Vec<DVec3> = model.points.iter().map(|p| p.xyz).collect();
    ctx.progress.set(0.1);

    // ICP target: the LiDAR cloud thinned to `target_voxel_m`.
    let target = geom::voxel_downsample(
        &cloud.positions,
        None,
        &VoxelParams {
            voxel_size: p.target_voxel_m as f32,
        },
        &SubProgress::new(ctx.progress, 0.1, 0.05),
    )?
    .positions;
    let params = IcpParams {
        method: if p.point_to_plane {
            IcpMethod::PointToPlane
        } else {
            IcpMethod::PointToPoint
        },
        estimate_scale: p.estimate_scale,
        max_iterations: p.icp_max_iterations as usize,
        start_distance: p.icp_max_distance_m,
        min_distance: p.icp_min_distance_m,
        robust: RobustKernel::Trimmed {
            keep_fraction: p.icp_keep_fraction,
        },
        relative_rmse_tolerance: p.icp_relative_rmse,
        ..Default::default()
    };

    // Coarse, and ICP from it. The automatic path verifies its candidates with one pass of
    // the surface refinement, whose surface and result the refinement below goes on from.
    let mut surface: Option<SurfaceTarget> = None;
    let mut refine_start: Option<Similarity> = None;
    let (coarse, method, pairs, confidence, fine, candidates) = match &ctx.inputs.control_points {
        Some(path) => {
            let cps = tables::read_control_points(path)?;
            let src: Vec<DVec3> = cps.iter().map(|c| c.sfm).collect();
            let dst: Vec<DVec3> = cps.iter().map(|c| c.lidar - offset).collect();
            let fit = geom::similarity_from_pairs(&src, &dst, true)
                .map_err(|e| StageError::Input(format!("{}: {e}", file_name(path))))?;
            let pairs: Vec<serde_json::Value> = cps
                .iter()
                .zip(&fit.residuals)
                .map(|(c, r)| json!({ "name": c.name, "residual_m": r }))
                .collect();
            ctx.progress.log(&format!(
                "control points: {} pairs, RMSE {:.3} m",
                cps.len(),
                fit.rmse
            ));
            if ctx.progress.is_cancelled() {
                return Err(StageError::Cancelled);
            }
            let icp_progress = SubProgress::new(ctx.progress, 0.5, 0.4);
            let fine = icp_from(&sfm, &fit.transform, &target, &params, &icp_progress)?;
            (
                fit.transform,
                "control_points",
                pairs,
                1.0,
                fine,
                serde_json::Value::Null,
            )
        }
        None if !p.automatic => {
            return Err(StageError::Input(
                "control points are required: supply at least 4 pairs (CSV \
                 sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z), or leave \
                 params.register.automatic on (its default) to align automatically"
                    .into(),
            ));
        }
        None => {
            let rays = camera_rays(&model);
            let cands = geom::coarse::align_candidates(
                &sfm,
                &rays,
                &cloud.positions,
                &geom::coarse::CoarseParams::default(),
                &SubProgress::new(ctx.progress, 0.15, 0.35),
            )
            .map_err(|e| match e {
                geom::GeomError::Cancelled => StageError::Cancelled,
                other => StageError::Input(format!(
                    "automatic registration failed ({other}); supply control points \
                     (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)"
                )),
            })?;
            let st = SurfaceTarget::new(
                &cloud.positions,
                p.refine_voxel_m,
                &SubProgress::new(ctx.progress, 0.5, 0.05),
            )?;
            if cands.is_empty() {
                return Err(StageError::Input(
                    "automatic registration found no candidate alignment; supply control \
                     points (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)"
                        .into(),
                ));
            }
            let v = verify_candidates(
                &sfm,
                &cands,
                &target,
                &params,
                &st,
                &surface_params(p),
                &SubProgress::new(ctx.progress, 0.55, 0.35),
            )?;
            surface = Some(st);
            refine_start = Some(v.refined);
            ctx.progress.log(&format!(
                "automatic alignment: {} candidates verified by ICP; best on-cloud share {:.3} \
                 (elevated {:.3}), best distinct other {:.3}; confidence {:.2}",
                cands.len(),
                v.best_fit,
                v.best_elevated,
                v.runner_up,
                v.confidence
            ));
            if v.best_fit < p.min_fitness {
                return Err(StageError::Input(format!(
                    "automatic registration rejected: after ICP and the surface refinement only \
                     {:.0}% of the SfM points lie on the LiDAR cloud (< {:.0}%); the photos \
                     and the scan may not overlap. {}. Supply control points (at least 4 \
                     pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)",
                    v.best_fit * 100.0,
                    p.min_fitness * 100.0,
                    weighed(&v.candidates)
                )));
            }
            if v.confidence < p.min_confidence {
                return Err(StageError::Input(format!(
                    "automatic registration is not confident enough ({:.2} < {:.2}): no \
                     candidate alignment clearly puts the photos' points on the LiDAR cloud \
                     (the best scores {:.2}, the best distinct other {:.2}); the photos and the \
                     scan may not overlap. {}. Supply control points (at least 4 pairs, CSV \
                     sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)",
                    v.confidence,
                    p.min_confidence,
                    v.best_fit + v.best_elevated,
                    v.runner_up,
                    weighed(&v.candidates)
                )));
            }
            (
                v.coarse,
                "automatic",
                Vec::new(),
                v.confidence,
                v.fine,
                candidates_json(&v.candidates),
            )
        }
    };
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }
    ctx.progress.log(&format!(
        "ICP: fitness {:.2}, inlier RMSE {:.3} m, scale correction {:.4}, {} iterations",
        fine.fitness, fine.inlier_rmse, fine.scale, fine.iterations
    ));
    let icp_t = coarse.then(&fine.transform());
    let (local, fitness, rmse, iterations, converged, uncertainty) = if p.refine {
        let pairs_local = match &ctx.inputs.control_points {
            Some(path) => {
                let cps = tables::read_control_points(path)?;
                Some((
                    cps.iter().map(|c| c.sfm).collect::<Vec<_>>(),
                    cps.iter().map(|c| c.lidar - offset).collect::<Vec<_>>(),
                ))
            }
            None => None,
        };
        let surface = match surface.take() {
            Some(s) => s,
            None => SurfaceTarget::new(
                &cloud.positions,
                p.refine_voxel_m,
                &SubProgress::new(ctx.progress, 0.9, 0.02),
            )?,
        };
        let r = refine_on_surface(
            &sfm,
            &surface,
            &refine_start.unwrap_or(icp_t),
            pairs_local.as_ref().map(|(a, b)| geom::surface::PairPrior {
                sfm: a,
                lidar: b,
                sigma_m: p.control_point_sigma_m,
            }),
            &surface_params(p),
            // Without control points the pose after ICP is often still tenths of a degree and
            // about a percent off (docs/results/registration.md: stand 1 left ICP at 0.37° and 1.2 %); further
            // passes carry the refinement on from where the last stopped.
            if method == "automatic" {
                AUTOMATIC_REFINE_PASSES
            } else {
                1
            },
            &SubProgress::new(ctx.progress, 0.9, 0.06),
        )?;
        ctx.progress.log(&format!(
            "surface refinement: {} SfM points on LiDAR surfaces ({:.0}%), robust RMS {:.4} m, \
             {} iterations; standard errors: rotation {:.4?} deg, scale {:.4}%",
            r.used,
            r.fitness * 100.0,
            r.rmse_m,
            r.iterations,
            r.std_rotation_deg,
            r.std_scale * 100.0
        ));
        let split = if p.uncertainty_splits > 0 {
            Some(geom::surface::split_half_spread(
                &sfm,
                &surface.thin,
                &surface.index,
                &r.transform,
                &surface_params(p),
                p.uncertainty_splits as usize,
                // Ends short of 1.0: the stage reports 1.0 only once its model is written.
                &SubProgress::new(ctx.progress, 0.96, 0.03),
            )?)
        } else {
            None
        };
        // Per parameter, the larger of the normal-matrix and the split-half standard error.
        // The halves leave the control pairs out, so with control points this is the SfM
        // points' own spread: an upper bound there.
        let wider = |a: f64, b: Option<f64>| b.map_or(a, |b| a.max(b));
        let std_rotation_deg: [f64; 3] = std::array::from_fn(|k| {
            wider(r.std_rotation_deg[k], split.map(|s| s.std_rotation_deg[k]))
        });
        let std_translation_m: [f64; 3] = std::array::from_fn(|k| {
            wider(
                r.std_translation_m[k],
                split.map(|s| s.std_translation_m[k]),
            )
        });
        let std_scale = wider(r.std_scale, split.map(|s| s.std_scale));
        if let Some(s) = &split {
            ctx.progress.log(&format!(
                "split-half check ({} splits): standard errors rotation {:.4?} deg, scale {:.4}%",
                s.splits,
                s.std_rotation_deg,
                s.std_scale * 100.0
            ));
        }
        let std_rot = std_rotation_deg.iter().map(|v| v * v).sum::<f64>().sqrt();
        if method == "automatic"
            && (std_rot > AUTOMATIC_MAX_STD_ROTATION_DEG || std_scale > AUTOMATIC_MAX_STD_SCALE)
        {
            return Err(StageError::Input(format!(
                "automatic registration is not precise enough: the SfM points pin the \
                 rotation only to {std_rot:.3}° and the scale to {:.3}% (one standard error; \
                 at most {AUTOMATIC_MAX_STD_ROTATION_DEG}° and {:.2}% are accepted without \
                 control points), so the alignment may be tenths of a degree off; supply \
                 control points (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)",
                std_scale * 100.0,
                AUTOMATIC_MAX_STD_SCALE * 100.0
            )));
        }
        let u = json!({
            "rotation_deg": std_rotation_deg,
            "scale": std_scale,
            "translation_m": std_translation_m,
            "points_on_surfaces": r.used,
            "normal_matrix": {
                "rotation_deg": r.std_rotation_deg,
                "scale": r.std_scale,
                "translation_m": r.std_translation_m,
            },
            "split_half": split,
        });
        (
            r.transform,
            r.fitness,
            r.rmse_m,
            fine.iterations + r.iterations,
            r.converged,
            u,
        )
    } else {
        (
            icp_t,
            fine.fitness,
            fine.inlier_rmse,
            fine.iterations,
            fine.converged,
            serde_json::Value::Null,
        )
    };
    // Each control pair's residual under the final transform too (metres, LiDAR frame).
    let pairs: Vec<serde_json::Value> = match &ctx.inputs.control_points {
        Some(path) => {
            let cps = tables::read_control_points(path)?;
            pairs
                .into_iter()
                .zip(&cps)
                .map(|(mut v, c)| {
                    let r = (local.apply(c.sfm) - (c.lidar - offset)).length();
                    v["residual_final_m"] = json!(r);
                    v
                })
                .collect()
        }
        None => pairs,
    };
    let to_file = Similarity {
        translation: local.translation + offset,
        ..local
    };

    // Outputs: the model in the LiDAR frame (local coordinates), and the report.
    let registered = transform_model(&model, &local);
    let sparse = ctx.out_dir.join("sparse");
    std::fs::create_dir_all(&sparse).map_err(|e| IoError::io(&sparse, e))?;
    colmap::write_text(&registered, &sparse)?;
    ctx.progress.set(1.0);
    Ok(json!({
        "sfm_to_lidar": similarity_json(&to_file),
        "sfm_to_lidar_local": similarity_json(&local),
        "lidar_offset": [offset.x, offset.y, offset.z],
        "method": method,
        "coarse": similarity_json(&coarse),
        "pairs": pairs,
        "fitness": fitness,
        "rmse_m": rmse,
        "icp_fitness": fine.fitness,
        "icp_rmse_m": fine.inlier_rmse,
        "icp_iterations": iterations,
        "icp_converged": converged,
        "uncertainty": uncertainty,
        "confidence": confidence,
        "candidates": candidates,
        "sfm_points": sfm.len(),
        "lidar_points_target": target.len(),
        "registered_model_frame": "lidar_local",
    }))
}

/// The surface refinement's parameters from the stage's.
pub fn surface_params(p: &RegisterParams) -> geom::surface::SurfaceParams {
    geom::surface::SurfaceParams {
        radius_m: p.refine_radius_m,
        max_radius_m: p.refine_max_radius_m,
        max_fit_rms_m: p.refine_max_fit_rms_m,
        huber_m: p.refine_huber_m,
        max_distance_m: p.refine_max_distance_m,
        rounds: p.refine_rounds.max(1) as usize,
        estimate_scale: p.estimate_scale,
        ..Default::default()
    }
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}
