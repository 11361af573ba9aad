//! End-to-end tests of the forest room: the inventory and the wood/leaf labels on plots of
//! `sylva synth` with known truth (the LiDAR side alone, [`crate::synth::lidar_plot`]), and
//! on the real public clouds (skipped with a message when they are absent).

use super::*;
use crate::io::pointcloud::{PointCloud, read_point_cloud};
use crate::io::tables::FieldTree;
use crate::progress::{Cancelled, NoProgress};
use crate::synth::scene::Label;
use crate::synth::trees::TreeTruth;
use crate::synth::{Preset, SynthParams, lidar_plot};

/// A generated plot as these tests read it.
struct Plot {
    /// The scan (local coordinates: the scene frame; `offset`: synth's `geo_offset`).
    cloud: PointCloud,
    /// Every tree's truth, local coordinates.
    trees: Vec<TreeTruth>,
    /// Per point: the generator's ground label.
    is_ground: Vec<bool>,
    /// Per point: the generator's wood label (stems and every branch).
    is_trunk: Vec<bool>,
}

/// The LiDAR side of the plot `p` describes, without colour (as the clouds of most scanners:
/// the colour test adds its own).
fn generate(p: &SynthParams) -> Plot {
    let plot = lidar_plot(
        &SynthParams {
            lidar_rgb: false,
            ..p.clone()
        },
        &NoProgress,
    )
    .expect("synth");
    Plot {
        is_ground: plot
            .labels
            .iter()
            .map(|l| *l == Label::Ground as u8)
            .collect(),
        is_trunk: plot
            .labels
            .iter()
            .map(|l| *l == Label::Wood as u8)
            .collect(),
        cloud: plot.cloud,
        trees: plot.trees,
    }
}

/// The plot of the inventory tests: `sylva synth`'s stand preset (1 cm range noise, terrain
/// relief, stones and shrubs, the handheld scan's occlusion) cut to 14 trees, which puts them
/// on a 16 m radius at canopy closure 0.5, with the first two at 8 and 60 cm DBH (the ends of
/// the species' range) and five leaning more than 4°; 1 M LiDAR points. Seed 1. Measured:
/// 14 of 14 stems, DBH RMSE 0.15 cm, ground at most 1.5 cm off, leaning axes within 0.6°;
/// about 1 s to generate.
fn stand() -> Plot {
    generate(&SynthParams {
        seed: 1,
        trees: Some(14),
        lidar_points: Some(1_000_000),
        stem_dbh_cm: vec![8.0, 60.0],
        ..SynthParams::new(Preset::Stand)
    })
}

/// The plot of the wood/leaf tests: four trees of the stand preset on a 7 m radius, 1 M LiDAR
/// points. Seed 2. The labels' precision needs the points per square metre of a full stand:
/// on the 14-tree plot above (a fifth of this density) it falls to 0.58; measured here trunk
/// recall 0.92, precision 0.89 (a full 5.2 M-point stand, seed 1: 0.90 and 0.87).
fn dense() -> Plot {
    generate(&SynthParams {
        seed: 2,
        trees: Some(4),
        lidar_points: Some(1_000_000),
        ..SynthParams::new(Preset::Stand)
    })
}

/// The generated trees as field data in the cloud's original coordinates.
fn field_of(plot: &Plot) -> Vec<FieldTree> {
    plot.trees
        .iter()
        .enumerate()
        .map(|(i, t)| FieldTree {
            tree_id: Some(format!("T{i}")),
            x: plot.cloud.offset.x + t.base.x,
            y: plot.cloud.offset.y + t.base.y,
            dbh_cm: t.dbh_m * 100.0,
        })
        .collect()
}

/// Per point of `plot`: whether it is off the ground (what the segmentation tests include).
fn non_ground(plot: &Plot) -> Vec<bool> {
    plot.is_ground.iter().map(|g| !g).collect()
}

