//! Stage `export`: the deliverables in one folder — the splats as an INRIA-layout PLY that
//! common splat viewers open, as glTF 2.0 with `KHR_gaussian_splatting` (`splats.glb`,
//! [`crate::splat::export_gltf`]) and, with `params.export.tiles`, as a 3D Tiles tileset
//! (`tileset.json`, `tiles/`; [`crate::splat::tiles`]), the labelled cloud and its anchors as
//! COPC (`cloud.copc.laz`, `anchors.copc.laz`; [`crate::io::copc`]) and, with `params.export.compact`, the compact web formats
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
    // A model without Gaussians has nothing to tile; the report says so (null).
    let tiles = if ctx.params.export.tiles && !model.is_empty() {
        write_tiles(ctx, &model, &dbh.join("trees.csv"), &train_report, &crs)?
    } else {
        serde_json::Value::Null
    };
    let copc = write_clouds(ctx, &crs)?;
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
        "tiles": tiles,
        "copc": copc,
        "offset": train_report["offset"],
        "crs": crs.label,
    }))
}

/// Writes stage `segment`'s labelled cloud and its anchors as COPC (`cloud.copc.laz`,
/// `anchors.copc.laz`; [`crate::io::copc`]) with the job's CRS; returns the report's `copc`.
fn write_clouds(
    ctx: &StageContext<'_>,
    crs: &crate::io::crs::CrsRecord,
) -> Result<serde_json::Value, StageError> {
    use crate::io::copc::{
        self, CLASS_GROUND, CLASS_LEAF, CLASS_UNASSIGNED, CLASS_WOOD, LabelledCloud,
    };
    let segment = ctx.output_of(Stage::Segment, Stage::Export)?;
    let wkt = crs.crs.as_ref().and_then(copc::wkt_of);
    let mut report = serde_json::Map::new();
    for (from, to) in [
        ("labelled.ply", "cloud.copc.laz"),
        ("anchors.ply", "anchors.copc.laz"),
    ] {
        let path = segment.join(from);
        let (cloud, fields) =
            crate::io::ply::read_ply_with_fields(&path, &crate::progress::NoProgress)?;
        let field = |name: &str| fields.iter().find(|f| f.name == name).map(|f| &f.values);
        let (ground, label, tree) = (field("ground"), field("label"), field("tree"));
        let at = |v: Option<&Vec<f32>>, i: usize| v.and_then(|v| v.get(i)).copied();
        let classes: Vec<u8> = (0..cloud.len())
            .map(|i| match (at(ground, i), at(label, i)) {
                (Some(g), _) if g >= 0.5 => CLASS_GROUND,
                (_, Some(l)) if l == f32::from(crate::forest::segment::TRUNK) => CLASS_WOOD,
                (_, Some(_)) => CLASS_LEAF,
                _ => CLASS_UNASSIGNED,
            })
            .collect();
        let trees: Vec<u32> = (0..cloud.len())
            .map(|i| at(tree, i).map_or(0, |t| t.max(0.0) as u32))
            .collect();
        let count = |c: u8| classes.iter().filter(|&&k| k == c).count();
        let counts = json!({
            "points": cloud.len(),
            "ground": count(CLASS_GROUND),
            "wood": count(CLASS_WOOD),
            "leaf": count(CLASS_LEAF),
            "unassigned": count(CLASS_UNASSIGNED),
            "in_trees": trees.iter().filter(|&&t| t > 0).count(),
        });
        let Some(points) = LabelledCloud::new(&cloud, classes, trees) else {
            return Err(StageError::Input(format!(
                "{}: inconsistent fields",
                path.display()
            )));
        };
        let out = ctx.out_dir.join(to);
        copc::write_copc(&out, &points, wkt.clone())?;
        report.insert(to.to_string(), counts);
    }
    if wkt.is_none() {
        report.insert(
            "crs".into(),
            json!("none declared: the job has no CRS, or one known only as a PROJ string"),
        );
    }
    Ok(serde_json::Value::Object(report))
}

