//! Stage `train`: Gaussian splatting of the registered photos (docs/method.md Stage 4), initialised
//! from the labelled LiDAR anchors (the paper's method) or from the SfM points (vanilla 3DGS).
//!
//! Outputs in the registered model's frame (the LiDAR local frame of stage `ingest`, offset in
//! the report): `splats.ply` (INRIA layout plus `trunk_prob`), `eval.json` (held-out PSNR and
//! SSIM per view; with exposure compensation, on the right halves), `loss.csv`, `loss.png`,
//! `renders/*.png` (render left, photo right) and, with exposure compensation,
//! `exposure.json` (every photo's learned colour transform; the splats carry none).

use serde_json::json;
use std::collections::HashMap;

use super::params::{InitSource, TrainBackend, TrainParams, TrunkTerm};
use super::{Stage, StageContext, StageError};
use crate::forest::dbh::{StemAxis, in_dbh_band};
use crate::io::colmap;
use crate::io::ply;
use crate::progress::{NoProgress, SubProgress};
use crate::splat::backend::{Backend, CpuBackend, DeviceKind, TrainError};
use crate::splat::bind;
use crate::splat::budget::default_budget;
use crate::splat::dataset::{self, Dataset, DatasetError};
use crate::splat::init::Anchor;
use crate::splat::model::Gaussians;
use crate::splat::plan::{self, MemoryPlan, MemorySource};
use crate::splat::semantic::{AnchorIndex, MAX_ANCHORS, SemanticAnchors};
use crate::splat::start::{Start, initial_gaussians};
use crate::splat::trainer;
use crate::splat::trunk_diag::{SliceFn, TrunkMonitor};

impl From<TrainError> for StageError {
    fn from(e: TrainError) -> Self {
        match e {
            TrainError::Cancelled => StageError::Cancelled,
            TrainError::Invalid(m) => StageError::Input(m),
            // A missing or failing GPU is the service's fault, not the input's.
            TrainError::Device(m) => StageError::Device(m),
        }
    }
}

impl From<DatasetError> for StageError {
    fn from(e: DatasetError) -> Self {
        match e {
            DatasetError::Cancelled => StageError::Cancelled,
            DatasetError::Io(e) => StageError::Io(e),
            DatasetError::Invalid(m) => StageError::Input(m),
        }
    }
}

/// The backend `params` ask for; a clear error when it cannot start.
pub fn backend_for(params: &TrainParams) -> Result<Box<dyn Backend>, TrainError> {
    let background = [0.0; 3];
    match params.backend {
        TrainBackend::Cpu => Ok(Box::new(CpuBackend::new(background))),
        TrainBackend::Gpu => Ok(Box::new(crate::splat::gpu::GpuBackend::new(background)?)),
    }
}

/// `params` with the budget of [`default_budget`] when it asks for the default (0), and where
/// the budget came from: "params", "default for <kind>" or "none".
pub fn with_budget(params: &TrainParams, kind: DeviceKind) -> (TrainParams, String) {
    let mut p = params.clone();
    if p.max_gaussians > 0 {
        return (p, "params".into());
    }
    match default_budget(kind) {
        Some(b) => {
            p.max_gaussians = b;
            (p, format!("default for {}", kind.as_str()))
        }
        None => (p, "none".into()),
    }
}

/// The budget of [`with_budget`], lowered to what the device's memory holds, and the memory
/// plan the backend then follows (`splat::plan`; `None` on the CPU reference, or on a GPU that
/// does not report its memory when `params.gpu_memory_mb` is 0).
fn budget_and_plan(
    ctx: &StageContext<'_>,
    params: &TrainParams,
    backend: &mut dyn Backend,
    data: &Dataset,
    trunk_anchors: Option<&SemanticAnchors>,
) -> Result<(TrainParams, String, Option<MemoryPlan>), StageError> {
    let (mut p, mut source) = with_budget(params, backend.device_kind());
    let input = plan::run_input(
        backend,
        data,
        &p.config(),
        p.gpu_memory_mb,
        p.depth_weight > 0.0,
        trunk_anchors,
    );
    let Some(input) = input else {
        if backend.device_kind() != DeviceKind::CpuReference {
            ctx.progress.log(
                "the GPU does not report its memory: no memory plan (set params.train.gpu_memory_mb to plan one)",
            );
        }
        return Ok((p, source, None));
    };
    let plan = plan::plan(&input).map_err(|e| match input.source {
        MemorySource::Params => StageError::Input(format!("params.train.gpu_memory_mb: {e}")),
        MemorySource::Device => StageError::Device(e.to_string()),
    })?;
    ctx.progress.log(&plan.describe());
    if plan.memory_bound {
        source = format!(
            "{source}, lowered to what {} MB hold",
            input.device_bytes >> 20
        );
    }
    p.max_gaussians = plan.budget;
    backend.set_plan(&plan)?;
    Ok((p, source, Some(plan)))
}