/// The wood/leaf segmentation of `plot`'s points marked in `include` (default parameters).
fn segment_non_ground(plot: &Plot, colors: Option<&[[u8; 3]]>, include: &[bool]) -> WoodLeaf {
    segment_wood_leaf(
        &plot.cloud.positions,
        colors,
        Some(include),
        &SegmentParams::default(),
        &NoProgress,
    )
    .expect("segmentation")
}

#[test]
fn wood_leaf_labels_match_the_generated_truth() {
    let plot = dense();
    let include = non_ground(&plot);
    let wood = segment_non_ground(&plot, None, &include);
    let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
    for i in 0..plot.cloud.len() {
        if plot.is_ground[i] {
            assert_eq!(wood.labels[i], LEAF);
            assert_eq!(wood.trunk_probability[i], 0.0);
            continue;
        }
        let p = wood.trunk_probability[i];
        assert!((0.0..=1.0).contains(&p));
        assert_eq!(p >= 0.5, wood.labels[i] == TRUNK, "P {p} vs label at {i}");
        match (wood.labels[i] == TRUNK, plot.is_trunk[i]) {
            (true, true) => tp += 1,
            (true, false) => fp += 1,
            (false, true) => fneg += 1,
            _ => {}
        }
    }
    let recall = tp as f64 / (tp + fneg) as f64;
    let precision = tp as f64 / (tp + fp) as f64;
    println!("trunk recall {recall:.3}, precision {precision:.3}");
    assert!(recall >= 0.90, "trunk recall {recall}");
    assert!(precision >= 0.85, "trunk precision {precision}");
    // Deterministic: the same cloud gives the same labels.
    let again = segment_non_ground(&plot, None, &include);
    assert_eq!(again.labels, wood.labels);
}

#[test]
fn inventory_of_a_generated_plot_finds_every_stem_with_accurate_dbh_and_ground() {
    let plot = stand();
    let inv = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress).expect("inventory");
    let field = field_of(&plot);
    let cmp = compare_with_field(&inv.trees, &field, 1.0);
    for line in accuracy_lines(&cmp) {
        println!("{line}");
    }
    for r in &inv.trees {
        println!(
            "tree {} dbh {:.2} cm n {} rms {:.1} mm arc {:.2} {}",
            r.tree_id, r.dbh_lidar_cm, r.n_points, r.rms_mm, r.arc_coverage, r.quality
        );
    }
    assert!(cmp.recall >= 0.95, "recall {}", cmp.recall);
    assert!(cmp.precision >= 0.95, "precision {}", cmp.precision);
    let rmse = cmp.rmse_cm.expect("matches");
    assert!(rmse <= 1.0, "DBH RMSE {rmse} cm");
    // Ground height under each matched stem.
    for m in &cmp.matches {
        let row = inv
            .trees
            .iter()
            .find(|r| r.tree_id == m.tree_id)
            .expect("row");
        let truth = plot
            .trees
            .iter()
            .min_by(|a, b| {
                let d = |t: &TreeTruth| {
                    (plot.cloud.offset.x + t.base.x - row.x)
                        .hypot(plot.cloud.offset.y + t.base.y - row.y)
                };
                d(a).total_cmp(&d(b))
            })
            .expect("truth");
        let err = (row.ground_z - (plot.cloud.offset.z + truth.base.z)).abs();
        println!("tree {} ground error {:.1} mm", row.tree_id, err * 1000.0);
        assert!(err <= 0.03, "ground error {err} m at tree {}", row.tree_id);
        assert!(row.dbh_gs_cm.is_none());
    }
    assert_eq!(inv.labels.len(), plot.cloud.len());
    assert_eq!(inv.trunk_probability.len(), plot.cloud.len());
}

