//! Tree heights and crowns against the generator's truth on `stand` seeds, for the tree
//! segmentation's parameters (`forest::crowns`): height RMSE, crown-diameter error (mean and
//! worst) and the segmentation's seconds, one row per seed and setting.
//!
//! `cargo run --profile test --example crowns_bench -- [SEEDS] [key=value,key=value ...]`
//! (SEEDS `5` for 1-5 or a range `6-10`; default 1-5 with the default parameters, then each
//! setting given as `CrownParams` fields over the defaults, e.g. `edge_power=1,max_edge_m=0.5`). With `CROWNS_BENCH_TREES` set, every tree's figures go to stderr;
//! `CROWNS_BENCH_HIDDEN_STEM_M` and `CROWNS_BENCH_INTERLOCK` turn on the generator's
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
    println!("| seed | setting | height RMSE m | crown error mean / worst % | trees | seconds |");
    println!("|---|---|---|---|---|---|");
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
            for (stem, tree) in inv.stems.iter().zip(&seg.trees) {
                let truth = plot.trees.iter().find(|t| {
                    let b = stem.base.as_dvec3();
                    (t.base.x - b.x).hypot(t.base.y - b.y) < 1.0
                });
                let Some(truth) = truth else { continue };
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
                "| {seed} | {name} | {:.2} | {:.1} / {:.1} | {n} | {secs:.2} |",
                (sq / n.max(1) as f64).sqrt(),
                100.0 * rel / n.max(1) as f64,
                100.0 * worst
            );
        }
    }
    Ok(())
}
