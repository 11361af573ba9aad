//! The LiDAR inventory against the truth of generated stands (`sylva synth --preset stand`,
//! 1 cm range noise), five seeds: stems found, DBH, ground height, wood/leaf labels.

use sylva::forest::{InventoryParams, TRUNK, compare_with_field, inventory};
use sylva::io::pointcloud::read_point_cloud;
use sylva::io::tables::read_field_dbh;
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams};

#[test]
fn stands_of_five_seeds_meet_the_accuracy_goals() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut report = Vec::new();
    for seed in 1..=5u64 {
        let out = dir.path().join(format!("stand-{seed}"));
        let mut p = SynthParams::new(Preset::Stand);
        p.seed = seed;
        // The inventory reads only the LiDAR: a few small photos keep the test quick.
        p.images = Some(4);
        p.width = Some(160);
        p.height = Some(90);
        sylva::synth::generate(&p, &out, &NoProgress).expect("synth");
        let cloud = read_point_cloud(&out.join("lidar.laz"), &NoProgress).expect("laz");
        let inv = inventory(&cloud, &InventoryParams::default(), &NoProgress).expect("inventory");

        // Stems with DBH >= 8 cm: detection and DBH.
        let field: Vec<_> = read_field_dbh(&out.join("field_dbh.csv"))
            .expect("field")
            .into_iter()
            .filter(|t| t.dbh_cm >= 8.0)
            .collect();
        let rows: Vec<_> = inv
            .trees
            .iter()
            .filter(|r| r.dbh_lidar_cm >= 6.0)
            .cloned()
            .collect();
        let cmp = compare_with_field(&rows, &field, 1.0);
        let recall = cmp.recall;
        let precision = cmp.precision;
        let rmse = cmp.rmse_cm.expect("rmse");

        // Ground height at the stems against the generator's stem base.
        let truth: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
                .expect("json");
        let mut ground_err: f64 = 0.0;
        let (mut h_sq, mut n_h, mut crown_rel): (f64, usize, Vec<f64>) = (0.0, 0, Vec::new());
        let mut tree_lines = Vec::new();
        for t in truth["trees"].as_array().expect("trees") {
            let (x, y, z) = (
                t["x"].as_f64().expect("x"),
                t["y"].as_f64().expect("y"),
                t["z"].as_f64().expect("z"),
            );
            let nearest = inv
                .trees
                .iter()
                .min_by(|a, b| ((a.x - x).hypot(a.y - y)).total_cmp(&(b.x - x).hypot(b.y - y)));
            if let Some(r) = nearest.filter(|r| (r.x - x).hypot(r.y - y) < 1.0) {
                ground_err = ground_err.max((r.ground_z - z).abs());
                // Height and crown of the same tree against the generator's.
                let (th, td) = (
                    t["height_m"].as_f64().expect("height"),
                    t["crown_diameter_m"].as_f64().expect("crown"),
                );
                let (h, d) = (r.height_m.unwrap_or(0.0), r.crown_diameter_m.unwrap_or(0.0));
                h_sq += (h - th).powi(2);
                n_h += 1;
                crown_rel.push(d / td - 1.0);
                tree_lines.push(format!(
                    "  tree {}: height {h:.2} m (truth {th:.2}), crown {d:.2} m (truth {td:.2}), \
                     crown base {:.2} m (truth {:.2})",
                    r.tree_id,
                    r.crown_base_m.unwrap_or(f64::NAN),
                    t["crown_base_m"].as_f64().unwrap_or(f64::NAN)
                ));
            }
        }
        let height_rmse = (h_sq / n_h.max(1) as f64).sqrt();
        let crown_worst = crown_rel.iter().fold(0.0f64, |a, e| a.max(e.abs()));
        let crown_mean =
            crown_rel.iter().map(|e| e.abs()).sum::<f64>() / crown_rel.len().max(1) as f64;
        for l in &tree_lines {
            println!("{l}");
        }

        // Wood/leaf against the generator's labels (1 wood, 2 leaf), non-ground points.
        let labels = std::fs::read(out.join("labels.bin")).expect("labels");
        let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
        for (i, truth_label) in labels.iter().enumerate() {
            if inv.is_ground[i] || !matches!(truth_label, 1 | 2) {
                continue;
            }
            let said_trunk = inv.labels[i] == TRUNK;
            match (said_trunk, *truth_label == 1) {
                (true, true) => tp += 1,
                (true, false) => fp += 1,
                (false, true) => fneg += 1,
                _ => {}
            }
        }
        let trunk_recall = tp as f64 / (tp + fneg).max(1) as f64;
        let trunk_precision = tp as f64 / (tp + fp).max(1) as f64;
        let line = format!(
            "seed {seed}: stems recall {recall:.3} precision {precision:.3}, DBH RMSE {rmse:.2} cm, \
             ground error {:.1} cm, trunk recall {trunk_recall:.3} precision {trunk_precision:.3}, \
             height RMSE {height_rmse:.2} m ({n_h} trees), crown diameter error mean {:.1} % \
             worst {:.1} %",
            ground_err * 100.0,
            crown_mean * 100.0,
            crown_worst * 100.0
        );
        println!("{line}");
        report.push((
            line,
            recall,
            precision,
            rmse,
            ground_err,
            trunk_recall,
            trunk_precision,
            (height_rmse, crown_worst),
        ));
    }
    // The goals, on every seed: stems recall and precision >= 95 %, DBH RMSE
    // <= 1.0 cm, ground at the stems <= 3 cm, and wood/leaf against the generator's labels
    // (where "wood" includes every branch down to 6 mm radius) trunk recall >= 0.90 and
    // precision >= 0.85, all asserted at the goal (measured values in docs/results/inventory.md, "LiDAR
    // inventory" paragraph).
    for (line, recall, precision, rmse, ground_err, trunk_recall, trunk_precision, (h, crown)) in
        report
    {
        assert!(recall >= 0.95 && precision >= 0.95, "{line}");
        assert!(rmse <= 1.0, "{line}");
        assert!(ground_err <= 0.03, "{line}");
        assert!(trunk_recall >= 0.90, "{line}");
        assert!(trunk_precision >= 0.85, "{line}");
        // Issue 27's goals: height RMSE <= 0.5 m, every crown diameter within 15 %.
        assert!(h <= 0.5, "{line}");
        assert!(crown <= 0.15, "{line}");
    }
}

