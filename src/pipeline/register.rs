//! Stage `register`: the similarity that maps the SfM frame onto the LiDAR frame
//! (docs/method.md Stage 1), and the COLMAP model moved into the LiDAR frame.
//!
//! Coarse: from control point pairs (Umeyama, residual per pair) or, without them, the
//! automatic alignment of [`crate::geom::coarse`]. Fine: ICP of the SfM points onto the
//! LiDAR cloud thinned to `target_voxel_m`, estimating scale too; then the surface
//! refinement of [`crate::geom::surface`] (similarity Gauss-Newton of the SfM points onto
//! quadric patches of the LiDAR surface, the control points as extra observations), whose
//! standard errors the report gives as `uncertainty`: per parameter the larger of the
//! normal-matrix error and the spread over split halves of the SfM points (both are in the
//! report too, as `normal_matrix` and `split_half`). Everything runs in the
//! LiDAR cloud's local frame (file coordinates minus the ingest offset) so f32 positions stay
//! precise; the report gives `sfm_to_lidar` in the file's own coordinates.

use std::path::Path;

use glam::{DMat3, DQuat, DVec3, Vec3};
use serde_json::json;

use super::{Stage, StageContext, StageError};
use crate::geom::{self, IcpMethod, IcpParams, RobustKernel, Similarity, VoxelParams};
use crate::io::colmap::{self, ColmapModel};
use crate::io::pointcloud::{self, PointCloud};
use crate::io::{IoError, tables};
use crate::progress::{Progress, SubProgress};

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
/// (C' = s R C + t), camera rotations turn (R_cw' = R_cw Rᵀ); intrinsics are unchanged.
pub fn transform_model(model: &ColmapModel, s: &Similarity) -> ColmapModel {
    let mut out = model.clone();
    let rt = s.rotation.transpose();
    for im in out.images.values_mut() {
        let q = DQuat::from_xyzw(im.qvec[1], im.qvec[2], im.qvec[3], im.qvec[0]).normalize();
        let r_cw = DMat3::from_quat(q);
        let t_cw = DVec3::from_array(im.tvec);
        let r_new = r_cw * rt;
        let t_new = t_cw * s.scale - r_new * s.translation;
        let mut qn = DQuat::from_mat3(&r_new).normalize();
        if qn.w < 0.0 {
            qn = -qn;
        }
        im.qvec = [qn.w, qn.x, qn.y, qn.z];
        im.tvec = t_new.to_array();
    }
    for p in &mut out.points {
        p.xyz = s.apply(p.xyz);
    }
    out
}

/// Camera centre (world) and viewing direction (world) of every registered image.
pub fn camera_rays(model: &ColmapModel) -> Vec<(DVec3, DVec3)> {
    model
        .images
        .values()
        .map(|im| {
            let q = DQuat::from_xyzw(im.qvec[1], im.qvec[2], im.qvec[3], im.qvec[0]).normalize();
            let r_wc = DMat3::from_quat(q).transpose();
            let centre = -(r_wc * DVec3::from_array(im.tvec));
            (centre, r_wc * DVec3::Z)
        })
        .collect()
}