#[test]
fn leaning_stems_are_cut_across_their_own_axis() {
    let plot = stand();
    let inv = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress).expect("inventory");
    let leaning: Vec<_> = plot.trees.iter().filter(|t| t.lean_deg > 4.0).collect();
    assert!(!leaning.is_empty());
    for t in leaning {
        let stem = inv
            .stems
            .iter()
            .min_by(|a, b| {
                let d = |s: &Stem| s.base.as_dvec3().truncate().distance(t.base.truncate());
                d(a).total_cmp(&d(b))
            })
            .expect("a stem");
        let angle = stem
            .axis
            .as_dvec3()
            .dot(t.axis)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees();
        assert!(
            angle < 2.5,
            "axis off by {angle}° for a stem leaning {}°",
            t.lean_deg
        );
    }
}

#[test]
fn cancelling_stops_the_inventory() {
    // Any cloud will do: a small `tiny` plot.
    let plot = generate(&SynthParams {
        seed: 1,
        lidar_points: Some(20_000),
        ..SynthParams::new(Preset::Tiny)
    });
    let r = inventory(&plot.cloud, &InventoryParams::default(), &Cancelled);
    assert!(matches!(r, Err(ForestError::Cancelled)), "{r:?}");
}

/// The inventory (default parameters) of the real cloud `rel` under the real-data folder, or
/// `None` where this machine lacks it.
fn real_data_inventory(rel: &str) -> Option<Inventory> {
    let path = crate::io::real_data(rel)?;
    let cloud = read_point_cloud(&path, &NoProgress).expect("read");
    Some(inventory(&cloud, &InventoryParams::default(), &NoProgress).expect("inventory"))
}

#[test]
fn pine_plot_gives_a_dbh_with_quality_figures_for_every_stem() {
    let Some(inv) = real_data_inventory("TreeLS_extdata/pine_plot.laz") else {
        return;
    };
    println!("{}", trees_csv(&inv.trees));
    // About 14 stems of DBH 9-30 cm (TreeLS documentation); the plot's edges cut one or two
    // more (measured: 16, DBH 8.2-30.1 cm, every fit converged, RMS 4.5-6.7 mm).
    assert!(
        (14..=17).contains(&inv.trees.len()),
        "{} stems found",
        inv.trees.len()
    );
    for (r, d) in inv.trees.iter().zip(&inv.dbh) {
        assert!((7.5..32.0).contains(&r.dbh_lidar_cm), "{r:?}");
        assert!(d.circle.converged, "{r:?}");
        assert!(
            r.n_points >= 20 && r.rms_mm < 10.0 && r.arc_coverage > 0.3,
            "{r:?}"
        );
        // Inside the 10 x 10 m plot, on the ground (z 49–50 m).
        assert!(
            (-0.5..10.5).contains(&r.x) && (-0.5..10.5).contains(&r.y),
            "{r:?}"
        );
        assert!((48.8..50.5).contains(&r.ground_z), "{r:?}");
    }
    let good = inv.trees.iter().filter(|r| r.quality == "good").count();
    assert!(
        good * 10 >= inv.trees.len() * 7,
        "{good} good of {}",
        inv.trees.len()
    );
}

#[test]
fn single_pine_gives_one_tree_of_about_25_cm() {
    let Some(inv) = real_data_inventory("TreeLS_extdata/pine.laz") else {
        return;
    };
    assert_eq!(inv.trees.len(), 1, "{:?}", inv.trees);
    let dbh = inv.trees[0].dbh_lidar_cm;
    assert!((23.5..26.5).contains(&dbh), "DBH {dbh} cm");
}

#[test]
fn lidr_trunk_slice_gives_one_trunk_circle() {
    let Some(path) = crate::io::real_data("lidR_extdata/dbh.laz") else {
        return;
    };
    let cloud = read_point_cloud(&path, &NoProgress).expect("read");
    let (lo, hi) = cloud.bounds().expect("points");
    // A 10 cm slice at 4.1–4.2 m: already cut, no ground; fit the circle directly.
    assert!(hi.z - lo.z < 0.15, "z range {} .. {}", lo.z, hi.z);
    let pts: Vec<[f64; 2]> = cloud
        .positions
        .iter()
        .map(|p| [p.x as f64, p.y as f64])
        .collect();
    let fit = fit_circle_robust(&pts, &CircleParams::default()).expect("a circle");
    let dbh_cm = fit.fit.radius * 200.0;
    println!("dbh.laz: {dbh_cm:.1} cm, {fit:?}");
    assert!((26.0..32.0).contains(&dbh_cm), "diameter {dbh_cm} cm");
    assert!(fit.converged && fit.fit.rms < 0.01 && fit.arc_coverage > 0.5);
}

