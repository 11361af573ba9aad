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

use std::collections::BTreeMap;
use std::path::Path;

use glam::{DMat3, DVec3, Vec3};
use serde_json::json;

use super::ingest::GPS_FILE;
use super::params::{RegisterParams, RegisterStart};
use super::{Stage, StageContext, StageError};
use crate::geom::coarse::CoarseAlignment;
use crate::geom::register::{
    AUTOMATIC_MAX_STD_ROTATION_DEG, AUTOMATIC_MAX_STD_SCALE, AUTOMATIC_REFINE_PASSES, CandidateRun,
    MIN_LAYERED_SHARE, SurfaceEvidence, SurfaceTarget, icp_from, layered_share, refine_on_surface,
    surface_evidence, verify_candidates,
};
use crate::geom::{self, IcpMethod, IcpParams, IcpResult, RobustKernel, Similarity};
use crate::io::colmap::{self, ColmapModel};
use crate::io::gps::GpsFix;
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
    let model = colmap::read_model(
        &ctx.sfm_model_dir(Stage::Register)?,
        &crate::progress::NoProgress,
    )?;
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

/// What one registration works on, in the LiDAR cloud's local frame: the stage's context and
/// parameters, the SfM points and cameras, the cloud, the ICP target thinned from it and the
/// ICP parameters.
struct Aligner<'a, 'c> {
    ctx: &'a StageContext<'c>,
    p: &'a RegisterParams,
    sfm: Vec<DVec3>,
    rays: Vec<(DVec3, DVec3)>,
    cloud: PointCloud,
    target: Vec<Vec3>,
    icp: IcpParams,
    /// The control point pairs, when given: as read, and SfM and LiDAR (local frame) sides.
    control: Option<ControlPairs>,
}

/// The job's control point pairs, read once.
struct ControlPairs {
    points: Vec<tables::ControlPoint>,
    sfm: Vec<DVec3>,
    lidar_local: Vec<DVec3>,
}

/// Where the fine stage starts: the coarse similarity, how it was found, and ICP from it.
struct Start {
    coarse: Similarity,
    /// The report's `method`: `control_points` or `automatic`.
    method: &'static str,
    /// The report's `start`: `control_points`, `search`, `gps` or `model_frame`.
    label: &'static str,
    /// Each control pair's residual under the coarse fit (none without control points).
    pairs: Vec<serde_json::Value>,
    confidence: f64,
    fine: IcpResult,
    /// The report's `candidates` (null with control points).
    candidates: serde_json::Value,
    /// The automatic path's surface and the pose its verification refined to, which the
    /// refinement goes on from.
    verified: Option<(SurfaceTarget, Similarity)>,
    /// The report's `verification` (null with control points): which rule judged the
    /// automatic alignment and its figures.
    verification: serde_json::Value,
}

/// The final pose (local frame) and its figures.
struct Refined {
    transform: Similarity,
    fitness: f64,
    rmse: f64,
    iterations: usize,
    converged: bool,
    /// The report's `uncertainty` (null without the surface refinement).
    uncertainty: serde_json::Value,
}

