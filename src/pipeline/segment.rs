//! Stage `segment`: the forest analysis of the LiDAR cloud (docs/method.md Stage 3 and the LiDAR
//! half of Stage 5) — ground and DTM, wood/leaf labels with a trunk probability per point,
//! stems and their LiDAR diameters — and the labels carried over to the anchors for the
//! trainer. The same [`crate::forest::inventory`] serves `sylva inventory`.
//!
//! The anchors take the label and trunk probability of their nearest LiDAR point: the anchor
//! set is a 2 cm voxel thinning of the same surfaces, so a nearest-point transfer keeps the
//! segmentation of the full-density cloud, whose eigen features are better defined than on a
//! thinned one.
//!
//! Outputs (LiDAR local frame, offset in the PLY headers): `labelled.ply` (fields `label`
//! 0 leaf / 1 trunk, `ground` 0/1, `trunk_prob`, `height_m` above the DTM, `tree` the tree id
//! or 0), `anchors.ply` (anchor colour, normals, `label`, `trunk_prob`), `dtm.json`,
//! `stems.json` (stems, rows and crowns), and the LiDAR-only inventory `trees.csv` /
//! `trees.geojson` / `trees.gpkg` / `crs.json` / `plot.json` (original coordinates; stage `dbh` writes the
//! final one with the Gaussian diameters beside these).

use serde_json::json;

use super::{Stage, StageContext, StageError};
use crate::forest::{self, ForestError};
use crate::geom::PointIndex;
use crate::io::ply::{self, ScalarField};
use crate::progress::SubProgress;

impl From<ForestError> for StageError {
    fn from(e: ForestError) -> Self {
        match e {
            ForestError::Cancelled => StageError::Cancelled,
            ForestError::Io(e) => StageError::Io(e),
            other => StageError::Input(other.to_string()),
        }
    }
}