/// The report's `memory`: the plan and what the device held at most against it.
fn memory_note(
    ctx: &StageContext<'_>,
    plan: Option<&MemoryPlan>,
    backend: &dyn Backend,
    data: &Dataset,
) -> serde_json::Value {
    let used = backend.memory_use();
    let host = data.host_photos();
    if let (Some(plan), Some(used)) = (plan, used) {
        ctx.progress.log(&format!(
            "GPU memory: at most {:.0} MB allocated ({:.0} MB reserved) of {:.0} MB planned; {} photo uploads, {} steps over the plan",
            used.peak_allocated_bytes as f64 / 1048576.0,
            used.peak_reserved_bytes as f64 / 1048576.0,
            plan.total_bytes as f64 / 1048576.0,
            used.photo_uploads,
            used.over_plan_steps
        ));
    }
    json!({ "plan": plan, "used": used, "host_photos": host })
}

/// The labelled anchors of stage `segment` (LiDAR local frame): position, colour, trunk
/// probability; whether the anchor is labelled trunk; and the normals when the file has them.
fn read_anchors(ctx: &StageContext<'_>) -> Result<LabelledAnchors, StageError> {
    let segment = ctx.output_of(Stage::Segment, Stage::Train)?;
    let (cloud, fields) = ply::read_ply_with_fields(&segment.join("anchors.ply"), &NoProgress)?;
    let field = |name: &str| {
        fields
            .iter()
            .find(|f| f.name == name)
            .map(|f| f.values.clone())
    };
    let prob = field("trunk_prob").unwrap_or_else(|| vec![0.0; cloud.len()]);
    // Label 1 is trunk (stage `segment`); without labels, the probability decides.
    let is_trunk: Vec<bool> = match field("label") {
        Some(l) => l.iter().map(|&v| v == 1.0).collect(),
        None => prob.iter().map(|&p| p >= 0.5).collect(),
    };
    let colours = cloud
        .colors
        .clone()
        .unwrap_or_else(|| vec![[128; 3]; cloud.len()]);
    let anchors = (0..cloud.len())
        .map(|i| Anchor {
            position: cloud.positions[i].to_array(),
            colour: colours[i],
            trunk_prob: prob.get(i).copied().unwrap_or(0.0),
        })
        .collect();
    let normals = match (field("nx"), field("ny"), field("nz")) {
        (Some(x), Some(y), Some(z)) if x.len() == cloud.len() => Some(
            (0..x.len())
                .map(|i| {
                    [
                        x[i],
                        y.get(i).copied().unwrap_or(0.0),
                        z.get(i).copied().unwrap_or(0.0),
                    ]
                })
                .collect(),
        ),
        _ => None,
    };
    Ok((anchors, is_trunk, normals))
}

