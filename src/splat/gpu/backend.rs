//! The trainer's GPU backend: the model, its gradients and the Adam moments live on the GPU;
//! one step is the forward render (one 4-byte read of the intersection count, which sizes the
//! sort), then the fused loss, the backward passes and Adam recorded into one command buffer.
//! Training images are uploaded packed RGBA8 on first use and stay on the GPU, or, under a
//! memory plan ([`crate::splat::plan`]), share a fixed number of slots ([`super::photos`]);
//! the allocator's figures are sampled after every step and model upload
//! ([`Backend::memory_use`]). The loss is read back
//! only when the loop asks for it; the model, the moments and the densification statistics only
//! when the strategy refines.

use std::time::Instant;

use super::adam::{AdamRates, GpuAdam, MomentPair};
use super::buffers::{read_buffer, storage_zeroed};
use super::exposure::{ExposureScratch, GpuExposure};
use super::loss::{LOSS_OUT_BYTES, LossKernel};
use super::photos::PhotoCache;
use super::{GpuContext, GpuError, GpuGrads, GpuSplats, Renderer};
use crate::splat::adam::{AdamState, Moments};
use crate::splat::backend::{
    Backend, DeviceKind, MemoryUse, PhaseTimes, Step, StepLoss, TrainError,
};
use crate::splat::bind::BindConfig;
use crate::splat::camera::{Camera, RenderOptions};
use crate::splat::cameras::View;
use crate::splat::exposure::{EXPOSURE_FLOATS, ExposureSlot};
use crate::splat::model::Gaussians;
use crate::splat::plan::MemoryPlan;
use crate::splat::semantic::{SemanticAnchors, SemanticConfig};
use crate::splat::strategy::DensifyStats;

use super::depth::DepthLoss;
use super::mcmc::GpuMcmc;
use super::semantic::GpuSemantic;
use crate::splat::depth::DepthTargets;
use crate::splat::mcmc::StepTerms;

impl From<GpuError> for TrainError {
    fn from(e: GpuError) -> Self {
        TrainError::Device(e.to_string())
    }
}

/// Steps a run may skip for exceeding the memory plan's tile intersections before it fails
/// (or a tenth of its steps, when more): a few large early Gaussians may pass the room once or
/// twice; more means the plan does not fit the scene.
pub const MAX_OVER_PLAN_STEPS: u64 = 5;

/// The model and optimiser on the GPU.
struct OnDevice {
    splats: GpuSplats,
    grads: GpuGrads,
    adam: GpuAdam,
    /// Trunk probabilities stay on the CPU (not trained); kept to rebuild the model.
    trunk_prob: Vec<f32>,
}

/// See the module documentation.
pub struct GpuBackend {
    ctx: GpuContext,
    renderer: Renderer,
    loss: LossKernel,
    background: [f32; 3],
    options: RenderOptions,
    state: Option<OnDevice>,
    /// The photos (and depth maps) on the GPU.
    photos: PhotoCache,
    /// The photo of the latest step (a prefetch does not take its slot).
    current: Option<String>,
    /// Tile intersections a training step may have (the plan's; `None`: no limit).
    max_intersections: Option<u64>,
    memory: MemoryUse,
    /// Training steps asked for so far (skipped ones included).
    steps: u64,
    /// dL/dimage and the loss of the latest step, resized with the image.
    dl_dimage: Option<(usize, wgpu::Buffer)>,
    loss_out: wgpu::Buffer,
    times: PhaseTimes,
    /// Wait for the GPU after every pass so the phase times are true (slower; for benchmarks).
    timed: bool,
    /// The semantic term's anchors and scratch, once installed, and its current weight.
    semantic: Option<GpuSemantic>,
    gamma: f32,
    /// Sylva's trunk binding, once installed (its anchors are those of `semantic`).
    bind: Option<BindConfig>,
    /// The strategy's per-step terms (MCMC noise and regularisers), once installed.
    mcmc: Option<GpuMcmc>,
    /// LiDAR depth supervision: the maps (uploaded per view on first use) and the kernel.
    depth: DepthTargets,
    depth_loss: DepthLoss,
    /// The per-image exposures, once installed, and their per-step buffers (resized with the
    /// image).
    exposure: Option<GpuExposure>,
    exposure_scratch: Option<ExposureScratch>,
}