/// Writes `tileset.json` and `tiles/` (see [`crate::splat::tiles`]) with the trees of
/// `trees_csv` as its metadata; returns the report's `tiles`.
fn write_tiles(
    ctx: &StageContext<'_>,
    model: &crate::splat::model::Gaussians,
    trees_csv: &std::path::Path,
    train_report: &serde_json::Value,
    crs: &crate::io::crs::CrsRecord,
) -> Result<serde_json::Value, StageError> {
    use crate::splat::tiles::{self, TileParams, TreeMeta};
    let offset: [f64; 3] = serde_json::from_value(train_report["offset"].clone())
        .map_err(|e| StageError::Input(format!("the train report's offset: {e}")))?;
    let mut reader = csv::Reader::from_path(trees_csv)
        .map_err(|e| StageError::Input(format!("{}: {e}", trees_csv.display())))?;
    let mut trees = Vec::new();
    for row in reader.deserialize::<crate::forest::TreeRow>() {
        let t = row.map_err(|e| StageError::Input(format!("{}: {e}", trees_csv.display())))?;
        trees.push(TreeMeta {
            id: t.tree_id.to_string(),
            position: [t.x - offset[0], t.y - offset[1], t.ground_z - offset[2]],
            dbh_m: t.dbh_lidar_cm / 100.0,
            height_m: t.height_m.unwrap_or(-1.0),
        });
    }
    let georef = match (&crs.crs, model.bounds()) {
        (Some(c), Some((lo, hi))) => Some(
            tiles::local_to_ecef(c, offset, lo.map(f64::from), hi.map(f64::from))
                .map_err(|e| StageError::Input(format!("placing the tileset on the Earth: {e}")))?,
        ),
        _ => None,
    };
    let per_tile = ctx.params.export.tile_gaussians;
    if per_tile == 0 {
        return Err(StageError::Input(
            "params.export.tile_gaussians is 0; a tile holds at least 1 Gaussian".into(),
        ));
    }
    let set = tiles::build(
        model,
        georef.as_ref().map(|g| &g.0),
        &trees,
        &TileParams {
            max_per_tile: per_tile as usize,
        },
    )
    .map_err(|e| super::io_err(ctx.out_dir, e))?;
    let mut bytes = 0u64;
    for t in &set.tiles {
        let path = ctx.out_dir.join(&t.path);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| super::io_err(dir, e))?;
        }
        std::fs::write(&path, &t.glb).map_err(|e| super::io_err(&path, e))?;
        bytes += t.glb.len() as u64;
    }
    let path = ctx.out_dir.join("tileset.json");
    std::fs::write(
        &path,
        serde_json::to_vec_pretty(&set.json).unwrap_or_default(),
    )
    .map_err(|e| super::io_err(&path, e))?;
    let root_bytes = set.tiles.first().map_or(0, |t| t.glb.len());
    ctx.progress.log(&format!(
        "3D Tiles: {} tiles ({} a level from the root), {:.1} MB; the root holds {} Gaussians in {:.2} MB; {}",
        set.tiles.len(),
        set.per_level.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(", "),
        bytes as f64 / 1e6,
        set.root_gaussians,
        root_bytes as f64 / 1e6,
        match &georef {
            Some((_, r)) => format!("placed on the Earth (ECEF) from {}, fit residual {:.2} mm", crs.label.as_deref().unwrap_or("the CRS"), r * 1000.0),
            None => "no CRS: left in the local frame".to_string(),
        }
    ));
    Ok(json!({
        "tiles": set.tiles.len(),
        "per_level": set.per_level,
        "bytes": bytes,
        "root_gaussians": set.root_gaussians,
        "root_bytes": root_bytes,
        "ecef": georef.is_some(),
        "georeference_residual_m": georef.map(|g| g.1),
    }))
}

fn read_json(path: &std::path::Path) -> Result<serde_json::Value, StageError> {
    let bytes = std::fs::read(path).map_err(|e| super::io_err(path, e))?;
    serde_json::from_slice(&bytes)
        .map_err(|e| StageError::Input(format!("{}: {e}", path.display())))
}
