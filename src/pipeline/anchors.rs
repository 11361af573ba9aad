//! Stage `anchors`: the fused cloud (registered LiDAR plus the SfM points moved into the
//! LiDAR frame) homogenised by a voxel grid and cleaned by the statistical outlier filter;
//! the survivors are the anchor set A (docs/method.md Stage 2, paper 3.3).
//!
//! Outputs (LiDAR local frame, offset in the PLY header): `fused.ply` (colour, scalar field
//! `source`: 0 LiDAR, 1 SfM) and `anchors.ply` (colour, normals nx/ny/nz).

use glam::Vec3;
use serde_json::json;

use super::{Stage, StageContext, StageError};
use crate::geom::{self, NormalOrientation, NormalParams, OutlierParams};
use crate::io::colmap;
use crate::io::ply::{self, ScalarField};
use crate::io::pointcloud::PointCloud;
use crate::progress::{NoProgress, SubProgress};

/// Grey given to LiDAR points of a cloud without colour, so SfM colours survive the fusion.
const NO_COLOUR: [u8; 3] = [128, 128, 128];

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let p = &ctx.params.anchors;
    let ingest = ctx.output_of(Stage::Ingest, Stage::Anchors)?;
    let register = ctx.output_of(Stage::Register, Stage::Anchors)?;
    let lidar = ctx.read_ingest_cloud(&ingest, 0.1)?;
    let model = colmap::read_model(&register.join("sparse"), &NoProgress)?;
    let lidar_has_colour = lidar.colors.is_some();
    let n_lidar = lidar.len();
    let mut positions = lidar.positions;
    let mut colours = lidar
        .colors
        .unwrap_or_else(|| vec![NO_COLOUR; positions.len()]);
    let mut source = vec![0.0f32; n_lidar];
    for pt in &model.points {
        positions.push(pt.xyz.as_vec3());
        colours.push(pt.rgb);
        source.push(1.0);
    }
    let n_fused = positions.len();
    let fused = PointCloud {
        offset: lidar.offset,
        positions,
        colors: Some(colours),
        intensity: None,
        format: lidar.format,
    };
    ply::write_ply(
        &ctx.out_dir.join("fused.ply"),
        &fused,
        &[ScalarField {
            name: "source".into(),
            values: source,
        }],
    )?;
    ctx.progress.set(0.2);

    // 1. Voxel homogenisation (centroid and mean colour per voxel).
    let colours = fused.colors.as_deref();
    let voxels = geom::voxel_downsample(
        &fused.positions,
        colours,
        p.voxel_size_m as f32,
        &SubProgress::new(ctx.progress, 0.2, 0.2),
    )?;
    let n_voxels = voxels.positions.len();
    // 2. Statistical outlier filter.
    let filter = geom::statistical_outlier_filter(
        &voxels.positions,
        &OutlierParams {
            k: p.outlier_k as usize,
            alpha: p.outlier_alpha,
        },
        &SubProgress::new(ctx.progress, 0.4, 0.3),
    )?;
    let keep = |i: usize| filter.keep[i];
    let anchors: Vec<Vec3> = (0..n_voxels)
        .filter(|&i| keep(i))
        .map(|i| voxels.positions[i])
        .collect();
    let anchor_colours: Option<Vec<[u8; 3]>> = voxels
        .colours
        .as_ref()
        .map(|c| (0..n_voxels).filter(|&i| keep(i)).map(|i| c[i]).collect());
    if anchors.len() < 10 {
        return Err(StageError::Input(format!(
            "only {} anchors survive the filters; the cloud is too sparse for voxel {} m",
            anchors.len(),
            p.voxel_size_m
        )));
    }
    // 3. Normals for the anchor PLY (k = 20, oriented by propagation, seeded upward).
    let normals = geom::estimate_normals(
        &anchors,
        &NormalParams {
            k: 20,
            orientation: NormalOrientation::Propagate { up: Vec3::Z },
        },
        &SubProgress::new(ctx.progress, 0.7, 0.25),
    )?
    .normals;
    let field = |name: &str, f: fn(&Vec3) -> f32| ScalarField {
        name: name.into(),
        values: normals.iter().map(f).collect(),
    };
    let n_anchors = anchors.len();
    let cloud = PointCloud {
        offset: fused.offset,
        positions: anchors,
        colors: anchor_colours,
        intensity: None,
        format: fused.format,
    };
    ply::write_ply(
        &ctx.out_dir.join("anchors.ply"),
        &cloud,
        &[
            field("nx", |n| n.x),
            field("ny", |n| n.y),
            field("nz", |n| n.z),
        ],
    )?;
    ctx.progress.set(1.0);
    Ok(json!({
        "voxel_size_m": p.voxel_size_m,
        "outlier_k": p.outlier_k,
        "outlier_alpha": p.outlier_alpha,
        "points": {
            "lidar": n_lidar,
            "sfm": model.points.len(),
            "fused": n_fused,
            "after_voxel": n_voxels,
            "after_outlier_filter": n_anchors,
        },
        "outlier_threshold_m": filter.threshold,
        "mean_neighbour_distance_m": filter.mu,
        "lidar_has_colour": lidar_has_colour,
        "offset": [fused.offset.x, fused.offset.y, fused.offset.z],
    }))
}
