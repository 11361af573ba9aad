//! The command line: `sylva run` on local files, and flags mirrored by environment variables.

mod common;

use std::path::Path;
use std::process::Command;

use common::*;

#[test]
fn run_until_ingest_writes_stage_folders_and_results() {
    let fx = fixture();
    let out = fx.dir.path().join("out");
    succeeds(
        Command::new(BIN)
            .args(["run", "--until", "ingest", "--lidar"])
            .arg(&fx.lidar)
            .arg("--colmap")
            .arg(&fx.colmap_zip)
            .arg("--control-points")
            .arg(&fx.control_points)
            .arg("--out")
            .arg(&out),
    );
    let results = read_json(&out.join("results.json"));
    assert_eq!(results["ingest"]["lidar"]["points"], fx.lidar_points);
    assert_eq!(results["ingest"]["control_points"], 4);
    assert!(out.join("ingest/cloud.ply").is_file());
    assert!(out.join("ingest/report.json").is_file());
    assert!(!out.join("ingest.partial").exists());
}

#[test]
fn run_from_a_stage_keeps_the_finished_ones_and_reports_resources() {
    let fx = fixture();
    let out = fx.dir.path().join("out");
    let run = |extra: &[&str]| {
        let mut c = Command::new(BIN);
        c.args(["run", "--lidar"])
            .arg(&fx.lidar)
            .arg("--colmap")
            .arg(&fx.colmap_dir)
            .arg("--control-points")
            .arg(&fx.control_points)
            .arg("--out")
            .arg(&out)
            .args(extra);
        c
    };
    // Not yet finished: a clear error naming the stage.
    let stderr = fails(&mut run(&["--from", "register", "--until", "register"]));
    assert!(stderr.contains("stage ingest has not finished"), "{stderr}");
    succeeds(&mut run(&["--until", "ingest"]));
    let ingest = read_json(&out.join("ingest/report.json"));
    succeeds(&mut run(&["--from", "sfm", "--until", "sfm"]));
    let results = read_json(&out.join("results.json"));
    // Ingest kept as it was (not run again), sfm run, each with what it took.
    assert_eq!(results["ingest"]["lidar"], ingest["lidar"]);
    assert_eq!(results["sfm"]["ran"], false);
    let r = &results["sfm"]["resources"];
    assert!(r["wall_s"].as_f64().is_some_and(|s| s >= 0.0), "{r}");
    assert!(r["peak_rss_mb"].as_f64().is_some_and(|m| m > 0.0), "{r}");
}

#[test]
fn run_stops_with_a_clear_error_when_registration_is_impossible() {
    let fx = fixture();
    let out = fx.dir.path().join("out");
    let stderr = fails(
        Command::new(BIN)
            .args(["run", "--lidar"])
            .arg(&fx.lidar)
            .arg("--colmap")
            .arg(&fx.colmap_dir)
            .arg("--out")
            .arg(&out),
    );
    // The fixture's photos do not show its LiDAR scene: the automatic alignment (the default
    // without control points) must refuse, not guess, and say what to supply.
    assert!(stderr.contains("stage register failed"), "{stderr}");
    assert!(stderr.contains("automatic registration"), "{stderr}");
    assert!(stderr.contains("supply control points"), "{stderr}");
    let results = read_json(&out.join("results.json"));
    assert!(results.get("ingest").is_some());
    assert!(results.get("register").is_none());
}

#[test]
fn bad_input_fails_with_the_file_named() {
    let fx = fixture();
    let bad = fx.dir.path().join("bad.las");
    std::fs::write(&bad, b"LASF but not really a LAS file").expect("write");
    let stderr = fails(
        Command::new(BIN)
            .args(["run", "--until", "ingest", "--lidar"])
            .arg(&bad)
            .arg("--colmap")
            .arg(&fx.colmap_dir)
            .arg("--out")
            .arg(fx.dir.path().join("out")),
    );
    assert!(stderr.contains("bad.las"), "{stderr}");
}