/// What the georeferenced starts gave when each was verified alone.
struct StartsWeighed {
    /// The best start that passed the gates, with its label and, when the cloud has no
    /// ground under its canopy, the surface evidence that passed it.
    chosen: Option<(
        geom::register::Verified,
        &'static str,
        Option<SurfaceEvidence>,
    )>,
    /// The starts that reached the cloud, passing or not (they compete again in a search).
    competing: Vec<(&'static str, CoarseAlignment)>,
    /// Why each start that did not pass failed.
    failures: Vec<String>,
    /// Every candidate run they made, for a refusal.
    runs: Vec<CandidateRun>,
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
    ctx.progress.set(0.1);
    // ICP target: the LiDAR cloud thinned to `target_voxel_m`.
    let target = geom::voxel_downsample(
        &cloud.positions,
        None,
        p.target_voxel_m as f32,
        &SubProgress::new(ctx.progress, 0.1, 0.05),
    )?
    .positions;
    let offset = cloud.offset;
    let control = match &ctx.inputs.control_points {
        Some(path) => {
            let points = tables::read_control_points(path)?;
            Some(ControlPairs {
                sfm: points.iter().map(|c| c.sfm).collect(),
                lidar_local: points.iter().map(|c| c.lidar - offset).collect(),
                points,
            })
        }
        None => None,
    };
    let a = Aligner {
        ctx,
        p,
        sfm: model.points.iter().map(|p| p.xyz).collect(),
        rays: camera_rays(&model),
        cloud,
        target,
        icp: icp_params(p),
        control,
    };

    let gps = if ctx.inputs.control_points.is_none() && p.start != RegisterStart::Search {
        gps_pairs(ctx, &model, &a.sfm, &a.rays, &a.cloud.positions, offset)?
    } else {
        None
    };
    let mut start = match (&ctx.inputs.control_points, &a.control) {
        (Some(path), Some(c)) => a.control_points(path, c)?,
        _ if !p.automatic => {
            return Err(StageError::Input(
                "control points are required: supply at least 4 pairs (CSV \
                 sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z), or leave \
                 params.register.automatic on (its default) to align automatically"
                    .into(),
            ));
        }
        _ => a.automatic(gps.as_ref())?,
    };
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }
    let fine = &start.fine;
    ctx.progress.log(&format!(
        "ICP: fitness {:.2}, inlier RMSE {:.3} m, scale correction {:.4}, {} iterations",
        fine.fitness, fine.inlier_rmse, fine.scale, fine.iterations
    ));
    let icp_fitness = fine.fitness;
    let icp_rmse = fine.inlier_rmse;
    let (coarse, method, label, confidence) =
        (start.coarse, start.method, start.label, start.confidence);
    let refined = if p.refine {
        a.refine(&mut start)?
    } else {
        Refined {
            transform: coarse.then(&start.fine.transform()),
            fitness: start.fine.fitness,
            rmse: start.fine.inlier_rmse,
            iterations: start.fine.iterations,
            converged: start.fine.converged,
            uncertainty: serde_json::Value::Null,
        }
    };
    let (candidates, mut pairs) = (start.candidates, start.pairs);
    let verification = start.verification;
    let local = refined.transform;
    let gps_report = match &gps {
        Some(g) => a.check_gps(g, &local, method)?,
        None => serde_json::Value::Null,
    };
    let residuals = a.residuals(&local, gps.as_ref())?;
    ctx.progress.log(&format!(
        "registered from the {label} start: SfM points to the cloud median {:.3} m, 90th \
         percentile {:.3} m{}",
        residuals["sfm_to_cloud_median_m"]
            .as_f64()
            .unwrap_or(f64::NAN),
        residuals["sfm_to_cloud_p90_m"].as_f64().unwrap_or(f64::NAN),
        residuals["cameras_to_gps_rms_m"]
            .as_f64()
            .map_or(String::new(), |r| format!(
                "; cameras {r:.2} m (RMS, horizontal) from their GPS positions"
            )),
    ));
    // Each control pair's residual under the final transform too (metres, LiDAR frame).
    if let Some(c) = &a.control {
        for ((v, sfm), lidar) in pairs.iter_mut().zip(&c.sfm).zip(&c.lidar_local) {
            v["residual_final_m"] = json!((local.apply(*sfm) - *lidar).length());
        }
    }
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
        "start": label,
        "gps": gps_report,
        "coarse": similarity_json(&coarse),
        "pairs": pairs,
        "fitness": refined.fitness,
        "rmse_m": refined.rmse,
        "icp_fitness": icp_fitness,
        "icp_rmse_m": icp_rmse,
        "icp_iterations": refined.iterations,
        "icp_converged": refined.converged,
        "uncertainty": refined.uncertainty,
        "confidence": confidence,
        "verification": verification,
        "residuals": residuals,
        "candidates": candidates,
        "sfm_points": a.sfm.len(),
        "lidar_points_target": a.target.len(),
        "registered_model_frame": "lidar_local",
    }))
}

