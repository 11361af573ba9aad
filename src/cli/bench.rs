//! `sylva bench`: the benchmarks that print tables (train here; load, soak, geom and method
//! in `loadbench`).

use super::*;

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// What to measure: train (steps per second, where the step time goes, peak memory),
    /// load (job status reads per second and latency of the HTTP API; flags marked `load:`)
    /// or soak (many small jobs through `sylva serve` and `sylva worker` processes with random
    /// cancels and one SIGKILL; jobs per hour, API latency and anything lost; flags marked
    /// `soak:`, and --jobs) or geom (read, voxel, outlier filter, normals and ICP on a real
    /// point cloud with per-phase peak memory; flags marked `geom:`) or method (the paper's
    /// ablation plus Sylva's binding on generated plots: render quality, DBH from the
    /// Gaussians and the LiDAR, trunk-surface distance; flags marked `method:`) or tiles (the
    /// 3D Tiles tileset of a generated twin of --gaussians Gaussians, 0 = 1 M: build time and
    /// size against PLY, glTF and SPZ).
    #[arg(env = "SYLVA_BENCH_WHAT", default_value = "train")]
    pub what: String,
    /// A COLMAP project to train on; without one a synthetic plot is generated.
    #[arg(long, env = "SYLVA_BENCH_COLMAP")]
    pub colmap: Option<PathBuf>,
    /// Synthetic preset when no --colmap is given (tiny, plot, stand, object).
    #[arg(long, env = "SYLVA_BENCH_PRESET", default_value = "tiny")]
    pub preset: String,
    /// Steps to time (the first step's shader compilation included).
    #[arg(long, env = "SYLVA_BENCH_STEPS", default_value_t = 100)]
    pub steps: u32,
    /// Longest image side, pixels (comma-separated for several rows).
    #[arg(long, env = "SYLVA_BENCH_RESOLUTION", default_value = "320")]
    pub resolution: String,
    /// Gaussians to train, comma-separated for several rows: a seeded even draw of the SfM
    /// points, or, past their number, each point spread into jittered copies
    /// (`splat::start::spread_to`); 0 = the SfM points as they are.
    #[arg(long, env = "SYLVA_BENCH_GAUSSIANS", default_value = "0")]
    pub gaussians: String,
    /// train: plan the GPU's memory as stage `train` does (`splat::plan`) for this many MiB
    /// (0 = what the device reports) and print the plan against the peak the allocator saw;
    /// without it, no plan (every photo stays on the GPU).
    #[arg(long, env = "SYLVA_BENCH_GPU_MEMORY_MB")]
    pub gpu_memory_mb: Option<u64>,
    /// train: hold out every 8th photo and print the held-out PSNR after the steps (the
    /// evaluation is not in the step times).
    #[arg(long, env = "SYLVA_BENCH_HELDOUT")]
    pub heldout: bool,
    /// gpu or cpu.
    #[arg(long, env = "SYLVA_BENCH_BACKEND", default_value = "gpu")]
    pub backend: String,
    /// train: pixels per thread of the GPU rasters (1, 2, 4, 8 or 16; 0 = the device's
    /// default: 8 on CPU adapters such as lavapipe, 1 on GPUs). For measuring the choice.
    #[arg(long, env = "SYLVA_BENCH_RASTER_PIXELS", default_value_t = 0)]
    pub raster_pixels: u32,
    #[command(flatten)]
    pub load: crate::loadbench::LoadArgs,
    #[command(flatten)]
    pub soak: crate::loadbench::soak::SoakArgs,
    #[command(flatten)]
    pub geom: crate::loadbench::geom::GeomBenchArgs,
    #[command(flatten)]
    pub method: crate::loadbench::method::MethodBenchArgs,
}