#[test]
fn every_flag_is_documented_and_mirrored_by_an_environment_variable() {
    for sub in ["serve", "worker", "run"] {
        let out = Command::new(BIN)
            .args([sub, "--help"])
            .output()
            .expect("help");
        let help = String::from_utf8_lossy(&out.stdout).to_string();
        // Each option starts a paragraph: "  --flag <VALUE>" then its text up to the next option.
        let mut blocks: Vec<String> = Vec::new();
        for line in help.lines() {
            let t = line.trim_start();
            if t.starts_with("--") || (t.starts_with('-') && t.get(2..4) == Some(", ")) {
                blocks.push(line.to_string());
            } else if let Some(b) = blocks.last_mut() {
                b.push_str(line);
            }
        }
        assert!(blocks.len() > 3, "{sub}: {help}");
        for b in blocks {
            if b.contains("--help") || b.contains("--version") {
                continue;
            }
            assert!(b.contains("[env: SYLVA_"), "{sub}: no env var for {b}");
            let text_len = b.split_whitespace().count();
            assert!(text_len > 4, "{sub}: undocumented flag {b}");
        }
    }
}

/// `sylva run` on the generated plot in `plot` (its four inputs) with `flags`, into `out`.
fn run_on_plot(plot: &Path, flags: &[&str], out: &Path) -> Command {
    let mut cmd = Command::new(BIN);
    cmd.args(["run", "--lidar"]).arg(plot.join("lidar.laz"));
    cmd.arg("--colmap").arg(plot.join("colmap"));
    cmd.arg("--control-points")
        .arg(plot.join("control_points.csv"));
    cmd.arg("--field-dbh").arg(plot.join("field_dbh.csv"));
    cmd.args(flags).arg("--out").arg(out);
    cmd
}

#[test]
fn run_until_segment_gives_the_lidar_inventory_of_a_synthetic_plot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plot = synth_plot(dir.path(), 2);
    // The plot's LAZ declares UTM zone 49N, as a scanner's georeferenced export would.
    let laz = plot.join("lidar.laz");
    let cloud = sylva::io::pointcloud::read_point_cloud(&laz, &sylva::progress::NoProgress)
        .expect("read lidar");
    let utm = sylva::io::crs::Crs::from_epsg(32649).expect("utm");
    sylva::io::las::write_las_with_crs(&laz, &cloud, true, Some(&utm)).expect("write lidar");
    let out = dir.path().join("out");
    succeeds(&mut run_on_plot(&plot, &["--until", "segment"], &out));
    let results = read_json(&out.join("results.json"));
    assert_eq!(results["ingest"]["lidar"]["crs"], "EPSG:32649");
    assert_eq!(results["ingest"]["lidar"]["crs_source"], "file");
    let seg = &results["segment"];
    let truth = read_json(&plot.join("truth.json"));
    let n_true = truth["trees"].as_array().map_or(0, Vec::len);
    assert!(n_true > 0);
    // Every generated stem is found and matched to its field record within 1 m.
    assert_eq!(seg["trees"].as_u64(), Some(n_true as u64), "{seg}");
    assert_eq!(
        seg["field"]["n_matched"].as_u64(),
        Some(n_true as u64),
        "{seg}"
    );
    let rmse = seg["field"]["rmse_cm"].as_f64().expect("rmse");
    assert!(rmse < 1.5, "DBH RMSE {rmse} cm");
    let csv = std::fs::read_to_string(out.join("segment/trees.csv")).expect("trees.csv");
    assert_eq!(
        csv.lines().next(),
        Some(
            "tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm,n_points,rms_mm,arc_coverage,quality,gs_quality,\
             height_m,crown_base_m,crown_area_m2,crown_diameter_m,basal_area_m2,volume_m3,agb_kg,carbon_kg,\
             height_quality,crown_gap_m"
        )
    );
    assert_eq!(csv.lines().count(), n_true + 1);
    // The anchors carry labels for the trainer, and some of them are trunk.
    let header = std::fs::read(out.join("segment/anchors.ply")).expect("anchors");
    let head = String::from_utf8_lossy(&header[..header.len().min(1024)]).to_string();
    assert!(head.contains("property float trunk_prob"), "{head}");
    assert!(seg["anchors"]["trunk"].as_u64().unwrap_or(0) > 100, "{seg}");
    for f in [
        "labelled.ply",
        "dtm.json",
        "stems.json",
        "trees.geojson",
        "crs.json",
    ] {
        assert!(out.join("segment").join(f).is_file(), "{f}");
    }
    // RFC 7946: the stems at their WGS84 longitude and latitude (the plot's 500 km easting is
    // zone 49's central meridian, 111° E; 4000 km north is about 36.1° N), native x, y kept.
    let gj = read_json(&out.join("segment/trees.geojson"));
    assert_eq!(gj["sylva_crs"]["label"], "EPSG:32649");
    let features = gj["features"].as_array().expect("features");
    assert_eq!(features.len(), n_true);
    for f in features {
        let c = &f["geometry"]["coordinates"];
        let (lon, lat) = (c[0].as_f64().expect("lon"), c[1].as_f64().expect("lat"));
        assert!(
            (lon - 111.0).abs() < 0.01 && (lat - 36.1).abs() < 0.1,
            "{f}"
        );
        let mut native = [(
            f["properties"]["x"].as_f64().expect("x"),
            f["properties"]["y"].as_f64().expect("y"),
        )];
        utm.to_wgs84(&mut native).expect("transform");
        assert!(
            (native[0].0 - lon).abs() < 1e-7 && (native[0].1 - lat).abs() < 1e-7,
            "{f}"
        );
    }
    assert_eq!(
        read_json(&out.join("segment/crs.json"))["label"],
        "EPSG:32649"
    );
}

