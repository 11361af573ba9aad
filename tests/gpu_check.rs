//! `benches/gpu_check.sh`, the GPU check of issue 41, run as its user would but at a small
//! size on whatever adapter the environment gives (lavapipe in CI): a `paper`-preset plot of
//! 12 photos at 640×360, two speed rows and the held-out row, with a memory plan that streams the
//! photos. On a real GPU the script runs at the paper's size.

mod common;

use std::process::Command;

#[test]
fn the_gpu_check_prints_its_three_rows_at_a_small_size() {
    if sylva::splat::gpu::GpuContext::new().is_err() {
        sylva::testing::skip("gpu", "no GPU adapter for benches/gpu_check.sh");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/gpu_check.sh");
    let out = Command::new("bash")
        .arg(script)
        .arg(dir.path())
        .env("SYLVA_BIN", common::BIN)
        .env("GPU_CHECK_IMAGES", "12")
        .env("GPU_CHECK_WIDTH", "640")
        .env("GPU_CHECK_HEIGHT", "360")
        .env("GPU_CHECK_RESOLUTION", "640")
        .env("GPU_CHECK_GAUSSIANS", "2000,4000")
        .env("GPU_CHECK_STEPS", "5")
        .env("GPU_CHECK_PSNR_GAUSSIANS", "2000")
        .env("GPU_CHECK_PSNR_STEPS", "40")
        // 100 MiB: the 12 photos (0.9 MB each) stream through a cache of 2 slots.
        .env("GPU_CHECK_MEMORY_MB", "100")
        .env("GPU_CHECK_LIDAR_POINTS", "20000")
        // The NeRF section builds and runs the GPU tests and a benchmark: minutes on a real
        // GPU, far more on lavapipe; its pieces are tested on their own (tests/gpu/nerf.rs).
        .env("GPU_CHECK_NERF_SECONDS", "0")
        .output()
        .expect("bash");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    // Three table rows (two speed rows and the held-out one), each with a planned and a
    // measured GPU memory, the photos streamed, the held-out PSNR a number.
    let rows: Vec<Vec<&str>> = stdout
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| device"))
        .map(|l| l.trim_matches('|').split('|').map(str::trim).collect())
        .collect();
    assert_eq!(rows.len(), 3, "{stdout}");
    for (r, gaussians) in rows.iter().zip(["2000", "4000", "2000"]) {
        assert_eq!(r[3], gaussians, "{r:?}");
        let planned: f64 = r[15].parse().expect("planned MiB");
        let peak: f64 = r[16].parse().expect("peak MiB");
        assert!(peak > 0.0 && peak <= planned, "{r:?}");
        assert!(r[17].contains(" of "), "photos streamed: {r:?}");
    }
    let psnr: f64 = rows[2][14].parse().expect("held-out PSNR");
    assert!(psnr > 10.0, "{psnr}");
    assert!(stdout.contains("## Held-out PSNR"), "{stdout}");
}