/// A stem as `stems.json` lists it (local coordinates, metres; the point list is left out).
#[derive(serde::Serialize)]
struct StemRecord<'a> {
    id: u32,
    base: [f32; 3],
    axis: [f32; 3],
    lean_deg: f32,
    dbh: &'a forest::StemDbh,
}

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let params = &ctx.params.segment;
    let ingest = ctx.output_of(Stage::Ingest, Stage::Segment)?;
    let anchors_dir = ctx.output_of(Stage::Anchors, Stage::Segment)?;
    let cloud = ctx.read_ingest_cloud(&ingest, 0.05)?;
    let inv = forest::inventory(&cloud, params, &SubProgress::new(ctx.progress, 0.05, 0.8))?;

    let heights = inv.dtm.heights_above(&cloud.positions);
    let field = |name: &str, values: Vec<f32>| ScalarField {
        name: name.into(),
        values,
    };
    ply::write_ply(
        &ctx.out_dir.join("labelled.ply"),
        &cloud,
        &[
            field("label", inv.labels.iter().map(|&l| l as f32).collect()),
            field(
                "ground",
                inv.is_ground.iter().map(|&g| f32::from(g)).collect(),
            ),
            field("trunk_prob", inv.trunk_probability.clone()),
            field("height_m", heights),
            field(
                "tree",
                inv.tree_of_point.iter().map(|&t| t as f32).collect(),
            ),
        ],
    )?;
    ctx.progress.set(0.9);

    // Labels for the anchors from their nearest LiDAR point.
    let (anchors, mut anchor_fields) = ply::read_ply_with_fields(
        &anchors_dir.join("anchors.ply"),
        &SubProgress::new(ctx.progress, 0.9, 0.02),
    )?;
    let index = PointIndex::new(&cloud.positions)?;
    // Anchors are in the same local frame as the cloud, up to a different offset.
    let shift = (anchors.offset - cloud.offset).as_vec3();
    let queries: Vec<glam::Vec3> = anchors.positions.iter().map(|p| *p + shift).collect();
    let nearest = index.nearest_batch(&queries, &SubProgress::new(ctx.progress, 0.92, 0.05))?;
    let (mut label, mut prob) = (Vec::new(), Vec::new());
    for nb in &nearest {
        let i = nb.map_or(0, |n| n.index as usize);
        let ground = inv.is_ground.get(i).copied().unwrap_or(true);
        label.push(if ground {
            0.0
        } else {
            f32::from(inv.labels[i])
        });
        prob.push(if ground {
            0.0
        } else {
            inv.trunk_probability[i]
        });
    }
    let trunk_anchors = label.iter().filter(|&&l| l > 0.5).count();
    anchor_fields.retain(|f| f.name != "label" && f.name != "trunk_prob");
    anchor_fields.push(field("label", label));
    anchor_fields.push(field("trunk_prob", prob));
    ply::write_ply(&ctx.out_dir.join("anchors.ply"), &anchors, &anchor_fields)?;

    // The ground model, the stems and the LiDAR-only inventory.
    let write_json = |name: &str, value: &serde_json::Value| -> Result<(), StageError> {
        let path = ctx.out_dir.join(name);
        let text = serde_json::to_vec_pretty(value).unwrap_or_default();
        super::write_synced(&path, &text).map_err(|e| super::io_err(&path, e))
    };
    let dtm = json!({
        "offset": [cloud.offset.x, cloud.offset.y, cloud.offset.z],
        "dtm": inv.dtm,
    });
    write_json("dtm.json", &dtm)?;
    let stems: Vec<StemRecord<'_>> = inv
        .stems
        .iter()
        .zip(&inv.dbh)
        .map(|(s, d)| StemRecord {
            id: s.id,
            base: s.base.to_array(),
            axis: s.axis.to_array(),
            lean_deg: s.lean_deg,
            dbh: d,
        })
        .collect();
    write_json(
        "stems.json",
        &json!({
            "offset": [cloud.offset.x, cloud.offset.y, cloud.offset.z],
            "stems": stems,
            "trees": inv.trees,
            "crowns": inv.crowns,
        }),
    )?;
    let summary = inv.summary(&inv.trees, params)?;
    for line in forest::summary_lines(&summary) {
        ctx.progress.log(&line);
    }
    forest::PlotFile::new(summary.clone(), &inv.footprint).write(ctx.out_dir)?;
    forest::write_trees_csv(&ctx.out_dir.join("trees.csv"), &inv.trees)?;
    let crs = ctx.crs(Stage::Segment)?;
    forest::write_trees_geojson(&ctx.out_dir.join("trees.geojson"), &inv.trees, &crs)?;
    forest::write_crs(ctx.out_dir, &crs)?;
    forest::write_trees_gpkg(
        &ctx.out_dir.join("trees.gpkg"),
        &inv.trees,
        &inv.crowns,
        cloud.offset,
        &crs,
    )?;
    let comparison = match &ctx.inputs.field_dbh {
        Some(path) => {
            let cmp = forest::compare_with_field_file(&inv.trees, path)?;
            for line in forest::accuracy_lines(&cmp) {
                ctx.progress.log(&line);
            }
            Some(cmp)
        }
        None => None,
    };
    ctx.progress.set(1.0);

    let n = cloud.len();
    let ground = inv.is_ground.iter().filter(|&&g| g).count();
    let trunk = inv
        .labels
        .iter()
        .zip(&inv.is_ground)
        .filter(|(l, g)| **l == forest::TRUNK && !**g)
        .count();
    // No stem is a finding about the cloud, not a failure: say what the cloud held.
    let finding = inv.stems.is_empty().then(|| {
        let why = format!(
            "no stems found: {trunk} of {n} points ({:.2} %) were labelled trunk wood and \
             {ground} ({:.1} %) ground. A cloud from above (nadir photogrammetry, airborne \
             LiDAR) sees the canopy, not the stems; a handheld or terrestrial scan under the \
             canopy is what finds them",
            100.0 * trunk as f64 / n.max(1) as f64,
            100.0 * ground as f64 / n.max(1) as f64,
        );
        ctx.progress.log(&why);
        why
    });
    Ok(json!({
        "finding": finding,
        "points": { "total": n, "ground": ground, "trunk": trunk, "leaf": n - ground - trunk },
        "anchors": { "total": anchors.len(), "trunk": trunk_anchors },
        "stems": inv.stems.len(),
        "trees": inv.trees.len(),
        "seconds": inv.seconds,
        "field": comparison,
        "plot": summary,
        "crs": crs.label,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::pointcloud::{CloudFormat, PointCloud};
    use crate::pipeline::{PipelineParams, StageInputs, execute_stage};

    /// A canopy seen from above (a rolling surface, nothing under it, no stem): the stage
    /// finishes and says why it found no stems.
    #[test]
    fn a_cloud_without_stems_is_a_finding_not_a_failure() {
        let dir = tempfile::tempdir().expect("tmp");
        let work = dir.path();
        let mut positions = Vec::new();
        for i in 0..200 {
            for j in 0..200 {
                let (x, y) = (i as f32 * 0.1, j as f32 * 0.1);
                let z = 8.0 + 1.5 * (x * 0.7).sin() * (y * 0.5).cos();
                positions.push(glam::Vec3::new(x, y, z));
            }
        }
        let cloud = PointCloud {
            offset: glam::DVec3::new(500_000.0, 4_000_000.0, 100.0),
            positions,
            colors: None,
            intensity: None,
            format: CloudFormat::Ply,
        };
        let ingest = work.join("ingest");
        let anchors = work.join("anchors");
        for d in [&ingest, &anchors] {
            std::fs::create_dir_all(d).expect("mkdir");
            std::fs::write(d.join(super::super::REPORT_FILE), b"{}").expect("report");
        }
        ply::write_ply(&ingest.join(super::super::INGEST_CLOUD), &cloud, &[]).expect("cloud");
        ply::write_ply(&anchors.join("anchors.ply"), &cloud, &[]).expect("anchors");
        let crs = crate::io::crs::resolve(None, Ok(None)).expect("crs");
        forest::write_crs(&ingest, &crs).expect("crs.json");
        let inputs = StageInputs::with_colmap(work.join("lidar.ply"), work.join("colmap"));
        let out = execute_stage(
            Stage::Segment,
            &inputs,
            work,
            &PipelineParams::default(),
            &crate::progress::NoProgress,
        )
        .expect("segment finishes");
        assert_eq!(out.report["stems"], 0, "{}", out.report);
        let finding = out.report["finding"].as_str().unwrap_or("");
        assert!(finding.starts_with("no stems found"), "{}", out.report);
        assert!(finding.contains("sees the canopy"), "{finding}");
    }
}
