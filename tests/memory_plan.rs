//! A job under a GPU memory plan too small for its photos and its budget (issue 41, item 4):
//! `tiny` seed 1 through every stage with `params.train.gpu_memory_mb` set so that the photos
//! must stream through a cache and the budget must bind, on whatever adapter the environment
//! gives (lavapipe in CI), and with `params.train.host_photo_mb` 0 so that the host keeps
//! the photos compressed. The job completes, the report says what was planned and what the
//! device and the host held, and nothing was allocated past the plan.

use std::path::Path;

use serde_json::Value;
use sylva::pipeline::params::PipelineParams;
use sylva::pipeline::{self, REPORT_FILE, Stage, StageInputs};
use sylva::progress::NoProgress;
use sylva::splat::budget::SOFTWARE_GPU_BUDGET;
use sylva::splat::plan::{self, MemorySource, PlanInput};
use sylva::splat::semantic::SemanticAnchors;
use sylva::synth::{Preset, SynthParams};

fn report(dir: &Path, stage: Stage) -> Value {
    let path = dir.join(stage.name()).join(REPORT_FILE);
    serde_json::from_slice(&std::fs::read(&path).expect("report")).expect("json")
}

#[test]
fn a_job_streams_its_photos_and_keeps_to_a_small_gpu_memory() {
    let Ok(ctx) = sylva::splat::gpu::GpuContext::new() else {
        sylva::testing::skip("gpu", "no GPU adapter for the memory plan's job");
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let plot = dir.path().join("plot");
    let synth = SynthParams {
        seed: 1,
        ..SynthParams::new(Preset::Tiny)
    };
    let summary = sylva::synth::generate(&synth, &plot, &NoProgress).expect("synth");
    let inputs = StageInputs::of_synth_plot(&plot);
    let out = dir.path().join("job");
    let mut params = PipelineParams::default();
    params.train.steps = 200;
    for &stage in Stage::Train.predecessors() {
        pipeline::execute_stage(stage, &inputs, &out, &params, &NoProgress)
            .unwrap_or_else(|e| panic!("stage {stage}: {e}"));
    }
    // The trunk term's anchors, as stage `train` will hold them on the GPU.
    let (cloud, fields) = sylva::io::ply::read_ply_with_fields(
        &out.join(Stage::Segment.name()).join("anchors.ply"),
        &NoProgress,
    )
    .expect("anchors");
    let label = fields.iter().find(|f| f.name == "label").expect("labels");
    let points: Vec<[f32; 3]> = cloud.positions.iter().map(|p| p.to_array()).collect();
    let is_trunk: Vec<bool> = label.values.iter().map(|&l| l == 1.0).collect();
    let anchors = SemanticAnchors::new(&points, None, &is_trunk).expect("trunk anchors");
    // What stage `train` will plan with at the defaults (exposure on: every photo trains;
    // Sylva's binding; the software GPU's budget): the smallest memory, in MiB, whose plan
    // streams the photos and lowers the budget.
    let input = PlanInput {
        device_bytes: 0,
        source: MemorySource::Params,
        photos: summary.images,
        photo_pixels: u64::from(summary.width) * u64::from(summary.height),
        depth_maps: false,
        exposure: true,
        trunk_term: true,
        mcmc: false,
        anchor_bytes: anchors.device_bytes(),
        budget: Some(SOFTWARE_GPU_BUDGET),
        intersections_per_gaussian: plan::INTERSECTIONS_PER_GAUSSIAN,
    };
    let mb = (1..1024u64)
        .find(|&mb| {
            plan::plan(&PlanInput {
                device_bytes: mb << 20,
                ..input.clone()
            })
            .is_ok_and(|p| !p.all_photos && p.memory_bound)
        })
        .expect("a memory that streams the photos and binds the budget");
    params.train.gpu_memory_mb = mb;
    // And a host that keeps every photo compressed (`splat::photo`).
    params.train.host_photo_mb = 0;
    for stage in [Stage::Train, Stage::Dbh, Stage::Export] {
        pipeline::execute_stage(stage, &inputs, &out, &params, &NoProgress)
            .unwrap_or_else(|e| panic!("stage {stage} under {mb} MiB: {e}"));
    }
    let train = report(&out, Stage::Train);
    let plan = &train["memory"]["plan"];
    let used = &train["memory"]["used"];
    eprintln!("{mb} MiB: plan {plan}\nused {used}");
    assert_eq!(plan["all_photos"], false, "{plan}");
    assert_eq!(plan["memory_bound"], true, "{plan}");
    let budget = plan["budget"].as_u64().expect("budget");
    assert!(budget < u64::from(SOFTWARE_GPU_BUDGET));
    assert_eq!(train["budget"]["max_gaussians"].as_u64(), Some(budget));
    assert!(train["gaussians"]["final"].as_u64().expect("final") <= budget);
    // The photos streamed: more uploads than slots.
    assert!(
        used["photo_uploads"].as_u64().expect("uploads")
            > plan["photo_slots"].as_u64().expect("slots"),
        "{used}"
    );
    // Within the plan, as the device's allocator counts it (where it gives a report).
    let peak = used["peak_allocated_bytes"].as_u64().expect("peak");
    if ctx.allocated_bytes().is_some() {
        assert!(
            peak > 0 && peak <= plan["total_bytes"].as_u64().expect("total"),
            "{used}"
        );
    }
    assert!(
        used["over_plan_steps"].as_u64().expect("over") <= 5,
        "{used}"
    );
    // The host held the photos compressed, in less memory than decoded.
    let host = &train["memory"]["host_photos"];
    assert_eq!(
        host["compressed"].as_u64(),
        Some(summary.images as u64),
        "{host}"
    );
    assert_eq!(host["decoded"].as_u64(), Some(0), "{host}");
    assert!(
        host["bytes"].as_u64().expect("bytes") < host["decoded_bytes"].as_u64().expect("decoded"),
        "{host}"
    );
    // A model that learned something, measured as always.
    let psnr = train["render"]["psnr"].as_f64().expect("psnr");
    let floor = train["baseline_psnr"].as_f64().expect("baseline");
    assert!(
        psnr > floor + 3.0,
        "held-out PSNR {psnr} dB, mean colour {floor} dB"
    );
    assert!(report(&out, Stage::Dbh).is_object());
    assert!(out.join(Stage::Export.name()).join(REPORT_FILE).exists());
}
