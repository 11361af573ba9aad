//! Capacity benchmark of the GPU splatting rasteriser: renders and back-propagates one frame of a
//! random model large enough to pass the adapter's storage-binding limit (projected records in
//! several slots, tile intersections in several bands) and prints one table row.
//!
//! `cargo run --profile test --example splat_capacity -- [--gaussians N] [--width W]
//! [--height H] [--sigma S] [--cap-mib C]` (defaults: 3,000,000 Gaussians, 640×360, σ = 0.05 m,
//! the adapter's own binding limit). The model is isotropic Gaussians uniform in a 4.8 × 2 × 2.6 m
//! box 4 m in front of a 0.8·W px focal-length camera, opacity 0.5, random colours; σ sets the
//! footprint and so the intersections (≈ 12 tiles per Gaussian at the defaults). Set
//! `WGPU_BACKEND=vulkan` for lavapipe.

use std::time::Instant;

use sylva::rng::SplitMix64;
use sylva::splat::camera::Camera;
use sylva::splat::gpu::buffers::{read_buffer, storage_from};
use sylva::splat::gpu::{GpuContext, GpuGrads, GpuSplats, Renderer};
use sylva::splat::model::{Gaussian, Gaussians};
use sylva::testing::peak_rss_mib;

fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> Result<T, String> {
    match args.iter().position(|a| a == name) {
        None => Ok(default),
        Some(i) => args
            .get(i + 1)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| format!("{name} needs a number")),
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n: usize = arg(&args, "--gaussians", 3_000_000)?;
    let w: u32 = arg(&args, "--width", 640)?;
    let h: u32 = arg(&args, "--height", 360)?;
    let sigma: f32 = arg(&args, "--sigma", 0.05)?;
    let cap_mib: u64 = arg(&args, "--cap-mib", 0)?;
    let mut ctx = GpuContext::new()?;
    if cap_mib > 0 {
        ctx.chunk_cap_bytes = Some(cap_mib << 20);
    }
    eprintln!(
        "{}: binding limit {} MiB, planning cap {} MiB",
        ctx.description,
        ctx.max_binding_bytes >> 20,
        ctx.chunk_binding_bytes() >> 20
    );

    let mut rng = SplitMix64::new(7);
    let mut model = Gaussians::default();
    let mut u = |half: f64| ((rng.uniform() * 2.0 - 1.0) * half) as f32;
    for _ in 0..n {
        let mean = [u(2.4), u(1.0), u(1.3)];
        let rgb = [u(0.5) + 0.5, u(0.5) + 0.5, u(0.5) + 0.5];
        model.push(Gaussian::isotropic(mean, sigma, rgb, 0.5));
    }
    let cam = Camera::look_at(
        [0.0, -4.0, 0.0],
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        w,
        h,
        0.8 * w as f32,
    );

    let renderer = Renderer::new(&ctx);
    let splats = GpuSplats::upload(&ctx, &model)?;
    drop(model);
    ctx.wait()?;
    let t0 = Instant::now();
    let frame = renderer.render(&ctx, &splats, &cam, [0.0; 3])?;
    ctx.wait()?;
    let render_s = t0.elapsed().as_secs_f64();
    let dl: Vec<[f32; 3]> = (0..w as usize * h as usize)
        .map(|i| {
            let s = if i % 2 == 0 { 1.0 } else { -1.0 };
            [s, -s, 0.5 * s]
        })
        .collect();
    let dl_buf = storage_from(&ctx, "dL/dimage", &dl)?;
    let grads = GpuGrads::new(&ctx, splats.count)?;
    let t1 = Instant::now();
    renderer.backward(&ctx, &splats, &frame, &dl_buf, &grads, false)?;
    ctx.wait()?;
    let backward_s = t1.elapsed().as_secs_f64();

    let image = frame.read_image(&ctx)?;
    let mean =
        image.iter().flatten().map(|&v| f64::from(v)).sum::<f64>() / (3 * image.len()) as f64;
    let g_op: Vec<f32> = read_buffer(&ctx, &grads.opacity_logits, splats.count as usize)?;
    let nonzero = g_op.iter().filter(|v| **v != 0.0).count();
    let finite =
        image.iter().flatten().all(|v| v.is_finite()) && g_op.iter().all(|v| v.is_finite());
    println!(
        "| Gaussians | image | intersections | slots × per slot | bands | render s | backward s | mean pixel | Gaussians with dL/dopacity ≠ 0 | finite | peak RSS MiB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {n} | {w}×{h} | {} | {} × {} | {} | {render_s:.2} | {backward_s:.2} | {mean:.4} | {nonzero} | {finite} | {:.0} |",
        frame.intersections,
        frame.slots.used(),
        frame.slots.per_slot,
        frame.bands.len(),
        peak_rss_mib()
    );
    Ok(())
}
