//! Benchmark of the geometry core on a synthetic forest plot (ground + stems + crowns),
//! printed as a table to compare with Open3D's figures in shared/bench/README.md.
//!
//! `cargo run --release --example geom_bench -- [MILLIONS ...]` (default: 1 9).

use std::time::Instant;

use glam::Vec3;
use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};
use rayon::prelude::*;
use sylva::geom::*;
use sylva::progress::NoProgress;

/// A plot of about `n` points: 45% ground, 25% stems, 30% crowns, one tree per 64 m².
/// Density grows with n like a tiled plot: the side grows as sqrt(n).
fn plot(n: usize, seed: u64) -> (Vec<Vec3>, f32) {
    let side = (n as f32 / 1.0e6).sqrt() * 30.0;
    let trees = ((side * side) / 64.0).max(1.0) as usize;
    let ground = n * 45 / 100;
    let per_stem = n * 25 / 100 / trees;
    let per_crown = n * 30 / 100 / trees;
    let gz = |x: f32, y: f32| 0.5 * (x / 7.0).sin() * (y / 9.0).cos();
    let chunks = 64;
    let mut pts: Vec<Vec3> = (0..chunks)
        .into_par_iter()
        .flat_map_iter(|c| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed * 1000 + c as u64);
            let mut out = Vec::with_capacity(ground / chunks + 1);
            for _ in 0..ground / chunks {
                let (x, y) = (rng.random_range(0.0..side), rng.random_range(0.0..side));
                out.push(Vec3::new(x, y, gz(x, y) + rng.random_range(-0.01..0.01)));
            }
            out
        })
        .collect();
    let tree_pts: Vec<Vec3> = (0..trees)
        .into_par_iter()
        .flat_map_iter(|t| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed * 7_000_000 + t as u64);
            let (cx, cy) = (rng.random_range(0.0..side), rng.random_range(0.0..side));
            let r = rng.random_range(0.08..0.35f32);
            let h = rng.random_range(8.0..20.0f32);
            let base = gz(cx, cy);
            let mut out = Vec::with_capacity(per_stem + per_crown);
            for _ in 0..per_stem {
                let a = rng.random_range(0.0..std::f32::consts::TAU);
                let z = rng.random_range(0.0..h * 0.7);
                let rr = r * (1.0 - 0.5 * z / h) + rng.random_range(-0.003..0.003);
                out.push(Vec3::new(cx + rr * a.cos(), cy + rr * a.sin(), base + z));
            }
            let crown = Vec3::new(cx, cy, base + h * 0.8);
            for _ in 0..per_crown {
                let d = Vec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                out.push(crown + d * Vec3::new(2.5, 2.5, 3.0));
            }
            out
        })
        .collect();
    pts.extend(tree_pts);
    (pts, side)
}

fn row(op: &str, n_in: usize, n_out: usize, secs: f64) {
    println!("| {op:<38} | {n_in:>10} | {n_out:>10} | {secs:>8.3} |");
}