impl GpuBackend {
    /// Finds an adapter and compiles the kernels; a clear error without one.
    pub fn new(background: [f32; 3]) -> Result<Self, TrainError> {
        Self::with_context(GpuContext::new()?, background)
    }

    /// As [`GpuBackend::new`] on a given context (e.g. one with a small
    /// [`GpuContext::chunk_cap_bytes`], to exercise chunking).
    pub fn with_context(ctx: GpuContext, background: [f32; 3]) -> Result<Self, TrainError> {
        let renderer = Renderer::new(&ctx);
        let loss = LossKernel::new(&ctx.device);
        let depth_loss = DepthLoss::new(&ctx);
        let loss_out = storage_zeroed(&ctx, "loss out", LOSS_OUT_BYTES)?;
        Ok(GpuBackend {
            ctx,
            renderer,
            loss,
            background,
            options: RenderOptions::default(),
            state: None,
            photos: PhotoCache::default(),
            current: None,
            max_intersections: None,
            memory: MemoryUse::default(),
            steps: 0,
            dl_dimage: None,
            loss_out,
            times: PhaseTimes::default(),
            timed: false,
            semantic: None,
            gamma: 0.0,
            bind: None,
            mcmc: None,
            depth: DepthTargets::default(),
            depth_loss,
            exposure: None,
            exposure_scratch: None,
        })
    }

    /// The exposures on the GPU, checked to hold image `index`.
    fn exposure_for(&self, index: usize) -> Result<&GpuExposure, TrainError> {
        let n = self.exposure.as_ref().map_or(0, GpuExposure::count);
        crate::splat::backend::check_slot(index, n)?;
        self.exposure
            .as_ref()
            .ok_or_else(|| TrainError::Invalid("no exposures on the GPU".into()))
    }

    /// Makes the exposure scratch fit images of `pixels` pixels.
    fn exposure_scratch_for(&mut self, pixels: usize) -> Result<(), TrainError> {
        if self
            .exposure_scratch
            .as_ref()
            .is_none_or(|s| s.pixels != pixels)
        {
            self.exposure_scratch = Some(ExposureScratch::new(&self.ctx, pixels)?);
        }
        Ok(())
    }

    fn state(&self) -> Result<&OnDevice, TrainError> {
        self.state
            .as_ref()
            .ok_or_else(|| TrainError::Invalid("no model on the GPU yet".into()))
    }

    /// Puts `view`'s photo and depth map on the GPU, keeping the slot of `keep`.
    fn resident(&mut self, view: &View, keep: Option<&str>) -> Result<(), TrainError> {
        let map = self.depth.for_view(&view.name);
        let depth = map.map(|m| (m, crate::splat::depth::valid_count(m)));
        self.photos.ensure(&self.ctx, view, depth, keep)?;
        Ok(())
    }

    /// A render of the current model (no step): within the plan's tile intersections like a
    /// step, failing with what to change where a view needs more.
    fn frame(&self, camera: &Camera, options: RenderOptions) -> Result<super::Frame, TrainError> {
        let state = self.state()?;
        self.renderer
            .render_passes_limited(
                &self.ctx,
                &state.splats,
                camera,
                self.background,
                options,
                false,
                self.max_intersections,
            )
            .map(|(f, _)| f)
            .map_err(|e| match e {
                GpuError::OverPlan { .. } => TrainError::Device(format!(
                    "rendering a view: {e}; raise params.train.gpu_memory_mb, or train at a lower resolution or with a smaller budget"
                )),
                e => e.into(),
            })
    }

    /// Samples the allocator's figures into the peaks.
    fn sample_memory(&mut self) {
        if let Some((allocated, reserved)) = self.ctx.allocated_bytes() {
            let m = &mut self.memory;
            m.peak_allocated_bytes = m.peak_allocated_bytes.max(allocated);
            m.peak_reserved_bytes = m.peak_reserved_bytes.max(reserved);
        }
    }

    fn wait_ms(&self, t: Instant) -> Result<f64, TrainError> {
        if self.timed {
            self.ctx.wait()?;
        }
        Ok(t.elapsed().as_secs_f64() * 1000.0)
    }
}

