//! Generates a synthetic plot and prints the summary with per-phase timings.
//!
//! `cargo run --release --example synth_stand -- [tiny|plot|stand|paper|object] [OUT] [SEED] [--top-view]`
//! (defaults: stand, out/stand, 1); `--views-only` redraws the pictures of an existing OUT. With `--top-view`, also writes OUT/top_view.png: the
//! LiDAR cloud seen orthographically from above, coloured by label (ground brown, wood
//! dark red, leaf green, other grey), highest point per pixel, and PNG copies of four views.

use std::path::PathBuf;
use std::time::Instant;

use sylva::io::pointcloud::read_point_cloud;
use sylva::progress::NoProgress;
use sylva::synth::{Preset, SynthParams, generate};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let top_view = args.iter().any(|a| a == "--top-view");
    let pos: Vec<&String> = args.iter().filter(|a| !a.starts_with("--")).collect();
    let preset = match pos.first() {
        Some(name) => {
            Preset::from_name(name).ok_or("preset must be tiny, plot, stand, paper or object")?
        }
        None => Preset::Stand,
    };
    let out = pos
        .get(1)
        .map_or_else(|| PathBuf::from("out").join(preset.name()), PathBuf::from);
    let seed = match pos.get(2) {
        Some(s) => s.parse()?,
        None => 1,
    };
    if args.iter().any(|a| a == "--views-only") {
        return write_top_view(&out);
    }
    let params = SynthParams {
        seed,
        ..SynthParams::new(preset)
    };
    let t0 = Instant::now();
    let summary = generate(&params, &out, &NoProgress)?;
    let total = t0.elapsed().as_secs_f64();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    println!("{:<8} {:>9}", "phase", "seconds");
    for t in &summary.timings {
        println!("{:<8} {:>9.2}", t.phase, t.seconds);
    }
    println!(
        "{:<8} {:>9.2}  ({} LiDAR points, {} images {}x{}, {} points3D, {} threads)",
        "total",
        total,
        summary.lidar_points,
        summary.images,
        summary.width,
        summary.height,
        summary.points3d,
        rayon::current_num_threads()
    );
    if top_view {
        write_top_view(&out)?;
    }
    Ok(())
}

fn write_top_view(out: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let cloud = read_point_cloud(&out.join("lidar.laz"), &NoProgress)?;
    let labels = std::fs::read(out.join("labels.bin"))?;
    // Frame the plot disc (plus 3 m) rather than the far ground the scanner also reached.
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("truth.json"))?)?;
    let (lo, hi) = cloud.bounds().ok_or("empty cloud")?;
    let r = truth["plot_radius_m"].as_f64().unwrap_or(50.0) + 3.0;
    let c = &truth["plot_center"];
    let (cx, cy) = (c[0].as_f64().unwrap_or(lo.x), c[1].as_f64().unwrap_or(lo.y));
    let lo = glam::DVec3::new(cx - r, cy - r, lo.z);
    let hi = glam::DVec3::new(cx + r, cy + r, hi.z);
    let size = 900u32;
    let scale = (size - 1) as f64 / (hi.x - lo.x).max(hi.y - lo.y).max(1e-6);
    let mut top = vec![f64::NEG_INFINITY; (size * size) as usize];
    let mut img = image::RgbImage::from_pixel(size, size, image::Rgb([255, 255, 255]));
    for i in 0..cloud.len() {
        let p = cloud.world(i);
        if p.x < lo.x || p.y < lo.y || p.x > hi.x || p.y > hi.y {
            continue;
        }
        let (u, v) = (((p.x - lo.x) * scale) as u32, ((hi.y - p.y) * scale) as u32);
        let k = (v.min(size - 1) * size + u.min(size - 1)) as usize;
        if p.z <= top[k] {
            continue;
        }
        top[k] = p.z;
        let shade = (0.6 + 0.4 * (p.z - lo.z) / (hi.z - lo.z).max(1e-6)) as f32;
        let base: [f32; 3] = match labels.get(i) {
            Some(0) => [150.0, 120.0, 85.0],
            Some(1) => [150.0, 40.0, 30.0],
            Some(2) => [60.0, 170.0, 60.0],
            _ => [140.0, 140.0, 150.0],
        };
        img.put_pixel(
            u.min(size - 1),
            v.min(size - 1),
            image::Rgb(base.map(|c| (c * shade).min(255.0) as u8)),
        );
    }
    img.save(out.join("top_view.png"))?;
    // PNG copies of a few rendered views, for viewers that show PNG only.
    let mut names: Vec<_> = std::fs::read_dir(out.join("colmap/images"))?
        .flatten()
        .map(|e| e.path())
        .collect();
    names.sort();
    for (k, p) in names.iter().enumerate().step_by((names.len() / 4).max(1)) {
        image::open(p)?.save(out.join(format!("preview_{k:03}.png")))?;
    }
    Ok(())
}
