//! Where the training steps run. The loop in [`super::trainer`] drives a [`Backend`]: the GPU
//! one ([`super::gpu`]) for real work, or [`CpuBackend`], the plain-Rust reference (f64 inside),
//! which trains tiny scenes slowly and serves to test the loop and to check the GPU.
//!
//! A backend owns the model and the optimiser state while it trains; the loop asks for them
//! back only when the strategy refines or training ends, so a GPU backend reads nothing back
//! on ordinary steps except, now and then, the loss.

use super::adam::{AdamState, LearningRates};
use super::bind::{self, BindConfig};
use super::camera::{Camera, RenderOptions};
use super::cameras::View;
use super::cpu;
use super::depth::{self, DepthTargets};
use super::exposure::{EXPOSURE_FLOATS, ExposureSlot, ExposureState};
use super::mcmc::{self, StepTerms};
use super::model::Gaussians;
use super::plan::MemoryPlan;
use super::semantic::{self, SemanticAnchors, SemanticConfig};
use super::strategy::DensifyStats;

/// Why training failed.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// No GPU adapter, or the GPU failed; the message says what to install or change.
    #[error("{0}")]
    Device(String),
    /// Inconsistent model or images.
    #[error("{0}")]
    Invalid(String),
    #[error("cancelled")]
    Cancelled,
}

/// Loss of the latest step: the photometric total with its L1 and SSIM parts, and the
/// semantic term L_geo before its weight gamma (0 while the term is off).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StepLoss {
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    pub geo: f32,
}

/// Milliseconds spent per phase since the backend started (summed over steps).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct PhaseTimes {
    pub projection_ms: f64,
    pub sort_ms: f64,
    pub raster_ms: f64,
    pub loss_ms: f64,
    pub backward_ms: f64,
    pub optimizer_ms: f64,
    /// Tile–Gaussian intersections (16×16 px tiles) summed over the steps; 0 where a backend
    /// does not bin by tiles (the CPU reference).
    pub intersections: u64,
}

/// What kind of device runs the steps; it sets the default Gaussian budget
/// ([`super::budget::default_budget`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DeviceKind {
    /// A hardware GPU (discrete, integrated or virtual).
    Gpu,
    /// A GPU API implemented on the CPU (Mesa's lavapipe, SwiftShader): wgpu's `DeviceType::Cpu`.
    SoftwareGpu,
    /// [`CpuBackend`], the plain-Rust reference.
    CpuReference,
}

impl DeviceKind {
    /// The name used in reports.
    pub fn as_str(self) -> &'static str {
        match self {
            DeviceKind::Gpu => "gpu",
            DeviceKind::SoftwareGpu => "software_gpu",
            DeviceKind::CpuReference => "cpu_reference",
        }
    }
}

/// What one optimisation step ([`Backend::step`]) trains on, and how.
#[derive(Clone, Copy)]
pub struct Step<'a> {
    /// The photo and its camera.
    pub view: &'a View,
    /// The image's learned exposure, applied to the render before the loss and trained with it
    /// (rate `lr.exposure`; docs/splatting.md "Exposure"); its index must be below the count
    /// given to [`Backend::set_exposures`].
    pub exposure: Option<ExposureSlot>,
    /// The learning rates of this step.
    pub lr: &'a LearningRates,
    /// The spherical-harmonics degree in use.
    pub sh_degree: u32,
    /// Accumulate the view-space statistics for densification.
    pub stats: bool,
}