fn moments_pair(m: &Moments) -> MomentPair {
    (m.m.clone(), m.v.clone())
}

fn to_moments(stride: usize, p: &MomentPair) -> Moments {
    Moments {
        stride,
        m: p.0.clone(),
        v: p.1.clone(),
    }
}

impl GpuBackend {
    /// The buffers a step on `view` needs, made or uploaded once: dL/dimage at the view's
    /// size, the exposure and its scratch when the view trains one, the photo, and the
    /// view's LiDAR depth map when the depth loss has one.
    fn step_buffers(
        &mut self,
        view: &View,
        exposure: Option<ExposureSlot>,
    ) -> Result<(), TrainError> {
        let pixels = view.camera.width as usize * view.camera.height as usize;
        if self.dl_dimage.as_ref().is_none_or(|(n, _)| *n != pixels) {
            let buf = storage_zeroed(&self.ctx, "dL/dimage", pixels as u64 * 12)?;
            self.dl_dimage = Some((pixels, buf));
        }
        if let Some(slot) = exposure {
            self.exposure_for(slot.index)?;
            self.exposure_scratch_for(pixels)?;
        }
        self.resident(view, None)?;
        self.current = Some(view.name.clone());
        Ok(())
    }
}

/// Submits what `enc` recorded and waits for it (a timed step's phase boundary); returns a
/// fresh encoder.
fn submit_and_wait(
    ctx: &GpuContext,
    enc: wgpu::CommandEncoder,
) -> Result<wgpu::CommandEncoder, TrainError> {
    ctx.queue.submit([enc.finish()]);
    ctx.wait()?;
    Ok(ctx.device.create_command_encoder(&Default::default()))
}

impl Backend for GpuBackend {
    fn device_name(&self) -> String {
        self.ctx.description.to_string()
    }

    fn device_kind(&self) -> DeviceKind {
        if self.ctx.adapter.get_info().device_type == wgpu::DeviceType::Cpu {
            DeviceKind::SoftwareGpu
        } else {
            DeviceKind::Gpu
        }
    }

    fn set_model(&mut self, model: &Gaussians, adam: &AdamState) -> Result<(), TrainError> {
        if adam.len() != model.len() {
            return Err(TrainError::Invalid(
                "model and optimiser state disagree in size".into(),
            ));
        }
        // The old model goes first, so a refinement never holds two models at once (the GPU
        // has finished with it: the strategy read it back before refining).
        self.state = None;
        let splats = GpuSplats::upload(&self.ctx, model)?;
        let grads = GpuGrads::new(&self.ctx, splats.count)?;
        let moments = [
            moments_pair(&adam.means),
            moments_pair(&adam.log_scales),
            moments_pair(&adam.rotations),
            moments_pair(&adam.opacity_logits),
            moments_pair(&adam.sh),
        ];
        let gpu_adam = GpuAdam::from_moments(&self.ctx, splats.count, adam.step, &moments)?;
        if let Some(sem) = self.semantic.as_mut() {
            sem.set_model(&self.ctx, &model.trunk_prob)?;
        }
        if let Some(m) = self.mcmc.as_mut() {
            m.set_model(&self.ctx, &model.trunk_prob)?;
        }
        self.state = Some(OnDevice {
            splats,
            grads,
            adam: gpu_adam,
            trunk_prob: model.trunk_prob.clone(),
        });
        self.sample_memory();
        Ok(())
    }

