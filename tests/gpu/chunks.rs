//! Per-Gaussian chunking, projected-record slots and intersection bands: with a small planning
//! cap (`GpuContext::chunk_cap_bytes`) a model of a few thousand Gaussians splits into many
//! chunks (the last one partial), several slots and several bands of tile rows; renders,
//! gradients, densification statistics and a few training steps must equal the one-binding run.

use crate::common;

use sylva::splat::adam::{AdamState, LearningRates};
use sylva::splat::backend::{Backend, Step};
use sylva::splat::cameras::View;
use sylva::splat::gpu::chunks::{ChunkPlan, SlotPlan};
use sylva::splat::gpu::renderer::{BandSpan, plan_bands};
use sylva::splat::gpu::{AtomicMode, GpuBackend, GpuContext, GpuSplats, Renderer};
use sylva::splat::model::Gaussians;
use sylva::splat::packed_image::PackedImage;

/// 128 Gaussians per chunk when the offset alignment is 256 bytes (64-Gaussian units).
const CAP: u64 = 2 * 64 * 192;

/// 256 Gaussians per chunk, 1024 per projected-record slot, 12,288 intersections per band (with
/// 256-byte offset alignment).
const BIG_CAP: u64 = 4 * 64 * 192;

fn chunked(ctx: &GpuContext) -> GpuContext {
    let mut c = ctx.clone();
    c.chunk_cap_bytes = Some(CAP);
    c
}

fn flat<const K: usize>(v: &[[f32; K]]) -> Vec<f32> {
    v.iter().flatten().copied().collect()
}

fn close(name: &str, got: &[f32], want: &[f32], tol: f32) {
    let (rel, bad) = common::compare(got, want, tol, tol * 0.1);
    eprintln!("  {name}: rel {rel:.2e}, bad {bad:.4}");
    assert!(
        rel < tol && bad < 0.01,
        "{name}: chunked differs from unchunked, rel {rel}, bad fraction {bad}"
    );
}

#[test]
fn plan_splits_into_aligned_whole_gaussian_chunks() {
    let Some(ctx) = common::context() else { return };
    let one = ChunkPlan::new(&ctx, 1000).expect("plan");
    assert_eq!(one.len(), 1);
    let c = chunked(&ctx);
    let plan = ChunkPlan::new(&c, 1000).expect("plan");
    assert!(plan.len() >= 4, "{plan:?}");
    assert_eq!(plan.per_chunk as u64 % (ctx.offset_alignment / 4), 0);
    assert!(plan.per_chunk as u64 * 192 <= CAP);
    let chunks: Vec<_> = plan.chunks().collect();
    assert_eq!(chunks.iter().map(|k| k.len).sum::<u32>(), 1000);
    assert!(chunks.windows(2).all(|w| w[0].base + w[0].len == w[1].base));
    assert!(chunks.last().is_some_and(|k| k.len < plan.per_chunk));
    // A cap below one aligned chunk is a clear error naming what does not fit.
    let mut tiny = ctx.clone();
    tiny.chunk_cap_bytes = Some(1000);
    let err = ChunkPlan::new(&tiny, 10).expect_err("too small");
    assert!(err.to_string().contains("SH"), "{err}");
}

#[test]
fn slot_and_band_plans() {
    let Some(ctx) = common::context() else { return };
    let c = chunked(&ctx);
    let slots = SlotPlan::new(&c, 1000).expect("slots");
    assert_eq!(slots.per_slot as u64 % (ctx.offset_alignment / 4), 0);
    assert!(slots.per_slot as u64 * 48 <= CAP);
    assert_eq!(slots.used(), 1000u32.div_ceil(slots.per_slot));
    assert!(slots.used() >= 2, "{slots:?}");
    // More than four slots' worth is a clear error naming the projected records.
    let err = SlotPlan::new(&c, 4 * slots.per_slot + 1).expect_err("too many");
    assert!(err.to_string().contains("projected"), "{err}");
    let band = |row0, rows, count| BandSpan { row0, rows, count };
    let bands = plan_bands(&[3, 4, 0, 5, 2, 7], 7).expect("bands");
    assert_eq!(bands, [band(0, 3, 7), band(3, 2, 7), band(5, 1, 7)]);
    assert_eq!(plan_bands(&[1, 2], 100).expect("one"), [band(0, 2, 3)]);
    let err = plan_bands(&[1, 9, 1], 8).expect_err("row too large");
    assert!(err.to_string().contains("one row"), "{err}");
}