/// Anchors, their trunk labels and their normals (when known).
type LabelledAnchors = (Vec<Anchor>, Vec<bool>, Option<Vec<[f32; 3]>>);

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let register = ctx.output_of(Stage::Register, Stage::Train)?;
    let model = colmap::read_model(&register.join("sparse"), &NoProgress)?;
    let images = ctx.images_dir()?;
    let depth_weight = ctx.params.train.depth_weight;
    if !(depth_weight.is_finite() && depth_weight >= 0.0) {
        return Err(StageError::Input(format!(
            "params.train.depth_weight must be finite and ≥ 0, got {depth_weight}"
        )));
    }
    let mut backend = backend_for(&ctx.params.train)?;
    let base_cfg = ctx.params.train.config();
    let data = dataset::load(
        &model,
        &images,
        base_cfg.resolution,
        base_cfg.test_every,
        base_cfg.host_photo_mb,
        &SubProgress::new(ctx.progress, 0.0, 0.05),
    )?;
    // The anchors: the initialisation of the paper's method, the targets of L_geo and the
    // surface of Sylva's binding (at most `semantic::MAX_ANCHORS` of them on the GPU).
    let train_params = &ctx.params.train;
    let wants_anchors =
        train_params.init == InitSource::Lidar || train_params.semantic != TrunkTerm::Off;
    let (anchors, is_trunk, normals) = if wants_anchors {
        let (a, t, n) = read_anchors(ctx)?;
        (Some(a), t, n)
    } else {
        (None, Vec::new(), None)
    };
    let set = anchors
        .as_deref()
        .and_then(|a| trunk_anchors(ctx, train_params, a, normals.as_deref(), &is_trunk));
    drop(normals);
    drop(is_trunk);
    let (budgeted, budget_source, memory_plan) = budget_and_plan(
        ctx,
        train_params,
        backend.as_mut(),
        &data,
        set.as_ref()
            .filter(|_| train_params.semantic != TrunkTerm::Off),
    )?;
    let params = &budgeted;
    let cfg = params.config();
    ctx.progress.log(&format!(
        "training on {} with a budget of {} Gaussians ({budget_source})",
        backend.device_name(),
        match params.max_gaussians {
            0 => "unbounded".to_string(),
            n => n.to_string(),
        }
    ));
    // The stems of stage `segment`, whose DBH band a cap keeps dense and the trunk monitor
    // follows; none without the anchors (vanilla runs need no stage `segment`).
    let offset = read_offset(ctx)?;
    let stems = if wants_anchors {
        stems_in_model_frame(ctx, offset)?
    } else {
        Vec::new()
    };
    let axes: Vec<StemAxis> = stems.iter().map(super::dbh::StemRecord::axis).collect();
    let band = |means: &[[f32; 3]]| in_dbh_band(means, &axes, &ctx.params.segment.dbh);
    let start = Start {
        lidar: params.init == InitSource::Lidar,
        sfm_fill_m: params.sfm_fill_m,
        max_gaussians: params.max_gaussians,
        sky_gaussians: params.sky_gaussians,
        seed: params.seed,
    };
    let mut init = initial_gaussians(&data, &start, anchors.as_deref(), &band)
        .map_err(|e| StageError::Input(e.to_string()))?;
    let n_init = init.len();
    let mut cfg = cfg;
    cfg.semantic.temperature_m = ctx.params.anchors.voxel_size_m as f32;
    cfg.semantic
        .validate()
        .and_then(|_| cfg.bind.validate())
        .and_then(|_| cfg.validate_exposure())
        .map_err(|e| StageError::Input(format!("params.train: {e}")))?;
    let trunk_note = trunk_term(
        ctx,
        params,
        &mut cfg,
        set.as_ref(),
        &mut init,
        backend.as_mut(),
    )?;
    let semantic_applied = (cfg.semantic.enabled && cfg.steps > cfg.semantic.gamma_start)
        || (cfg.bind.enabled && params.semantic == TrunkTerm::Bind);
    let monitor = match set.as_ref() {
        Some(set) => trunk_monitor(ctx, set, &cfg, &stems),
        None => None,
    };
    // LiDAR depth maps of every view (the anchors splatted at their voxel size): the targets of
    // the depth loss on the training views and the held-out depth error on the others.
    let lidar = anchors.as_ref().map(|a| LidarDepth {
        points: a.iter().map(|x| x.position).collect(),
        footprint_m: ctx.params.anchors.voxel_size_m as f32,
    });
    if params.depth_weight > 0.0 {
        let Some(lidar) = &lidar else {
            return Err(StageError::Input(
                "params.train.depth_weight needs the LiDAR anchors of stage segment".into(),
            ));
        };
        backend.set_depth_targets(crate::splat::depth::DepthTargets {
            weight: params.depth_weight as f32,
            maps: lidar.maps(&data.train),
        })?;
    }
    let mut strategy = trainer::strategy_for(&cfg)?;
    let outcome = trainer::train_monitored(
        backend.as_mut(),
        &data,
        init,
        &cfg,
        strategy.as_mut(),
        monitor.as_ref(),
        // Loading took the first 5 %, writing the outputs takes the last 3 %.
        &SubProgress::new(ctx.progress, 0.05, 0.92),
    )?;
    let memory = memory_note(ctx, memory_plan.as_ref(), backend.as_ref(), &data);
    trainer::write_outputs(ctx.out_dir, &outcome, &data)
        .map_err(|e| super::io_err(ctx.out_dir, e))?;
    // Held-out depth error against the LiDAR (also without the depth loss, to compare).
    let mut depth_note = json!({ "weight": params.depth_weight });
    if let Some(lidar) = &lidar
        && let Some((mae, rel, views)) = lidar.heldout_error(ctx, backend.as_mut(), &data.test)?
    {
        depth_note = json!({
            "weight": params.depth_weight,
            "heldout_mae_m": mae,
            "heldout_rel": rel,
            "views": views,
        });
    }
    ctx.progress.set(1.0);
    ctx.progress.log(&format!(
        "held-out PSNR {:.2} dB, SSIM {:.3} over {} views, {} (mean-colour baseline {:.2} dB)",
        outcome.eval.psnr,
        outcome.eval.ssim,
        outcome.eval.views.len(),
        outcome.eval.region.describe(),
        outcome.baseline_psnr
    ));
    Ok(json!({
        "device": outcome.device,
        "init": params.init,
        "semantic_applied": semantic_applied,
        "semantic": trunk_note,
        "trunk_diagnostics": {
            "first": outcome.losses.iter().find_map(|r| r.trunk),
            "last": outcome.losses.iter().rev().find_map(|r| r.trunk),
        },
        "final_geo_loss": outcome.losses.last().map(|r| r.geo),
        "steps": cfg.steps,
        "antialias": cfg.antialias,
        "resolution": data.train.first().map(|v| [v.camera.width, v.camera.height]),
        "views": { "train": data.train.len(), "test": data.test.len() },
        "gaussians": { "initial": n_init, "final": outcome.model.len() },
        "budget": { "max_gaussians": params.max_gaussians, "source": budget_source, "device_kind": backend.device_kind().as_str() },
        "memory": memory,
        "render": outcome.eval,
        "depth": depth_note,
        "baseline_psnr": outcome.baseline_psnr,
        "exposure": {
            "enabled": cfg.exposure,
            "images": outcome.exposures.len(),
            "lr_init": cfg.lr_exposure_init,
            "lr_final": cfg.lr_exposure_final,
            "lr_delay_steps": cfg.lr_exposure_delay_steps,
            "lr_delay_mult": cfg.lr_exposure_delay_mult,
        },
        "seconds": outcome.seconds,
        "steps_per_second": outcome.steps_per_second,
        "phase_ms": outcome.phase_times,
        "refinements": outcome.refinements.len(),
        "offset": offset,
    }))
}