    fn step(&mut self, step: &Step<'_>) -> Result<(), TrainError> {
        let Step {
            view,
            exposure,
            lr,
            sh_degree,
            ..
        } = *step;
        let (w, h) = (view.camera.width, view.camera.height);
        self.step_buffers(view, exposure)?;
        self.steps += 1;
        let t = Instant::now();
        let state = self
            .state
            .as_mut()
            .ok_or_else(|| TrainError::Invalid("no model on the GPU yet".into()))?;
        state.splats.sh_degree = sh_degree.min(3);
        // Timed: wait after projection (with its read-back), sort and raster so that each lands
        // in its own column; untimed, the forward's GPU work finishes inside later phases.
        let rendered = self.renderer.render_passes_limited(
            &self.ctx,
            &state.splats,
            &view.camera,
            self.background,
            self.options,
            self.timed,
            self.max_intersections,
        );
        let (frame, pt) = match rendered {
            Err(GpuError::OverPlan {
                intersections,
                limit,
            }) => {
                // Past the plan's room: skip the step rather than allocate past the plan; a run
                // where that is common has too little memory for its Gaussians at this size.
                self.memory.over_plan_steps += 1;
                self.memory.max_intersections = self.memory.max_intersections.max(intersections);
                if self.memory.over_plan_steps > MAX_OVER_PLAN_STEPS.max(self.steps / 10) {
                    return Err(TrainError::Device(format!(
                        "{} of {} steps had more tile intersections than the memory plan has room for ({intersections} against {limit}, {:.1} per Gaussian): raise params.train.gpu_memory_mb, or train at a lower resolution or with a smaller budget",
                        self.memory.over_plan_steps,
                        self.steps,
                        intersections as f64 / f64::from(state.splats.count.max(1)),
                    )));
                }
                return Ok(());
            }
            r => r?,
        };
        self.memory.max_intersections = self
            .memory
            .max_intersections
            .max(u64::from(frame.intersections));
        if self.timed {
            self.times.projection_ms += pt.project_ms;
            self.times.sort_ms += pt.sort_ms;
            self.times.raster_ms += pt.raster_ms;
        } else {
            self.times.raster_ms += t.elapsed().as_secs_f64() * 1000.0;
        }
        self.times.intersections += u64::from(frame.intersections);
        let resident = self.photos.get(&view.name);
        let (Some(target), Some((_, dl))) = (resident.map(|r| &r.photo), self.dl_dimage.as_ref())
        else {
            return Err(TrainError::Invalid("internal: missing step buffers".into()));
        };
        // With an exposure the loss sees the exposed render and writes dL/d(exposed render);
        // the exposure backward then fills `dl` for the raster backward.
        let exposed = match (exposure, &self.exposure, &self.exposure_scratch) {
            (Some(slot), Some(ex), Some(sc)) => Some((slot, ex, sc)),
            (Some(_), _, _) => {
                return Err(TrainError::Invalid(
                    "internal: missing exposure buffers".into(),
                ));
            }
            (None, _, _) => None,
        };
        let t = Instant::now();
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        let (loss_in, loss_grad) = match exposed {
            Some((slot, ex, sc)) => {
                ex.encode_apply(
                    &self.ctx,
                    &mut enc,
                    &frame.image,
                    Some(target),
                    sc,
                    w,
                    h,
                    slot,
                )?;
                (&sc.exposed, &sc.dl_out)
            }
            None => (&frame.image, dl),
        };
        self.loss
            .encode(
                &self.ctx.device,
                &mut enc,
                loss_in,
                target,
                loss_grad,
                &self.loss_out,
                w,
                h,
            )
            .map_err(|e| TrainError::Invalid(e.to_string()))?;
        if self.depth.weight > 0.0
            && let Some((map, valid)) = resident.and_then(|r| r.depth.as_ref())
        {
            self.depth_loss
                .encode(&self.ctx, &mut enc, &frame, map, self.depth.weight, *valid)?;
        }
        if self.timed {
            enc = submit_and_wait(&self.ctx, enc)?;
        }
        let loss_ms = t.elapsed().as_secs_f64() * 1000.0;
        let t = Instant::now();
        if let Some((slot, ex, sc)) = exposed {
            ex.encode_backward(&self.ctx, &mut enc, &frame.image, sc, dl, w, h, slot)?;
        }
        self.renderer.encode_backward(
            &self.ctx,
            &mut enc,
            &state.splats,
            &frame,
            dl,
            &state.grads,
        )?;
        if self.timed {
            enc = submit_and_wait(&self.ctx, enc)?;
        }
        if let Some(sem) = self.semantic.as_ref().filter(|_| self.gamma > 0.0) {
            sem.encode(
                &self.ctx,
                &mut enc,
                &state.splats,
                &state.grads,
                &self.loss_out,
                self.gamma,
            )?;
        }
        if let Some(m) = self.mcmc.as_ref() {
            m.encode_regularise(&self.ctx, &mut enc, &state.splats, &state.grads)?;
        }
        let backward_ms = t.elapsed().as_secs_f64() * 1000.0;
        let t = Instant::now();
        let rates = AdamRates {
            means: lr.position,
            log_scales: lr.scale,
            rotations: lr.rotation,
            opacity: lr.opacity,
            sh_dc: lr.sh_dc,
            sh_rest: lr.sh_rest,
        };
        state
            .adam
            .encode_step(&self.ctx, &mut enc, &state.splats, &state.grads, &rates)?;
        if let Some(m) = self.mcmc.as_ref() {
            m.encode_noise(
                &self.ctx,
                &mut enc,
                &state.splats,
                state.adam.step,
                lr.position,
            )?;
        }
        if let (Some(_), Some(ex)) = (exposure, self.exposure.as_mut()) {
            ex.encode_adam(&self.ctx, &mut enc, lr.exposure);
        }
        if let (Some(sem), Some(_)) = (self.semantic.as_ref(), self.bind.as_ref()) {
            sem.encode_bind(&self.ctx, &mut enc, &state.splats)?;
        }
        self.ctx.queue.submit([enc.finish()]);
        let optimizer_ms = self.wait_ms(t)?;
        // Every buffer of the step still exists (the frame until this returns, the sort's
        // scratch until the GPU is done with it): the step's high-water mark.
        self.sample_memory();
        drop(frame);
        self.times.loss_ms += loss_ms;
        self.times.backward_ms += backward_ms;
        self.times.optimizer_ms += optimizer_ms;
        Ok(())
    }