pub(super) async fn bench(a: BenchArgs) -> anyhow::Result<ExitCode> {
    use sylva::pipeline::params::{TrainBackend, TrainParams};
    if a.what == "load" {
        crate::loadbench::run(&a.load).await?;
        return Ok(ExitCode::SUCCESS);
    }
    if a.what == "soak" {
        let nothing_lost = crate::loadbench::soak::run(a.load.jobs, &a.soak).await?;
        return Ok(if nothing_lost {
            ExitCode::SUCCESS
        } else {
            ExitCode::FAILURE
        });
    }
    if a.what == "geom" {
        let args = a.geom.clone();
        tokio::task::spawn_blocking(move || crate::loadbench::geom::run(&args)).await??;
        return Ok(ExitCode::SUCCESS);
    }
    if a.what == "method" {
        let args = a.method.clone();
        tokio::task::spawn_blocking(move || crate::loadbench::method::run(&args)).await??;
        return Ok(ExitCode::SUCCESS);
    }
    if a.what == "tiles" {
        let sizes: Vec<usize> = a
            .gaussians
            .split(',')
            .map(|s| s.trim().parse::<usize>())
            .collect::<Result<_, _>>()
            .map_err(|e| anyhow::anyhow!("--gaussians: {e}"))?;
        let sizes: Vec<usize> = sizes
            .into_iter()
            .map(|n| if n == 0 { 1_000_000 } else { n })
            .collect();
        tokio::task::spawn_blocking(move || crate::loadbench::tiles::run(&sizes)).await??;
        return Ok(ExitCode::SUCCESS);
    }
    if a.what != "train" {
        anyhow::bail!(
            "unknown benchmark {:?}; available: train, load, soak, geom, method, tiles",
            a.what
        );
    }
    let backend = super::run::parse_backend(&a.backend)?;
    if a.raster_pixels != 0 && !(a.raster_pixels.is_power_of_two() && a.raster_pixels <= 16) {
        anyhow::bail!(
            "--raster-pixels must be 1, 2, 4, 8 or 16 (0: the device's default), got {}",
            a.raster_pixels
        );
    }
    let resolutions: Vec<u32> = a
        .resolution
        .split(',')
        .map(|r| r.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--resolution: {e}"))?;
    let counts: Vec<u32> = a
        .gaussians
        .split(',')
        .map(|r| r.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--gaussians: {e}"))?;
    tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
        let tmp = std::env::temp_dir().join(format!("sylva-bench-{}", std::process::id()));
        let colmap = match &a.colmap {
            Some(c) => c.clone(),
            None => {
                let preset = sylva::synth::Preset::from_name(&a.preset)
                    .ok_or_else(|| anyhow::anyhow!("unknown preset {:?}", a.preset))?;
                let p = sylva::synth::SynthParams::new(preset);
                eprintln!("generating a synthetic {} plot…", a.preset);
                sylva::synth::generate(&p, &tmp, &sylva::progress::NoProgress)?;
                tmp.join("colmap")
            }
        };
        let project = sylva::io::colmap::find_project(&colmap)?;
        let images = project
            .images_dir
            .clone()
            .ok_or_else(|| anyhow::anyhow!("{}: no images/ folder", colmap.display()))?;
        let model = sylva::io::colmap::read_model(&project.sparse_dir, &sylva::progress::NoProgress)?;
        println!(
            "| device | resolution (px) | images | Gaussians | tiles per Gaussian | steps/s | s/step | projection ms | sort ms | raster ms | loss ms | backward ms | optimiser ms | peak RSS MiB | held-out PSNR dB | GPU memory planned MiB | GPU peak allocated MiB | photos on the GPU | photo uploads |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
        for (res, count) in resolutions
            .iter()
            .flat_map(|&r| counts.iter().map(move |&c| (r, c)))
        {
            let params = TrainParams {
                steps: a.steps,
                resolution: res,
                backend,
                ..TrainParams::default()
            };
            let mut cfg = params.config();
            // Time the steps themselves: no densification; the held-out views only with
            // --heldout (evaluated after the timed steps).
            cfg.densify_until = 0;
            cfg.test_every = if a.heldout { 8 } else { 0 };
            cfg.exposure = false;
            let data = sylva::splat::dataset::load(&model, &images, cfg.resolution, cfg.test_every, cfg.host_photo_mb, &sylva::progress::NoProgress)?;
            let (mut init, _) = sylva::splat::start::sfm_gaussians(&data, count, params.seed, None)?;
            sylva::splat::start::spread_to(&mut init, count as usize, params.seed);
            let n = init.len();
            let mut backend = if a.raster_pixels > 0 && backend == TrainBackend::Gpu {
                let mut ctx = sylva::splat::gpu::GpuContext::new()?;
                ctx.raster_pixels = a.raster_pixels;
                Box::new(sylva::splat::gpu::GpuBackend::with_context(ctx, [0.0; 3])?)
                    as Box<dyn sylva::splat::backend::Backend>
            } else {
                sylva::pipeline::train::backend_for(&params)?
            };
            let plan = match a.gpu_memory_mb {
                Some(mb) => {
                    let mut c = cfg.clone();
                    c.max_gaussians = Some(n);
                    let input = sylva::splat::plan::run_input(backend.as_ref(), &data, &c, mb, false, None)
                        .ok_or_else(|| anyhow::anyhow!("--gpu-memory-mb: this backend has no GPU memory to plan (give a figure, or train on a GPU)"))?;
                    let plan = sylva::splat::plan::plan(&input)?;
                    if (plan.budget as usize) < n {
                        anyhow::bail!("{} Gaussians do not fit {} MiB: {}", n, input.device_bytes >> 20, plan.describe());
                    }
                    eprintln!("{}", plan.describe());
                    backend.set_plan(&plan)?;
                    Some(plan)
                }
                None => None,
            };
            backend.set_timed(true);
            let mut strategy = sylva::splat::trainer::default_strategy(&cfg);
            let out = sylva::splat::trainer::train(
                backend.as_mut(),
                &data,
                init,
                &cfg,
                &mut strategy,
                &sylva::progress::NoProgress,
            )?;
            let t = out.phase_times;
            let used = backend.memory_use();
            let mib = |b: u64| format!("{:.0}", b as f64 / 1048576.0);
            let steps = f64::from(cfg.steps);
            let first = data.train.first().map(|v| (v.camera.width, v.camera.height)).unwrap_or((0, 0));
            println!(
                "| {} | {}×{} | {} | {} | {} | {:.2} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {} | {} | {} | {} | {} |",
                out.device,
                first.0,
                first.1,
                data.train.len(),
                n,
                if t.intersections == 0 {
                    "–".to_string()
                } else {
                    format!("{:.1}", t.intersections as f64 / steps / n.max(1) as f64)
                },
                out.steps_per_second,
                1.0 / out.steps_per_second.max(1e-9),
                t.projection_ms / steps,
                t.sort_ms / steps,
                t.raster_ms / steps,
                t.loss_ms / steps,
                t.backward_ms / steps,
                t.optimizer_ms / steps,
                crate::loadbench::peak_rss_mib(),
                if a.heldout { format!("{:.2}", out.eval.psnr) } else { "–".into() },
                plan.as_ref().map_or("–".into(), |p| mib(p.total_bytes)),
                used.map_or("–".into(), |u| mib(u.peak_allocated_bytes)),
                plan.as_ref().map_or("all".into(), |p| if p.all_photos { "all".into() } else { format!("{} of {}", p.photo_slots, p.input.photos) }),
                used.map_or("–".into(), |u| u.photo_uploads.to_string()),
            );
            if let Some(u) = used.filter(|u| u.over_plan_steps > 0) {
                eprintln!("{} steps skipped: their tile intersections exceeded the plan's room", u.over_plan_steps);
            }
        }
        let _ = std::fs::remove_dir_all(&tmp);
        Ok(())
    })
    .await??;
    Ok(ExitCode::SUCCESS)
}