/// The anchors of the trunk term (L_geo's targets, the binding's surface), or `None`, said in
/// the log, when there are no trunk anchors to hold the trunks to: training goes on without.
fn trunk_anchors(
    ctx: &StageContext<'_>,
    params: &TrainParams,
    anchors: &[Anchor],
    normals: Option<&[[f32; 3]]>,
    is_trunk: &[bool],
) -> Option<SemanticAnchors> {
    let points: Vec<[f32; 3]> = anchors.iter().map(|a| a.position).collect();
    let set = SemanticAnchors::new(&points, normals, is_trunk)
        .map_err(|e| {
            ctx.progress
                .log(&format!("trunk term {} off: {e}", params.semantic.as_str()))
        })
        .ok()?;
    let all = set.trunk.len() + set.leaf.len();
    let set = set.thinned(MAX_ANCHORS, params.seed);
    if set.trunk.len() + set.leaf.len() < all {
        ctx.progress.log(&format!(
            "trunk term: {all} anchors drawn evenly down to {} ({} trunk, {} leaf), the most the term holds",
            MAX_ANCHORS,
            set.trunk.len(),
            set.leaf.len()
        ));
    }
    Some(set)
}

/// Sets up the trunk term `params.semantic` asks for on `backend` when the anchors give one
/// (`set`): the paper's L_geo, or Sylva's binding (whose surfels it starts in `init`); turns
/// both off in `cfg` otherwise. Returns the report's `semantic`.
fn trunk_term(
    ctx: &StageContext<'_>,
    params: &TrainParams,
    cfg: &mut crate::splat::config::TrainConfig,
    set: Option<&SemanticAnchors>,
    init: &mut Gaussians,
    backend: &mut dyn Backend,
) -> Result<serde_json::Value, StageError> {
    match (params.semantic, set) {
        (TrunkTerm::Paper, Some(set)) => {
            backend.set_semantic(set, &cfg.semantic)?;
            Ok(json!({
                "term": "paper",
                "trunk_anchors": set.trunk.len(),
                "leaf_anchors": set.leaf.len(),
                "n_pos_m": set.n_pos,
                "gamma_max": cfg.semantic.gamma_max,
                "gamma_start": cfg.semantic.gamma_start,
                "gamma_end": cfg.semantic.gamma_end,
                "temperature_m": cfg.semantic.temperature_m,
                "k": cfg.semantic.k,
                "beta": cfg.semantic.beta,
            }))
        }
        (TrunkTerm::Bind, Some(set)) => {
            if set.trunk_normals.is_empty() {
                return Err(StageError::Input(
                    "Sylva's binding needs the anchors' normals (segment/anchors.ply has no nx, ny, nz); rerun from stage anchors, or set params.train.semantic to \"paper\" or \"off\"".into(),
                ));
            }
            let surface = bind::surface_anchors(set, &cfg.bind);
            let index = AnchorIndex::new(&surface).ok_or_else(|| {
                StageError::Input("Sylva's binding: the trunk anchors cannot be indexed".into())
            })?;
            let surfels = bind::surfel_init(init, &index, &cfg.bind);
            backend.set_bind(&surface, &cfg.bind)?;
            ctx.progress.log(&format!(
                "trunk binding: {surfels} trunk surfels held within {} m of the LiDAR surface",
                cfg.bind.band_m
            ));
            Ok(json!({
                "term": "bind",
                "trunk_anchors": set.trunk.len(),
                "leaf_anchors": set.leaf.len(),
                "surfels": surfels,
                "band_m": cfg.bind.band_m,
                "surface_radius_m": cfg.bind.surface_radius_m,
                "normal_scale_m": cfg.bind.normal_scale_m,
            }))
        }
        _ => {
            cfg.semantic.enabled = false;
            cfg.bind.enabled = false;
            Ok(json!({ "term": params.semantic.as_str() }))
        }
    }
}

