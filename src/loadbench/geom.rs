//! `sylva bench geom`: the point-cloud core on a real file, phase by phase, with the time and
//! the peak resident memory after each phase, in the order of Open3D's benchmark
//! (`benches/open3d_compare.sh` runs both tools on the same files and prints the ratios):
//!
//! 1. read the LAS/LAZ file (`io::read_point_cloud`, parallel LAZ decompression);
//! 2. voxel homogenisation, edge 0.02 m (`voxel_downsample`, as `voxel_down_sample(0.02)`);
//! 3. statistical outlier filter, k = 16, alpha = 2.5, on the voxel result (as
//!    `remove_statistical_outlier(16, 2.5)`; index build included);
//! 4. normals from the 20 nearest neighbours of the kept points, no sign propagation (as
//!    `estimate_normals(KDTreeSearchParamKNN(20))`, which does not orient either; index build
//!    included);
//! 5. point-to-plane ICP on one square tile (`--icp-tile-m`, default [`ICP_TILE_M`]; the
//!    comparison script uses 100 m on its 1 M-point input, i.e. the whole 10 × 94 m strip, and
//!    the 10 m default on the 9.2 M-point plot), see [`icp_truth`]: target
//!    = the tile's raw points with KNN-20 normals (not timed), source = every 4th of them
//!    moved by the inverse of the known motion; fixed 0.2 m correspondence distance as
//!    Open3D's `registration_icp(source, target, 0.2, identity, PointToPlane)`; at most 50
//!    iterations on both sides, Open3D stopping when fitness and RMSE change by less than
//!    1e-6, sylva when the RMSE changes by less than 1e-6 of itself (5 and 6 iterations on
//!    the benchmark tile). The search structure's build is timed on both sides (Open3D's k-d
//!    tree, sylva's column grid). With 65,536 source points or more a second row runs
//!    sylva with `coarse_start` off (every point in every iteration, as Open3D).
//!
//! Peak memory is Linux `VmHWM` (the process's high-water mark, MiB), read after each phase:
//! it never decreases, so the figure after a phase is the peak of everything up to it. The raw
//! cloud is dropped after voxelisation (the ICP tile is cut from it first), as a pipeline that
//! keeps only the homogenised cloud would.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use glam::{DMat3, DVec3, Vec3};
use serde::Serialize;

use super::peak_rss_mib;
use sylva::geom::{
    IcpMethod, IcpParams, NormalOrientation, NormalParams, OutlierParams, RobustKernel, Similarity,
    estimate_normals, icp, statistical_outlier_filter, voxel_downsample,
};
use sylva::progress::NoProgress;

/// Default edge of the ICP tile, metres: the square whose corner is the cloud's minimum x, y
/// rounded down to whole metres (all heights kept). At 10 m, on the tiled benchmark plot, this
/// is the first copy of `pine_plot.laz` (82,168 points).
pub const ICP_TILE_M: f64 = 10.0;

/// Flags of `sylva bench geom`.
#[derive(Debug, Clone, Args)]
pub struct GeomBenchArgs {
    /// geom: the LAS/LAZ (or any supported) point cloud to measure on.
    #[arg(long, env = "SYLVA_BENCH_INPUT")]
    pub input: Option<PathBuf>,
    /// geom: phases to run, comma-separated, in order: read, voxel, outlier, normals, icp.
    /// `read,voxel,outlier` is the memory benchmark.
    #[arg(
        long,
        env = "SYLVA_BENCH_PHASES",
        default_value = "read,voxel,outlier,normals,icp"
    )]
    pub phases: String,
    /// geom: edge of the square ICP tile, metres, from the cloud's minimum corner (default
    /// [`ICP_TILE_M`]; `benches/open3d_compare.sh` uses 100 on its 1 M-point input, the whole
    /// input).
    #[arg(long, env = "SYLVA_BENCH_ICP_TILE_M", default_value_t = ICP_TILE_M)]
    pub icp_tile_m: f64,
    /// geom: also write the rows as JSON to this file (for `benches/open3d_compare.sh`).
    #[arg(long, env = "SYLVA_BENCH_JSON")]
    pub json: Option<PathBuf>,
}

