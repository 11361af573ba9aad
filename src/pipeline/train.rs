//! Stage `train`: Gaussian splatting of the registered photos (METHOD.md Stage 4), initialised
//! from the labelled LiDAR anchors (the paper's method) or from the SfM points (vanilla 3DGS).
//!
//! Outputs in the registered model's frame (the LiDAR local frame of stage `ingest`, offset in
//! the report): `splats.ply` (INRIA layout plus `trunk_prob`), `eval.json` (held-out PSNR and
//! SSIM per view), `loss.csv`, `loss.png` and `renders/*.png` (render left, photo right).

use serde_json::json;

use super::params::{InitSource, TrainBackend, TrainParams};
use super::{Stage, StageContext, StageError};
use crate::io::colmap;
use crate::io::ply;
use crate::progress::{NoProgress, SubProgress};
use crate::splat::backend::{Backend, CpuBackend, TrainError};
use crate::splat::dataset::{self, Dataset, DatasetError};
use crate::splat::init::{self, Anchor, AnchorInit};
use crate::splat::model::Gaussians;
use crate::splat::rng::SplitMix64;
use crate::splat::trainer;

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

/// Keeps a seeded random subset of `max` Gaussians (all when `max` is 0 or not exceeded).
pub fn cap_gaussians(g: &mut Gaussians, max: u32, seed: u64) {
    let n = g.len();
    if max == 0 || n <= max as usize {
        return;
    }
    let mut idx: Vec<usize> = (0..n).collect();
    let mut rng = SplitMix64::new(seed);
    for i in (1..n).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        idx.swap(i, j);
    }
    let mut keep = vec![false; n];
    for &i in &idx[..max as usize] {
        keep[i] = true;
    }
    g.retain_mask(&keep);
}

/// Initial Gaussians for `params.init`: LiDAR anchors labelled by stage `segment`, or the SfM
/// points of the dataset.
fn initial_gaussians(
    ctx: &StageContext<'_>,
    data: &Dataset,
    params: &TrainParams,
) -> Result<Gaussians, StageError> {
    let mut g = match params.init {
        InitSource::Sfm => init::from_sfm_points(&data.points, &data.colours)
            .map_err(|e| StageError::Input(format!("SfM initialisation: {e}")))?,
        InitSource::Lidar => {
            let segment = ctx.output_of(Stage::Segment, Stage::Train)?;
            let (cloud, fields) =
                ply::read_ply_with_fields(&segment.join("anchors.ply"), &NoProgress)?;
            let prob = fields
                .iter()
                .find(|f| f.name == "trunk_prob")
                .map(|f| f.values.clone())
                .unwrap_or_else(|| vec![0.0; cloud.len()]);
            let colours = cloud
                .colors
                .clone()
                .unwrap_or_else(|| vec![[128; 3]; cloud.len()]);
            let anchors: Vec<Anchor> = (0..cloud.len())
                .map(|i| Anchor {
                    position: cloud.positions[i].to_array(),
                    colour: colours[i],
                    trunk_prob: prob.get(i).copied().unwrap_or(0.0),
                })
                .collect();
            init::from_anchors(&anchors, &data.train, &AnchorInit::default())
                .map_err(|e| StageError::Input(format!("anchor initialisation: {e}")))?
        }
    };
    cap_gaussians(&mut g, params.max_gaussians, params.seed);
    Ok(g)
}

pub fn run(ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    let params = &ctx.params.train;
    let cfg = params.config();
    let register = ctx.output_of(Stage::Register, Stage::Train)?;
    let model = colmap::read_model(&register.join("sparse"), &NoProgress)?;
    let project = colmap::find_project(&ctx.inputs.colmap)?;
    let images = project.images_dir.ok_or_else(|| {
        StageError::Input("COLMAP project: no images/ folder beside the sparse model".into())
    })?;
    let mut backend = backend_for(params)?;
    ctx.progress
        .log(&format!("training on {}", backend.device_name()));
    let data = dataset::load(
        &model,
        &images,
        cfg.resolution,
        cfg.test_every,
        &SubProgress::new(ctx.progress, 0.0, 0.05),
    )?;
    let init = initial_gaussians(ctx, &data, params)?;
    let n_init = init.len();
    let mut strategy = trainer::default_strategy(&cfg);
    let outcome = trainer::train(
        backend.as_mut(),
        &data,
        init,
        &cfg,
        &mut strategy,
        &SubProgress::new(ctx.progress, 0.05, 0.95),
    )?;
    trainer::write_outputs(ctx.out_dir, &outcome, &data)
        .map_err(|e| super::io_err(ctx.out_dir, e))?;
    ctx.progress.log(&format!(
        "held-out PSNR {:.2} dB, SSIM {:.3} over {} views (mean-colour baseline {:.2} dB)",
        outcome.eval.psnr,
        outcome.eval.ssim,
        outcome.eval.views.len(),
        outcome.baseline_psnr
    ));
    let offset = read_offset(ctx)?;
    Ok(json!({
        "device": outcome.device,
        "init": params.init,
        // The semantic trunk term L_geo is not applied by this build's trainer yet.
        "semantic_applied": false,
        "steps": cfg.steps,
        "resolution": data.train.first().map(|v| [v.camera.width, v.camera.height]),
        "views": { "train": data.train.len(), "test": data.test.len() },
        "gaussians": { "initial": n_init, "final": outcome.model.len() },
        "render": outcome.eval,
        "baseline_psnr": outcome.baseline_psnr,
        "seconds": outcome.seconds,
        "steps_per_second": outcome.steps_per_second,
        "phase_ms": outcome.phase_times,
        "refinements": outcome.refinements.len(),
        "offset": offset,
    }))
}

/// The local frame's offset (file coordinates of the origin), from stage `ingest`'s cloud.
fn read_offset(ctx: &StageContext<'_>) -> Result<[f64; 3], StageError> {
    let ingest = ctx.output_of(Stage::Ingest, Stage::Train)?;
    let info = ply::inspect_ply(&ingest.join("cloud.ply"))?;
    Ok(info.sylva_offset.unwrap_or([0.0; 3]))
}