/// The LiDAR anchors as depth maps: points (training frame, metres) splatted at their voxel
/// size, `footprint_m`.
struct LidarDepth {
    points: Vec<[f32; 3]>,
    footprint_m: f32,
}

impl LidarDepth {
    /// The depth map of each of `views`, by view name.
    fn maps(&self, views: &[crate::splat::cameras::View]) -> HashMap<String, Vec<f32>> {
        views
            .iter()
            .map(|v| {
                (
                    v.name.clone(),
                    crate::splat::depth::lidar_depth(&self.points, &v.camera, self.footprint_m),
                )
            })
            .collect()
    }

    /// The trained model's depth on the held-out `views` against the LiDAR's: mean absolute
    /// error (metres), mean relative error and the views compared, or `None` when no view
    /// has LiDAR depth to compare.
    fn heldout_error(
        &self,
        ctx: &StageContext<'_>,
        backend: &mut dyn Backend,
        views: &[crate::splat::cameras::View],
    ) -> Result<Option<(f64, f64, usize)>, StageError> {
        if views.is_empty() {
            return Ok(None);
        }
        let maps = self.maps(views);
        let (mut mae, mut rel, mut n) = (0.0, 0.0, 0usize);
        for v in views {
            let rendered = backend.render_depth(&v.camera)?;
            if let Some((a, r)) = maps
                .get(&v.name)
                .and_then(|m| crate::splat::depth::depth_error(&rendered, m))
            {
                mae += a;
                rel += r;
                n += 1;
            }
        }
        if n == 0 {
            return Ok(None);
        }
        let (mae, rel) = (mae / n as f64, rel / n as f64);
        ctx.progress.log(&format!(
            "held-out depth against the LiDAR: mean absolute error {mae:.3} m, relative {:.1} % over {n} views",
            rel * 100.0
        ));
        Ok(Some((mae, rel, n)))
    }
}

/// Measurements per run of the trunk monitor (about 20, at least every 10 steps).
const MONITOR_POINTS: u32 = 20;

