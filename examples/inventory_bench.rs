//! Times the inventory on generated plots (`sylva synth`'s stand preset, LiDAR only: the
//! 14-tree, 1 M-point plot of the forest tests, then a stand of POINTS points with as many
//! points per tree) and on TreeLS pine_plot.laz, and prints a table: points, stems, seconds
//! per phase.
//!
//! `cargo run --release --example inventory_bench [POINTS [CLOUD...]]` (default 10e6; 0 skips
//! the generated plots). Each CLOUD (e.g. the 9.2 M-point cloud of
//! ../shared/bench/make_plot10m.py) is timed too. CPU s: user + system seconds of all
//! threads, so on a shared machine CPU s / 2 is what two free cores would need at best.

use std::time::Instant;

use sylva::forest::{InventoryParams, compare_with_field, inventory};
use sylva::io::pointcloud::{PointCloud, read_point_cloud};
use sylva::io::tables::FieldTree;
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams, lidar_plot};

/// CPU seconds (user + system, all threads) this process has used so far, from
/// /proc/self/stat (Linux; USER_HZ = 100 ticks per second); `None` elsewhere.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = stat.rsplit_once(')')?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    // After the command name: state is field 3, utime 14 and stime 15 (proc(5)).
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

fn run(name: &str, cloud: &PointCloud, field: Option<&[FieldTree]>) {
    let cpu0 = cpu_seconds();
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next().map(str::to_string))
        .unwrap_or_else(|| "?".into());
    let t = Instant::now();
    let inv = match inventory(cloud, &InventoryParams::default(), &NoProgress) {
        Ok(inv) => inv,
        Err(e) => {
            println!("| {name} | {} | failed: {e} |", cloud.len());
            return;
        }
    };
    let total = t.elapsed().as_secs_f64();
    let cpu = match (cpu0, cpu_seconds()) {
        (Some(a), Some(b)) => format!("{:.1}", b - a),
        _ => "n/a".into(),
    };
    let s = inv.seconds;
    let g = inv.segment_seconds;
    let acc = field.map_or(String::new(), |f| {
        let c = compare_with_field(&inv.trees, f, 1.0);
        format!(
            " recall {:.3} precision {:.3} RMSE {:.2} cm",
            c.recall,
            c.precision,
            c.rmse_cm.unwrap_or(f64::NAN)
        )
    });
    println!(
        "| {name} | {} | {} | {:.2} | {:.2} ({:.1} k-NN, {:.1} coarse, {:.1} 2-means, {:.1} clean-up) | {:.2} | {:.2} | {:.2} | {:.2} | {cpu} | {load} |{acc}",
        cloud.len(),
        inv.trees.len(),
        s.ground,
        s.segment,
        g.knn,
        g.coarse,
        g.kmeans,
        g.cleanup,
        s.stems,
        s.dbh,
        s.crowns,
        total
    );
}

fn main() {
    let target: f64 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(10e6);
    println!(
        "threads: {}\n\n| cloud | points | stems | ground s | segment s | stems s | dbh s | trees s | total s | CPU s | load before |\n|---|---|---|---|---|---|---|---|---|---|---|",
        rayon::current_num_threads()
    );
    if target > 0.0 {
        synthetic(target);
    }
    for path in std::env::args().skip(2) {
        match read_point_cloud(std::path::Path::new(&path), &NoProgress) {
            Ok(c) => run(&path, &c, None),
            Err(e) => println!("skipping {path}: {e}"),
        }
    }
    let dir = std::env::var_os("SYLVA_REAL_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from("../shared/data/real"));
    let path = dir.join("TreeLS_extdata/pine_plot.laz");
    match read_point_cloud(&path, &NoProgress) {
        Ok(c) => run("pine_plot.laz", &c, None),
        Err(e) => println!("skipping pine_plot.laz: {e}"),
    }
}

/// The forest tests' plot (14 trees of the stand preset, 1 M points, no colour), then a
/// stand of `target` points with as many trees as keep its points per tree (at most 500).
fn synthetic(target: f64) {
    let small = SynthParams {
        seed: 1,
        trees: Some(14),
        lidar_points: Some(1_000_000),
        stem_dbh_cm: vec![8.0, 60.0],
        lidar_rgb: false,
        ..SynthParams::new(Preset::Stand)
    };
    let trees = ((14.0 * target / 1e6).round() as usize).clamp(1, 500);
    let large = SynthParams {
        trees: Some(trees),
        lidar_points: Some(target.round() as usize),
        ..small.clone()
    };
    for (name, p) in [
        ("synthetic stand, 14 trees".to_string(), small),
        (format!("synthetic stand, {trees} trees"), large),
    ] {
        let t = Instant::now();
        let plot = match lidar_plot(&p, &NoProgress) {
            Ok(plot) => plot,
            Err(e) => {
                println!("| {name} | generation failed: {e} |");
                continue;
            }
        };
        eprintln!("{name}: generated in {:.1} s", t.elapsed().as_secs_f64());
        let field: Vec<FieldTree> = plot
            .trees
            .iter()
            .map(|t| FieldTree {
                tree_id: None,
                x: plot.cloud.offset.x + t.base.x,
                y: plot.cloud.offset.y + t.base.y,
                dbh_cm: t.dbh_m * 100.0,
            })
            .collect();
        run(&name, &plot.cloud, Some(&field));
    }
}