    fn last_loss(&mut self) -> Result<StepLoss, TrainError> {
        let v: Vec<f32> = read_buffer(&self.ctx, &self.loss_out, 4)?;
        Ok(StepLoss {
            loss: v.first().copied().unwrap_or(f32::NAN),
            l1: v.get(1).copied().unwrap_or(f32::NAN),
            ssim: v.get(2).copied().unwrap_or(f32::NAN),
            geo: v.get(3).copied().unwrap_or(0.0),
        })
    }

    fn set_exposures(&mut self, n: usize) -> Result<(), TrainError> {
        self.exposure = (n > 0)
            .then(|| GpuExposure::new(&self.ctx, n))
            .transpose()?;
        Ok(())
    }

    fn exposures(&mut self) -> Result<Vec<[f32; EXPOSURE_FLOATS]>, TrainError> {
        match self.exposure.as_ref() {
            Some(ex) => Ok(ex.download(&self.ctx)?.params),
            None => Ok(Vec::new()),
        }
    }

    fn render_exposed(
        &mut self,
        camera: &Camera,
        index: usize,
    ) -> Result<Vec<[f32; 3]>, TrainError> {
        self.exposure_for(index)?;
        let pixels = camera.width as usize * camera.height as usize;
        self.exposure_scratch_for(pixels)?;
        let frame = self.frame(camera, self.options)?;
        let (Some(ex), Some(sc)) = (self.exposure.as_ref(), self.exposure_scratch.as_ref()) else {
            return Err(TrainError::Invalid(
                "internal: missing exposure buffers".into(),
            ));
        };
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        let slot = ExposureSlot {
            index,
            left_half: false,
        };
        ex.encode_apply(
            &self.ctx,
            &mut enc,
            &frame.image,
            None,
            sc,
            camera.width,
            camera.height,
            slot,
        )?;
        self.ctx.queue.submit([enc.finish()]);
        Ok(read_buffer(&self.ctx, &sc.exposed, pixels)?)
    }

    fn set_semantic(
        &mut self,
        anchors: &SemanticAnchors,
        cfg: &SemanticConfig,
    ) -> Result<(), TrainError> {
        let mut sem = GpuSemantic::new(&self.ctx, anchors, cfg)?;
        if let Some(state) = self.state.as_ref() {
            sem.set_model(&self.ctx, &state.trunk_prob)?;
        }
        if let Some(b) = self.bind.as_ref() {
            sem.set_bind(b)?;
        }
        self.semantic = Some(sem);
        Ok(())
    }

    fn set_geo_weight(&mut self, gamma: f32) {
        self.gamma = gamma;
    }

