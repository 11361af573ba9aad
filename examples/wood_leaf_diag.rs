//! Diagnoses the LiDAR inventory on generated stands: where the wood/leaf labels go wrong
//! (by true class, by stem or branch, by height) and the ground error at the stems.
//!
//! `cargo run --release --example wood_leaf_diag -- DIR...` with DIR a `sylva synth` output
//! folder (lidar.laz, labels.bin, truth.json). `DIAG_PARAMS` may hold inventory parameters
//! as JSON (e.g. `{"segment":{"grow_linearity":0.45}}`), the defaults otherwise.

use sylva::forest::{InventoryParams, TRUNK, inventory};
use sylva::io::pointcloud::read_point_cloud;
use sylva::progress::NoProgress;

fn main() {
    let params: InventoryParams = match std::env::var("DIAG_PARAMS") {
        Ok(json) => match serde_json::from_str(&json) {
            Ok(p) => p,
            Err(e) => {
                eprintln!("DIAG_PARAMS: {e}");
                std::process::exit(2);
            }
        },
        Err(_) => InventoryParams::default(),
    };
    for dir in std::env::args().skip(1) {
        let dir = std::path::PathBuf::from(dir);
        let Ok(cloud) = read_point_cloud(&dir.join("lidar.laz"), &NoProgress) else {
            println!("{}: no cloud", dir.display());
            continue;
        };
        let labels = std::fs::read(dir.join("labels.bin")).unwrap_or_default();
        let truth: serde_json::Value = std::fs::read(dir.join("truth.json"))
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default();
        let t = std::time::Instant::now();
        let Ok(inv) = inventory(&cloud, &params, &NoProgress) else {
            println!("{}: inventory failed", dir.display());
            continue;
        };
        println!(
            "{}: {} points, {:.1} s ({:?})",
            dir.display(),
            cloud.len(),
            t.elapsed().as_secs_f64(),
            inv.seconds
        );
        // Trees: base, axis, radius.
        let trees: Vec<(glam::DVec3, glam::DVec3, f64)> = truth["trees"]
            .as_array()
            .map(|a| {
                a.iter()
                    .map(|t| {
                        let b = glam::DVec3::new(
                            t["x"].as_f64().unwrap_or(0.0),
                            t["y"].as_f64().unwrap_or(0.0),
                            t["z"].as_f64().unwrap_or(0.0),
                        ) - cloud.offset;
                        let ax = &t["axis"];
                        let a = glam::DVec3::new(
                            ax[0].as_f64().unwrap_or(0.0),
                            ax[1].as_f64().unwrap_or(0.0),
                            ax[2].as_f64().unwrap_or(1.0),
                        );
                        (b, a, t["dbh_cm"].as_f64().unwrap_or(0.0) / 200.0)
                    })
                    .collect()
            })
            .unwrap_or_default();
        // Category of a true wood point: stem (near an axis) or branch.
        let near_stem = |p: glam::DVec3| {
            trees.iter().any(|(b, a, r)| {
                let d = p - *b;
                let s = d.dot(*a);
                let off = (d - *a * s).length();
                off < r * 1.4 + 0.04 && s > -0.5 && s < 25.0
            })
        };
        // rows: truth class -> (n, predicted trunk, predicted ground)
        let names = [
            "ground",
            "wood-stem<2m",
            "wood-stem2-6m",
            "wood-stem>6m",
            "wood-branch",
            "leaf",
            "other",
        ];
        let mut tab = [[0usize; 3]; 7];
        let heights = inv.dtm.heights_above(&cloud.positions);
        for (i, &l) in labels.iter().enumerate() {
            let p = cloud.positions[i].as_dvec3();
            let cat = match l {
                0 => 0,
                1 => {
                    if near_stem(p) {
                        let h = heights[i];
                        if h < 2.0 {
                            1
                        } else if h < 6.0 {
                            2
                        } else {
                            3
                        }
                    } else {
                        4
                    }
                }
                2 => 5,
                _ => 6,
            };
            tab[cat][0] += 1;
            if inv.labels[i] == TRUNK {
                tab[cat][1] += 1;
            }
            if inv.is_ground[i] {
                tab[cat][2] += 1;
            }
        }
        for (n, r) in names.iter().zip(tab) {
            println!(
                "  {n:14} n {:8}  trunk {:6.3}  ground {:6.3}",
                r[0],
                r[1] as f64 / r[0].max(1) as f64,
                r[2] as f64 / r[0].max(1) as f64
            );
        }
        let wood_n: usize = tab[1..5].iter().map(|r| r[0] - r[2]).sum();
        let (tp, fp) = (tab[1..5].iter().map(|r| r[1]).sum::<usize>(), tab[5][1]);
        println!(
            "  trunk recall {:.3} precision {:.3}",
            tp as f64 / wood_n.max(1) as f64,
            tp as f64 / (tp + fp).max(1) as f64
        );
        // Ground at the stems.
        let mut worst = 0.0f64;
        for (b, _, r) in &trees {
            let row = inv.trees.iter().min_by(|x, y| {
                let d = |t: &sylva::forest::TreeRow| {
                    (t.x - cloud.offset.x - b.x).hypot(t.y - cloud.offset.y - b.y)
                };
                d(x).total_cmp(&d(y))
            });
            if let Some(row) = row {
                let dz = row.ground_z - cloud.offset.z - b.z;
                let dtm = inv.dtm.height_at(b.x as f32, b.y as f32) as f64 - b.z;
                worst = worst.max(dz.abs());
                print!(
                    " [r{:.0} dz {:+.1} dtm {:+.1}]",
                    r * 100.0,
                    dz * 100.0,
                    dtm * 100.0
                );
            }
        }
        println!("\n  worst ground error {:.1} cm", worst * 100.0);
        // DIAG_DUMP=1: per point x, y, z, trunk probability (f32) and truth label, predicted
        // label, ground flag (u8) to DIR/diag_dump.bin for analysis outside (16 bytes/point).
        if std::env::var_os("DIAG_DUMP").is_some() {
            let mut buf = Vec::with_capacity(cloud.len() * 16);
            for (i, p) in cloud.positions.iter().enumerate() {
                for v in [p.x, p.y, p.z, inv.trunk_probability[i]] {
                    buf.extend_from_slice(&v.to_le_bytes());
                }
            }
            for (i, _) in cloud.positions.iter().enumerate() {
                buf.extend([
                    labels.get(i).copied().unwrap_or(255),
                    inv.labels[i],
                    u8::from(inv.is_ground[i]),
                ]);
            }
            if let Err(e) = std::fs::write(dir.join("diag_dump.bin"), buf) {
                println!("  dump: {e}");
            }
        }
        if std::env::var_os("DIAG_FEATURES").is_none() {
            continue;
        }
        let include: Vec<bool> = inv.is_ground.iter().map(|g| !g).collect();
        let Ok(w) = sylva::forest::segment_wood_leaf(
            &cloud.positions,
            None,
            Some(&include),
            &params.segment,
            &NoProgress,
        ) else {
            continue;
        };
        // Histograms (10 bins) of features per class: stem, branch, leaf.
        let mut h = [[[0usize; 10]; 9]; 3];
        for (i, &l) in labels.iter().enumerate() {
            if !include[i] || !(l == 1 || l == 2) {
                continue;
            }
            let c = if l == 2 {
                2
            } else if near_stem(cloud.positions[i].as_dvec3()) {
                0
            } else {
                1
            };
            let f = w.features[i];
            let g = w.coarse.get(i).copied().unwrap_or_default();
            let v = [
                f.linearity,
                g.eigen.linearity,
                g.eigen.planarity,
                g.eigen.sphericity,
                g.verticality,
                g.spread_m * 10.0,
                g.voxels as f32 / 200.0,
                g.extent_m * 4.0,
                w.trunk_probability[i],
            ];
            for (k, x) in v.iter().enumerate() {
                h[c][k][((x * 10.0) as usize).min(9)] += 1;
            }
        }
        for (k, name) in [
            "fineL",
            "coarseL",
            "coarseP",
            "coarseS",
            "vert",
            "spread/10",
            "vox/200",
            "ext/25",
            "P",
        ]
        .iter()
        .enumerate()
        {
            for (c, cn) in ["stem", "branch", "leaf"].iter().enumerate() {
                let pct: Vec<String> = h[c][k].iter().map(|n| format!("{:7}", n)).collect();
                println!("  {name:8} {cn:7} {}", pct.join(" "));
            }
        }
    }
}
