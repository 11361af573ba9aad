//! GPU backward pass against the CPU reference, with both float-atomic strategies.

use crate::common;

use sylva::splat::camera::RenderOptions;
use sylva::splat::cpu::Render;
use sylva::splat::gpu::{AtomicMode, GpuContext, GpuSplats, Renderer};
use sylva::splat::model::GaussianGrads;

/// Scene extent per seed: seed 9 spreads Gaussians past the image edges (Jacobian clamp, culling).
fn spread(seed: u64) -> f32 {
    if seed == 9 { 3.5 } else { 1.2 }
}

struct Outcome {
    grads: GaussianGrads,
    stat: Vec<f32>,
    visible: Vec<u32>,
    radius: Vec<f32>,
}

fn gpu_backward(ctx: &GpuContext, seed: u64, n: usize, deg: u32, w: u32, h: u32) -> Outcome {
    gpu_backward_with(ctx, seed, n, deg, w, h, RenderOptions::default())
}

fn gpu_backward_with(
    ctx: &GpuContext,
    seed: u64,
    n: usize,
    deg: u32,
    w: u32,
    h: u32,
    opts: RenderOptions,
) -> Outcome {
    let model = scene(seed, n, deg, opts);
    let cam = common::camera(w, h, 0.8 * w as f32);
    let bg = [0.2, 0.1, 0.4];
    let renderer = Renderer::new(ctx);
    let splats = GpuSplats::upload(ctx, &model).expect("upload");
    let frame = renderer
        .render_with(ctx, &splats, &cam, bg, opts)
        .expect("render");
    let dl = common::random_dl((w * h) as usize, seed + 100);
    let grads = common::gpu_grads(ctx, &renderer, (&splats, &frame), &dl);
    let s = grads.download_stats(ctx).expect("stats");
    Outcome {
        grads: grads.download(ctx).expect("download"),
        stat: s.grad_sum,
        visible: s.visible_count,
        radius: s.max_radius,
    }
}

/// The scene of `seed`; with the 2-D Mip filter, its axes `e^-1` as long (0.02–0.14 m, about
/// 0.2–1.4 px at 0.8 · width focal length), so that the compensation matters.
fn scene(seed: u64, n: usize, deg: u32, opts: RenderOptions) -> sylva::splat::model::Gaussians {
    let mut model = common::scene(seed, n, deg, spread(seed));
    if opts.antialias {
        for s in &mut model.log_scales {
            *s = s.map(|v| v - 1.0);
        }
    }
    model
}

/// The CPU reference of [`gpu_backward_with`]'s case: its forward pass, and the gradients and
/// densification statistic of the same dL/dimage.
fn cpu_backward(
    (seed, n, deg): (u64, usize, u32),
    (w, h): (u32, u32),
    opts: RenderOptions,
) -> (Render, GaussianGrads, Vec<f32>) {
    let model = scene(seed, n, deg, opts);
    let cam = common::camera(w, h, 0.8 * w as f32);
    let bg = [0.2, 0.1, 0.4];
    let cpu = sylva::splat::cpu::render_with(&model, &cam, bg, opts).expect("cpu render");
    let dl = common::random_dl((w * h) as usize, seed + 100);
    let (want, want_stat) =
        sylva::splat::cpu::render_backward(&model, &cpu, &dl, None).expect("cpu backward");
    (cpu, want, want_stat)
}

fn flat<const K: usize>(v: &[[f32; K]]) -> Vec<f32> {
    v.iter().flatten().copied().collect()
}

fn check(name: &str, got: &[f32], want: &[f32]) {
    let (rel, bad) = common::compare(got, want, 2e-3, 2e-4);
    eprintln!("  {name}: rel {rel:.2e}, bad {bad:.4}");
    assert!(
        rel < 2e-3 && bad < 0.01,
        "{name} disagrees: rel {rel}, bad fraction {bad}"
    );
}

fn check_all(got: &GaussianGrads, want: &GaussianGrads) {
    check("means", &flat(&got.means), &flat(&want.means));
    check(
        "log_scales",
        &flat(&got.log_scales),
        &flat(&want.log_scales),
    );
    check("rotations", &flat(&got.rotations), &flat(&want.rotations));
    check("opacity", &got.opacity_logits, &want.opacity_logits);
    check("sh", &flat(&got.sh), &flat(&want.sh));
}

#[test]
fn backward_matches_cpu_reference() {
    let Some(ctx) = common::context() else { return };
    for (seed, n, deg, w, h) in [
        (5u64, 1usize, 0u32, 32u32, 24u32),
        (6, 60, 1, 48, 40),
        (7, 400, 3, 64, 64),
        (9, 500, 3, 64, 48),
    ] {
        let (cpu, want, want_stat) = cpu_backward((seed, n, deg), (w, h), Default::default());
        eprintln!(
            "seed {seed}, n {n}, degree {deg}, {w}x{h} ({})",
            ctx.description
        );
        let got = gpu_backward(&ctx, seed, n, deg, w, h);
        check_all(&got.grads, &want);
        check("densify stat", &got.stat, &want_stat);
        for (i, p) in cpu.projected.iter().enumerate() {
            assert_eq!(got.visible[i], u32::from(p.visible), "visibility of {i}");
            let want_r = if p.visible { p.radius as f32 } else { 0.0 };
            assert_eq!(got.radius[i], want_r, "screen radius of {i}");
        }
    }
}