/// [`RegisterParams`] as the geometry's ICP parameters.
fn icp_params(p: &RegisterParams) -> IcpParams {
    IcpParams {
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
    }
}

impl Aligner<'_, '_> {
    /// The report's `residuals` of the final pose `local`: each SfM point's distance to the
    /// nearest point of the ICP target (the cloud thinned to `target_voxel_m`), median and
    /// 90th percentile in metres, and the cameras' RMS horizontal distance from their GPS
    /// positions (null without GPS).
    fn residuals(
        &self,
        local: &Similarity,
        gps: Option<&GpsPairs>,
    ) -> Result<serde_json::Value, StageError> {
        let index = geom::PointIndex::new(&self.target)?;
        let moved: Vec<Vec3> = self.sfm.iter().map(|x| local.apply(*x).as_vec3()).collect();
        let mut d: Vec<f64> = index
            .nearest_batch(&moved, &crate::progress::NoProgress)?
            .iter()
            .map(|n| n.map_or(f64::INFINITY, |n| f64::from(n.dist2).sqrt()))
            .collect();
        d.sort_by(f64::total_cmp);
        let at = |q: f64| {
            d.get(((d.len().max(1) - 1) as f64 * q).round() as usize)
                .copied()
        };
        Ok(json!({
            "sfm_to_cloud_median_m": at(0.5),
            "sfm_to_cloud_p90_m": at(0.9),
            "cameras_to_gps_rms_m": gps.map(|g| g.rms_under(local)),
        }))
    }

    /// The coarse similarity from the control point pairs (Umeyama), and ICP from it.
    fn control_points(&self, path: &Path, c: &ControlPairs) -> Result<Start, StageError> {
        let fit = geom::similarity_from_pairs(&c.sfm, &c.lidar_local, true)
            .map_err(|e| StageError::Input(format!("{}: {e}", file_name(path))))?;
        let cps = &c.points;
        let pairs: Vec<serde_json::Value> = cps
            .iter()
            .zip(&fit.residuals)
            .map(|(c, r)| json!({ "name": c.name, "residual_m": r }))
            .collect();
        self.ctx.progress.log(&format!(
            "control points: {} pairs, RMSE {:.3} m",
            cps.len(),
            fit.rmse
        ));
        if self.ctx.progress.is_cancelled() {
            return Err(StageError::Cancelled);
        }
        let icp_progress = SubProgress::new(self.ctx.progress, 0.5, 0.4);
        let fine = icp_from(
            &self.sfm,
            &fit.transform,
            &self.target,
            &self.icp,
            &icp_progress,
        )?;
        Ok(Start {
            coarse: fit.transform,
            method: "control_points",
            label: "control_points",
            pairs,
            confidence: 1.0,
            fine,
            candidates: serde_json::Value::Null,
            verified: None,
            verification: serde_json::Value::Null,
        })
    }