/// `--crs` overrides what the file declares (and the outputs say so); a CRS in degrees is
/// refused before any work, naming what to do.
#[test]
fn run_takes_the_crs_from_the_flag_and_refuses_degrees() {
    let fx = fixture();
    let out = fx.dir.path().join("out");
    let run = |crs: &str, out: &Path| {
        let mut cmd = Command::new(BIN);
        cmd.args(["run", "--until", "ingest", "--crs", crs, "--lidar"])
            .arg(&fx.lidar)
            .arg("--colmap")
            .arg(&fx.colmap_dir)
            .arg("--out")
            .arg(out);
        cmd
    };
    succeeds(&mut run("EPSG:25832", &out));
    let results = read_json(&out.join("results.json"));
    assert_eq!(results["ingest"]["lidar"]["crs"], "EPSG:25832");
    assert_eq!(results["ingest"]["lidar"]["crs_source"], "given");
    assert_eq!(
        read_json(&out.join("ingest/crs.json"))["label"],
        "EPSG:25832"
    );
    let stderr = fails(&mut run("EPSG:4326", &fx.dir.path().join("out2")));
    assert!(
        stderr.contains("--crs") && stderr.contains("degrees"),
        "{stderr}"
    );
}

#[test]
fn a_whole_run_trains_on_the_cpu_reference_and_exports_splats_and_both_diameters() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plot = synth_plot(dir.path(), 3);
    // The LAZ declares UTM zone 49N, so that the tileset is placed on the Earth.
    let laz = plot.join("lidar.laz");
    let cloud = sylva::io::pointcloud::read_point_cloud(&laz, &sylva::progress::NoProgress)
        .expect("read lidar");
    let utm = sylva::io::crs::Crs::from_epsg(32649).expect("utm");
    sylva::io::las::write_las_with_crs(&laz, &cloud, true, Some(&utm)).expect("write lidar");
    let params = dir.path().join("params.json");
    std::fs::write(&params, r#"{"train": {"max_gaussians": 1500}}"#).expect("params");
    let out = dir.path().join("out");
    let params = params.to_str().expect("path");
    let flags = [
        "--params",
        params,
        "--backend",
        "cpu",
        "--steps",
        "60",
        "--resolution",
        "48",
        "--init",
        "lidar",
    ];
    succeeds(&mut run_on_plot(&plot, &flags, &out));
    let results = read_json(&out.join("results.json"));
    let train = &results["train"];
    assert_eq!(
        train["gaussians"]["initial"].as_u64(),
        Some(1500),
        "{train}"
    );
    assert!(train["render"]["psnr"].as_f64().is_some(), "{train}");
    // Sylva's binding by default: trunk surfels held on the LiDAR surface from step 0.
    assert_eq!(train["semantic_applied"], true, "{train}");
    assert_eq!(train["semantic"]["term"], "bind", "{train}");
    let last = &train["trunk_diagnostics"]["last"];
    assert!(
        last["surface_abs_mm"].as_f64().is_some_and(|d| d <= 15.0),
        "{last}"
    );
    assert!(
        train["semantic"]["trunk_anchors"].as_u64().unwrap_or(0) > 0,
        "{train}"
    );
    assert!(
        train["device"].as_str().unwrap_or("").contains("cpu"),
        "{train}"
    );
    for f in ["splats.ply", "eval.json", "loss.csv", "loss.png"] {
        assert!(out.join("train").join(f).is_file(), "{f}");
    }
    let loss = std::fs::read_to_string(out.join("train/loss.csv")).expect("loss.csv");
    assert_eq!(loss.lines().count(), 1 + 6, "{loss}");
    // Stage dbh fills the inventory with both diameters' columns and scores them.
    // (results.json's `dbh` is the accuracy summary docs/method.md asks for.)
    let dbh = &results["dbh"];
    assert!(dbh["rmse_lidar_cm"].as_f64().is_some(), "{dbh}");
    assert_eq!(dbh["matched"].as_u64(), Some(3), "{dbh}");
    let csv = std::fs::read_to_string(out.join("dbh/trees.csv")).expect("trees.csv");
    let lidar = std::fs::read_to_string(out.join("segment/trees.csv")).expect("trees.csv");
    assert_eq!(csv.lines().count(), lidar.lines().count());
    // Stage export: the splats in both formats, the inventory and the frame.
    let ply = std::fs::read(out.join("export/splats.ply")).expect("splats.ply");
    assert!(String::from_utf8_lossy(&ply[..512]).contains("element vertex 1500"));
    let compact = std::fs::metadata(out.join("export/splats.splat")).expect("splat");
    assert_eq!(compact.len(), 1500 * 32);
    let frame = read_json(&out.join("export/frame.json"));
    assert!(
        frame["offset"].is_array() && frame["sfm_to_lidar"]["scale"].is_number(),
        "{frame}"
    );
    assert!(out.join("export/trees.csv").is_file());
    // The glTF splats are the PLY's to float precision.
    let from_ply = sylva::splat::export::read_ply(ply.as_slice()).expect("ply");
    let glb = std::fs::read(out.join("export/splats.glb")).expect("splats.glb");
    let from_glb = sylva::splat::export_gltf::read_glb(glb.as_slice()).expect("glb");
    assert_eq!(from_glb.means, from_ply.means);
    for i in 0..from_ply.len() {
        for k in 0..3 {
            let (a, b) = (from_glb.log_scales[i][k], from_ply.log_scales[i][k]);
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                "log scale {a} vs {b}"
            );
        }
        let (a, b) = (from_glb.opacity_logits[i], from_ply.opacity_logits[i]);
        assert!(
            (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
            "opacity {a} vs {b}"
        );
        let n = from_ply.sh_degree as usize;
        let coefs = 3 * (n + 1) * (n + 1);
        assert_eq!(from_glb.sh[i][..coefs], from_ply.sh[i][..coefs]);
    }
    // The tileset: on the Earth where the inventory puts the trees, within 1 cm.
    let tileset = read_json(&out.join("export/tileset.json"));
    let m: Vec<f64> = tileset["root"]["transform"]
        .as_array()
        .expect("a root transform to ECEF")
        .iter()
        .map(|v| v.as_f64().expect("f64"))
        .collect();
    let m = glam::DMat4::from_cols_slice(&m);
    let meta = &tileset["metadata"]["properties"];
    let ids = meta["treeId"].as_array().expect("ids");
    assert_eq!(ids.len(), 3, "{meta}");
    let gj = read_json(&out.join("export/trees.geojson"));
    for (id, pos) in ids
        .iter()
        .zip(meta["position"].as_array().expect("positions"))
    {
        let local: Vec<f64> = pos
            .as_array()
            .expect("xyz")
            .iter()
            .map(|v| v.as_f64().expect("f64"))
            .collect();
        let ecef = m.transform_point3(glam::DVec3::new(local[0], local[1], local[2]));
        let tree = gj["features"]
            .as_array()
            .expect("features")
            .iter()
            .find(|f| {
                f["properties"]["tree_id"]
                    .as_u64()
                    .map(|v| v.to_string())
                    .as_deref()
                    == id.as_str()
            })
            .expect("the same tree in trees.geojson");
        let c = &tree["geometry"]["coordinates"];
        let want = sylva::splat::tiles::wgs84_to_ecef(
            c[0].as_f64().expect("lon"),
            c[1].as_f64().expect("lat"),
            tree["properties"]["ground_z"].as_f64().expect("z"),
        );
        let off = (ecef - glam::DVec3::from_array(want)).length();
        assert!(
            off < 0.01,
            "tree {id}: {off} m between the tileset and trees.geojson"
        );
    }
    let export = &results["export"]["tiles"];
    assert_eq!(export["ecef"], true, "{export}");
    assert!(
        export["root_bytes"].as_u64().expect("bytes") < 5_000_000,
        "{export}"
    );
    let root_uri = tileset["root"]["content"]["uri"].as_str().expect("uri");
    assert!(out.join("export").join(root_uri).is_file(), "{root_uri}");
    // The labelled cloud as COPC, read by laspy's CopcReader (not Sylva's): every point, the
    // CRS, the classes and tree ids the export report counted.
    let copc = &results["export"]["copc"]["cloud.copc.laz"];
    let Some(python) = laspy_python() else {
        return;
    };
    let script = r#"
import sys, json, laspy, numpy as np
with laspy.CopcReader.open(sys.argv[1]) as r:
    p = r.query()
    wkt = [v.string for v in r.header.vlrs if v.record_id == 2112]
    c = np.asarray(p.classification)
    t = np.asarray(p["tree_id"])
    print(json.dumps({"points": int(r.header.point_count), "read": len(p),
        "ground": int((c == 2).sum()), "leaf": int((c == 5).sum()), "wood": int((c == 64).sum()),
        "in_trees": int((t > 0).sum()), "trees": sorted(int(v) for v in np.unique(t) if v > 0),
        "wkt": wkt[0] if wkt else "", "version": str(r.header.version)}))
"#;
    let run = Command::new(&python)
        .args(["-c", script])
        .arg(out.join("export/cloud.copc.laz"))
        .output()
        .expect("python");
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let got: serde_json::Value = serde_json::from_slice(&run.stdout).expect("json");
    for k in ["points", "ground", "leaf", "wood", "in_trees"] {
        assert_eq!(got[k], copc[k], "{k}: laspy {got} vs report {copc}");
    }
    assert_eq!(got["read"], got["points"], "{got}");
    assert_eq!(got["trees"], serde_json::json!([1, 2, 3]), "{got}");
    assert!(
        got["wkt"]
            .as_str()
            .is_some_and(|w| w.contains("UTM zone 49N")),
        "{got}"
    );
    assert_eq!(got["version"], "1.4", "{got}");
}