#[test]
fn backward_with_antialias_matches_cpu_reference() {
    let Some(ctx) = common::context() else { return };
    let opts = RenderOptions { antialias: true };
    for (seed, n, deg, w, h) in [
        (5u64, 1usize, 0u32, 32u32, 24u32),
        (6, 60, 1, 48, 40),
        (7, 400, 3, 64, 64),
        (9, 500, 3, 64, 48),
    ] {
        let (cpu, want, want_stat) = cpu_backward((seed, n, deg), (w, h), opts);
        let model = scene(seed, n, deg, opts);
        let cam = common::camera(w, h, 0.8 * w as f32);
        let plain = sylva::splat::cpu::render(&model, &cam, [0.2, 0.1, 0.4]).expect("cpu render");
        let dimmed = cpu
            .projected
            .iter()
            .zip(&plain.projected)
            .filter(|(a, b)| a.visible && a.opacity < 0.5 * b.opacity)
            .count();
        eprintln!(
            "seed {seed}, n {n}, degree {deg}, {w}x{h}, antialias ({dimmed} Gaussians at rho < 0.5; {})",
            ctx.description
        );
        let got = gpu_backward_with(&ctx, seed, n, deg, w, h, opts);
        check_all(&got.grads, &want);
        check("densify stat", &got.stat, &want_stat);
        for (i, p) in cpu.projected.iter().enumerate() {
            assert_eq!(got.visible[i], u32::from(p.visible), "visibility of {i}");
        }
    }
}

#[test]
fn float_atomics_and_cas_fallback_agree() {
    let Some(cas) = common::context_with(Some(AtomicMode::CompareSwap)) else {
        return;
    };
    let Some(native) = common::context_with(Some(AtomicMode::Float)) else {
        return;
    };
    assert_eq!(cas.atomic_mode, AtomicMode::CompareSwap);
    if native.atomic_mode != AtomicMode::Float {
        eprintln!("adapter has no float atomics: only the CAS path is tested");
    }
    let a = gpu_backward(&cas, 8, 300, 2, 64, 48);
    let b = gpu_backward(&native, 8, 300, 2, 64, 48);
    check_all(&a.grads, &b.grads);
}

#[test]
fn every_pixels_per_thread_variant_matches_cpu_reference() {
    let Some(ctx) = common::context() else { return };
    for (seed, n, deg, w, h) in [(7u64, 400usize, 3u32, 64u32, 64u32), (9, 500, 3, 40, 56)] {
        let (_, want, want_stat) = cpu_backward((seed, n, deg), (w, h), Default::default());
        for pix in [1u32, 2, 4, 8, 16] {
            let mut c = ctx.clone();
            c.raster_pixels = pix;
            eprintln!("seed {seed}, {w}x{h}, {pix} pixels per thread");
            let got = gpu_backward(&c, seed, n, deg, w, h);
            check_all(&got.grads, &want);
            check("densify stat", &got.stat, &want_stat);
        }
    }
}

/// The depth channel's backward (a loss on the expected depth) against the CPU reference.
#[test]
fn depth_backward_matches_cpu_reference() {
    let Some(ctx) = common::context() else { return };
    for (seed, n, w, h) in [(6u64, 60usize, 48u32, 40u32), (9, 500, 64, 48)] {
        let model = common::scene(seed, n, 1, spread(seed));
        let cam = common::camera(w, h, 0.8 * w as f32);
        let bg = [0.2, 0.1, 0.4];
        let pixels = (w * h) as usize;
        let cpu = sylva::splat::cpu::render(&model, &cam, bg).expect("cpu render");
        let dl = common::random_dl(pixels, seed + 100);
        let dd: Vec<f32> = (0..pixels)
            .map(|p| 0.05 * (p as f32 * 0.37).sin())
            .collect();
        let (want, _) =
            sylva::splat::cpu::render_backward(&model, &cpu, &dl, Some(&dd)).expect("cpu backward");
        let (without, _) =
            sylva::splat::cpu::render_backward(&model, &cpu, &dl, None).expect("cpu backward");
        let moved = want
            .means
            .iter()
            .zip(&without.means)
            .filter(|(a, b)| (a[2] - b[2]).abs() > 1e-4 * (1.0 + b[2].abs()))
            .count();
        assert!(
            moved > n / 10,
            "the depth term barely changes the gradients ({moved})"
        );
        let renderer = Renderer::new(&ctx);
        let splats = GpuSplats::upload(&ctx, &model).expect("upload");
        let frame = renderer.render(&ctx, &splats, &cam, bg).expect("render");
        ctx.queue
            .write_buffer(&frame.depth_grad, 0, bytemuck::cast_slice(&dd));
        let grads = common::gpu_grads(&ctx, &renderer, (&splats, &frame), &dl);
        eprintln!("seed {seed}, n {n}, {w}x{h}, with a depth loss");
        check_all(&grads.download(&ctx).expect("download"), &want);
    }
}