/// One place the training steps can run.
pub trait Backend {
    /// Human-readable device name (e.g. the GPU adapter).
    fn device_name(&self) -> String;
    /// The kind of device (see [`DeviceKind`]).
    fn device_kind(&self) -> DeviceKind;
    /// Installs `model` and its optimiser state (at start and after every refinement).
    fn set_model(&mut self, model: &Gaussians, adam: &AdamState) -> Result<(), TrainError>;
    /// One optimisation step (see [`Step`]): render, loss, backward, Adam.
    fn step(&mut self, step: &Step<'_>) -> Result<(), TrainError>;
    /// Installs `n` per-image exposure transforms (docs/splatting.md "Exposure"), each the
    /// identity with zero Adam moments; 0 removes them. They live apart from the model:
    /// [`Backend::set_model`] leaves them as they are.
    fn set_exposures(&mut self, n: usize) -> Result<(), TrainError>;
    /// The learned transforms, `[A | b]` row-major per image (a GPU backend reads them back
    /// here); empty without exposures.
    fn exposures(&mut self) -> Result<Vec<[f32; EXPOSURE_FLOATS]>, TrainError>;
    /// Renders the current model from `camera` with the learned exposure of image `index`
    /// applied (RGB, row-major), with the options of [`Backend::set_render_options`] as
    /// [`Backend::render`]: the held-out metrics with exposure compensation are of the mode
    /// the model was trained in.
    fn render_exposed(
        &mut self,
        camera: &Camera,
        index: usize,
    ) -> Result<Vec<[f32; 3]>, TrainError>;
    /// Installs the labelled anchors of the semantic term L_geo (docs/method.md Stage 4). The term
    /// stays off until [`Backend::set_geo_weight`] gives it a positive weight.
    fn set_semantic(
        &mut self,
        anchors: &SemanticAnchors,
        cfg: &SemanticConfig,
    ) -> Result<(), TrainError>;
    /// The weight gamma of L_geo for the following steps (0 turns it off).
    fn set_geo_weight(&mut self, gamma: f32);
    /// Installs Sylva's trunk binding ([`crate::splat::bind`]) on the labelled anchors (with
    /// their normals): from the next step on, every bound Gaussian is projected onto the LiDAR
    /// surface after each optimiser step.
    fn set_bind(&mut self, anchors: &SemanticAnchors, cfg: &BindConfig) -> Result<(), TrainError>;
    /// Installs (or, with `None`, removes) what a strategy adds to every step on the device:
    /// the MCMC position noise and regularisers ([`crate::splat::mcmc`]).
    fn set_step_terms(&mut self, terms: Option<StepTerms>) -> Result<(), TrainError>;
    /// Installs LiDAR depth maps of the training views and the weight of the depth loss
    /// ([`crate::splat::depth`]); a weight of 0 turns the loss off.
    fn set_depth_targets(&mut self, targets: DepthTargets) -> Result<(), TrainError>;
    /// Renders the expected depth Σ T α z from `camera`, metres per pixel (row-major), with the
    /// options of [`Backend::set_render_options`].
    fn render_depth(&mut self, camera: &Camera) -> Result<Vec<f32>, TrainError>;
    /// dL/d(mean) of the latest step, per Gaussian (photometric plus L_geo when it is on);
    /// a GPU backend reads it back here, so call it only now and then (diagnostics).
    fn position_grads(&mut self) -> Result<Vec<[f32; 3]>, TrainError>;
    /// The loss of the latest step (a GPU backend reads it back here).
    fn last_loss(&mut self) -> Result<StepLoss, TrainError>;
    /// The accumulated statistics, which are then reset.
    fn take_stats(&mut self) -> Result<DensifyStats, TrainError>;
    /// The current model and optimiser state.
    fn model(&mut self) -> Result<(Gaussians, AdamState), TrainError>;
    /// How every later step and [`Backend::render`] rasterise (default: [`RenderOptions`]'s);
    /// the trainer sets its configuration's at the start, so that the held-out renders of a
    /// model use the mode it was trained with.
    fn set_render_options(&mut self, options: RenderOptions);
    /// Renders the current model from `camera` (RGB in [0, 1], row-major) with the options of
    /// [`Backend::set_render_options`].
    fn render(&mut self, camera: &Camera) -> Result<Vec<[f32; 3]>, TrainError>;
    /// Time spent per phase so far.
    fn phase_times(&self) -> PhaseTimes;
    /// Wait for the device after every phase so that [`Backend::phase_times`] are exact
    /// (slower; for benchmarks). Backends that run synchronously ignore it.
    fn set_timed(&mut self, _timed: bool) {}
    /// The device's own memory, bytes, where the backend can tell (a GPU's driver); `None`
    /// for the CPU reference, which trains in host memory.
    fn device_memory(&self) -> Option<u64> {
        None
    }
    /// Follows `plan` from now on ([`crate::splat::plan`]): at most its photo slots on the
    /// device, and no step past its tile intersections (such a step is skipped and counted
    /// in [`MemoryUse::over_plan_steps`]). The CPU reference keeps everything in host memory
    /// and has nothing to plan.
    fn set_plan(&mut self, _plan: &MemoryPlan) -> Result<(), TrainError> {
        Ok(())
    }
    /// Names the photo the next step trains on, so a device can upload it while the current
    /// step runs. The CPU reference reads photos from host memory and needs no notice.
    fn prefetch(&mut self, _view: &View) -> Result<(), TrainError> {
        Ok(())
    }
    /// What the device's memory held at most so far and how the photos moved; `None` where
    /// the backend does not measure it (the CPU reference).
    fn memory_use(&self) -> Option<MemoryUse> {
        None
    }
}

/// What a device's memory held during a run ([`Backend::memory_use`]), bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct MemoryUse {
    /// The most the allocator had given to live buffers, sampled at the end of every step
    /// (when the step's buffers all exist) and after every upload of the model; 0 where the
    /// driver gives no allocator report.
    pub peak_allocated_bytes: u64,
    /// The most it had reserved in memory blocks (what the device really gives up).
    pub peak_reserved_bytes: u64,
    /// Photos written to the device, and steps whose photo was already there.
    pub photo_uploads: u64,
    pub photo_hits: u64,
    /// Steps skipped because their tile intersections exceeded the plan's room.
    pub over_plan_steps: u64,
    /// The most tile intersections one step had.
    pub max_intersections: u64,
}