    fn set_bind(&mut self, anchors: &SemanticAnchors, cfg: &BindConfig) -> Result<(), TrainError> {
        // The binding searches the same anchor grids as L_geo; L_geo's own settings only
        // matter when it is switched on as well.
        let sem_cfg = SemanticConfig::default();
        self.bind = Some(cfg.clone());
        self.set_semantic(anchors, &sem_cfg)
    }

    fn set_step_terms(&mut self, terms: Option<StepTerms>) -> Result<(), TrainError> {
        self.mcmc = match terms {
            Some(t) => {
                let trunk_prob = self.state.as_ref().map_or(&[][..], |s| &s.trunk_prob[..]);
                Some(GpuMcmc::new(&self.ctx, t, trunk_prob)?)
            }
            None => None,
        };
        Ok(())
    }

    fn set_depth_targets(&mut self, targets: DepthTargets) -> Result<(), TrainError> {
        self.depth = targets;
        self.photos.clear_depth();
        Ok(())
    }

    fn render_depth(&mut self, camera: &Camera) -> Result<Vec<f32>, TrainError> {
        let frame = self.frame(camera, self.options)?;
        Ok(frame.read_depth(&self.ctx)?)
    }

    fn position_grads(&mut self) -> Result<Vec<[f32; 3]>, TrainError> {
        let state = self.state()?;
        let n = state.splats.count as usize;
        let flat: Vec<f32> = read_buffer(&self.ctx, &state.grads.means, 3 * n)?;
        Ok((0..n)
            .map(|i| [flat[3 * i], flat[3 * i + 1], flat[3 * i + 2]])
            .collect())
    }

    fn take_stats(&mut self) -> Result<DensifyStats, TrainError> {
        let state = self.state()?;
        let s = state.grads.download_stats(&self.ctx)?;
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        state.grads.reset_stats(&mut enc);
        self.ctx.queue.submit([enc.finish()]);
        Ok(DensifyStats {
            grad_sum: s.grad_sum,
            visible_count: s.visible_count,
            max_radius: s.max_radius,
        })
    }

    fn model(&mut self) -> Result<(Gaussians, AdamState), TrainError> {
        let state = self.state()?;
        let n = state.splats.count as usize;
        let mut model = Gaussians {
            means: vec![[0.0; 3]; n],
            log_scales: vec![[0.0; 3]; n],
            rotations: vec![[0.0; 4]; n],
            opacity_logits: vec![0.0; n],
            sh: vec![[0.0; crate::splat::model::SH_FLOATS]; n],
            trunk_prob: state.trunk_prob.clone(),
            sh_degree: state.splats.sh_degree,
        };
        state.splats.download_into(&self.ctx, &mut model)?;
        let m = state.adam.download_moments(&self.ctx)?;
        let strides = [3, 3, 4, 1, crate::splat::model::SH_FLOATS];
        let get = |k: usize| to_moments(strides[k], &m[k]);
        let adam = AdamState {
            step: state.adam.step,
            means: get(0),
            log_scales: get(1),
            rotations: get(2),
            opacity_logits: get(3),
            sh: get(4),
        };
        Ok((model, adam))
    }

    fn set_render_options(&mut self, options: RenderOptions) {
        self.options = options;
    }

    fn render(&mut self, camera: &Camera) -> Result<Vec<[f32; 3]>, TrainError> {
        let frame = self.frame(camera, self.options)?;
        Ok(frame.read_image(&self.ctx)?)
    }

    fn phase_times(&self) -> PhaseTimes {
        self.times
    }

    fn set_timed(&mut self, timed: bool) {
        self.timed = timed;
    }

    fn device_memory(&self) -> Option<u64> {
        self.ctx.device_memory_bytes()
    }

    fn set_plan(&mut self, plan: &MemoryPlan) -> Result<(), TrainError> {
        self.photos
            .set_slots((!plan.all_photos).then_some(plan.photo_slots));
        self.max_intersections = Some(plan.max_intersections);
        Ok(())
    }

    fn prefetch(&mut self, view: &View) -> Result<(), TrainError> {
        let keep = self.current.clone();
        self.resident(view, keep.as_deref())
    }

    fn memory_use(&self) -> Option<MemoryUse> {
        Some(MemoryUse {
            photo_uploads: self.photos.uploads,
            photo_hits: self.photos.hits,
            ..self.memory
        })
    }
}