fn load_inputs(ctx: &StageContext<'_>) -> Result<(PointCloud, ColmapModel), StageError> {
    let ingest = ctx.output_of(Stage::Ingest, Stage::Register)?;
    let cloud = pointcloud::read_point_cloud(
        &ingest.join("cloud.ply"),
        &SubProgress::new(ctx.progress, 0.0, 0.1),
    )?;
    let model = colmap::read_model(&ingest.join("sparse"), &crate::progress::NoProgress)?;
    Ok((cloud, model))
}

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
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
            let source: Vec<Vec3> = sfm
                .iter()
                .map(|x| fit.transform.apply(*x).as_vec3())
                .collect();
            let fine = icp_two_phase(
                &source,
                &target,
                &params,
                &SubProgress::new(ctx.progress, 0.5, 0.4),
            )?;
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
                 sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z), or set \
                 params.register.automatic = true to try the experimental automatic alignment"
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
                p,
                &SubProgress::new(ctx.progress, 0.5, 0.05),
            )?;
            let v = verify_candidates(
                &sfm,
                &cands,
                &target,
                &params,
                &st,
                p,
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
                     and the scan may not overlap; supply control points (at least 4 pairs)",
                    v.best_fit * 100.0,
                    p.min_fitness * 100.0
                )));
            }
            if v.confidence < p.min_confidence {
                return Err(StageError::Input(format!(
                    "automatic registration is not confident enough ({:.2} < {:.2}): no \
                     candidate alignment clearly puts the photos' points on the LiDAR cloud; \
                     the photos and the scan may not overlap; supply control points (at least \
                     4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)",
                    v.confidence, p.min_confidence
                )));
            }
            (
                v.coarse,
                "automatic",
                Vec::new(),
                v.confidence,
                v.fine,
                v.table,
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
                p,
                &SubProgress::new(ctx.progress, 0.9, 0.02),
            )?,
        };
        let r = refine_on_surface(
            &sfm,
            &surface,
            &refine_start.unwrap_or(icp_t),
            pairs_local
                .as_ref()
                .map(|(a, b)| (a.as_slice(), b.as_slice())),
            p,
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

/// ICP rigid first, then with scale from there: the point-to-point similarity step is
/// unstable when scale and rotation are both off, a rigid phase settles the rotation first.
pub fn icp_two_phase(
    source: &[Vec3],
    target: &[Vec3],
    params: &IcpParams,
    progress: &dyn Progress,
) -> Result<geom::IcpResult, StageError> {
    let index = geom::PointIndex::new(target)?;
    let normals = if params.method == IcpMethod::PointToPlane {
        Some(
            geom::estimate_normals_with_index(
                target,
                &index,
                &geom::NormalParams {
                    k: params.normal_k,
                    orientation: geom::NormalOrientation::None,
                },
                &SubProgress::new(progress, 0.0, 0.3),
            )?
            .normals,
        )
    } else {
        None
    };
    let rigid = IcpParams {
        estimate_scale: false,
        ..*params
    };
    let first = geom::icp_with_index(
        source,
        target,
        &index,
        normals.as_deref(),
        &Similarity::IDENTITY,
        &rigid,
        &SubProgress::new(progress, 0.3, 0.35),
    )?;
    if !params.estimate_scale {
        return Ok(first);
    }
    let second = IcpParams {
        start_distance: first.max_distance.max(params.min_distance) * 2.0,
        ..*params
    };
    geom::icp_with_index(
        source,
        target,
        &index,
        normals.as_deref(),
        &first.transform(),
        &second,
        &SubProgress::new(progress, 0.65, 0.35),
    )
    .map_err(StageError::from)
}

/// The LiDAR cloud thinned to `refine_voxel_m` and indexed: the surface the refinement fits
/// patches to.
pub struct SurfaceTarget {
    pub thin: Vec<Vec3>,
    pub index: geom::PointIndex,
}

impl SurfaceTarget {
    pub fn new(
        lidar: &[Vec3],
        p: &super::params::RegisterParams,
        progress: &dyn Progress,
    ) -> Result<SurfaceTarget, StageError> {
        let thin = geom::voxel_downsample(
            lidar,
            None,
            &VoxelParams {
                voxel_size: p.refine_voxel_m as f32,
            },
            progress,
        )?
        .positions;
        let index = geom::PointIndex::new(&thin)?;
        Ok(SurfaceTarget { thin, index })
    }
}

/// The final refinement ([`geom::surface`]): from `initial` (SfM → LiDAR local), the
/// similarity that puts the SfM points on the LiDAR surface thinned to `refine_voxel_m`, with
/// the control point pairs (SfM, LiDAR local) as extra observations when given. Up to
/// `passes` runs of the refinement, each from the last one's result, stopping once a pass
/// no longer moves the pose.
pub fn refine_on_surface(
    sfm: &[DVec3],
    surface: &SurfaceTarget,
    initial: &Similarity,
    pairs: Option<(&[DVec3], &[DVec3])>,
    p: &super::params::RegisterParams,
    passes: usize,
    progress: &dyn Progress,
) -> Result<geom::surface::SurfaceResult, StageError> {
    let (thin, index) = (&surface.thin, &surface.index);
    let params = surface_params(p);
    let mut start = *initial;
    let mut iterations = 0;
    let passes = passes.max(1);
    for pass in 0..passes {
        let r = geom::surface::refine_on_surface(
            sfm,
            None,
            thin,
            index,
            &start,
            pairs.map(|(sfm, lidar)| geom::surface::PairPrior {
                sfm,
                lidar,
                sigma_m: p.control_point_sigma_m,
            }),
            &params,
            &SubProgress::new(
                progress,
                0.4 + 0.6 * pass as f64 / passes as f64,
                0.6 / passes as f64,
            ),
        )?;
        iterations += r.iterations;
        // Settled: the pass moved the pose by less than 0.001°, 0.001 % and 0.1 mm at the
        // points' centroid (well below the goals of 0.05°, 0.1 % and 1 cm).
        let rel = start.inverse().then(&r.transform);
        let centroid = sfm.iter().copied().sum::<DVec3>() / sfm.len().max(1) as f64;
        let moved = (r.transform.apply(centroid) - start.apply(centroid)).length();
        let settled =
            rel.rotation_angle_deg() < 1e-3 && (rel.scale - 1.0).abs() < 1e-5 && moved < 1e-4;
        if settled || pass + 1 == passes {
            return Ok(geom::surface::SurfaceResult { iterations, ..r });
        }
        start = r.transform;
    }
    Err(StageError::Input("surface refinement ran no pass".into()))
}

/// The surface refinement's parameters from the stage's.
pub fn surface_params(p: &super::params::RegisterParams) -> geom::surface::SurfaceParams {
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

/// Passes of the surface refinement from each automatic candidate and again for the chosen
/// one (see [`refine_on_surface`]); it stops earlier once a pass no longer moves the pose.
/// One pass left the light stand of the tests 0.7° off (elevated on-cloud share 0.11, too
/// low to be told from a wrong pose); five brought it to 0.05° (0.38).
const AUTOMATIC_REFINE_PASSES: usize = 5;

/// Without control points the surface refinement must pin the rotation to this standard
/// error (degrees, the norm over the three axes; the larger of the normal-matrix and the
/// split-half error per axis) or the stage refuses: 0.025° puts the goal of 0.05° (issue 4)
/// at 2 sigma, a 95 % chance of meeting it. When the gate read the normal matrix alone it
/// stood at 2.5 sigma, because that matrix read the yaw 1.3-1.9 times too tight on `tiny`
/// (20 draws of seed 4's SfM noise spread its yaw by 0.028° where it said 0.020°); the
/// split halves measure the spread on the data (docs/results/registration.md). Measured: `stand`
/// 0.003-0.006°, `tiny` 0.018-0.039°.
const AUTOMATIC_MAX_STD_ROTATION_DEG: f64 = 0.025;
/// The same for the scale (relative): 0.05 % puts the goal of 0.1 % at 2 sigma (measured:
/// `stand` 0.004 %, light stand 0.02 %, `tiny` 0.017-0.028 %).
const AUTOMATIC_MAX_STD_SCALE: f64 = 0.0005;

/// The automatic alignment chosen among the coarse candidates.
pub struct Verified {
    /// The chosen candidate's coarse similarity and the ICP result from it.
    pub coarse: Similarity,
    pub fine: geom::IcpResult,
    /// The chosen candidate after ICP and one pass of the surface refinement.
    pub refined: Similarity,
    /// Share of SfM points on the LiDAR cloud after ICP and one surface pass (see
    /// [`on_cloud_shares`]), the same for the elevated ones, and the best distinct other
    /// candidate's score (on-cloud plus elevated on-cloud share).
    pub best_fit: f64,
    pub best_elevated: f64,
    pub runner_up: f64,
    pub confidence: f64,
    /// Every candidate's coarse and final similarity and scores (the report's `candidates`).
    pub table: serde_json::Value,
}

/// An SfM point is on the LiDAR cloud when the thinned cloud has a point within this distance
/// (metres): the 5 cm voxel grid leaves surface points up to ~3.5 cm from the nearest kept
/// point, plus ~1 cm SfM noise.
const ON_CLOUD_M: f64 = 0.06;
/// A point this far above the LiDAR's local ground is "elevated" (stems, stones, crowns),
/// metres: above the `tiny`/`stand` terrain relief within the ground window.
const ELEVATED_M: f64 = 0.5;

/// Lowest point of the cloud per 0.5 m cell, then the lowest within ±1 m: the local ground
/// (none for a cloud over 4 km across: no point then counts as elevated, and the automatic
/// alignment gets no confidence).
struct GroundGrid {
    x0: f64,
    y0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    z: Vec<f64>,
}

impl GroundGrid {
    fn new(points: &[Vec3]) -> Option<GroundGrid> {
        let cell = 0.5;
        let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
        for p in points {
            lo = lo.min(p.as_dvec3());
            hi = hi.max(p.as_dvec3());
        }
        if points.is_empty() {
            return None;
        }
        let nx = ((hi.x - lo.x) / cell).floor() as usize + 1;
        let ny = ((hi.y - lo.y) / cell).floor() as usize + 1;
        if nx.saturating_mul(ny) > 64_000_000 {
            return None;
        }
        let mut z = vec![f64::NAN; nx * ny];
        for p in points {
            let i = ((f64::from(p.x) - lo.x) / cell) as usize;
            let j = ((f64::from(p.y) - lo.y) / cell) as usize;
            let k = j.min(ny - 1) * nx + i.min(nx - 1);
            let v = f64::from(p.z);
            if z[k].is_nan() || v < z[k] {
                z[k] = v;
            }
        }
        let mut out = vec![f64::NAN; nx * ny];
        for j in 0..ny {
            for i in 0..nx {
                let mut m = f64::NAN;
                for b in j.saturating_sub(2)..(j + 3).min(ny) {
                    for a in i.saturating_sub(2)..(i + 3).min(nx) {
                        let v = z[b * nx + a];
                        if !v.is_nan() && (m.is_nan() || v < m) {
                            m = v;
                        }
                    }
                }
                out[j * nx + i] = m;
            }
        }
        Some(GroundGrid {
            x0: lo.x,
            y0: lo.y,
            cell,
            nx,
            ny,
            z: out,
        })
    }

    /// Ground height under (x, y), None outside the cloud.
    fn at(&self, x: f64, y: f64) -> Option<f64> {
        let i = ((x - self.x0) / self.cell).floor();
        let j = ((y - self.y0) / self.cell).floor();
        if i < 0.0 || j < 0.0 || i >= self.nx as f64 || j >= self.ny as f64 {
            return None;
        }
        let v = self.z[j as usize * self.nx + i as usize];
        (!v.is_nan()).then_some(v)
    }
}

/// Share of the SfM points that lie on the LiDAR cloud under `t` (nearest thinned LiDAR
/// point within [`ON_CLOUD_M`]), the same share among the elevated points (more than
/// [`ELEVATED_M`] above the LiDAR's local ground: flat ground fits under a wrong yaw too,
/// stems and crowns do not), and how many points are elevated.
fn on_cloud_shares(
    sfm: &[DVec3],
    t: &Similarity,
    index: &geom::PointIndex,
    ground: Option<&GroundGrid>,
) -> (f64, f64, usize) {
    use rayon::prelude::*;
    let (on, elevated, on_elevated) = sfm
        .par_iter()
        .map(|p| {
            let q = t.apply(*p);
            let on = index
                .nearest(q.as_vec3())
                .is_some_and(|n| f64::from(n.dist2).sqrt() <= ON_CLOUD_M);
            let up = ground
                .and_then(|g| g.at(q.x, q.y))
                .is_some_and(|z| q.z - z > ELEVATED_M);
            (usize::from(on), usize::from(up), usize::from(on && up))
        })
        .reduce(|| (0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    (
        on as f64 / sfm.len().max(1) as f64,
        on_elevated as f64 / elevated.max(1) as f64,
        elevated,
    )
}

/// Runs ICP and one pass of the surface refinement from every coarse candidate and keeps the
/// one after which the most SfM points, and the most elevated ones (stems, stones, crowns),
/// lie on the LiDAR cloud. The confidence is high only when the elevated share is high in
/// itself and the best clearly beats the best distinct other candidate.
pub fn verify_candidates(
    sfm: &[DVec3],
    cands: &[geom::coarse::CoarseAlignment],
    target: &[Vec3],
    params: &IcpParams,
    surface: &SurfaceTarget,
    p: &super::params::RegisterParams,
    progress: &dyn Progress,
) -> Result<Verified, StageError> {
    let index = geom::PointIndex::new(target)?;
    let grid = GroundGrid::new(target);
    let n = cands.len().max(1) as f64;
    let mut runs = Vec::with_capacity(cands.len());
    for (k, c) in cands.iter().enumerate() {
        if progress.is_cancelled() {
            return Err(StageError::Cancelled);
        }
        let source: Vec<Vec3> = sfm
            .iter()
            .map(|x| c.transform.apply(*x).as_vec3())
            .collect();
        let fine = icp_two_phase(
            &source,
            target,
            params,
            &SubProgress::new(progress, k as f64 / n, 0.5 / n),
        )?;
        let t = refine_on_surface(
            sfm,
            surface,
            &c.transform.then(&fine.transform()),
            None,
            p,
            AUTOMATIC_REFINE_PASSES,
            &SubProgress::new(progress, (k as f64 + 0.5) / n, 0.5 / n),
        )?
        .transform;
        let (all, elevated, n_elevated) = on_cloud_shares(sfm, &t, &index, grid.as_ref());
        progress.log(&format!(
            "candidate {k}: raster score {:.3}, yaw {:.1}°, scale {:.4}; after ICP and one surface \
             pass: on-cloud {:.3}, elevated {:.3} of {n_elevated}; ICP fitness {:.3}",
            c.score, c.yaw_deg, c.scale, all, elevated, fine.fitness
        ));
        runs.push((c.transform, fine, t, all, elevated, n_elevated));
    }
    let score = |r: &(Similarity, geom::IcpResult, Similarity, f64, f64, usize)| r.3 + r.4;
    let Some(best) = runs
        .iter()
        .enumerate()
        .max_by(|a, b| score(a.1).total_cmp(&score(b.1)))
        .map(|(i, _)| i)
    else {
        return Err(StageError::Input(
            "automatic registration found no candidate alignment; supply control points \
             (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)"
                .into(),
        ));
    };
    // Distinct: the final poses differ by more than 1° or 2 % or move the SfM centroid by
    // more than 0.25 m (the same pose reached from two starts is no rival).
    let centroid = sfm.iter().copied().sum::<DVec3>() / sfm.len().max(1) as f64;
    let b = &runs[best];
    let distinct = |r: &(Similarity, geom::IcpResult, Similarity, f64, f64, usize)| {
        let rel = b.2.inverse().then(&r.2);
        rel.rotation_angle_deg() > 1.0
            || (rel.scale - 1.0).abs() > 0.02
            || (r.2.apply(centroid) - b.2.apply(centroid)).length() > 0.25
    };
    let runner_up = runs
        .iter()
        .filter(|r| distinct(r))
        .map(score)
        .fold(0.0, f64::max);
    let best_score = score(b);
    // Confidence: full when the best beats every distinct rival by 0.6 (on-cloud plus
    // elevated on-cloud share) and puts at least 0.6 of its elevated points on the cloud;
    // 0.5 (the default threshold) needs 0.3 of each. Measured (docs/results/registration.md
    // results): after ICP and the surface passes the right candidates of `stand` seeds 1-5
    // put 0.75-0.79 of their elevated points on the cloud (the light stand of the tests
    // 0.38), wrong candidates on `stand` at most 0.04, on `tiny` at most 0.11; the overall
    // share does not discriminate (flat ground fits under a wrong yaw too: wrong `tiny`
    // candidates reach 0.44-0.66). Fewer than 50 elevated points: no confidence.
    let confidence = if b.5 < 50 {
        0.0
    } else {
        ((best_score - runner_up) / 0.6)
            .min(b.4 / 0.6)
            .clamp(0.0, 1.0)
    };
    let table = json!(
        runs.iter()
            .map(|r| json!({
                "coarse": similarity_json(&r.0),
                "final": similarity_json(&r.2),
                "on_cloud": r.3,
                "elevated_on_cloud": r.4,
                "elevated_points": r.5,
                "icp_fitness": r.1.fitness,
            }))
            .collect::<Vec<_>>()
    );
    Ok(Verified {
        coarse: b.0,
        fine: b.1,
        refined: b.2,
        best_fit: b.3,
        best_elevated: b.4,
        runner_up,
        confidence,
        table,
    })
}