#[test]
fn colour_joins_the_features_when_the_cloud_has_it() {
    let plot = dense();
    let include = non_ground(&plot);
    // Brown bark, green leaves, with some spread.
    let colors: Vec<[u8; 3]> = plot
        .is_trunk
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let j = (i % 17) as u8 * 2;
            if *t {
                [95 + j, 65 + j, 40]
            } else {
                [60, 130 + j, 50 + j]
            }
        })
        .collect();
    let score = |colors: Option<&[[u8; 3]]>| {
        let w = segment_non_ground(&plot, colors, &include);
        let ok = (0..plot.cloud.len())
            .filter(|&i| include[i] && (w.labels[i] == TRUNK) == plot.is_trunk[i])
            .count();
        ok as f64 / include.iter().filter(|m| **m).count() as f64
    };
    let (geometric, coloured) = (score(None), score(Some(&colors)));
    println!("accuracy geometry only {geometric:.3}, with colour {coloured:.3}");
    assert!(coloured >= geometric, "{coloured} < {geometric}");
}

/// Issue 40.3: real single trees, whose height is known without a field crew: the top of the
/// cloud above zero for a height-normalised cloud (TreeLS), above its lowest point for a tree
/// cut out of its plot with z not normalised (PyTLidar's TreeQSM demo trees and AdTree's), read
/// under `segment.cloud = "segmented_tree"`. The tree with the most points is the tree; its
/// height must be within 0.5 m of the cloud's. Measured (2026-11-28, docs/results/inventory.md):
/// within 0.07 m on every tree but AdTree's tree13, in which the plot's band tests found no
/// stem (a sparse street scan: 40 stem points in the band, the stem hidden above 1.3 m). Since
/// 2026-11-29 a `segmented_tree` cloud in which they find none is tried again with them relaxed
/// (`StemParams::for_one_tree`), and tree13 is found within 0.01 m. AdTree's three street
/// trees (mobile scans of Lille and Paris) joined the set then (within 0.10 m). All must be
/// found when all are here (a clean clone has three of them in tests/data/real, which are
/// checked). AdTree's `ahn3_delft.xyz` is not here: an airborne scan of a tree, with 16 of its
/// 2,488 points under 3 m, it has no stem to measure.
#[test]
fn real_single_trees_have_the_height_of_their_cloud() {
    let cases = [
        ("TreeLS_extdata/pine.laz", CloudKind::Normalised),
        ("TreeLS_extdata/spruce.laz", CloudKind::Normalised),
        ("PyTLidar_trees/tree_1.las", CloudKind::SegmentedTree),
        ("PyTLidar_trees/tree_2.las", CloudKind::SegmentedTree),
        ("AdTree_trees/tree1.xyz", CloudKind::SegmentedTree),
        ("AdTree_trees/tree7.xyz", CloudKind::SegmentedTree),
        ("AdTree_trees/tree13.xyz", CloudKind::SegmentedTree),
        ("AdTree_trees/tree33.xyz", CloudKind::SegmentedTree),
        ("AdTree_trees/Lille_11.xyz", CloudKind::SegmentedTree),
        ("AdTree_trees/Lille_2.xyz", CloudKind::SegmentedTree),
        (
            "AdTree_trees/Paris_Luxembourg_1.xyz",
            CloudKind::SegmentedTree,
        ),
    ];
    let (mut found, mut missing) = (0, 0);
    let mut off = Vec::new();
    let mut table = vec!["| tree | cloud | truth m | sylva m | error m | quality |".to_string()];
    for (rel, kind) in cases {
        // A clean clone has some of them (tests/data/real): those are checked.
        let Some(path) = crate::io::real_data(rel) else {
            missing += 1;
            continue;
        };
        let cloud = read_point_cloud(&path, &NoProgress).expect("read");
        // File coordinates.
        let (lo, hi) = cloud.bounds().expect("points");
        let truth = match kind {
            CloudKind::Normalised => hi.z,
            _ => hi.z - lo.z,
        };
        let params = InventoryParams {
            cloud: kind,
            ..InventoryParams::default()
        };
        let inv = inventory(&cloud, &params, &NoProgress).expect("inventory");
        let Some((row, crown)) = inv
            .trees
            .iter()
            .zip(&inv.crowns)
            .max_by_key(|(_, c)| c.points)
        else {
            table.push(format!("| {rel} | {kind:?} | {truth:.2} | no stem | | |"));
            continue;
        };
        found += 1;
        let h = row.height_m.expect("a height");
        table.push(format!(
            "| {rel} | {kind:?} | {truth:.2} | {h:.2} | {:+.2} | {} |",
            h - truth,
            crown.height_quality().as_str()
        ));
        if (h - truth).abs() > 0.5 {
            off.push(rel);
        }
    }
    println!("{}", table.join("\n"));
    assert!(
        off.is_empty(),
        "{off:?} off by more than 0.5 m:\n{}",
        table.join("\n")
    );
    if missing == 0 {
        assert!(
            found == cases.len(),
            "{found} of {} single trees found:\n{}",
            cases.len(),
            table.join("\n")
        );
    }
}

