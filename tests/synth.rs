//! `sylva synth` through the real binary, and its files read back by independent readers:
//! laspy (Python, in a venv made here) for the LAZ, COLMAP itself for the model where the
//! Debian package is installed.

mod common;

use std::path::Path;
use std::process::Command;

use common::{BIN, laspy_python, succeeds};
use serde_json::Value;

fn synth(out: &Path, extra: &[&str]) {
    succeeds(
        Command::new(BIN)
            .args(["synth", "--preset", "tiny", "--seed", "5", "--out"])
            .arg(out)
            .args(extra),
    );
}

#[test]
fn synth_cli_writes_what_a_field_team_brings_home_plus_the_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The same plot into `dir/name`.
    let synth_into = |name: &str| {
        let out = dir.path().join(name);
        synth(&out, &["--binary", "--noise-cm", "0.5"]);
        out
    };
    let out = synth_into("plot");
    for f in [
        "lidar.laz",
        "control_points.csv",
        "field_dbh.csv",
        "truth.json",
        "labels.bin",
        "colmap/sparse/0/cameras.bin",
        "colmap/sparse/0/images.bin",
        "colmap/sparse/0/points3D.bin",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let truth: Value =
        serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
            .expect("json");
    for key in ["sfm_to_world", "trees", "test_images"] {
        assert!(truth.get(key).is_some(), "truth.json lacks {key}");
    }
    assert_eq!(
        truth["sfm_to_world"]["rotation"].as_array().map(Vec::len),
        Some(3)
    );
    let field = std::fs::read_to_string(out.join("field_dbh.csv")).expect("field");
    assert!(field.starts_with("tree_id,x,y,dbh_cm\n"), "{field}");
    let trees = truth["trees"].as_array().expect("trees").len();
    assert!((1..=3).contains(&trees));
    assert_eq!(field.lines().count(), trees + 1);
    let cps = std::fs::read_to_string(out.join("control_points.csv")).expect("cps");
    assert!(cps.lines().count() > 6, "at least 6 control point pairs");
    let images = std::fs::read_dir(out.join("colmap/images"))
        .expect("images")
        .count();
    assert!(images >= 20, "{images} images");
    let cloud = sylva::io::pointcloud::read_point_cloud(
        &out.join("lidar.laz"),
        &sylva::progress::NoProgress,
    )
    .expect("laz");
    let labels = std::fs::read(out.join("labels.bin")).expect("labels");
    assert_eq!(cloud.len(), labels.len());
    assert!(
        cloud.offset.x > 499_000.0 && cloud.offset.y > 3_999_000.0,
        "{:?}",
        cloud.offset
    );
    // The same seed gives the same bytes, through the CLI too.
    let again = synth_into("again");
    for f in [
        "lidar.laz",
        "truth.json",
        "labels.bin",
        "colmap/sparse/0/points3D.bin",
    ] {
        assert_eq!(
            std::fs::read(out.join(f)).ok(),
            std::fs::read(again.join(f)).ok(),
            "{f} differs"
        );
    }
}

#[test]
fn the_laz_reads_in_laspy_with_the_same_points() {
    let Some(python) = laspy_python() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("plot");
    synth(&out, &[]);
    let script = r#"
import sys, laspy, json
las = laspy.read(sys.argv[1])
print(json.dumps({"n": len(las.points), "min": [float(las.x.min()), float(las.y.min()), float(las.z.min())],
                  "max": [float(las.x.max()), float(las.y.max()), float(las.z.max())], "version": str(las.header.version)}))
"#;
    let run = succeeds(
        Command::new(&python)
            .arg("-c")
            .arg(script)
            .arg(out.join("lidar.laz")),
    );
    let v: Value = serde_json::from_slice(&run.stdout).expect("json");
    let cloud = sylva::io::pointcloud::read_point_cloud(
        &out.join("lidar.laz"),
        &sylva::progress::NoProgress,
    )
    .expect("laz");
    assert_eq!(v["n"].as_u64(), Some(cloud.len() as u64));
    let (lo, hi) = cloud.bounds().expect("bounds");
    for (k, (a, b)) in [(lo.x, hi.x), (lo.y, hi.y), (lo.z, hi.z)]
        .iter()
        .enumerate()
    {
        let (pa, pb) = (
            v["min"][k].as_f64().expect("min"),
            v["max"][k].as_f64().expect("max"),
        );
        assert!(
            (pa - a).abs() < 1e-3 && (pb - b).abs() < 1e-3,
            "axis {k}: laspy {pa}..{pb}, sylva {a}..{b}"
        );
    }
}

#[test]
fn the_model_loads_in_colmap_where_installed() {
    let has_colmap = Command::new("colmap")
        .arg("help")
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_colmap {
        sylva::testing::skip(
            "colmap",
            "the colmap program is not installed (Debian package colmap)",
        );
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("plot");
    synth(&out, &[]);
    let run = Command::new("colmap")
        .args(["model_analyzer", "--path"])
        .arg(out.join("colmap/sparse/0"))
        .output()
        .expect("colmap");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(run.status.success(), "{text}");
    assert!(text.contains("Registered images"), "{text}");
}

#[test]
fn inventory_of_a_synthetic_plot_matches_its_field_measurements() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("plot");
    synth(&out, &[]);
    let csv = dir.path().join("trees.csv");
    let geojson = dir.path().join("trees.geojson");
    let run = succeeds(
        Command::new(BIN)
            .arg("inventory")
            .arg(out.join("lidar.laz"))
            .arg("--out")
            .arg(&csv)
            .arg("--geojson")
            .arg(&geojson)
            .arg("--field")
            .arg(out.join("field_dbh.csv")),
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    let text = std::fs::read_to_string(&csv).expect("trees.csv");
    assert!(
        text.starts_with(
            "tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm,n_points,rms_mm,arc_coverage,quality,gs_quality,\
             height_m,crown_base_m,crown_area_m2,crown_diameter_m,basal_area_m2,volume_m3,agb_kg,carbon_kg,\
             height_quality,crown_gap_m\n"
        ),
        "{text}"
    );
    let truth: Value =
        serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
            .expect("json");
    let trees = truth["trees"].as_array().expect("trees");
    assert_eq!(text.lines().count(), trees.len() + 1, "{text}");
    assert!(
        stdout.contains("recall 100.0%, precision 100.0%"),
        "{stdout}"
    );
    // DBH within 1 cm of the tape for every tree (LiDAR noise 1 cm).
    let rmse: f64 = stdout
        .lines()
        .find_map(|l| l.strip_prefix("DBH: RMSE "))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .expect("RMSE line");
    assert!(rmse <= 1.0, "DBH RMSE {rmse} cm");
    let g: Value =
        serde_json::from_slice(&std::fs::read(&geojson).expect("geojson")).expect("json");
    assert_eq!(g["type"], "FeatureCollection");
    assert_eq!(g["features"].as_array().map(Vec::len), Some(trees.len()));
}