/// The stems of stage `segment` in the training frame: the Gaussians live in the registered
/// model's frame (stage ingest's `offset`), the stems in stage segment's, so the stems are
/// shifted when the two differ.
fn stems_in_model_frame(
    ctx: &StageContext<'_>,
    offset: [f64; 3],
) -> Result<Vec<super::dbh::StemRecord>, StageError> {
    let (stems_offset, mut stems) =
        super::dbh::read_stems(&ctx.output_of(Stage::Segment, Stage::Train)?)?;
    let shift = glam::Vec3::new(
        (stems_offset[0] - offset[0]) as f32,
        (stems_offset[1] - offset[1]) as f32,
        (stems_offset[2] - offset[2]) as f32,
    );
    for s in &mut stems {
        s.base = (glam::Vec3::from_array(s.base) + shift).to_array();
        s.dbh.center += shift;
    }
    Ok(stems)
}

/// The trunk monitor of this run: the anchors and the stems of stage `segment` (training
/// frame) with their LiDAR circles, measured on the breast-height slice stage `dbh` fits.
/// None when the segment stage found no stems.
fn trunk_monitor(
    ctx: &StageContext<'_>,
    set: &SemanticAnchors,
    cfg: &crate::splat::config::TrainConfig,
    stems: &[super::dbh::StemRecord],
) -> Option<TrunkMonitor> {
    let stems: Vec<StemCircle> = stems
        .iter()
        .map(|s| StemCircle {
            base: glam::Vec3::from_array(s.base),
            axis: glam::Vec3::from_array(s.axis),
            center: s.dbh.center,
            radius_m: (s.dbh.diameter_m / 2.0) as f32,
            height_m: s.dbh.slice_height_m,
        })
        .collect();
    if stems.is_empty() {
        return None;
    }
    let half = ctx.params.segment.dbh.half_thickness_m;
    let slice: Box<SliceFn> = Box::new(move |centres: &[glam::Vec3]| {
        let mut out = Vec::new();
        for s in &stems {
            out.extend(crate::forest::dbh::slice_offsets(
                centres,
                s.base,
                s.axis,
                s.height_m,
                half,
                2.0 * s.radius_m + 0.10,
                s.center,
                s.radius_m,
            ));
        }
        out
    });
    let every = (cfg.steps / MONITOR_POINTS).max(trainer::LOSS_EVERY);
    let mut m = TrunkMonitor::new(set, &cfg.semantic, slice, every);
    if let Some(m) = m.as_mut() {
        m.min_opacity = ctx.params.dbh.min_opacity as f32;
    }
    m
}

/// A stem's breast-height circle in the training frame.
struct StemCircle {
    base: glam::Vec3,
    axis: glam::Vec3,
    center: glam::Vec3,
    radius_m: f32,
    height_m: f32,
}

/// The local frame's offset (file coordinates of the origin), from stage `ingest`'s cloud.
fn read_offset(ctx: &StageContext<'_>) -> Result<[f64; 3], StageError> {
    let ingest = ctx.output_of(Stage::Ingest, Stage::Train)?;
    let info = ply::inspect_ply(&ingest.join(super::INGEST_CLOUD))?;
    Ok(info.sylva_offset.unwrap_or([0.0; 3]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::budget::{CPU_REFERENCE_BUDGET, SOFTWARE_GPU_BUDGET};

    #[test]
    fn the_default_budget_follows_the_device_and_a_given_one_wins() {
        let p = TrainParams::default();
        assert_eq!(p.max_gaussians, 0);
        let (b, src) = with_budget(&p, DeviceKind::SoftwareGpu);
        assert_eq!(
            (b.max_gaussians, src.as_str()),
            (SOFTWARE_GPU_BUDGET, "default for software_gpu")
        );
        let (b, _) = with_budget(&p, DeviceKind::CpuReference);
        assert_eq!(b.max_gaussians, CPU_REFERENCE_BUDGET);
        let (b, src) = with_budget(&p, DeviceKind::Gpu);
        assert_eq!((b.max_gaussians, src.as_str()), (0, "none"));
        let given = TrainParams {
            max_gaussians: 500,
            ..TrainParams::default()
        };
        let (b, src) = with_budget(&given, DeviceKind::SoftwareGpu);
        assert_eq!((b.max_gaussians, src.as_str()), (500, "params"));
        assert_eq!(b.config().max_gaussians, Some(500));
    }
}