/// The CPU reference as a backend (see the module docs).
pub struct CpuBackend {
    model: Gaussians,
    adam: AdamState,
    stats: DensifyStats,
    loss: StepLoss,
    background: [f32; 3],
    options: RenderOptions,
    times: PhaseTimes,
    semantic: Option<(semantic::AnchorIndex, f32, SemanticConfig)>,
    gamma: f32,
    bind: Option<(semantic::AnchorIndex, BindConfig)>,
    /// dL/d(mean) of the latest step.
    last_mean_grads: Vec<[f32; 3]>,
    /// The strategy's per-step terms (MCMC), if any, and the flags of the model's Gaussians
    /// under them (set with the model or the terms).
    terms: Option<StepTerms>,
    mcmc_flags: Vec<u32>,
    /// LiDAR depth supervision.
    depth: DepthTargets,
    /// The per-image exposures and their Adam state.
    exposure: ExposureState,
}

impl CpuBackend {
    pub fn new(background: [f32; 3]) -> Self {
        CpuBackend {
            model: Gaussians::default(),
            adam: AdamState::new(0),
            stats: DensifyStats::default(),
            loss: StepLoss::default(),
            background,
            options: RenderOptions::default(),
            times: PhaseTimes::default(),
            semantic: None,
            gamma: 0.0,
            bind: None,
            last_mean_grads: Vec::new(),
            terms: None,
            mcmc_flags: Vec::new(),
            depth: DepthTargets::default(),
            exposure: ExposureState::new(0),
        }
    }
}

/// Why an exposure slot cannot be used with `n` installed exposures.
pub(crate) fn check_slot(slot: usize, n: usize) -> Result<(), TrainError> {
    if slot >= n {
        return Err(TrainError::Invalid(format!(
            "exposure of image {slot} asked for, but {n} exposures are installed"
        )));
    }
    Ok(())
}

fn invalid(e: impl std::fmt::Display) -> TrainError {
    TrainError::Invalid(e.to_string())
}

fn ms(t: std::time::Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1000.0
}

impl Backend for CpuBackend {
    fn device_name(&self) -> String {
        format!("cpu reference ({} threads)", rayon::current_num_threads())
    }

    fn device_kind(&self) -> DeviceKind {
        DeviceKind::CpuReference
    }