    /// The automatic alignment: the georeferenced starts the data give, each verified alone;
    /// when none passes (or there is none), the search over yaw, scale and offset, with the
    /// starts that reached the cloud competing. Refuses when no candidate clearly puts the
    /// SfM points on the cloud.
    fn automatic(&self, gps: Option<&GpsPairs>) -> Result<Start, StageError> {
        let (ctx, p) = (self.ctx, self.p);
        let st = SurfaceTarget::new(
            &self.cloud.positions,
            p.refine_voxel_m,
            &SubProgress::new(ctx.progress, 0.12, 0.03),
        )?;
        let starts = georeferenced_starts(ctx, &self.sfm, &self.cloud, gps)?;
        let layered = layered_share(&self.target);
        ctx.progress.log(&format!(
            "{:.3} of the cloud's points stand more than 0.5 m above the lowest of their 0.5 m \
             cell: {}",
            layered,
            if layered >= MIN_LAYERED_SHARE {
                "it sees ground under the trees"
            } else {
                "a surface without ground under the canopy (a georeferenced start is verified \
                 by the surface evidence)"
            }
        ));
        let surface_gps = (layered < MIN_LAYERED_SHARE)
            .then(|| gps.and_then(|g| g.fit.as_ref()))
            .flatten();
        let weighed_starts = self.verify_starts(&starts, &st, surface_gps)?;
        if weighed_starts.chosen.is_none() && !starts.is_empty() {
            if p.start != RegisterStart::Auto {
                let labels: Vec<&str> = weighed_starts.competing.iter().map(|s| s.0).collect();
                return Err(refused(
                    &weighed_starts.runs,
                    &labels,
                    format!(
                        "automatic registration rejected: {}. {}. Set \
                         params.register.start = \"search\" to search without it, or \
                         {SUPPLY_CONTROL_POINTS}",
                        weighed_starts.failures.join("; "),
                        weighed(&weighed_starts.runs)
                    ),
                ));
            }
            ctx.progress.log(
                "no georeferenced start verified; searching over yaw, scale and offset instead",
            );
        }
        let (v, label, evidence) = match weighed_starts.chosen {
            Some(found) => found,
            None => {
                let (v, label) = self.search(&weighed_starts.competing, &st)?;
                (v, label, None)
            }
        };
        let verification = match &evidence {
            Some(e) => json!({
                "rule": "surface",
                "layered_share": layered,
                "on_cloud": e.on_cloud,
                "shift_m": e.shift_m,
                "shifted_on_cloud": e.shifted,
                "peak_sigmas": e.peak_sigmas,
            }),
            None => json!({
                "rule": "elevated",
                "layered_share": layered,
                "on_cloud": v.best_fit,
                "elevated_on_cloud": v.best_elevated,
                "runner_up": v.runner_up,
            }),
        };
        Ok(Start {
            coarse: v.coarse,
            method: "automatic",
            label,
            pairs: Vec::new(),
            confidence: v.confidence,
            candidates: candidates_json(&v.candidates),
            fine: v.fine,
            verified: Some((st, v.refined)),
            verification,
        })
    }

