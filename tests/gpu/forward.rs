//! GPU forward render against the CPU reference (splat-cpu).

use crate::common;

use sylva::splat::camera::RenderOptions;
use sylva::splat::gpu::{GpuSplats, Renderer};

#[test]
fn forward_matches_cpu_reference() {
    forward_matches_cpu_reference_with(RenderOptions::default());
}

#[test]
fn forward_with_antialias_matches_cpu_reference() {
    forward_matches_cpu_reference_with(RenderOptions { antialias: true });
}

fn forward_matches_cpu_reference_with(opts: RenderOptions) {
    let Some(ctx) = common::context() else { return };
    let renderer = Renderer::new(&ctx);
    let cases = [
        (1u64, 1usize, 0u32, 32u32, 24u32, [0.0f32; 3]),
        (2, 50, 1, 64, 48, [0.1, 0.2, 0.3]),
        (3, 300, 3, 64, 64, [0.0; 3]),
        (4, 500, 2, 61, 37, [1.0, 1.0, 1.0]),
    ];
    for (seed, n, deg, w, h, bg) in cases {
        let model = common::scene(seed, n, deg, 1.2);
        let cam = common::camera(w, h, 0.8 * w as f32);
        let cpu = sylva::splat::cpu::render_with(&model, &cam, bg, opts).expect("cpu render");
        let splats = GpuSplats::upload(&ctx, &model).expect("upload");
        let frame = renderer
            .render_with(&ctx, &splats, &cam, bg, opts)
            .expect("gpu render");
        let img = frame.read_image(&ctx).expect("read");
        let t = frame.read_final_t(&ctx).expect("read");
        let got: Vec<f32> = img.iter().flatten().copied().collect();
        let want: Vec<f32> = cpu.image.iter().flatten().copied().collect();
        let max = got
            .iter()
            .zip(&want)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        let (rel, bad) = common::compare(&got, &want, 1e-3, 1e-4);
        let (trel, tbad) = common::compare(&t, &cpu.final_t, 1e-3, 1e-4);
        let depth = frame.read_depth(&ctx).expect("read");
        let (drel, dbad) = common::compare(&depth, &cpu.depth, 1e-3, 1e-4);
        assert!(
            n < 50 || cpu.depth.iter().filter(|&&d| d > 0.5).count() > (w * h / 10) as usize,
            "the scene covers too little of the image for the depth check"
        );
        assert!(
            drel < 1e-4 && dbad < 0.002,
            "depth disagrees: rel {drel} bad {dbad}"
        );
        eprintln!(
            "{opts:?} seed {seed}: n {n}, {w}x{h}, isect {}: image max {max:.2e} rel {rel:.2e} bad {bad:.4}; T rel {trel:.2e} bad {tbad:.4}",
            frame.intersections
        );
        assert!(rel < 1e-4 && bad < 0.002, "image disagrees");
        assert!(trel < 1e-4 && tbad < 0.002, "final T disagrees");
    }
}

#[test]
fn every_pixels_per_thread_variant_renders_the_same_image() {
    let Some(ctx) = common::context() else { return };
    let model = common::scene(3, 300, 2, 1.2);
    let cam = common::camera(61, 37, 48.0);
    let cpu = sylva::splat::cpu::render(&model, &cam, [0.1, 0.2, 0.3]).expect("cpu render");
    let want: Vec<f32> = cpu.image.iter().flatten().copied().collect();
    let mut first: Option<Vec<[f32; 3]>> = None;
    for pix in [1u32, 2, 4, 8, 16] {
        let mut c = ctx.clone();
        c.raster_pixels = pix;
        let renderer = Renderer::new(&c);
        let splats = GpuSplats::upload(&c, &model).expect("upload");
        let frame = renderer
            .render(&c, &splats, &cam, [0.1, 0.2, 0.3])
            .expect("render");
        let img = frame.read_image(&c).expect("image");
        let got: Vec<f32> = img.iter().flatten().copied().collect();
        let (rel, bad) = common::compare(&got, &want, 1e-3, 1e-4);
        eprintln!("{pix} pixels per thread: rel {rel:.2e}, bad {bad:.4}");
        assert!(rel < 1e-4 && bad < 0.001, "{pix} pixels per thread");
        // Each pixel's blending is the same arithmetic in every variant: identical images.
        match &first {
            None => first = Some(img),
            Some(f) => assert_eq!(f, &img, "{pix} pixels per thread"),
        }
    }
}