struct Pass {
    image: Vec<[f32; 3]>,
    grads: Vec<Vec<f32>>,
    densify: Vec<f32>,
    bands: usize,
    slots: u32,
    intersections: u32,
}

fn render_and_backward(ctx: &GpuContext, model: &Gaussians, w: u32, h: u32) -> Pass {
    let cam = common::camera(w, h, 0.8 * w as f32);
    let renderer = Renderer::new(ctx);
    let splats = GpuSplats::upload(ctx, model).expect("upload");
    let frame = renderer
        .render(ctx, &splats, &cam, [0.1, 0.2, 0.3])
        .expect("render");
    let dl = common::random_dl((w * h) as usize, 77);
    let grads = common::gpu_grads(ctx, &renderer, (&splats, &frame), &dl);
    let g = grads.download(ctx).expect("download");
    let s = grads.download_stats(ctx).expect("stats");
    Pass {
        bands: frame.bands.len(),
        slots: frame.slots.used(),
        intersections: frame.intersections,
        image: frame.read_image(ctx).expect("image"),
        grads: vec![
            flat(&g.means),
            flat(&g.log_scales),
            flat(&g.rotations),
            g.opacity_logits,
            flat(&g.sh),
        ],
        densify: s.grad_sum,
    }
}

#[test]
fn chunked_render_and_backward_equal_unchunked() {
    let Some(ctx) = common::context() else { return };
    let model = common::scene(31, 1000, 3, 1.5);
    let (w, h) = (96, 72);
    let a = render_and_backward(&ctx, &model, w, h);
    let b = render_and_backward(&chunked(&ctx), &model, w, h);
    // Projection and blending do the same arithmetic per Gaussian and pixel: the image is equal.
    assert_eq!(a.image, b.image, "chunked render differs");
    // Gradients sum over pixels with atomics, whose order varies between runs.
    for (k, (ga, gb)) in a.grads.iter().zip(&b.grads).enumerate() {
        close(&format!("gradient group {k}"), gb, ga, 1e-4);
    }
    close("densify stat", &b.densify, &a.densify, 1e-4);
}

/// A frame with more Gaussians and intersections than one (capped) binding holds: three slots
/// of projected records and screen gradients, several bands of tile rows, against the
/// one-binding run and the CPU reference.
#[test]
fn slotted_and_banded_frame_equals_single_binding() {
    let Some(ctx) = common::context() else { return };
    let mut c = ctx.clone();
    c.chunk_cap_bytes = Some(BIG_CAP);
    let model = common::scene(34, 3000, 3, 1.2);
    let (w, h) = (128, 96);
    let a = render_and_backward(&ctx, &model, w, h);
    let b = render_and_backward(&c, &model, w, h);
    eprintln!(
        "{} intersections: one binding {} band(s), {} slot(s); capped {} bands, {} slots",
        a.intersections, a.bands, a.slots, b.bands, b.slots
    );
    assert_eq!((a.bands, a.slots), (1, 1));
    assert!(b.bands >= 2 && b.slots >= 3, "capped run not split");
    assert_eq!(a.image, b.image, "banded render differs");
    for (k, (ga, gb)) in a.grads.iter().zip(&b.grads).enumerate() {
        close(&format!("gradient group {k}"), gb, ga, 1e-4);
    }
    close("densify stat", &b.densify, &a.densify, 1e-4);
    let cam = common::camera(w, h, 0.8 * w as f32);
    let bg = [0.1, 0.2, 0.3];
    let cpu = sylva::splat::cpu::render(&model, &cam, bg).expect("cpu render");
    let (rel, bad) = common::compare(&flat(&b.image), &flat(&cpu.image), 1e-3, 1e-4);
    eprintln!("  banded image vs CPU: rel {rel:.2e}, bad {bad:.4}");
    assert!(
        rel < 1e-4 && bad < 0.002,
        "banded image disagrees with the CPU reference"
    );
    let dl = common::random_dl((w * h) as usize, 77);
    let (want, want_stat) =
        sylva::splat::cpu::render_backward(&model, &cpu, &dl, None).expect("cpu backward");
    let want = [
        flat(&want.means),
        flat(&want.log_scales),
        flat(&want.rotations),
        want.opacity_logits,
        flat(&want.sh),
    ];
    for (k, (gb, wc)) in b.grads.iter().zip(&want).enumerate() {
        let (rel, bad) = common::compare(gb, wc, 2e-3, 2e-4);
        eprintln!("  banded gradient group {k} vs CPU: rel {rel:.2e}, bad {bad:.4}");
        assert!(rel < 2e-3 && bad < 0.01, "banded gradient group {k} vs CPU");
    }
    let (rel, bad) = common::compare(&b.densify, &want_stat, 2e-3, 2e-4);
    assert!(
        rel < 2e-3 && bad < 0.01,
        "banded densify stat vs CPU: {rel} {bad}"
    );
    // The compare-and-swap template, one copy per gradient slot.
    let Some(mut cas) = common::context_with(Some(AtomicMode::CompareSwap)) else {
        return;
    };
    cas.chunk_cap_bytes = Some(BIG_CAP);
    let d = render_and_backward(&cas, &model, w, h);
    assert_eq!((d.bands, d.slots), (b.bands, b.slots));
    assert_eq!(a.image, d.image, "banded render (CAS build) differs");
    for (k, (ga, gd)) in a.grads.iter().zip(&d.grads).enumerate() {
        close(&format!("CAS gradient group {k}"), gd, ga, 1e-4);
    }
}