#[test]
fn demo_runs_a_generated_plot_through_the_api_and_prints_the_inventory() {
    let dir = tempfile::tempdir().expect("tempdir");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port");
    let out = Command::new(BIN)
        .args(["demo", "--exit", "--steps", "20", "--listen"])
        .arg(format!("127.0.0.1:{port}"))
        .arg("--data")
        .arg(dir.path())
        .output()
        .expect("demo");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm"),
        "{stdout}"
    );
    assert!(stdout.contains("| held-out PSNR (dB) |"), "{stdout}");
    assert!(stdout.contains("| trees matched | 3 |"), "{stdout}");
    // The plot and the job stay in the data folder for the web page.
    assert!(dir.path().join("demo-plot/truth.json").is_file());
    assert!(dir.path().join("sylva.db").is_file());
}

/// `sylva inventory` on a generated plot with `--crs`, `--summary`, `--geojson` and
/// `--gpkg`: the stand figures printed and written, and a GeoPackage that GDAL's own reader
/// (pyogrio, PyPI's GDAL bindings, in the test venv) opens: stems as points and crowns as
/// polygons in the given CRS, one of each per tree, with the CSV's columns.
#[test]
fn inventory_prints_the_plot_and_writes_a_geopackage_gdal_reads() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plot = synth_plot(dir.path(), 3);
    let out = dir.path().join("trees.csv");
    let gpkg = dir.path().join("trees.gpkg");
    let output = succeeds(
        Command::new(BIN)
            .args(["inventory", "--crs", "EPSG:32633", "--summary", "--out"])
            .arg(&out)
            .arg("--gpkg")
            .arg(&gpkg)
            .arg("--geojson")
            .arg(dir.path().join("trees.geojson"))
            .arg(plot.join("lidar.laz")),
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains("stems/ha") && stdout.contains("Chave"),
        "{stdout}"
    );
    let summary = read_json(&dir.path().join("trees.plot.json"));
    let rows = std::fs::read_to_string(&out).expect("csv").lines().count() - 1;
    assert!(rows > 0);
    assert_eq!(summary["stems"].as_u64(), Some(rows as u64), "{summary}");
    assert_eq!(summary["dbh_source"], "lidar");
    assert!(
        summary["area_m2"].as_f64().unwrap_or(0.0) > 100.0,
        "{summary}"
    );
    assert_eq!(
        read_json(&dir.path().join("trees.crs.json"))["label"],
        "EPSG:32633"
    );

    let python = match test_tool("SYLVA_TEST_PYTHON_GDAL", "python3") {
        Ok(p)
            if Command::new(&p)
                .args(["-c", "import pyogrio"])
                .status()
                .is_ok_and(|s| s.success()) =>
        {
            p
        }
        _ => {
            sylva::testing::skip(
                "gdal",
                "pyogrio (GDAL's reader, from PyPI) is not in target/test-venv; scripts/test installs it",
            );
            return;
        }
    };
    let script = r#"
