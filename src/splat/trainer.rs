//! The training loop (docs/method.md Stage 4): views in a seeded random order, one optimisation step
//! per view on a [`Backend`], the strategy's refinement at its schedule, the SH degree schedule,
//! then the held-out evaluation. Writes nothing itself; [`write_outputs`] saves the results.

use std::path::Path;
use std::time::Instant;

use super::adam::{AdamState, LearningRates};
use super::backend::{Backend, PhaseTimes, Step, StepLoss, TrainError};
use super::config::{StrategyKind, TrainConfig};
use super::dataset::Dataset;
use super::eval::{EvalRegion, EvalReport, LossRecord, ViewMetrics, save_side_by_side, to_rgb8};
use super::exposure::EXPOSURE_FLOATS;
use super::mcmc::McmcStrategy;
use super::model::Gaussians;
use super::strategy::{DefaultStrategy, RefineReport, Strategy};
use super::trunk_diag::{TrunkDiag, TrunkMonitor};
use crate::progress::Progress;
use crate::rng::SplitMix64;

/// How often the loss is read back and recorded, steps. One read per this many steps keeps a
/// GPU backend from stalling on every step.
pub const LOSS_EVERY: u32 = 10;

/// What training produced.
#[derive(Debug, Clone)]
pub struct TrainOutcome {
    pub model: Gaussians,
    pub eval: EvalReport,
    /// PSNR of the mean training colour on the held-out views (on `eval.region`, as the
    /// model's), dB: the floor any model must beat.
    pub baseline_psnr: f32,
    pub losses: Vec<LossRecord>,
    pub refinements: Vec<(u32, RefineReport)>,
    pub device: String,
    pub seconds: f64,
    pub steps_per_second: f64,
    pub phase_times: PhaseTimes,
    /// Test renders (name, 8-bit RGB image, width, height) for saving beside the ground truth;
    /// with exposure compensation, the compensated renders. 8-bit, as their PNGs hold them:
    /// the paper's 108 held-out views at 1920×1080 take 0.7 GB so, 2.7 GB in f32.
    pub renders: Vec<(String, Vec<[u8; 3]>, u32, u32)>,
    /// With exposure compensation, every image's learned `[A | b]` (row-major 3×4, training
    /// views then held-out views); empty without. The model carries no exposure.
    pub exposures: Vec<(String, [f32; EXPOSURE_FLOATS])>,
}

/// Trains `init` on `data` for `cfg.steps` steps with `strategy`.
pub fn train(
    backend: &mut dyn Backend,
    data: &Dataset,
    init: Gaussians,
    cfg: &TrainConfig,
    strategy: &mut dyn Strategy,
    progress: &dyn Progress,
) -> Result<TrainOutcome, TrainError> {
    train_monitored(backend, data, init, cfg, strategy, None, progress)
}

