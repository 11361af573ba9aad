//! Training quality on a generated plot with the GPU trainer (lavapipe in CI): held-out PSNR
//! against the mean-colour baseline. Skips with a printed reason when there is no adapter.

use sylva::pipeline::params::{TrainBackend, TrainParams};
use sylva::progress::NoProgress;
use sylva::splat::{dataset, init, trainer};
use sylva::synth::{Preset, SynthParams};

#[test]
fn gpu_training_on_a_tiny_plot_beats_the_mean_colour_on_held_out_views() {
    // lavapipe spreads workgroups over a thread pool, so the backward pass's float atomic adds
    // land in a different order each run; over 1000 steps, densification decisions amplify
    // that, and the held-out PSNR of 4 views at 80 px spread from 20.1 to 24.0 dB across six
    // runs. One lavapipe thread runs the workgroups in a fixed order: the run is reproducible
    // (23.28 dB twice), so this checks the method, not the draw. A value the caller set wins.
    if std::env::var_os("LP_NUM_THREADS").is_none() {
        // SAFETY: this binary holds this one test, and nothing else reads the environment
        // before the adapter below is created.
        unsafe { std::env::set_var("LP_NUM_THREADS", "1") };
    }
    // The figures below were measured with the reference protocol: no exposure compensation,
    // full held-out images (the generated photos share one exposure).
    let params = TrainParams {
        steps: 1000,
        resolution: 80,
        backend: TrainBackend::Gpu,
        exposure: false,
        ..TrainParams::default()
    };
    let mut backend = match sylva::pipeline::train::backend_for(&params) {
        Ok(b) => b,
        Err(e) => {
            sylva::testing::skip("gpu", &e.to_string());
            return;
        }
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let mut p = SynthParams::new(Preset::Tiny);
    p.seed = 1;
    // The Gaussians start from the SfM points: 1500 of them (the preset's 12 000 serve
    // registration) keep the lavapipe run under the 10 k Gaussians a CPU test can afford.
    p.points3d = Some(1_500);
    sylva::synth::generate(&p, dir.path(), &NoProgress).expect("synth");
    let project = sylva::io::colmap::find_project(&dir.path().join("colmap")).expect("project");
    let model = sylva::io::colmap::read_model(&project.sparse_dir, &NoProgress).expect("model");
    let images = project.images_dir.expect("images");
    let cfg = params.config();
    let data = dataset::load(
        &model,
        &images,
        cfg.resolution,
        cfg.test_every,
        cfg.host_photo_mb,
        &NoProgress,
    )
    .expect("dataset");
    let g = init::from_sfm_points(&data.points, &data.colours).expect("init");
    let mut strategy = trainer::default_strategy(&cfg);
    let out = trainer::train(backend.as_mut(), &data, g, &cfg, &mut strategy, &NoProgress)
        .expect("train");
    println!(
        "{}: held-out PSNR {:.2} dB, SSIM {:.3}; mean colour {:.2} dB; {} Gaussians; {:.1} steps/s",
        out.device,
        out.eval.psnr,
        out.eval.ssim,
        out.baseline_psnr,
        out.model.len(),
        out.steps_per_second
    );
    assert_eq!(out.eval.views.len(), 4);
    // Measured on lavapipe: 22.93 dB against 12.81 dB (+10.1 dB, the goal is +10).
    // Float atomics add in a scheduling-dependent order, so runs differ slightly: the
    // assertion leaves half a decibel for that.
    assert!(
        out.eval.psnr >= out.baseline_psnr + 9.5,
        "held-out PSNR {:.2} dB, baseline {:.2} dB",
        out.eval.psnr,
        out.baseline_psnr
    );
}
