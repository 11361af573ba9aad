//! The memory plan (`splat::plan`) against the buffers a GPU run really makes, as the
//! device's allocator counts them (wgpu's allocator report), and the photo cache against
//! keeping every photo: a plan that streams the photos trains the same model.

use crate::common;
use crate::test_scenes::{random_scene, ring_dataset_sized};

use sylva::splat::adam::AdamState;
use sylva::splat::backend::Backend;
use sylva::splat::config::TrainConfig;
use sylva::splat::gpu::{GpuBackend, GpuContext};
use sylva::splat::plan::{
    self, BYTES_PER_INTERSECTION, FIXED_BYTES, MemoryPlan, MemorySource, PlanInput,
    STEP_BYTES_PER_GAUSSIAN,
};

const W: u32 = 256;
const H: u32 = 192;

fn allocated(ctx: &GpuContext) -> u64 {
    ctx.allocated_bytes().map_or(0, |(a, _)| a)
}

/// The smallest device (in MiB) whose plan streams the photos and holds `n` Gaussians.
fn streaming_plan(input: &PlanInput, n: u32) -> MemoryPlan {
    (1..4096u64)
        .filter_map(|mb| {
            plan::plan(&PlanInput {
                device_bytes: mb << 20,
                ..input.clone()
            })
            .ok()
        })
        .find(|p| !p.all_photos && p.budget >= n)
        .expect("some device size streams the photos and holds the Gaussians")
}

#[test]
fn the_plan_holds_what_a_run_allocates_and_streamed_photos_train_the_same_model() {
    let Some(ctx) = common::context() else { return };
    if ctx.allocated_bytes().is_none() {
        sylva::testing::skip("gpu", "the adapter gives no allocator report");
        return;
    }
    let n = 3000usize;
    let truth = random_scene(11, 400, 0);
    let data = ring_dataset_sized(&truth, 48, (W, H), 230.0);
    // Gaussians of 1–4 cm, as a trained plot's: about 3 tiles each at this size.
    let mut init = random_scene(12, n, 0);
    for s in &mut init.log_scales {
        *s = s.map(|v| v - 2.5);
    }
    let cfg = TrainConfig {
        steps: 60,
        exposure: false,
        densify_until: 0,
        ..TrainConfig::default()
    };
    let input = PlanInput {
        device_bytes: 0,
        source: MemorySource::Params,
        photos: data.train.len(),
        photo_pixels: u64::from(W * H),
        depth_maps: false,
        exposure: false,
        trunk_term: false,
        mcmc: false,
        anchor_bytes: 0,
        budget: Some(n as u32),
        intersections_per_gaussian: plan::INTERSECTIONS_PER_GAUSSIAN,
    };
    let plan = streaming_plan(&input, n as u32);
    assert!(plan.photo_slots < data.train.len(), "{plan:?}");

    let run = |plan: Option<&MemoryPlan>| {
        let mut backend = GpuBackend::with_context(ctx.clone(), [0.0; 3]).expect("backend");
        ctx.wait().expect("wait");
        let base = allocated(&ctx);
        // The model's buffers: what the plan counts per Gaussian for the whole run.
        backend.set_model(&init, &AdamState::new(n)).expect("model");
        let model = allocated(&ctx) - base;
        if let Some(p) = plan {
            backend.set_plan(p).expect("plan");
        }
        let mut strategy = sylva::splat::trainer::default_strategy(&cfg);
        let out = sylva::splat::trainer::train(
            &mut backend,
            &data,
            init.clone(),
            &cfg,
            &mut strategy,
            &sylva::progress::NoProgress,
        )
        .expect("train");
        let used = backend
            .memory_use()
            .expect("the GPU backend measures its memory");
        (out, used, base, model)
    };

    let (free, free_used, _, _) = run(None);
    let (planned, used, base, model) = run(Some(&plan));
    let per_gaussian = input.model_bytes_per_gaussian() * n as u64;
    eprintln!(
        "model {model} B against {per_gaussian} planned; peak {} B above {base} B; plan {plan:?}; used {used:?}",
        used.peak_allocated_bytes
    );
    // The model as planned, to the allocator's alignment (256 B a buffer, 15 buffers).
    assert!(
        model >= per_gaussian && model <= per_gaussian + 16 * 4096,
        "model {model} B, planned {per_gaussian} B"
    );
    // The whole run within the plan, and the plan's step terms not far above what a step took.
    assert!(used.peak_allocated_bytes <= plan.total_bytes, "{used:?}");
    let photos = plan.photo_slots as u64 * input.bytes_per_photo();
    let step = used
        .peak_allocated_bytes
        .saturating_sub(base + model + photos);
    let step_planned = input.frame_bytes()
        + n as u64 * STEP_BYTES_PER_GAUSSIAN
        + used.max_intersections * BYTES_PER_INTERSECTION;
    assert!(
        step <= step_planned + FIXED_BYTES / 16 && step * 2 >= step_planned,
        "a step took {step} B above the model and photos, the plan counts {step_planned} B"
    );
    // The photos streamed through the cache, and the run trained as with every photo kept.
    assert!(used.photo_uploads > plan.photo_slots as u64, "{used:?}");
    assert_eq!(free_used.photo_uploads, data.train.len() as u64);
    assert_eq!(used.over_plan_steps, 0);
    let (a, b) = (planned.eval.psnr, free.eval.psnr);
    assert!((a - b).abs() < 0.05, "held-out PSNR {a} streamed, {b} kept");
}
