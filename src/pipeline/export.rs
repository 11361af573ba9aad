//! Stage `export`: the deliverables in one folder — the splats as an INRIA-layout PLY that
//! common splat viewers open and as glTF 2.0 with `KHR_gaussian_splatting` (`splats.glb`,
//! [`crate::splat::export_gltf`]) and, with `params.export.compact`, the compact web formats
//! (antimatter15 `splats.splat`, and Niantic's `splats.spz` version 2, which keeps the SH
//! bands); the final inventory with its `crs.json`; and `frame.json`, which says how the
//! splats' local metric frame maps to the LiDAR file's own coordinates and which CRS those are.
//!
//! The splats stay in the local frame (file coordinates minus `offset`): projected coordinates
//! such as UTM eastings need more digits than the f32 of splat files can hold (about 3 cm at
//! 500 km), so adding the offset is left to the consumer, as for LAS files.

use std::io::Write;

use serde_json::json;

use super::{Stage, StageContext, StageError};

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let train = ctx.output_of(Stage::Train, Stage::Export)?;
    let dbh = ctx.output_of(Stage::Dbh, Stage::Export)?;
    let register = ctx.output_of(Stage::Register, Stage::Export)?;
    let splats = train.join("splats.ply");
    let file = std::fs::File::open(&splats).map_err(|e| super::io_err(&splats, e))?;
    let model = crate::splat::export::read_ply(std::io::BufReader::new(file))
        .map_err(|e| StageError::Input(format!("{}: {e}", splats.display())))?;
    let write = |name: &str, f: &dyn Fn(&mut dyn Write) -> std::io::Result<()>| {
        let path = ctx.out_dir.join(name);
        let mut out = std::io::BufWriter::new(
            std::fs::File::create(&path).map_err(|e| super::io_err(&path, e))?,
        );
        f(&mut out)
            .and_then(|()| out.flush())
            .map_err(|e| super::io_err(&path, e))
    };
    write("splats.ply", &|w| {
        crate::splat::export::write_ply_with(w, &model, false)
    })?;
    // The same splats as glTF with KHR_gaussian_splatting, for glTF and 3D Tiles clients;
    // the frame rides in the asset's extras.
    let train_report: serde_json::Value = read_json(&train.join(super::REPORT_FILE))?;
    let crs = ctx.crs(Stage::Export)?;
    write("splats.glb", &|w| {
        let extras = json!({
            "frame": "local, z up; file coordinates = position + offset (metres), in crs",
            "offset": train_report["offset"],
            "crs": crs.label,
        });
        let (doc, bin) = crate::splat::export_gltf::gltf_parts(
            &model,
            &crate::splat::export_gltf::Z_UP_TO_Y_UP,
            extras,
        );
        crate::splat::export_gltf::write_glb_parts(w, &doc, &bin)
    })?;
    if ctx.params.export.compact {
        write("splats.splat", &|w| {
            crate::splat::export_splat::write_splat(w, &model)
        })?;
        write("splats.spz", &|w| {
            crate::splat::export_spz::write_spz(w, &model)
        })?;
    }
    for name in ["trees.csv", "trees.geojson"] {
        let (from, to) = (dbh.join(name), ctx.out_dir.join(name));
        std::fs::copy(&from, &to).map_err(|e| super::io_err(&from, e))?;
    }
    // plot.json and trees.gpkg exist where stage `dbh` ran with plot summaries.
    for name in [crate::forest::PLOT_FILE, "trees.gpkg"] {
        let from = dbh.join(name);
        if from.is_file() {
            let to = ctx.out_dir.join(name);
            std::fs::copy(&from, &to).map_err(|e| super::io_err(&from, e))?;
        }
    }
    let register_report: serde_json::Value = read_json(&register.join(super::REPORT_FILE))?;
    crate::forest::write_crs(ctx.out_dir, &crs)?;
    let frame = json!({
        "splats_frame": "local",
        "offset": train_report["offset"],
        "note": "file coordinates = splat position + offset (metres), in `crs`",
        "crs": crs,
        "sfm_to_lidar": register_report["sfm_to_lidar"],
    });
    write("frame.json", &|w| {
        w.write_all(&serde_json::to_vec_pretty(&frame).unwrap_or_default())
    })?;
    ctx.progress.set(1.0);
    Ok(json!({
        "gaussians": model.len(),
        "compact": ctx.params.export.compact,
        "offset": train_report["offset"],
        "crs": crs.label,
    }))
}

fn read_json(path: &std::path::Path) -> Result<serde_json::Value, StageError> {
    let bytes = std::fs::read(path).map_err(|e| super::io_err(path, e))?;
    serde_json::from_slice(&bytes)
        .map_err(|e| StageError::Input(format!("{}: {e}", path.display())))
}