    fn set_model(&mut self, model: &Gaussians, adam: &AdamState) -> Result<(), TrainError> {
        if !model.is_consistent() || adam.len() != model.len() {
            return Err(invalid("model and optimiser state disagree in size"));
        }
        self.model = model.clone();
        self.adam = adam.clone();
        self.stats = DensifyStats::zeros(model.len());
        if let Some(t) = self.terms.as_ref() {
            self.mcmc_flags = mcmc::flags(&model.trunk_prob, t);
        }
        Ok(())
    }

    fn step(&mut self, step: &Step<'_>) -> Result<(), TrainError> {
        let view = step.view;
        if let Some(slot) = step.exposure {
            check_slot(slot.index, self.exposure.len())?;
        }
        self.model.sh_degree = step.sh_degree;
        let t = std::time::Instant::now();
        let render = cpu::render_with(&self.model, &view.camera, self.background, self.options)
            .map_err(invalid)?;
        self.times.raster_ms += ms(t);
        let t = std::time::Instant::now();
        let target = view.image.image().map_err(invalid)?.to_rgb_f32();
        let (w, h) = (view.camera.width, view.camera.height);
        // With an exposure: loss of the exposed render, then back through the transform.
        let mut exposure_grad = None;
        let (loss, grad) = match step.exposure {
            None => cpu::loss_and_grad(&render.image, &target, w, h).map_err(invalid)?,
            Some(slot) => {
                let e = self.exposure.params[slot.index].map(f64::from);
                let target64: Vec<[f64; 3]> = target.iter().map(|p| p.map(f64::from)).collect();
                let right = slot.left_half.then_some(target64.as_slice());
                let out = cpu::exposure::apply(render.image_f64(), &e, w as usize, right);
                let (loss, dl_dout) =
                    cpu::loss_and_grad_f64(&out, &target64, w, h).map_err(invalid)?;
                let (dl_drgb, de) = cpu::exposure::backward(
                    render.image_f64(),
                    &e,
                    &dl_dout,
                    w as usize,
                    slot.left_half,
                );
                exposure_grad = Some((slot.index, de.map(|v| v as f32)));
                let grad = dl_drgb.iter().map(|p| p.map(|v| v as f32)).collect();
                (loss, grad)
            }
        };
        self.times.loss_ms += ms(t);
        let t = std::time::Instant::now();
        let depth_grad = self
            .depth
            .for_view(&view.name)
            .map(|map| depth::loss_and_grad(&render.depth, map, self.depth.weight).1);
        let (mut grads, grad_stat) =
            cpu::render_backward(&self.model, &render, &grad, depth_grad.as_deref())
                .map_err(invalid)?;
        let mut geo = 0.0;
        if let Some((index, n_pos, cfg)) = self.semantic.as_ref().filter(|_| self.gamma > 0.0) {
            let targets = semantic::geo_targets_indexed(&self.model, index, cfg);
            let (l, d_mu, d_s) = semantic::geo_loss_and_grad(&self.model, &targets, *n_pos);
            let gamma = f64::from(self.gamma);
            for i in 0..self.model.len() {
                for a in 0..3 {
                    grads.means[i][a] += (gamma * d_mu[i][a]) as f32;
                    grads.log_scales[i][a] += (gamma * d_s[i][a]) as f32;
                }
            }
            geo = l as f32;
        }
        if let Some(terms) = self.terms.as_ref() {
            mcmc::regularise_grads(
                &self.model,
                &self.mcmc_flags,
                terms,
                &mut grads.opacity_logits,
                &mut grads.log_scales,
            );
        }
        self.times.backward_ms += ms(t);
        if step.stats {
            let radii: Vec<f32> = render
                .projected
                .iter()
                .map(|p| if p.visible { p.radius as f32 } else { 0.0 })
                .collect();
            self.stats.add_view(&grad_stat, &radii);
        }
        let t = std::time::Instant::now();
        self.adam
            .step(&mut self.model, &grads, step.lr)
            .map_err(invalid)?;
        if let Some(terms) = self.terms.as_ref() {
            mcmc::add_noise(
                &mut self.model,
                &self.mcmc_flags,
                terms,
                step.lr.position,
                self.adam.step,
            );
        }
        if let Some((index, de)) = exposure_grad {
            self.exposure.adam_step(index, &de, step.lr.exposure);
        }
        if let Some((index, cfg)) = self.bind.as_ref() {
            bind::project(&mut self.model, index, cfg);
        }
        self.last_mean_grads = grads.means;
        self.times.optimizer_ms += ms(t);
        self.loss = StepLoss {
            loss: loss.loss as f32,
            l1: loss.l1 as f32,
            ssim: loss.ssim as f32,
            geo,
        };
        Ok(())
    }