/// One generated `tiny` tree (its whole plot), and the tree alone: its wood and leaves, without
/// the ground, stones and shrubs, as a segmented tree is shared.
fn one_tree_cut_out() -> (crate::synth::LidarPlot, PointCloud) {
    let plot = lidar_plot(
        &SynthParams {
            trees: Some(1),
            lidar_rgb: false,
            ..SynthParams::new(Preset::Tiny)
        },
        &NoProgress,
    )
    .expect("synth");
    let mut cut = plot.cloud.clone();
    cut.positions = cut
        .positions
        .iter()
        .zip(&plot.labels)
        .filter(|(_, l)| **l == Label::Wood as u8 || **l == Label::Leaf as u8)
        .map(|(p, _)| *p)
        .collect();
    cut.intensity = None;
    (plot, cut)
}

/// `segmented_tree` measures from the stem's lowest point: a generated tree with its ground cut
/// away and lifted by 100 m gives the same height and DBH as the whole plot, where `auto`
/// refuses it (its stem stands on no ground).
#[test]
fn a_segmented_tree_is_measured_from_its_lowest_point() {
    let (plot, mut cut) = one_tree_cut_out();
    let whole = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress).expect("plot");
    assert_eq!(whole.trees.len(), 1, "{:?}", whole.trees);
    cut.offset.z += 100.0;
    let auto = inventory(&cut, &InventoryParams::default(), &NoProgress);
    assert!(
        matches!(&auto, Err(ForestError::NotAPlot(m)) if m.contains("segmented_tree")),
        "{:?}",
        auto.map(|i| i.trees)
    );
    let params = InventoryParams {
        cloud: CloudKind::SegmentedTree,
        ..InventoryParams::default()
    };
    let tree = inventory(&cut, &params, &NoProgress).expect("segmented tree");
    assert_eq!(tree.trees.len(), 1, "{:?}", tree.trees);
    let (a, b) = (&whole.trees[0], &tree.trees[0]);
    assert!(
        (a.dbh_lidar_cm - b.dbh_lidar_cm).abs() < 0.5,
        "{a:?}\n{b:?}"
    );
    let (ha, hb) = (a.height_m.expect("height"), b.height_m.expect("height"));
    assert!((ha - hb).abs() < 0.3, "{ha} against {hb}");
}