/// [`train`] with the trunk monitor measuring every `monitor.every` steps (and at the last):
/// the model and the latest position gradients are read back then, never on other steps.
pub fn train_monitored(
    backend: &mut dyn Backend,
    data: &Dataset,
    init: Gaussians,
    cfg: &TrainConfig,
    strategy: &mut dyn Strategy,
    monitor: Option<&TrunkMonitor>,
    progress: &dyn Progress,
) -> Result<TrainOutcome, TrainError> {
    if init.is_empty() || !init.is_consistent() {
        return Err(TrainError::Invalid(
            "no Gaussians to train: the initialisation is empty".into(),
        ));
    }
    if cfg.exposure {
        cfg.validate_exposure().map_err(TrainError::Invalid)?;
    }
    let start = Instant::now();
    let mut model = init;
    let mut adam = AdamState::new(model.len());
    backend.set_model(&model, &adam)?;
    backend.set_step_terms(strategy.step_terms(cfg.seed))?;
    // Training steps and the held-out renders below rasterise alike.
    backend.set_render_options(cfg.render_options());
    // With exposure compensation every view trains its own transform, the held-out ones on
    // their left halves (docs/splatting.md "Exposure").
    let step_views = data.step_views(cfg.exposure);
    if step_views.is_empty() {
        return Err(TrainError::Invalid("no training views".into()));
    }
    if cfg.exposure {
        backend.set_exposures(data.train.len() + data.test.len())?;
    }
    let mut rng = SplitMix64::new(cfg.seed);
    let mut order: Vec<usize> = Vec::new();
    let mut losses = Vec::new();
    let mut refinements = Vec::new();
    let mut count = model.len();
    progress.log(&format!(
        "training {} Gaussians for {} steps on {} ({} training and {} held-out views{})",
        count,
        cfg.steps,
        backend.device_name(),
        data.train.len(),
        data.test.len(),
        if cfg.exposure {
            "; exposure compensation on: the held-out views' left halves train, their right halves are measured"
        } else {
            ""
        }
    ));
    for step in 1..=cfg.steps {
        if progress.is_cancelled() {
            return Err(TrainError::Cancelled);
        }
        if order.is_empty() {
            order = shuffled(step_views.len(), &mut rng);
        }
        let (view, slot) = step_views[order.pop().unwrap_or(0)];
        let lr = LearningRates::at(cfg, step, data.extent);
        if cfg.semantic.enabled {
            backend.set_geo_weight(cfg.semantic.gamma_at(step));
        }
        backend.step(&Step {
            view,
            exposure: slot,
            lr: &lr,
            sh_degree: cfg.sh_degree_at(step),
            stats: step < cfg.densify_until,
        })?;
        // The next step's photo, named now so a device can upload it while this step runs
        // (the next round's order is drawn here, as it would be at the next step).
        if step < cfg.steps {
            if order.is_empty() {
                order = shuffled(step_views.len(), &mut rng);
            }
            if let Some(&next) = order.last() {
                backend.prefetch(step_views[next].0)?;
            }
        }
        if strategy.wants_refine(step) {
            let stats = backend.take_stats()?;
            strategy.absorb_stats(&stats);
            (model, adam) = backend.model()?;
            let report = strategy.refine(step, &mut model, &mut adam, data.extent);
            if report != RefineReport::default()
                && (report.before != report.after || report.opacity_reset)
            {
                refinements.push((step, report));
            }
            count = model.len();
            backend.set_model(&model, &adam)?;
        }
        let measure = monitor.filter(|m| step % m.every == 0 || step == cfg.steps);
        if step % LOSS_EVERY == 0 || step == cfg.steps || measure.is_some() {
            let trunk = match measure {
                Some(m) => Some(observe_trunk(backend, m, cfg, step, progress)?),
                None => None,
            };
            let StepLoss {
                loss,
                l1,
                ssim,
                geo,
            } = backend.last_loss()?;
            if !loss.is_finite() {
                return Err(TrainError::Invalid(format!(
                    "the loss became {loss} at step {step}; lower the learning rates"
                )));
            }
            losses.push(LossRecord {
                step,
                loss,
                l1,
                ssim,
                geo,
                n_gaussians: count,
                seconds: start.elapsed().as_secs_f64(),
                trunk,
            });
            progress.set(f64::from(step) / f64::from(cfg.steps) * 0.95);
            let every = (cfg.steps / 20).max(LOSS_EVERY);
            if step % every == 0 || step == cfg.steps {
                let secs = start.elapsed().as_secs_f64();
                progress.log(&format!(
                    "step {step}/{} loss {loss:.4} (L1 {l1:.4}, SSIM {ssim:.3}) {count} Gaussians {:.2} steps/s",
                    cfg.steps,
                    f64::from(step) / secs.max(1e-9)
                ));
            }
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let (model, _) = backend.model()?;
    let heldout = evaluate_heldout(backend, data, cfg)?;
    let exposures = if cfg.exposure {
        let names = data.all_views().map(|v| v.name.clone());
        names.zip(backend.exposures()?).collect()
    } else {
        Vec::new()
    };
    progress.set(1.0);
    Ok(TrainOutcome {
        model,
        eval: heldout.eval,
        baseline_psnr: heldout.baseline_psnr,
        losses,
        refinements,
        device: backend.device_name(),
        seconds,
        steps_per_second: f64::from(cfg.steps) / seconds.max(1e-9),
        phase_times: backend.phase_times(),
        renders: heldout.renders,
        exposures,
    })
}

/// One measurement of the trunk monitor at `step`: the model and the latest position
/// gradients read back, measured and logged.
fn observe_trunk(
    backend: &mut dyn Backend,
    monitor: &TrunkMonitor,
    cfg: &TrainConfig,
    step: u32,
    progress: &dyn Progress,
) -> Result<TrunkDiag, TrainError> {
    let grads = backend.position_grads()?;
    let (now, _) = backend.model()?;
    let d = monitor.observe(&now, Some(&grads), cfg.semantic.gamma_at(step));
    progress.log(&format!(
        "step {step}: trunk Gaussians {:.1} mm from the LiDAR surface (signed {:+.1} mm, {} in the DBH slices, {:.0} % of them in L_geo's S of {}); L_geo/photometric position gradient {}",
        d.surface_abs_mm.unwrap_or(f64::NAN),
        d.surface_offset_mm.unwrap_or(f64::NAN),
        d.slice_count,
        d.slice_in_s.unwrap_or(0.0) * 100.0,
        d.s_count,
        d.geo_photo_grad_ratio.map_or("n/a".into(), |r| format!("{r:.2e}"))
    ));
    Ok(d)
}

/// The held-out views rendered and measured, beside a flat mean-colour image.
struct Heldout {
    eval: EvalReport,
    /// Mean PSNR of the mean colour over the same views and region, dB.
    baseline_psnr: f32,
    renders: Vec<(String, Vec<[u8; 3]>, u32, u32)>,
}

/// Renders and measures every held-out view: with exposure compensation each view's learned
/// exposure is applied and only its right half measured (the left half trained it).
fn evaluate_heldout(
    backend: &mut dyn Backend,
    data: &Dataset,
    cfg: &TrainConfig,
) -> Result<Heldout, TrainError> {
    let region = if cfg.exposure {
        EvalRegion::RightHalf
    } else {
        EvalRegion::Full
    };
    let mut views = Vec::new();
    let mut renders = Vec::new();
    let mean = mean_colour(data)?;
    let mut baseline = Vec::new();
    let measure = |name: &str, img: &[[f32; 3]], truth: &super::packed_image::PackedImage| {
        ViewMetrics::measure(name, img, truth, region)
            .map_err(|e| TrainError::Invalid(e.to_string()))
    };
    for (j, v) in data.test.iter().enumerate() {
        let img = if cfg.exposure {
            backend.render_exposed(&v.camera, data.train.len() + j)?
        } else {
            backend.render(&v.camera)?
        };
        let truth = v.image.image().map_err(|e| photo_error(&v.name, e))?;
        views.push(measure(&v.name, &img, &truth)?);
        let flat = vec![mean; img.len()];
        baseline.push(measure(&v.name, &flat, &truth)?.psnr);
        renders.push((
            v.name.clone(),
            to_rgb8(&img),
            v.camera.width,
            v.camera.height,
        ));
    }
    Ok(Heldout {
        eval: EvalReport::from_views_in(views, region),
        baseline_psnr: baseline.iter().sum::<f32>() / baseline.len().max(1) as f32,
        renders,
    })
}

/// A photo that could not be decoded, as a training error.
fn photo_error(name: &str, e: super::photo::PhotoError) -> TrainError {
    TrainError::Invalid(format!("{name}: {e}"))
}

/// Mean colour of the training images, RGB in [0, 1].
pub fn mean_colour(data: &Dataset) -> Result<[f32; 3], TrainError> {
    let mut sum = [0.0f64; 3];
    let mut n = 0.0f64;
    for v in &data.train {
        let img = v.image.image().map_err(|e| photo_error(&v.name, e))?;
        for p in img.to_rgb_f32() {
            for c in 0..3 {
                sum[c] += f64::from(p[c]);
            }
            n += 1.0;
        }
    }
    Ok(sum.map(|s| (s / n.max(1.0)) as f32))
}

/// The default strategy of `cfg` (reference adaptive density control).
pub fn default_strategy(cfg: &TrainConfig) -> DefaultStrategy {
    DefaultStrategy::new(cfg)
}

/// The strategy `cfg.strategy` names; MCMC without a budget is refused with the reason.
pub fn strategy_for(cfg: &TrainConfig) -> Result<Box<dyn Strategy>, TrainError> {
    Ok(match cfg.strategy {
        StrategyKind::Default => Box::new(DefaultStrategy::new(cfg)),
        StrategyKind::Mcmc => Box::new(McmcStrategy::new(cfg).map_err(TrainError::Invalid)?),
    })
}

/// Saves `splats.ply` (INRIA layout plus `trunk_prob`), `eval.json`, `loss.csv`, `loss.png`
/// and `renders/<name>.png` (render left, ground truth right) under `out`; with exposure
/// compensation also `exposure.json`, every image's learned transform.
pub fn write_outputs(out: &Path, outcome: &TrainOutcome, data: &Dataset) -> std::io::Result<()> {
    std::fs::create_dir_all(out.join("renders"))?;
    let mut ply = std::io::BufWriter::new(std::fs::File::create(out.join("splats.ply"))?);
    super::export::write_ply_with(&mut ply, &outcome.model, true)?;
    std::io::Write::flush(&mut ply)?;
    let eval = serde_json::to_vec_pretty(&outcome.eval).unwrap_or_default();
    std::fs::write(out.join("eval.json"), eval)?;
    super::eval::write_loss_csv(
        std::fs::File::create(out.join("loss.csv"))?,
        &outcome.losses,
    )?;
    super::plot::save_loss_plot(&out.join("loss.png"), &outcome.losses, 640, 360)
        .map_err(std::io::Error::other)?;
    if !outcome.exposures.is_empty() {
        let images: serde_json::Map<String, serde_json::Value> = outcome
            .exposures
            .iter()
            .map(|(name, e)| {
                let rows: Vec<&[f32]> = e.chunks(4).collect();
                (name.clone(), serde_json::json!(rows))
            })
            .collect();
        let doc = serde_json::json!({
            "layout": "per image, rows of [A | b]: out = A · rgb + b (docs/splatting.md \"Exposure\")",
            "images": images,
        });
        std::fs::write(
            out.join("exposure.json"),
            serde_json::to_vec_pretty(&doc).unwrap_or_default(),
        )?;
    }
    for ((name, img, w, h), view) in outcome.renders.iter().zip(&data.test) {
        let file = name.replace(['/', '\\'], "_");
        let stem = file.rsplit_once('.').map_or(file.as_str(), |(s, _)| s);
        let truth: Vec<[u8; 3]> = view
            .image
            .image()
            .map_err(std::io::Error::other)?
            .pixels
            .iter()
            .map(|&p| {
                let c = super::packed_image::unpack(p);
                [c[0], c[1], c[2]]
            })
            .collect();
        save_side_by_side(
            &out.join("renders").join(format!("{stem}.png")),
            img,
            &truth,
            *w,
            *h,
        )
        .map_err(std::io::Error::other)?;
    }
    Ok(())
}

/// `0..n` in a random order (Fisher–Yates with the seeded generator: the same seed visits
/// views identically); the trainer pops from the end.
fn shuffled(n: usize, rng: &mut SplitMix64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..order.len()).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        order.swap(i, j);
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;
    use crate::splat::backend::CpuBackend;
    use crate::splat::camera::Camera;
    use crate::splat::cpu;
    use crate::splat::cpu::test_scenes::{
        check_learned_exposures, grey_blobs, jitter_exposures, random_scene, ring_dataset,
    };
    use crate::splat::model::Gaussian;

    /// The default configuration of a `steps`-step run as `change` leaves it, its schedules
    /// scaled to the run.
    fn config_for(steps: u32, change: impl FnOnce(&mut TrainConfig)) -> TrainConfig {
        let mut cfg = TrainConfig {
            steps,
            ..TrainConfig::default()
        };
        change(&mut cfg);
        cfg.scaled_to(steps)
    }

    /// Trains `init` on `data` with `backend` and `cfg`'s default strategy.
    fn train_cpu(
        backend: &mut CpuBackend,
        data: &Dataset,
        init: Gaussians,
        cfg: &TrainConfig,
    ) -> TrainOutcome {
        let mut strategy = default_strategy(cfg);
        train(backend, data, init, cfg, &mut strategy, &NoProgress).expect("train")
    }

    #[test]
    fn cpu_training_beats_the_mean_colour_on_held_out_views() {
        let truth = random_scene(7, 30, 0);
        let data = ring_dataset(&truth, 16);
        let init = grey_blobs(&truth);
        let cfg = config_for(300, |_| {});
        let mut backend = CpuBackend::new([0.0; 3]);
        let out = train_cpu(&mut backend, &data, init, &cfg);
        let first = out.losses.first().expect("loss").loss;
        let last = out.losses.last().expect("loss").loss;
        assert!(last < 0.5 * first, "loss {first} -> {last}");
        assert!(
            out.eval.psnr > out.baseline_psnr + 6.0,
            "held-out PSNR {} vs baseline {}",
            out.eval.psnr,
            out.baseline_psnr
        );
        assert_eq!(out.eval.views.len(), 2);
    }

    /// Photos with known per-image exposures: with compensation on, the learned gains follow
    /// the true ones and the held-out right halves are far better rendered than without.
    #[test]
    fn exposure_compensation_learns_the_photos_exposures() {
        let truth = random_scene(7, 30, 0);
        let mut data = ring_dataset(&truth, 16);
        let exposures = jitter_exposures(&mut data, 5);
        let init = grey_blobs(&truth);
        let run = |exposure: bool| {
            let cfg = config_for(300, |c| c.exposure = exposure);
            let mut backend = CpuBackend::new([0.0; 3]);
            train_cpu(&mut backend, &data, init.clone(), &cfg)
        };
        let off = run(false);
        let on = run(true);
        assert_eq!(off.eval.region, EvalRegion::Full);
        assert!(off.exposures.is_empty());
        assert_eq!(on.exposures.len(), 16);
        check_learned_exposures(&off, &on, &data, &exposures);
    }

    /// Photos held compressed on the host (a run past `host_photo_mb`) train exactly as the
    /// same photos held decoded: the compression is lossless and every use decodes it.
    #[test]
    fn photos_held_compressed_train_exactly_as_decoded_ones() {
        let truth = random_scene(6, 16, 0);
        let data = ring_dataset(&truth, 12);
        let mut small = data.clone();
        for v in small.train.iter_mut().chain(small.test.iter_mut()) {
            v.image = v.image.clone().compressed().expect("compress");
        }
        let host = small.host_photos();
        assert_eq!((host.compressed, host.decoded), (12, 0));
        assert!(host.bytes < host.decoded_bytes, "{host:?}");
        let cfg = config_for(40, |_| {});
        let init = grey_blobs(&truth);
        let run = |d: &Dataset| {
            let mut backend = CpuBackend::new([0.0; 3]);
            train_cpu(&mut backend, d, init.clone(), &cfg)
        };
        let (a, b) = (run(&data), run(&small));
        assert_eq!(a.model, b.model);
        assert_eq!(a.eval, b.eval);
        assert_eq!(a.renders, b.renders);
        assert_eq!(a.baseline_psnr, b.baseline_psnr);
    }

    /// A configuration with the 2-D Mip filter reaches the backend: the held-out renders of the
    /// trained model are its filtered renders, not the default ones (the backend starts off).
    #[test]
    fn held_out_renders_use_the_configured_antialiasing() {
        use crate::splat::camera::RenderOptions;
        let truth = random_scene(8, 20, 0);
        let data = ring_dataset(&truth, 16);
        let cfg = config_for(20, |c| c.antialias = true);
        let mut backend = CpuBackend::new([0.0; 3]);
        let out = train_cpu(&mut backend, &data, truth.clone(), &cfg);
        assert_eq!(out.renders.len(), data.test.len());
        for ((_, img, _, _), view) in out.renders.iter().zip(&data.test) {
            let on = RenderOptions { antialias: true };
            let want = cpu::render_with(&out.model, &view.camera, [0.0; 3], on).expect("render");
            let plain = cpu::render(&out.model, &view.camera, [0.0; 3]).expect("render");
            assert_eq!(img, &to_rgb8(&want.image));
            assert_ne!(img, &to_rgb8(&plain.image));
        }
    }

    /// The same with exposure compensation on: the held-out renders are the filtered renders
    /// under each held-out photo's learned transform. Until stop 61 this path rendered without
    /// the filter, and the README demo's plot measured 1.65 dB low with it.
    #[test]
    fn exposed_held_out_renders_use_the_configured_antialiasing() {
        use crate::splat::camera::RenderOptions;
        let truth = random_scene(8, 20, 0);
        let data = ring_dataset(&truth, 16);
        let cfg = config_for(20, |c| {
            c.antialias = true;
            c.exposure = true;
        });
        let mut backend = CpuBackend::new([0.0; 3]);
        let out = train_cpu(&mut backend, &data, truth.clone(), &cfg);
        assert_eq!(out.renders.len(), data.test.len());
        let on = RenderOptions { antialias: true };
        for (j, ((_, img, _, _), view)) in out.renders.iter().zip(&data.test).enumerate() {
            let e = out.exposures[data.train.len() + j].1.map(f64::from);
            let w = view.camera.width as usize;
            let expose = |r: &cpu::Render| -> Vec<[f32; 3]> {
                cpu::exposure::apply(r.image_f64(), &e, w, None)
                    .iter()
                    .map(|p| p.map(|v| v as f32))
                    .collect()
            };
            let want = cpu::render_with(&out.model, &view.camera, [0.0; 3], on).expect("render");
            let plain = cpu::render(&out.model, &view.camera, [0.0; 3]).expect("render");
            assert_eq!(img, &to_rgb8(&expose(&want)));
            assert_ne!(img, &to_rgb8(&expose(&plain)));
        }
    }

    #[test]
    fn mcmc_training_fills_its_budget_and_fits_the_views() {
        let truth = random_scene(4, 12, 0);
        let data = ring_dataset(&truth, 16);
        let mut init = grey_blobs(&truth);
        // Two Gaussians start dead: the first refinement moves them onto live ones.
        init.opacity_logits[0] = -9.0;
        init.opacity_logits[1] = -9.0;
        let cap = 16;
        let cfg = config_for(300, |c| {
            c.max_gaussians = Some(cap);
            c.strategy = StrategyKind::Mcmc;
        });
        let mut backend = CpuBackend::new([0.0; 3]);
        let mut strategy = strategy_for(&cfg).expect("strategy");
        let out = train(
            &mut backend,
            &data,
            init,
            &cfg,
            strategy.as_mut(),
            &NoProgress,
        )
        .expect("train");
        assert!(out.losses.iter().all(|r| r.n_gaussians <= cap));
        assert_eq!(out.model.len(), cap);
        let relocated: usize = out.refinements.iter().map(|(_, r)| r.relocated).sum();
        assert!(relocated >= 2, "{:?}", out.refinements);
        assert!(
            out.eval.psnr > out.baseline_psnr + 6.0,
            "held-out PSNR {} vs baseline {}",
            out.eval.psnr,
            out.baseline_psnr
        );
    }

    #[test]
    fn lidar_depth_supervision_lowers_the_held_out_depth_error() {
        use crate::splat::depth::{DepthTargets, depth_error};
        // Opaque surfaces, as the LiDAR sees.
        let mut truth = random_scene(5, 12, 0);
        truth.opacity_logits.iter_mut().for_each(|o| *o = 4.0);
        let data = ring_dataset(&truth, 16);
        // The "LiDAR": the truth's expected depth where it covers at least half the pixel.
        let lidar = |cam: &Camera| -> Vec<f32> {
            let r = cpu::render(&truth, cam, [0.0; 3]).expect("render");
            r.depth
                .iter()
                .zip(&r.final_t)
                .map(|(&d, &t)| if t < 0.5 { d } else { 0.0 })
                .collect()
        };
        let init = grey_blobs(&truth);
        let cfg = config_for(300, |_| {});
        let run = |weight: f32| {
            let mut backend = CpuBackend::new([0.0; 3]);
            backend
                .set_depth_targets(DepthTargets {
                    weight,
                    maps: data
                        .train
                        .iter()
                        .map(|v| (v.name.clone(), lidar(&v.camera)))
                        .collect(),
                })
                .expect("targets");
            let out = train_cpu(&mut backend, &data, init.clone(), &cfg);
            let mut err = 0.0;
            for v in &data.test {
                let d = backend.render_depth(&v.camera).expect("depth");
                err += depth_error(&d, &lidar(&v.camera)).expect("pixels").0;
            }
            (out, err / data.test.len() as f64)
        };
        let (plain, e_plain) = run(0.0);
        let (guided, e_guided) = run(5.0);
        // Measured: 0.634 m without, 0.554 m with (weight 5, 300 steps on the CPU reference).
        assert!(
            e_guided < 0.92 * e_plain,
            "held-out depth error {e_plain:.4} m without, {e_guided:.4} m with the depth loss"
        );
        assert!(
            guided.eval.psnr > guided.baseline_psnr + 6.0,
            "PSNR {} (without {}) vs baseline {}",
            guided.eval.psnr,
            plain.eval.psnr,
            guided.baseline_psnr
        );
    }

    #[test]
    fn the_semantic_term_lowers_l_geo_while_the_photos_still_fit() {
        use crate::splat::semantic::{SemanticAnchors, SemanticConfig};
        let truth = random_scene(7, 30, 0);
        let data = ring_dataset(&truth, 16);
        // Every other true Gaussian is "trunk": its mean is a trunk anchor; the rest are leaves.
        let is_trunk: Vec<bool> = (0..truth.len()).map(|i| i % 2 == 0).collect();
        let anchors = SemanticAnchors::new(&truth.means, None, &is_trunk).expect("anchors");
        let mut init = Gaussians::default();
        for (m, &trunk) in truth.means.iter().zip(&is_trunk) {
            let mut g =
                Gaussian::isotropic([m[0] + 0.1, m[1] - 0.1, m[2] + 0.05], 0.15, [0.5; 3], 0.9);
            g.trunk_prob = if trunk { 1.0 } else { 0.0 };
            init.push(g);
        }
        let run = |semantic: SemanticConfig| {
            let cfg = config_for(300, |c| c.semantic = semantic);
            let mut backend = CpuBackend::new([0.0; 3]);
            backend
                .set_semantic(&anchors, &cfg.semantic)
                .expect("semantic");
            train_cpu(&mut backend, &data, init.clone(), &cfg)
        };
        let vanilla = run(SemanticConfig::default());
        // A strong weight (far above the paper's 0.02) so the pull is plain to see in 300 steps;
        // the temperature is wide because this scene's anchors are far apart.
        let strong = SemanticConfig {
            enabled: true,
            gamma_max: 5.0,
            temperature_m: 0.5,
            ..SemanticConfig::default()
        };
        let guided = run(strong.clone());
        // The ramp of a 300-step run starts at step 30: no term before, a positive one after.
        assert!(vanilla.losses.iter().all(|r| r.geo == 0.0));
        assert!(
            guided
                .losses
                .iter()
                .filter(|r| r.step <= 30)
                .all(|r| r.geo == 0.0)
        );
        assert!(
            guided
                .losses
                .iter()
                .filter(|r| r.step > 30)
                .any(|r| r.geo > 0.0)
        );
        // L_geo of the final models, by its own definition: the guided one is far lower.
        let geo_of = |m: &Gaussians| {
            let t = crate::splat::semantic::geo_targets(m, &anchors, &strong);
            crate::splat::semantic::geo_loss_and_grad(m, &t, anchors.n_pos).0
        };
        let (before, after) = (geo_of(&vanilla.model), geo_of(&guided.model));
        assert!(
            after < 0.3 * before,
            "L_geo {before:.4} vanilla vs {after:.4} guided"
        );
        assert!(guided.eval.psnr > guided.baseline_psnr + 3.0);
    }
}