    fn set_exposures(&mut self, n: usize) -> Result<(), TrainError> {
        self.exposure = ExposureState::new(n);
        Ok(())
    }

    fn exposures(&mut self) -> Result<Vec<[f32; EXPOSURE_FLOATS]>, TrainError> {
        Ok(self.exposure.params.clone())
    }

    fn render_exposed(
        &mut self,
        camera: &Camera,
        index: usize,
    ) -> Result<Vec<[f32; 3]>, TrainError> {
        check_slot(index, self.exposure.len())?;
        let render = cpu::render_with(&self.model, camera, self.background, self.options)
            .map_err(invalid)?;
        let e = self.exposure.params[index].map(f64::from);
        let out = cpu::exposure::apply(render.image_f64(), &e, camera.width as usize, None);
        Ok(out.iter().map(|p| p.map(|v| v as f32)).collect())
    }

    fn set_semantic(
        &mut self,
        anchors: &SemanticAnchors,
        cfg: &SemanticConfig,
    ) -> Result<(), TrainError> {
        cfg.validate().map_err(TrainError::Invalid)?;
        let index = semantic::AnchorIndex::new(anchors)
            .ok_or_else(|| TrainError::Invalid("the semantic term needs trunk anchors".into()))?;
        self.semantic = Some((index, anchors.n_pos, cfg.clone()));
        Ok(())
    }

    fn set_geo_weight(&mut self, gamma: f32) {
        self.gamma = gamma;
    }

    fn set_bind(&mut self, anchors: &SemanticAnchors, cfg: &BindConfig) -> Result<(), TrainError> {
        cfg.validate().map_err(TrainError::Invalid)?;
        let index = semantic::AnchorIndex::new(anchors)
            .ok_or_else(|| TrainError::Invalid("the trunk binding needs trunk anchors".into()))?;
        self.bind = Some((index, cfg.clone()));
        Ok(())
    }

    fn set_step_terms(&mut self, terms: Option<StepTerms>) -> Result<(), TrainError> {
        self.terms = terms;
        self.mcmc_flags = terms.map_or_else(Vec::new, |t| mcmc::flags(&self.model.trunk_prob, &t));
        Ok(())
    }

    fn set_depth_targets(&mut self, targets: DepthTargets) -> Result<(), TrainError> {
        self.depth = targets;
        Ok(())
    }

    fn render_depth(&mut self, camera: &Camera) -> Result<Vec<f32>, TrainError> {
        Ok(
            cpu::render_with(&self.model, camera, self.background, self.options)
                .map_err(invalid)?
                .depth,
        )
    }

    fn position_grads(&mut self) -> Result<Vec<[f32; 3]>, TrainError> {
        Ok(self.last_mean_grads.clone())
    }

    fn last_loss(&mut self) -> Result<StepLoss, TrainError> {
        Ok(self.loss)
    }

    fn take_stats(&mut self) -> Result<DensifyStats, TrainError> {
        Ok(std::mem::replace(
            &mut self.stats,
            DensifyStats::zeros(self.model.len()),
        ))
    }

    fn model(&mut self) -> Result<(Gaussians, AdamState), TrainError> {
        Ok((self.model.clone(), self.adam.clone()))
    }

    fn set_render_options(&mut self, options: RenderOptions) {
        self.options = options;
    }

    fn render(&mut self, camera: &Camera) -> Result<Vec<[f32; 3]>, TrainError> {
        Ok(
            cpu::render_with(&self.model, camera, self.background, self.options)
                .map_err(invalid)?
                .image,
        )
    }

    fn phase_times(&self) -> PhaseTimes {
        self.times
    }
}