/// A `segmented_tree` whose stem is hidden above 1.3 m (as AdTree's tree13: a street scan
/// whose foliage hides the stem between 1.3 m and the crown) fails the plot's band tests (the
/// band 1–2 m is 30 % filled), and is found with them relaxed (`StemParams::for_one_tree`),
/// with the height of the whole cloud. Without the retry it has no row.
#[test]
fn a_segmented_tree_with_its_stem_hidden_above_breast_height_keeps_its_height() {
    let (_, mut cut) = one_tree_cut_out();
    let foot = cut
        .positions
        .iter()
        .map(|p| p.z)
        .fold(f32::INFINITY, f32::min);
    cut.positions
        .retain(|p| !(1.3..2.5).contains(&(p.z - foot)));
    let (lo, hi) = cut.bounds().expect("points");
    let params = InventoryParams {
        cloud: CloudKind::SegmentedTree,
        ..InventoryParams::default()
    };
    let tree = inventory(&cut, &params, &NoProgress).expect("segmented tree");
    assert_eq!(tree.trees.len(), 1, "{:?}", tree.trees);
    let h = tree.trees[0].height_m.expect("height");
    assert!(
        (h - (hi.z - lo.z)).abs() < 0.3,
        "{h} m against the cloud's {} m",
        hi.z - lo.z
    );
    // The plot's tests alone find nothing in it.
    let strict = InventoryParams {
        cloud: CloudKind::Normalised,
        ..InventoryParams::default()
    };
    let mut lifted = cut.clone();
    lifted.offset.z -= lo.z; // bounds are in file coordinates
    let plain = inventory(&lifted, &strict, &NoProgress).expect("normalised");
    assert!(plain.trees.is_empty(), "{:?}", plain.trees);
}

/// The generator's tree standing within 1 m of an inventory row (`offset`: the cloud's).
fn truth_at<'a>(
    trees: &'a [TreeTruth],
    offset: glam::DVec3,
    row: &TreeRow,
) -> Option<&'a TreeTruth> {
    trees.iter().find(|t| {
        let b = t.base + offset;
        (b.x - row.x).hypot(b.y - row.y) < 1.0
    })
}

/// The height RMSE of the inventory of `stand` plot `seed` against the generator's tree tops
/// (metres), with the trees matched and the worst error (metres, tree id); the upper stems
/// hidden over up to `hidden_stem_m` when given.
fn stand_height_rmse(seed: u64, hidden_stem_m: Option<f64>) -> (f64, usize, (f64, u32)) {
    let plot = lidar_plot(
        &SynthParams {
            seed,
            hidden_stem_m,
            lidar_rgb: false,
            ..SynthParams::new(Preset::Stand)
        },
        &NoProgress,
    )
    .expect("synth");
    let inv = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress).expect("inv");
    let (mut sq, mut n) = (0.0, 0usize);
    let mut worst = (0.0f64, 0u32);
    for r in &inv.trees {
        let Some(t) = truth_at(&plot.trees, plot.cloud.offset, r) else {
            continue;
        };
        let e = r.height_m.unwrap_or(0.0) - t.height_m;
        sq += e * e;
        n += 1;
        if e.abs() > worst.0.abs() {
            worst = (e, r.tree_id);
        }
    }
    ((sq / n.max(1) as f64).sqrt(), n, worst)
}