    /// Verifies each georeferenced start on its own (one far off the cloud, as from a wrong
    /// CRS, fails ICP without taking the others down) and keeps the best that passes the
    /// gates. `surface_gps`: the GPS fit when the cloud has no ground under its canopy; the
    /// `gps` start is then judged by [`surface_evidence`] instead of the elevated share
    /// (docs/method.md, Stage 1): a GPS fit within the ICP's first correspondence distance,
    /// and a pose whose on-cloud share is a peak against the pose moved by three times the
    /// fit's RMS (at least that distance).
    fn verify_starts(
        &self,
        starts: &[(&'static str, CoarseAlignment)],
        st: &SurfaceTarget,
        surface_gps: Option<&geom::coarse::PositionFit>,
    ) -> Result<StartsWeighed, StageError> {
        let (ctx, p) = (self.ctx, self.p);
        let mut out = StartsWeighed {
            chosen: None,
            competing: Vec::new(),
            failures: Vec::new(),
            runs: Vec::new(),
        };
        for (k, (label, start)) in starts.iter().enumerate() {
            let share = 0.15 / starts.len() as f64;
            let verified = verify_candidates(
                &self.sfm,
                std::slice::from_ref(start),
                &self.target,
                &self.icp,
                st,
                &surface_params(p),
                &SubProgress::new(ctx.progress, 0.15 + share * k as f64, share),
            );
            let mut v = match verified {
                Ok(v) => v,
                Err(geom::GeomError::Cancelled) => return Err(StageError::Cancelled),
                Err(e) => {
                    ctx.progress
                        .log(&format!("the {label} start does not reach the cloud: {e}"));
                    out.failures
                        .push(format!("the {label} start does not reach the cloud ({e})"));
                    continue;
                }
            };
            let mut evidence = None;
            if let (Some(fit), "gps") = (surface_gps, *label) {
                let e = surface_evidence(
                    &self.sfm,
                    &v.refined,
                    &geom::PointIndex::new(&self.target)?,
                    (3.0 * fit.rms_m).max(p.icp_max_distance_m),
                );
                let gps_ok = fit.rms_m <= p.icp_max_distance_m;
                ctx.progress.log(&format!(
                    "{label} start on a cloud without ground: GPS fit {:.2} m RMS ({} the \
                     ICP's reach of {:.2} m); on-cloud share {:.3}, at most {:.3} with the \
                     pose moved {:.2} m ({:.1} standard errors below)",
                    fit.rms_m,
                    if gps_ok { "within" } else { "beyond" },
                    p.icp_max_distance_m,
                    e.on_cloud,
                    e.shifted,
                    e.shift_m,
                    e.peak_sigmas
                ));
                v.confidence = if gps_ok { e.confidence() } else { 0.0 };
                evidence = Some(e);
            }
            ctx.progress.log(&format!(
                "{label} start: on-cloud share {:.3} (elevated {:.3}); confidence {:.2}",
                v.best_fit, v.best_elevated, v.confidence
            ));
            out.runs.extend(v.candidates.iter().copied());
            out.competing.push((label, start.clone()));
            let passes = v.best_fit >= p.min_fitness && v.confidence >= p.min_confidence;
            if !passes {
                out.failures.push(format!(
                    "from the {label} start ICP and the surface refinement put {:.0}% of the \
                     SfM points on the LiDAR cloud (at least {:.0}% needed) with confidence \
                     {:.2} (at least {:.2} needed)",
                    v.best_fit * 100.0,
                    p.min_fitness * 100.0,
                    v.confidence,
                    p.min_confidence
                ));
            } else if out
                .chosen
                .as_ref()
                .is_none_or(|(c, _, _)| v.best_fit + v.best_elevated > c.best_fit + c.best_elevated)
            {
                out.chosen = Some((v, label, evidence));
            }
        }
        Ok(out)
    }

    /// The search over yaw, scale and offset ([`geom::coarse::align_candidates`]), its
    /// candidates and the georeferenced starts in `competing` verified together; refuses
    /// when the best is not on the cloud or not clearly better than the others.
    fn search(
        &self,
        competing: &[(&'static str, CoarseAlignment)],
        st: &SurfaceTarget,
    ) -> Result<(geom::register::Verified, &'static str), StageError> {
        let (ctx, p) = (self.ctx, self.p);
        let mut cands = geom::coarse::align_candidates(
            &self.sfm,
            &self.rays,
            &self.cloud.positions,
            &geom::coarse::CoarseParams::default(),
            &SubProgress::new(ctx.progress, 0.3, 0.2),
        )
        .map_err(|e| match e {
            geom::GeomError::Cancelled => StageError::Cancelled,
            other => StageError::Input(format!(
                "automatic registration failed ({other}); {SUPPLY_CONTROL_POINTS}"
            )),
        })?;
        if cands.is_empty() {
            return Err(StageError::Input(format!(
                "automatic registration found no candidate alignment; {SUPPLY_CONTROL_POINTS}"
            )));
        }
        // A georeferenced start that reached the cloud but did not verify alone still
        // competes.
        let mut labels = vec!["search"; cands.len()];
        labels.extend(competing.iter().map(|s| s.0));
        cands.extend(competing.iter().map(|s| s.1.clone()));
        let v = verify_candidates(
            &self.sfm,
            &cands,
            &self.target,
            &self.icp,
            st,
            &surface_params(p),
            &SubProgress::new(ctx.progress, 0.55, 0.35),
        )?;
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
            return Err(refused(
                &v.candidates,
                &labels,
                format!(
                    "automatic registration rejected: after ICP and the surface refinement only \
                     {:.0}% of the SfM points lie on the LiDAR cloud (< {:.0}%); the photos and \
                     the scan may not overlap. {}; {SUPPLY_CONTROL_POINTS}",
                    v.best_fit * 100.0,
                    p.min_fitness * 100.0,
                    weighed(&v.candidates)
                ),
            ));
        }
        if v.confidence < p.min_confidence {
            return Err(refused(
                &v.candidates,
                &labels,
                format!(
                    "automatic registration is not confident enough ({:.2} < {:.2}): no \
                     candidate alignment clearly puts the photos' points on the LiDAR cloud \
                     (the best scores {:.2}, the best distinct other {:.2}); the photos and the \
                     scan may not overlap. {}; {SUPPLY_CONTROL_POINTS}",
                    v.confidence,
                    p.min_confidence,
                    v.best_fit + v.best_elevated,
                    v.runner_up,
                    weighed(&v.candidates)
                ),
            ));
        }
        let best = v
            .candidates
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.score().total_cmp(&b.1.score()))
            .map_or(0, |(i, _)| i);
        let label = labels.get(best).copied().unwrap_or("search");
        Ok((v, label))
    }

    /// The surface refinement from `start` (the automatic path's verified pose, else ICP's),
    /// with the control points as extra observations when there are any, and its standard
    /// errors: per parameter the larger of the normal matrix's and the split halves' spread.
    /// Refuses an automatic alignment that the SfM points do not pin down.
    fn refine(&self, start: &mut Start) -> Result<Refined, StageError> {
        let (ctx, p) = (self.ctx, self.p);
        let automatic = start.method == "automatic";
        let (surface, from) = match start.verified.take() {
            Some((surface, refined)) => (surface, refined),
            None => (
                SurfaceTarget::new(
                    &self.cloud.positions,
                    p.refine_voxel_m,
                    &SubProgress::new(ctx.progress, 0.9, 0.02),
                )?,
                start.coarse.then(&start.fine.transform()),
            ),
        };
        let r = refine_on_surface(
            &self.sfm,
            &surface,
            &from,
            self.control.as_ref().map(|c| geom::surface::PairPrior {
                sfm: &c.sfm,
                lidar: &c.lidar_local,
                sigma_m: p.control_point_sigma_m,
            }),
            &surface_params(p),
            // Without control points the pose after ICP is often still tenths of a degree and
            // about a percent off (docs/results/registration.md: stand 1 left ICP at 0.37° and
            // 1.2 %); further passes carry the refinement on from where the last stopped.
            if automatic {
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
                &self.sfm,
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
        if automatic
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
        Ok(Refined {
            transform: r.transform,
            fitness: r.fitness,
            rmse: r.rmse_m,
            iterations: start.fine.iterations + r.iterations,
            converged: r.converged,
            uncertainty: json!({
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
            }),
        })
    }

    /// The photos' GPS positions against where the alignment `local` puts their cameras: the
    /// report's `gps`. Refuses an automatic alignment that puts them more than
    /// `max_gps_disagreement_m` (or 3× the GPS fit's RMS) away.
    fn check_gps(
        &self,
        g: &GpsPairs,
        local: &Similarity,
        method: &str,
    ) -> Result<serde_json::Value, StageError> {
        let fit = g.fit.as_ref();
        let final_rms = g.rms_under(local);
        let bound = self
            .p
            .max_gps_disagreement_m
            .max(fit.map_or(0.0, |f| 3.0 * f.rms_m));
        self.ctx.progress.log(&format!(
            "GPS: {} photos with a position; the alignment puts their cameras {final_rms:.2} m \
             (RMS, horizontal) from them",
            g.pairs.len()
        ));
        if method == "automatic" && final_rms > bound {
            return Err(StageError::Input(format!(
                "automatic registration contradicts the photos' GPS positions: it puts the \
                 cameras {final_rms:.1} m (RMS, horizontal) from where their GPS says they \
                 were (at most {bound:.1} m accepted). Check the LiDAR's CRS (params.crs), \
                 set params.register.start = \"search\" to ignore the GPS, or \
                 {SUPPLY_CONTROL_POINTS}"
            )));
        }
        Ok(json!({
            "photos": g.pairs.len(),
            "fit_used": fit.map(|f| f.used),
            "fit_rms_m": fit.map(|f| f.rms_m),
            "fit_yaw_std_deg": fit.map(|f| f.yaw_std_deg),
            "fit_error": g.fit_error,
            "final_rms_m": final_rms,
        }))
    }
}

/// The photos' GPS positions (stage `ingest`'s gps.json) paired with their cameras, in the
/// LiDAR cloud's local frame, and the coarse alignment they give.
struct GpsPairs {
    /// (camera centre in the SfM frame, GPS position: x, y projected into the LiDAR's CRS,
    /// z the EXIF altitude, all minus the ingest offset) per photo with a position.
    pairs: Vec<(DVec3, DVec3)>,
    /// The start from them ([`geom::coarse::from_positions`]), or why there is none.
    fit: Option<geom::coarse::PositionFit>,
    fit_error: Option<String>,
}

impl GpsPairs {
    /// RMS horizontal distance, metres, between the cameras moved by `t` and their GPS
    /// positions.
    fn rms_under(&self, t: &Similarity) -> f64 {
        let sq: f64 = self
            .pairs
            .iter()
            .map(|(c, g)| (t.apply(*c) - *g).truncate().length_squared())
            .sum();
        (sq / self.pairs.len().max(1) as f64).sqrt()
    }
}

/// The photos' GPS positions with their cameras, when ingest found any and the LiDAR's CRS
/// is known (else `None`, saying why in the log; an error when `start` is `gps`).
fn gps_pairs(
    ctx: &StageContext<'_>,
    model: &ColmapModel,
    sfm: &[DVec3],
    rays: &[(DVec3, DVec3)],
    lidar: &[Vec3],
    offset: DVec3,
) -> Result<Option<GpsPairs>, StageError> {
    let p = &ctx.params.register;
    let forced = p.start == RegisterStart::Gps;
    let ingest = ctx.output_of(Stage::Ingest, Stage::Register)?;
    let path = ingest.join(GPS_FILE);
    let fixes: BTreeMap<String, GpsFix> = match std::fs::read(&path) {
        Ok(bytes) => serde_json::from_slice(&bytes)
            .map_err(|e| IoError::format(&path, format!("GPS positions: {e}")))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if forced {
                return Err(StageError::Input(
                    "params.register.start is \"gps\" but no registered photo carries a GPS \
                     position (EXIF GPSLatitude/GPSLongitude)"
                        .into(),
                ));
            }
            return Ok(None);
        }
        Err(e) => return Err(IoError::io(&path, e).into()),
    };
    let crs = crate::forest::output::read_crs(&ingest)?;
    let Some(crs) = crs.crs else {
        let why = format!(
            "{} photos carry GPS positions, but the LiDAR's CRS is unknown, so they cannot be \
             placed on the cloud; give it with params.crs to start from them",
            fixes.len()
        );
        if forced {
            return Err(StageError::Input(why));
        }
        ctx.progress.log(&why);
        return Ok(None);
    };
    let mut pairs = Vec::new();
    for im in model.images.values() {
        let Some(fix) = fixes.get(&im.name) else {
            continue;
        };
        let mut xy = [(fix.lon, fix.lat)];
        crs.from_wgs84(&mut xy)
            .map_err(|e| StageError::Input(format!("GPS position of {}: {e}", im.name)))?;
        let centre = geom::register::camera_ray(im.qvec, im.tvec).0;
        let gps = DVec3::new(xy[0].0, xy[0].1, fix.alt.unwrap_or(offset.z)) - offset;
        pairs.push((centre, gps));
    }
    if pairs.is_empty() {
        return Ok(None);
    }
    let (fit, fit_error) = match geom::coarse::from_positions(sfm, rays, &pairs, lidar) {
        Ok(f) => (Some(f), None),
        Err(e) if forced => {
            return Err(StageError::Input(format!(
                "the photos' GPS positions give no start: {e}"
            )));
        }
        Err(e) => (None, Some(e.to_string())),
    };
    Ok(Some(GpsPairs {
        pairs,
        fit,
        fit_error,
    }))
}

/// Whether the COLMAP model's points, read as LiDAR file coordinates, mostly lie within the
/// LiDAR cloud's extent widened by 20 m (100 m vertically): then its frame is probably the
/// LiDAR's CRS already.
fn model_in_lidar_frame(sfm: &[DVec3], cloud: &PointCloud) -> bool {
    let Some((lo, hi)) = cloud.bounds() else {
        return false;
    };
    let margin = DVec3::new(20.0, 20.0, 100.0);
    let (lo, hi) = (lo - margin, hi + margin);
    let inside = sfm
        .iter()
        .filter(|q| q.cmpge(lo).all() && q.cmple(hi).all())
        .count();
    !sfm.is_empty() && inside * 2 >= sfm.len()
}

/// The georeferenced starts `params.register.start` asks for, labelled: `model_frame` (the
/// model's coordinates taken as the LiDAR file's, its height settled on the terrain) and
/// `gps` (from the photos' positions). `auto` takes those the data give.
fn georeferenced_starts(
    ctx: &StageContext<'_>,
    sfm: &[DVec3],
    cloud: &PointCloud,
    gps: Option<&GpsPairs>,
) -> Result<Vec<(&'static str, CoarseAlignment)>, StageError> {
    let p = &ctx.params.register;
    let mut starts = Vec::new();
    let frame = match p.start {
        RegisterStart::ModelFrame => true,
        RegisterStart::Auto => model_in_lidar_frame(sfm, cloud),
        _ => false,
    };
    if frame {
        let identity = Similarity {
            scale: 1.0,
            rotation: DMat3::IDENTITY,
            translation: -cloud.offset,
        };
        let t = geom::coarse::on_terrain(&identity, sfm, &cloud.positions);
        ctx.progress.log(&format!(
            "the COLMAP model's frame is taken as the LiDAR's (height moved {:.2} m onto the \
             terrain)",
            t.translation.z - identity.translation.z
        ));
        starts.push(("model_frame", CoarseAlignment::fixed(t)));
    }
    if matches!(p.start, RegisterStart::Auto | RegisterStart::Gps)
        && let Some(g) = gps
    {
        match (&g.fit, &g.fit_error) {
            (Some(fit), _) => {
                ctx.progress.log(&format!(
                    "GPS start: {} of {} photos' positions fit their cameras to {:.2} m RMS; \
                     yaw {:.1}° ± {:.2}°, scale {:.4}",
                    fit.used,
                    fit.given,
                    fit.rms_m,
                    fit.alignment.yaw_deg,
                    fit.yaw_std_deg,
                    fit.alignment.scale
                ));
                starts.push(("gps", fit.alignment.clone()));
            }
            (None, why) => ctx.progress.log(&format!(
                "the photos' GPS positions give no start: {}",
                why.as_deref().unwrap_or("no fit")
            )),
        }
    }
    Ok(starts)
}

/// A refusal of the automatic alignment: `detail`, with every candidate it weighed
/// (labelled by where it started) for the job's problem and the web page.
fn refused(runs: &[CandidateRun], labels: &[&str], detail: String) -> StageError {
    let candidates = runs
        .iter()
        .zip(labels.iter().chain(std::iter::repeat(&"search")))
        .map(|(r, start)| {
            json!({
                "start": start,
                "on_cloud": r.on_cloud,
                "elevated_on_cloud": r.elevated_on_cloud,
                "elevated_points": r.elevated_points,
                "rotation_deg": r.refined.rotation_angle_deg(),
                "scale": r.refined.scale,
                "icp_fitness": r.fine.fitness,
            })
        })
        .collect();
    StageError::Refused { detail, candidates }
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