fn main() -> Result<(), GeomError> {
    let sizes: Vec<f64> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let sizes = if sizes.is_empty() {
        vec![1.0, 9.0]
    } else {
        sizes
    };
    println!("rayon threads: {}", rayon::current_num_threads());
    for m in sizes {
        let n = (m * 1.0e6) as usize;
        let t = Instant::now();
        let (cloud, side) = plot(n, 42);
        println!(
            "\nsynthetic plot {:.0} m × {:.0} m, {} points (generated in {:.2} s)\n",
            side,
            side,
            cloud.len(),
            t.elapsed().as_secs_f64()
        );
        println!(
            "| {:<38} | {:>10} | {:>10} | {:>8} |",
            "operation", "points in", "points out", "seconds"
        );
        println!("|{:-<40}|{:-<12}|{:-<12}|{:-<10}|", "", "", "", "");

        let t = Instant::now();
        let vox = voxel_downsample(&cloud, None, &VoxelParams::default(), &NoProgress)?;
        row(
            "voxel_downsample(0.02)",
            cloud.len(),
            vox.positions.len(),
            t.elapsed().as_secs_f64(),
        );
        let pts = vox.positions;

        let t = Instant::now();
        let index = PointIndex::new(&pts)?;
        row(
            "k-d tree build",
            pts.len(),
            index.len(),
            t.elapsed().as_secs_f64(),
        );

        let t = Instant::now();
        let out = statistical_outlier_filter(&pts, &OutlierParams::default(), &NoProgress)?;
        row(
            "statistical_outlier_filter(16, 2.5)",
            pts.len(),
            out.kept,
            t.elapsed().as_secs_f64(),
        );
        let anchors: Vec<Vec3> = pts
            .iter()
            .zip(&out.keep)
            .filter(|(_, k)| **k)
            .map(|(p, _)| *p)
            .collect();

        let t = Instant::now();
        let up = NormalParams {
            k: 20,
            orientation: NormalOrientation::Up(Vec3::Z),
        };
        let normals = estimate_normals(&anchors, &up, &NoProgress)?;
        row(
            "estimate_normals(k 20, up)",
            anchors.len(),
            normals.normals.len(),
            t.elapsed().as_secs_f64(),
        );

        let t = Instant::now();
        let prop = estimate_normals(&anchors, &NormalParams::default(), &NoProgress)?;
        row(
            "estimate_normals(k 20, propagated)",
            anchors.len(),
            prop.normals.len(),
            t.elapsed().as_secs_f64(),
        );

        let t = Instant::now();
        let feats = eigen_features(&anchors, 20, &NoProgress)?;
        row(
            "eigen_features(k 20)",
            anchors.len(),
            feats.len(),
            t.elapsed().as_secs_f64(),
        );

        // ICP on one 10 × 10 m tile: target = the tile with its normals, source = every
        // 4th point of the tile moved by a small similarity.
        let tile: Vec<usize> = (0..anchors.len())
            .filter(|&i| anchors[i].x < 10.0 && anchors[i].y < 10.0)
            .collect();
        let target: Vec<Vec3> = tile.iter().map(|&i| anchors[i]).collect();
        let tn: Vec<Vec3> = tile.iter().map(|&i| normals.normals[i]).collect();
        let truth = Similarity {
            scale: 1.0,
            rotation: glam::DMat3::from_rotation_z(0.5f64.to_radians()),
            translation: glam::DVec3::new(0.05, -0.03, 0.02),
        };
        let inv = truth.inverse();
        let source: Vec<Vec3> = target
            .iter()
            .step_by(4)
            .map(|p| inv.apply_f32(*p))
            .collect();
        for (name, method) in [
            ("ICP point-to-plane, 10 m tile", IcpMethod::PointToPlane),
            ("ICP point-to-point, 10 m tile", IcpMethod::PointToPoint),
        ] {
            let params = IcpParams {
                method,
                estimate_scale: false,
                start_distance: 0.2,
                min_distance: 0.02,
                ..IcpParams::default()
            };
            let t = Instant::now();
            let tindex = PointIndex::new(&target)?;
            let res = icp_with_index(
                &source,
                &target,
                &tindex,
                Some(&tn),
                &Similarity::IDENTITY,
                &params,
                &NoProgress,
            )?;
            let secs = t.elapsed().as_secs_f64();
            row(name, target.len(), source.len(), secs);
            println!(
                "|   {} its, fitness {:.3}, rmse {:.4} m, rot err {:.4}°, t err {:.2} mm",
                res.iterations,
                res.fitness,
                res.inlier_rmse,
                (res.rotation * truth.rotation.transpose())
                    .to_cols_array()
                    .iter()
                    .zip(glam::DMat3::IDENTITY.to_cols_array())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max)
                    .to_degrees(),
                (res.translation - truth.translation).length() * 1000.0
            );
        }
    }
    Ok(())
}