/// Issue 40.1's gate on two `stand` plots with the hidden-stem knob at 3 m, each holding one
/// of the two faults measured on them (2026-11-29, docs/results/inventory.md): on seed 4 the
/// tallest tree's bridge landed on a branch beside its stem that the graph does not join to
/// the stem above, so a neighbour took the stem and crown (14.87 m measured 6.33, RMSE 2.35 m);
/// on seed 6 a neighbour's crown reaching in from one side made the stem below the gap look
/// clothed, so no bridge stood (14.50 m measured 4.89, RMSE 2.58 m). Now 0.04 and 0.18 m.
#[test]
fn hidden_stems_under_touching_crowns_keep_their_heights() {
    for seed in [4, 6] {
        let (rmse, n, worst) = stand_height_rmse(seed, Some(3.0));
        println!("seed {seed}: height RMSE {rmse:.2} m over {n} trees, worst {worst:?}");
        assert!(n >= 15, "seed {seed}: {n} trees matched");
        assert!(rmse <= 0.5, "seed {seed}: RMSE {rmse} m, worst {worst:?}");
    }
}

/// Issue 40.1's gate on the two plain `stand` plots that missed it (docs/results/inventory.md,
/// 2026-11-29): on seed 7 a neighbour took the top of a tree whose crown touches its own
/// across their leaves (11.82 m measured 9.70, RMSE 0.69 m), and on seed 10 a 15.58 m tree's
/// top was a piece 1.7 m above the rest of its crown that no path reached (measured 13.53,
/// RMSE 0.52 m). Leaf-to-leaf edges 4 times dearer and the pieces given to the nearest tree
/// took them to 0.34 and 0.17 m.
#[test]
fn touching_crowns_and_tops_apart_keep_their_heights() {
    for seed in [7, 10] {
        let (rmse, n, worst) = stand_height_rmse(seed, None);
        println!("seed {seed}: height RMSE {rmse:.2} m over {n} trees, worst {worst:?}");
        assert!(n >= 15, "seed {seed}: {n} trees matched");
        assert!(rmse <= 0.5, "seed {seed}: RMSE {rmse} m, worst {worst:?}");
    }
}

/// Issue 40.1 on the inventory plot with the hidden-stem knob (every tree's upper stem hidden
/// over 0.3–3 m from its crown base up): the crowns come as pieces apart from their stems, and
/// the bridges of the stems' columns give them back. Without bridges the heights are those of
/// the visible stems; with them, the height RMSE against the generator's must be at least
/// three times smaller, and most trees flagged `bridged` with the gap they crossed.
#[test]
fn hidden_upper_stems_are_bridged_and_flagged() {
    let plot = generate(&SynthParams {
        seed: 1,
        trees: Some(14),
        lidar_points: Some(1_000_000),
        hidden_stem_m: Some(3.0),
        ..SynthParams::new(Preset::Stand)
    });
    let rmse = |params: &InventoryParams| {
        let inv = inventory(&plot.cloud, params, &NoProgress).expect("inventory");
        let (mut sq, mut n, mut bridged) = (0.0, 0usize, 0usize);
        for r in &inv.trees {
            let Some(t) = truth_at(&plot.trees, plot.cloud.offset, r) else {
                continue;
            };
            sq += (r.height_m.unwrap_or(0.0) - t.height_m).powi(2);
            n += 1;
            if r.height_quality == Some(crowns::HeightQuality::Bridged) {
                assert!(
                    r.crown_gap_m.is_some_and(|g| (0.3..=5.0).contains(&g)),
                    "{r:?}"
                );
                bridged += 1;
            }
        }
        assert!(n >= 12, "{n} trees matched");
        ((sq / n as f64).sqrt(), bridged, n)
    };
    let no_bridges = InventoryParams {
        crowns: CrownParams {
            gap_max_m: 0.0,
            ..CrownParams::default()
        },
        ..InventoryParams::default()
    };
    let (before, none, _) = rmse(&no_bridges);
    let (after, bridged, n) = rmse(&InventoryParams::default());
    println!(
        "height RMSE {before:.2} m without bridges, {after:.2} m with; {bridged} of {n} bridged"
    );
    assert_eq!(none, 0);
    assert!(before > 3.0, "without bridges {before} m");
    assert!(
        after * 3.0 < before,
        "with bridges {after} m, without {before} m"
    );
    assert!(bridged * 2 > n, "{bridged} of {n} bridged");
}