import json, sys, pyogrio
out = {}
for layer in ("trees", "crowns"):
    info = pyogrio.read_info(sys.argv[1], layer=layer)
    out[layer] = {"crs": info["crs"], "features": int(info["features"]),
                  "geometry": info["geometry_type"], "fields": list(info["fields"])}
print(json.dumps(out))
"#;
    let run = succeeds(Command::new(&python).args(["-c", script]).arg(&gpkg));
    let text = String::from_utf8_lossy(&run.stdout);
    let info: serde_json::Value = serde_json::from_str(text.trim()).expect("json");
    // One feature per tree in each layer, in the given CRS.
    for (layer, geometry) in [("trees", "Point"), ("crowns", "Polygon")] {
        assert_eq!(info[layer]["crs"], "EPSG:32633", "{info}");
        assert_eq!(info[layer]["geometry"], geometry, "{info}");
        assert_eq!(
            info[layer]["features"].as_u64(),
            Some(rows as u64),
            "{info}"
        );
    }
    let fields = info["trees"]["fields"].as_array().expect("fields");
    for f in [
        "tree_id",
        "dbh_lidar_cm",
        "height_m",
        "crown_diameter_m",
        "agb_kg",
    ] {
        assert!(fields.iter().any(|x| x == f), "{f}: {info}");
    }
}