/// One row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct GeomRow {
    /// Phase name (read, voxel, outlier, normals, icp).
    pub phase: String,
    /// Points in.
    pub points_in: usize,
    /// Points out (kept, voxels, normals; source points for ICP).
    pub points_out: usize,
    /// Wall-clock seconds of the phase.
    pub seconds: f64,
    /// CPU seconds (user + system, all threads) of the phase: less sensitive than wall time
    /// to other processes on the cores.
    pub cpu_seconds: f64,
    /// Peak resident memory of the process up to the end of this phase, MiB (`VmHWM`).
    pub peak_rss_mib: f64,
    /// Free-form detail (ICP convergence and error).
    pub note: String,
}

/// The ICP benchmark's known motion, target = T(source): a 0.5° rotation about the vertical
/// through the tile centre `c` and a (5, -3, 2) cm shift. Point-to-plane ICP from identity must
/// recover it; the largest displacement on the tile is about 12 cm.
pub fn icp_truth(c: DVec3) -> Similarity {
    let rotation = DMat3::from_rotation_z(0.5f64.to_radians());
    Similarity {
        scale: 1.0,
        rotation,
        translation: c - rotation * c + DVec3::new(0.05, -0.03, 0.02),
    }
}

/// CPU time of this process so far (user + system, all threads), seconds.
pub fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes one plain-old-data struct that we own.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } != 0 {
        return 0.0;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

/// Starts timing a phase: wall clock and CPU time.
struct Clock {
    wall: Instant,
    cpu: f64,
}

impl Clock {
    fn start() -> Self {
        Clock {
            wall: Instant::now(),
            cpu: cpu_seconds(),
        }
    }

    /// (wall seconds, CPU seconds) since the start.
    fn read(&self) -> (f64, f64) {
        (self.wall.elapsed().as_secs_f64(), cpu_seconds() - self.cpu)
    }
}

/// Runs the benchmark and prints the table (blocking; call from a blocking thread).
pub fn run(a: &GeomBenchArgs) -> anyhow::Result<Vec<GeomRow>> {
    let input = a
        .input
        .as_ref()
        .context("sylva bench geom needs --input FILE (a LAS/LAZ point cloud)")?;
    let phases: Vec<&str> = a.phases.split(',').map(str::trim).collect();
    if !(a.icp_tile_m.is_finite() && a.icp_tile_m > 0.0) {
        anyhow::bail!(
            "--icp-tile-m must be a positive number of metres, not {}",
            a.icp_tile_m
        );
    }
    for p in &phases {
        if !["read", "voxel", "outlier", "normals", "icp"].contains(p) {
            anyhow::bail!("unknown phase {p:?}; phases: read, voxel, outlier, normals, icp");
        }
    }
    let wants = |p: &str| phases.contains(&p);
    println!(
        "sylva bench geom: {} ({} rayon threads)",
        input.display(),
        rayon::current_num_threads()
    );
    let mut rows = Vec::new();
    let push = |rows: &mut Vec<GeomRow>, row: GeomRow| {
        println!(
            "| {:<28} | {:>10} | {:>10} | {:>8.3} | {:>8.3} | {:>9.0} | {}",
            row.phase,
            row.points_in,
            row.points_out,
            row.seconds,
            row.cpu_seconds,
            row.peak_rss_mib,
            row.note
        );
        rows.push(row);
    };
    println!(
        "| {:<28} | {:>10} | {:>10} | {:>8} | {:>8} | {:>9} | note",
        "phase", "points in", "points out", "seconds", "CPU s", "peak MiB"
    );
    println!(
        "|{:-<30}|{:-<12}|{:-<12}|{:-<10}|{:-<10}|{:-<11}|------",
        "", "", "", "", "", ""
    );

    let t = Clock::start();
    let cloud = sylva::io::pointcloud::read_point_cloud(input, &NoProgress)
        .with_context(|| format!("reading {}", input.display()))?;
    let (secs, cpu) = t.read();
    let file_bytes = std::fs::metadata(input).map(|m| m.len()).unwrap_or(0);
    push(
        &mut rows,
        GeomRow {
            phase: "read".into(),
            points_in: cloud.len(),
            points_out: cloud.len(),
            seconds: secs,
            cpu_seconds: cpu,
            peak_rss_mib: peak_rss_mib(),
            note: format!("{:?}, {:.1} MB", cloud.format, file_bytes as f64 / 1e6),
        },
    );

    // The ICP tile, in local coordinates, cut before the raw cloud is dropped.
    let tile = if wants("icp") {
        let lo = cloud
            .bounds()
            .map(|(lo, _)| lo)
            .context("the input cloud is empty")?;
        let corner = DVec3::new(lo.x.floor(), lo.y.floor(), 0.0) - cloud.offset;
        let (x0, y0, edge) = (corner.x, corner.y, a.icp_tile_m);
        let tile: Vec<Vec3> = cloud
            .positions
            .iter()
            .filter(|p| {
                let (x, y) = (f64::from(p.x), f64::from(p.y));
                x >= x0 && x < x0 + edge && y >= y0 && y < y0 + edge
            })
            .copied()
            .collect();
        Some((tile, corner))
    } else {
        None
    };

    if !wants("voxel") {
        icp_phase(tile, a.icp_tile_m, &mut rows, &push)?;
        return finish(a, rows);
    }
    let n_raw = cloud.len();
    let t = Clock::start();
    // The anchors stage's voxel (docs/method.md Stage 2.1).
    let voxel_m = sylva::pipeline::params::AnchorParams::default().voxel_size_m as f32;
    let vox = voxel_downsample(&cloud.positions, None, voxel_m, &NoProgress)?;
    let (secs, cpu) = t.read();
    drop(cloud);
    push(
        &mut rows,
        GeomRow {
            phase: "voxel_down_sample(0.02)".into(),
            points_in: n_raw,
            points_out: vox.positions.len(),
            seconds: secs,
            cpu_seconds: cpu,
            peak_rss_mib: peak_rss_mib(),
            note: String::new(),
        },
    );
    let pts = vox.positions;

    if !wants("outlier") {
        icp_phase(tile, a.icp_tile_m, &mut rows, &push)?;
        return finish(a, rows);
    }
    let t = Clock::start();
    let out = statistical_outlier_filter(&pts, &OutlierParams::default(), &NoProgress)?;
    let kept: Vec<Vec3> = pts
        .iter()
        .zip(&out.keep)
        .filter(|(_, k)| **k)
        .map(|(p, _)| *p)
        .collect();
    let (secs, cpu) = t.read();
    drop(pts);
    push(
        &mut rows,
        GeomRow {
            phase: "statistical_outlier(16, 2.5)".into(),
            points_in: out.keep.len(),
            points_out: kept.len(),
            seconds: secs,
            cpu_seconds: cpu,
            peak_rss_mib: peak_rss_mib(),
            note: format!("threshold {:.4} m", out.threshold),
        },
    );
    drop(out);

    if wants("normals") {
        let t = Clock::start();
        let params = NormalParams {
            k: 20,
            orientation: NormalOrientation::None,
        };
        let normals = estimate_normals(&kept, &params, &NoProgress)?;
        let (secs, cpu) = t.read();
        push(
            &mut rows,
            GeomRow {
                phase: "estimate_normals(knn 20)".into(),
                points_in: kept.len(),
                points_out: normals.normals.len(),
                seconds: secs,
                cpu_seconds: cpu,
                peak_rss_mib: peak_rss_mib(),
                note: String::new(),
            },
        );
    }
    drop(kept);

    icp_phase(tile, a.icp_tile_m, &mut rows, &push)?;
    finish(a, rows)
}

/// Phase 5, point-to-plane ICP on the tile (see the module docs), when it was asked for.
fn icp_phase(
    tile: Option<(Vec<Vec3>, DVec3)>,
    edge: f64,
    rows: &mut Vec<GeomRow>,
    push: &dyn Fn(&mut Vec<GeomRow>, GeomRow),
) -> anyhow::Result<()> {
    if let Some((target, corner)) = tile {
        if target.len() < 100 {
            anyhow::bail!(
                "the ICP tile holds {} points; the input needs a {edge} x {edge} m corner",
                target.len()
            );
        }
        // Target normals as Open3D's run: KNN 20, not timed (part of the input).
        let params = NormalParams {
            k: 20,
            orientation: NormalOrientation::None,
        };
        let tn = estimate_normals(&target, &params, &NoProgress)?.normals;
        let centre = corner + DVec3::new(edge / 2.0, edge / 2.0, 0.0);
        let truth = icp_truth(centre);
        let inv = truth.inverse();
        let source: Vec<Vec3> = target
            .iter()
            .step_by(4)
            .map(|p| inv.apply_f32(*p))
            .collect();
        // Open3D's recipe: a fixed 0.2 m correspondence distance, no robust kernel, at most
        // 50 iterations, stop when the RMSE changes by less than 1e-6 (relative). Sylva's
        // default starts a large source on a subsample; the second row, run when that
        // applies, iterates on every point throughout as Open3D does.
        let variants: &[(bool, &str)] = if source.len() >= 65_536 {
            &[
                (true, "icp point-to-plane, tile"),
                (false, "icp every point every iteration, tile"),
            ]
        } else {
            &[(true, "icp point-to-plane, tile")]
        };
        for &(coarse_start, phase) in variants {
            let params = IcpParams {
                method: IcpMethod::PointToPlane,
                estimate_scale: false,
                start_distance: 0.2,
                min_distance: 0.2,
                shrink: 1.0,
                robust: RobustKernel::None,
                max_iterations: 50,
                relative_rmse_tolerance: 1e-6,
                coarse_start,
                ..IcpParams::default()
            };
            let t = Clock::start();
            let res = icp(
                &source,
                &target,
                Some(&tn),
                &Similarity::IDENTITY,
                &params,
                &NoProgress,
            )?;
            let (secs, cpu) = t.read();
            let rot_err = (res.rotation * truth.rotation.transpose())
                .to_cols_array()
                .iter()
                .zip(DMat3::IDENTITY.to_cols_array())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max)
                .to_degrees();
            let t_err = (res.translation - truth.translation).length() * 1000.0;
            push(
                rows,
                GeomRow {
                    phase: phase.into(),
                    points_in: target.len(),
                    points_out: source.len(),
                    seconds: secs,
                    cpu_seconds: cpu,
                    peak_rss_mib: peak_rss_mib(),
                    note: format!(
                        "{} its, fitness {:.3}, rmse {:.4} m, rot err {:.4} deg, t err {:.2} mm",
                        res.iterations, res.fitness, res.inlier_rmse, rot_err, t_err
                    ),
                },
            );
        }
    }
    Ok(())
}

fn finish(a: &GeomBenchArgs, rows: Vec<GeomRow>) -> anyhow::Result<Vec<GeomRow>> {
    println!("peak RSS {:.0} MiB", peak_rss_mib());
    if let Some(path) = &a.json {
        std::fs::write(path, serde_json::to_vec_pretty(&rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icp_truth_turns_about_the_tile_centre() {
        let c = DVec3::new(5.0, 5.0, 0.0);
        let t = icp_truth(c);
        let moved = t.apply(c);
        assert!((moved - c - DVec3::new(0.05, -0.03, 0.02)).length() < 1e-12);
        let corner = t.apply(DVec3::ZERO);
        let shift = (corner - DVec3::ZERO).length();
        assert!(shift > 0.05 && shift < 0.15, "corner moves {shift} m");
    }
}