fn view(model: &Gaussians, w: u32, h: u32) -> View {
    let camera = common::camera(w, h, 0.8 * w as f32);
    let img = sylva::splat::cpu::render(model, &camera, [0.0; 3]).expect("target render");
    let bytes: Vec<u8> = img
        .image
        .iter()
        .flat_map(|p| {
            let q = p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
            [q[0], q[1], q[2], 255]
        })
        .collect();
    View {
        name: "target".into(),
        camera,
        image: PackedImage::from_rgba8(w, h, &bytes).expect("image").into(),
    }
}

fn train(ctx: &GpuContext, model: &Gaussians, view: &View, steps: u32) -> (Gaussians, f32) {
    let mut be = GpuBackend::with_context(ctx.clone(), [0.0; 3]).expect("backend");
    be.set_model(model, &AdamState::new(model.len()))
        .expect("set model");
    let lr = LearningRates {
        position: 1e-3,
        sh_dc: 2.5e-3,
        sh_rest: 1.25e-4,
        opacity: 5e-2,
        scale: 5e-3,
        rotation: 1e-3,
        exposure: 0.0,
    };
    for _ in 0..steps {
        let step = Step {
            view,
            exposure: None,
            lr: &lr,
            sh_degree: 3,
            stats: true,
        };
        be.step(&step).expect("step");
    }
    let loss = be.last_loss().expect("loss").loss;
    (be.model().expect("model").0, loss)
}

#[test]
fn chunked_training_steps_equal_unchunked() {
    let Some(ctx) = common::context() else { return };
    let model = common::scene(32, 700, 3, 1.2);
    let target = view(&common::scene(33, 300, 0, 1.0), 64, 48);
    let (a, la) = train(&ctx, &model, &target, 5);
    let (b, lb) = train(&chunked(&ctx), &model, &target, 5);
    eprintln!("loss after 5 steps: unchunked {la}, chunked {lb}");
    assert!((la - lb).abs() <= 1e-4 * la.abs().max(1e-3), "{la} vs {lb}");
    close("means", &flat(&b.means), &flat(&a.means), 1e-3);
    close(
        "log_scales",
        &flat(&b.log_scales),
        &flat(&a.log_scales),
        1e-3,
    );
    close("rotations", &flat(&b.rotations), &flat(&a.rotations), 1e-3);
    close("opacity", &b.opacity_logits, &a.opacity_logits, 1e-3);
    close("sh", &flat(&b.sh), &flat(&a.sh), 1e-3);
    // Atomic sums vary in order between runs, and Adam's normalised step turns a tiny gradient's
    // rounding into a full step for a few floats: hence 1e-3 and 1% of entries.
    // The steps moved the model (so the comparison is not of two untouched copies).
    let moved = flat(&a.sh)
        .iter()
        .zip(flat(&model.sh))
        .any(|(x, y)| (x - y).abs() > 1e-4);
    assert!(moved, "five steps left the SH unchanged");
}
