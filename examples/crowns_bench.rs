//! Tree heights and crowns against the generator's truth on `stand` seeds, for the tree
//! segmentation's parameters (`forest::crowns`): height RMSE, crown-diameter error (mean and
//! worst), the share of the generator's tree points given to their own tree (its per-point
//! owner, `LidarPlot::tree_of_point`) and the segmentation's seconds, one row per seed and
//! setting.
//!
//! `cargo run --profile test --example crowns_bench -- [SEEDS] [key=value,key=value ...]`
//! (SEEDS `5` for 1-5 or a range `6-10`; default 1-5 with the default parameters, then each
//! setting given as `CrownParams` fields over the defaults, e.g. `edge_power=1,max_edge_m=0.5`).
//! With `CROWNS_BENCH_TREES` set, every tree's figures go to stderr (with who took its top and
//! how many of its points no path reached); `CROWNS_BENCH_HIDDEN_STEM_M` and `CROWNS_BENCH_INTERLOCK` turn on the generator's
//! hidden-stem and interlocking-crown knobs (`SynthParams::hidden_stem_m`, `crown_interlock`).

use std::time::Instant;

use sylva::forest::{CrownParams, InventoryParams, inventory, segment_trees_labelled};
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams, lidar_plot};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    // SEEDS: `5` (1 to 5) or `6-10`.
    let range = args.first().map_or("5", String::as_str);
    let (first, last) = match range.split_once('-') {
        Some((a, b)) => (a.parse()?, b.parse()?),
        None => (1u64, range.parse()?),
    };
    let mut settings = vec![CrownParams::default()];
    for spec in args.iter().skip(1) {
        // `key=value,key=value` over the defaults, e.g. `axis_reach_m=0,gap_max_m=0`.
        let mut obj = serde_json::Map::new();
        for kv in spec.split(',') {
            let (k, v) = kv
                .split_once('=')
                .ok_or("settings are key=value,key=value")?;
            obj.insert(k.to_string(), serde_json::from_str(v)?);
        }
        settings.push(serde_json::from_value(serde_json::Value::Object(obj))?);
    }
    println!(
        "| seed | setting | height RMSE m | crown error mean / worst % | tree points given to \
         their tree % | trees | seconds |"
    );
    println!("|---|---|---|---|---|---|---|");
    for seed in first..=last {
        let mut p = SynthParams::new(Preset::Stand);
        p.seed = seed;
        let knob = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<f64>().ok());
        p.hidden_stem_m = knob("CROWNS_BENCH_HIDDEN_STEM_M");
        p.crown_interlock = knob("CROWNS_BENCH_INTERLOCK");
        let plot = lidar_plot(&p, &NoProgress)?;
        let inv = inventory(&plot.cloud, &InventoryParams::default(), &NoProgress)?;
        let pts = &plot.cloud.positions;
        let heights = inv.dtm.heights_above(pts);
        for (k, s) in settings.iter().enumerate() {
            let name = if k == 0 { "default" } else { args[k].as_str() };
            let t = Instant::now();
            let seg = segment_trees_labelled(
                pts,
                &heights,
                &inv.is_ground,
                Some(&inv.labels),
                &inv.stems,
                s,
                &NoProgress,
            )?;
            let secs = t.elapsed().as_secs_f64();
            let (mut sq, mut rel, mut worst, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
            // The generator's tree under each stem (its id), and the points' agreement with
            // the generator's owner of each point.
            let truth_of: Vec<Option<&sylva::synth::trees::TreeTruth>> = inv
                .stems
                .iter()
                .map(|stem| {
                    plot.trees.iter().find(|t| {
                        let b = stem.base.as_dvec3();
                        (t.base.x - b.x).hypot(t.base.y - b.y) < 1.0
                    })
                })
                .collect();
            let (mut agree, mut owned) = (0usize, 0usize);
            for (&seg_t, &true_id) in seg.tree_of_point.iter().zip(&plot.tree_of_point) {
                if true_id == 0 {
                    continue;
                }
                owned += 1;
                let id = truth_of
                    .get(seg_t as usize)
                    .copied()
                    .flatten()
                    .map_or(0, |t| t.id);
                agree += usize::from(id == usize::from(true_id));
            }
            for (k, (stem, tree)) in inv.stems.iter().zip(&seg.trees).enumerate() {
                let Some(truth) = truth_of[k] else { continue };
                if std::env::var_os("CROWNS_BENCH_TREES").is_some() {
                    // The tree's points by the generator: how many the segmentation gave it,
                    // and who got its highest point.
                    let mine = |i: usize| usize::from(plot.tree_of_point[i]) == truth.id;
                    let (mut total, mut kept, mut top, mut top_i) = (0usize, 0usize, f32::MIN, 0);
                    for (i, p) in pts.iter().enumerate() {
                        if mine(i) {
                            total += 1;
                            kept += usize::from(seg.tree_of_point[i] as usize == k);
                            if p.z > top {
                                (top, top_i) = (p.z, i);
                            }
                        }
                    }
                    let taken = seg.tree_of_point[top_i];
                    let lost: Vec<f32> = (0..pts.len())
                        .filter(|&i| mine(i) && seg.tree_of_point[i] == u32::MAX)
                        .map(|i| pts[i].z - stem.base.z)
                        .collect();
                    let given: usize = (0..pts.len())
                        .filter(|&i| seg.tree_of_point[i] as usize == k && !mine(i))
                        .count();
                    // Horizontal distance of the top from a stem's axis, metres.
                    let off = |s: &sylva::forest::Stem| {
                        let p = pts[top_i];
                        let a = if s.axis.z > 0.05 {
                            s.axis
                        } else {
                            glam::Vec3::Z
                        };
                        (p - (s.base + a * ((p.z - s.base.z) / a.z)))
                            .truncate()
                            .length()
                    };
                    let taker = inv.stems.get(taken as usize);
                    eprintln!(
                        "seed {seed} stem {}: tree {} has {total} points, {kept} kept, {given} \
                         of others taken; its top ({:.2} m up, {:.2} m off its axis) went to \
                         stem {} ({:.2} m off its axis)",
                        stem.id,
                        truth.id,
                        top - stem.base.z,
                        off(stem),
                        taker.map_or(-1, |s| s.id as i64),
                        taker.map_or(f32::NAN, off),
                    );
                    if !lost.is_empty() {
                        let (lo, hi) = lost
                            .iter()
                            .fold((f32::MAX, f32::MIN), |(a, b), &z| (a.min(z), b.max(z)));
                        eprintln!(
                            "  {} of its points reached by no path, {lo:.2}-{hi:.2} m up",
                            lost.len()
                        );
                    }
                }
                let crown_truth = 2.0 * (truth.crown_area_m2 / std::f64::consts::PI).sqrt();
                sq += (tree.height_m - truth.height_m).powi(2);
                if std::env::var_os("CROWNS_BENCH_TREES").is_some() {
                    eprintln!(
                        "seed {seed} {name} stem {}: gap {:?} height {:.2} (truth {:.2}), crown {:.2} (truth \
                         {crown_truth:.2}), {} points",
                        stem.id,
                        tree.gap_m,
                        tree.height_m,
                        truth.height_m,
                        tree.crown_diameter_m,
                        tree.points
                    );
                }
                let e = tree.crown_diameter_m / crown_truth - 1.0;
                rel += e.abs();
                worst = worst.max(e.abs());
                n += 1;
            }
            println!(
                "| {seed} | {name} | {:.2} | {:.1} / {:.1} | {:.1} | {n} | {secs:.2} |",
                (sq / n.max(1) as f64).sqrt(),
                100.0 * rel / n.max(1) as f64,
                100.0 * worst,
                100.0 * agree as f64 / owned.max(1) as f64
            );
        }
    }
    Ok(())
}