/// The 2-means of the wood/leaf split on more rows than its warm-start threshold (400 000):
/// the subsample pass and the full pass together still put every row with its blob, and the
/// result is the same on every run.
#[test]
fn two_means_warm_start_on_many_rows_separates_the_blobs() {
    use sylva::forest::kmeans::kmeans;
    let n = 600_000;
    let mut unit = sylva::testing::centred_unit(1);
    let mut rows = Vec::with_capacity(n * 3);
    for i in 0..n {
        let c = if i % 3 == 0 { 4.0 } else { 0.0 };
        rows.extend([c + unit(), c + unit(), unit()]);
    }
    let a = kmeans(&rows, 3, 2, 100, 7, &NoProgress).expect("kmeans");
    let b = kmeans(&rows, 3, 2, 100, 7, &NoProgress).expect("kmeans");
    assert_eq!(a, b);
    let blob = a.assignment[0];
    for (i, &l) in a.assignment.iter().enumerate() {
        assert_eq!(l == blob, i % 3 == 0, "row {i}");
    }
}

/// Clouds that are not whole plots (issue 27.6), cut from a generated plot whose whole-cloud
/// inventory is the reference: a height-normalised cloud (measured either way) and one with its
/// ground cut away (measured under `cloud = normalised`), a single tree with its ground
/// (measured as it is), and a breast-height slice and a cloud without ground under `auto`
/// (refused, saying what to give instead).
#[test]
fn partial_clouds_are_measured_under_their_assumption_or_refused_plainly() {
    use sylva::forest::{CloudKind, ForestError};
    use sylva::io::pointcloud::PointCloud;
    let mut p = SynthParams::new(Preset::Tiny);
    p.seed = 3;
    let plot = sylva::synth::lidar_plot(&p, &NoProgress).expect("plot");
    let whole = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress).expect("whole");
    assert!(!whole.trees.is_empty());
    let heights = whole.dtm.heights_above(&plot.cloud.positions);
    let cut = |keep: &dyn Fn(usize) -> bool, normalise: bool| {
        let mut offset = plot.cloud.offset;
        if normalise {
            offset.z = 0.0;
        }
        let positions = plot
            .cloud
            .positions
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(i, q)| {
                if normalise {
                    glam::Vec3::new(q.x, q.y, heights[i])
                } else {
                    *q
                }
            })
            .collect();
        PointCloud {
            offset,
            positions,
            colors: None,
            intensity: None,
            format: plot.cloud.format,
        }
    };
    let normalised = InventoryParams {
        cloud: CloudKind::Normalised,
        ..InventoryParams::default()
    };
    // Each measured cloud finds every stem of the whole cloud with its DBH within 0.5 cm and
    // its height within 0.3 m.
    let same_trees = |what: &str, inv: &sylva::forest::Inventory| {
        assert_eq!(inv.trees.len(), whole.trees.len(), "{what}");
        for (a, b) in inv.trees.iter().zip(&whole.trees) {
            assert!((a.x - b.x).hypot(a.y - b.y) < 0.1, "{what}: {a:?} {b:?}");
            assert!(
                (a.dbh_lidar_cm - b.dbh_lidar_cm).abs() < 0.5,
                "{what}: {a:?} {b:?}"
            );
            let (ha, hb) = (a.height_m.unwrap_or(0.0), b.height_m.unwrap_or(0.0));
            assert!((ha - hb).abs() < 0.3, "{what}: height {ha} against {hb}");
        }
    };
    let z_is_height = cut(&|_| true, true);
    same_trees(
        "height-normalised, normalised",
        &inventory(&z_is_height, &normalised, &NoProgress).expect("normalised"),
    );
    same_trees(
        "height-normalised, auto",
        &inventory(&z_is_height, &InventoryParams::default(), &NoProgress).expect("auto"),
    );
    let no_ground_normalised = cut(&|i| heights[i] >= 0.5, true);
    same_trees(
        "no ground, normalised",
        &inventory(&no_ground_normalised, &normalised, &NoProgress).expect("no ground"),
    );

    let refused = |what: &str, cloud: &PointCloud, words: &[&str]| match inventory(
        cloud,
        &InventoryParams::default(),
        &NoProgress,
    ) {
        Err(ForestError::NotAPlot(m)) => {
            println!("{what}: {m}");
            for w in words {
                assert!(m.contains(w), "{what}: {m}");
            }
        }
        Err(e) => panic!("{what}: the wrong refusal: {e}"),
        Ok(inv) => panic!(
            "{what}: measured {} trees instead of refusing",
            inv.trees.len()
        ),
    };
    refused(
        "breast-height slice",
        &cut(&|i| (1.2..=1.4).contains(&heights[i]), false),
        &["slice", "whole cloud"],
    );
    refused(
        "no ground, auto",
        &cut(&|i| heights[i] >= 0.5, false),
        &["ground", "normalised"],
    );

    // One tree with the ground around it, cut 1.5 m around its stem: that stem, same DBH.
    let first = &whole.trees[0];
    let (ox, oy) = (plot.cloud.offset.x, plot.cloud.offset.y);
    let one = cut(
        &|i| {
            let q = plot.cloud.positions[i];
            (f64::from(q.x) + ox - first.x).hypot(f64::from(q.y) + oy - first.y) < 1.5
        },
        false,
    );
    let inv = inventory(&one, &InventoryParams::default(), &NoProgress).expect("one tree");
    let found = inv
        .trees
        .iter()
        .find(|r| (r.x - first.x).hypot(r.y - first.y) < 0.1)
        .expect("the tree");
    assert!(
        (found.dbh_lidar_cm - first.dbh_lidar_cm).abs() < 0.5,
        "{found:?} {first:?}"
    );
}
