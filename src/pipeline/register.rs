//! Stage `register`: the similarity that maps the SfM frame onto the LiDAR frame
//! (METHOD.md Stage 1), and the COLMAP model moved into the LiDAR frame.
//!
//! Coarse: from control point pairs (Umeyama, residual per pair) or, without them, the
//! automatic alignment of [`crate::geom::coarse`]. Fine: ICP of the SfM points onto the
//! LiDAR cloud thinned to `target_voxel_m`, estimating scale too; then the surface
//! refinement of [`crate::geom::surface`] (similarity Gauss-Newton of the SfM points onto
//! quadric patches of the LiDAR surface, the control points as extra observations), whose
//! standard errors the report gives as `uncertainty`. Everything runs in the
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

    // Coarse.
    let (coarse, method, pairs, confidence) = match &ctx.inputs.control_points {
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
            (fit.transform, "control_points", pairs, 1.0)
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
            let c = geom::coarse::align(
                &sfm,
                &rays,
                &cloud.positions,
                &geom::coarse::CoarseParams::default(),
                &SubProgress::new(ctx.progress, 0.1, 0.4),
            )
            .map_err(|e| match e {
                geom::GeomError::Cancelled => StageError::Cancelled,
                other => StageError::Input(format!(
                    "automatic registration failed ({other}); supply control points \
                     (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)"
                )),
            })?;
            ctx.progress.log(&format!(
                "automatic coarse alignment: confidence {:.2}",
                c.confidence
            ));
            if c.confidence < p.min_confidence {
                return Err(StageError::Input(format!(
                    "automatic registration is not confident enough ({:.2} < {:.2}): the \
                     photos and the LiDAR cloud may not overlap; supply control points \
                     (at least 4 pairs, CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z)",
                    c.confidence, p.min_confidence
                )));
            }
            (c.transform, "automatic", Vec::new(), c.confidence)
        }
    };
    if ctx.progress.is_cancelled() {
        return Err(StageError::Cancelled);
    }

    // Fine: ICP of the coarsely aligned SfM points onto the thinned LiDAR cloud.
    let target = geom::voxel_downsample(
        &cloud.positions,
        None,
        &VoxelParams {
            voxel_size: p.target_voxel_m as f32,
        },
        &SubProgress::new(ctx.progress, 0.5, 0.1),
    )?
    .positions;
    let source: Vec<Vec3> = sfm.iter().map(|x| coarse.apply(*x).as_vec3()).collect();
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
    let fine = icp_two_phase(
        &source,
        &target,
        &params,
        &SubProgress::new(ctx.progress, 0.6, 0.3),
    )?;
    if method == "automatic" && fine.fitness < p.min_fitness {
        return Err(StageError::Input(format!(
            "automatic registration rejected: after ICP only {:.0}% of the SfM points lie on \
             the LiDAR cloud (< {:.0}%); the photos and the scan may not overlap; supply \
             control points (at least 4 pairs)",
            fine.fitness * 100.0,
            p.min_fitness * 100.0
        )));
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
        let r = refine_on_surface(
            &sfm,
            &cloud.positions,
            &icp_t,
            pairs_local
                .as_ref()
                .map(|(a, b)| (a.as_slice(), b.as_slice())),
            p,
            &SubProgress::new(ctx.progress, 0.9, 0.08),
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
        let u = json!({
            "rotation_deg": r.std_rotation_deg,
            "scale": r.std_scale,
            "translation_m": r.std_translation_m,
            "points_on_surfaces": r.used,
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

/// The final refinement ([`geom::surface`]): from `initial` (SfM → LiDAR local), the
/// similarity that puts the SfM points on the LiDAR surface thinned to `refine_voxel_m`, with
/// the control point pairs (SfM, LiDAR local) as extra observations when given.
pub fn refine_on_surface(
    sfm: &[DVec3],
    lidar: &[Vec3],
    initial: &Similarity,
    pairs: Option<(&[DVec3], &[DVec3])>,
    p: &super::params::RegisterParams,
    progress: &dyn Progress,
) -> Result<geom::surface::SurfaceResult, StageError> {
    let thin = geom::voxel_downsample(
        lidar,
        None,
        &VoxelParams {
            voxel_size: p.refine_voxel_m as f32,
        },
        &SubProgress::new(progress, 0.0, 0.3),
    )?
    .positions;
    let index = geom::PointIndex::new(&thin)?;
    let params = surface_params(p);
    geom::surface::refine_on_surface(
        sfm,
        None,
        &thin,
        &index,
        initial,
        pairs.map(|(sfm, lidar)| geom::surface::PairPrior {
            sfm,
            lidar,
            sigma_m: p.control_point_sigma_m,
        }),
        &params,
        &SubProgress::new(progress, 0.4, 0.6),
    )
    .map_err(StageError::from)
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
