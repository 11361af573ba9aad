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
use crate::io::colmap;
use crate::io::ply;
use crate::progress::{NoProgress, SubProgress};
use crate::rng::SplitMix64;
use crate::splat::backend::{Backend, CpuBackend, DeviceKind, TrainError};
use crate::splat::bind;
use crate::splat::dataset::{self, Dataset, DatasetError};
use crate::splat::init::{self, Anchor, AnchorInit};
use crate::splat::model::Gaussians;
use crate::splat::semantic::{AnchorIndex, SemanticAnchors};
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

/// Default Gaussian budget on a software GPU (lavapipe), when `params.train.max_gaussians` is
/// 0: measured on `stand` seed 1 with `sylva bench method` (docs/results/twin.md, "Budgets"),
/// where it kept a 500-step run at 80 px within a few minutes on 2 cores.
pub const SOFTWARE_GPU_BUDGET: u32 = 10_000;

/// Default Gaussian budget on the CPU reference backend (docs/results/twin.md, "Budgets"): the
/// demo's, which trains `tiny` in seconds on 2 cores.
pub const CPU_REFERENCE_BUDGET: u32 = 3_000;

/// The Gaussian budget a run gets when `params.train.max_gaussians` is 0: none on a hardware
/// GPU (the reference 3DGS has no cap; not measured here, there being no GPU on the machines
/// Sylva is tested on), [`SOFTWARE_GPU_BUDGET`] on a software one, [`CPU_REFERENCE_BUDGET`] on
/// the CPU reference.
pub fn default_budget(kind: DeviceKind) -> Option<u32> {
    match kind {
        DeviceKind::Gpu => None,
        DeviceKind::SoftwareGpu => Some(SOFTWARE_GPU_BUDGET),
        DeviceKind::CpuReference => Some(CPU_REFERENCE_BUDGET),
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

/// Share of a Gaussian cap reserved for trunk Gaussians (trunk probability ≥ 0.5). The trunks
/// are a small part of a plot, yet the Gaussian DBH of stage `dbh` fits circles to the trunk
/// Gaussians of a 20 cm slice: a uniform subset of a capped initialisation leaves too few
/// there (about 10 per stem with 10 k of the 179 k anchors of `tiny`). Sylva's choice.
pub const TRUNK_SHARE_OF_CAP: f64 = 0.5;

/// Share of the trunk Gaussians' part of a cap kept for the band of the DBH slices (Gaussians
/// within reach of a stem's axis between 0.5 and 2.1 m along it, [`super::dbh::in_dbh_band`]):
/// half (Sylva's choice). The trunk surfels are what stage `dbh` measures; an even draw over
/// the whole trunk surface leaves a 20 cm slice of a 17-stem plot about 8 surfels at a cap
/// of 10 000, too few for a circle (10 inliers at least), while the rest of the trunks, which
/// only the photos see, render as well from a coarser draw.
pub const DBH_BAND_SHARE_OF_TRUNKS: f64 = 0.5;

/// The start of `sylva train` and the real-photo tests: one Gaussian per SfM point of `data`
/// (coloured from the photos where the model has no colours, [`Dataset`]), plus, with `fill`,
/// Gaussians where the training photos see what no SfM point covers
/// ([`init::fill_uncovered`]); capped at `max` by a draw of `seed` (0 = no cap) with the
/// scales taken again from what the cap kept. Also returns what the fill added (before the
/// cap; all zero without `fill`).
pub fn sfm_gaussians(
    data: &Dataset,
    max: u32,
    seed: u64,
    fill: Option<&init::CoverageFill>,
) -> Result<(Gaussians, init::FillReport), init::InitError> {
    let mut g = init::from_sfm_points(&data.points, &data.colours)?;
    let report = match fill {
        Some(fill) => init::fill_uncovered(&mut g, &data.train, fill),
        None => init::FillReport::default(),
    };
    let before = g.len();
    cap_gaussians(&mut g, max, seed, None, 0);
    if g.len() < before {
        init::rescale_from_spacing(&mut g, 3, 0.0);
    }
    Ok((g, report))
}

/// Keeps at most `max` Gaussians (all when `max` is 0 or not exceeded): up to
/// [`TRUNK_SHARE_OF_CAP`] of the cap from the trunk Gaussians (of that, up to
/// [`DBH_BAND_SHARE_OF_TRUNKS`] from those `band` marks, when given), the rest from the
/// others; a share one side does not use goes to the other. Each part is drawn evenly in
/// space ([`voxel_draw`]): one Gaussian per cell of the finest grid that fits the share, the
/// grid shifted by the seed, so a slice of a stem holds surfels all round its circumference
/// rather than a random subset's clumps and gaps. Scales are left as they are: the caller
/// sets them from the spacing of what is kept ([`crate::splat::init::rescale_from_spacing`]).
///
/// `added_later` Gaussians of the others' side (the sky dome) join the model after the cap:
/// the trunks' share is of `max + added_later`, so the dome's room comes from the others.
pub fn cap_gaussians(
    g: &mut Gaussians,
    max: u32,
    seed: u64,
    band: Option<&[bool]>,
    added_later: u32,
) {
    let n = g.len();
    if max == 0 || n <= max as usize {
        return;
    }
    let max = max as usize;
    let in_band = |i: usize| band.is_some_and(|b| b.get(i).copied().unwrap_or(false));
    let (trunk, other): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| g.trunk_prob[i] >= 0.5);
    let (trunk_band, trunk_rest): (Vec<usize>, Vec<usize>) =
        trunk.iter().partition(|&&i| in_band(i));
    let share_of = max + added_later as usize;
    let reserve = ((share_of as f64 * TRUNK_SHARE_OF_CAP) as usize)
        .min(trunk.len())
        .min(max);
    let from_other = (max - reserve).min(other.len());
    let from_trunk = (max - from_other).min(trunk.len());
    let band_reserve =
        ((from_trunk as f64 * DBH_BAND_SHARE_OF_TRUNKS) as usize).min(trunk_band.len());
    let from_rest = (from_trunk - band_reserve).min(trunk_rest.len());
    let from_band = from_trunk - from_rest;
    let mut rng = SplitMix64::new(seed);
    let mut keep = vec![false; n];
    for (part, count) in [
        (&trunk_band, from_band),
        (&trunk_rest, from_rest),
        (&other, from_other),
    ] {
        for i in voxel_draw(&g.means, part, count, &mut rng) {
            keep[i] = true;
        }
    }
    g.retain_mask(&keep);
}

/// Exactly `count` of the points `idx` of `means` (all when there are no more), spread evenly:
/// a bisection of the log cell edge (24 halvings, to 1e-6 of its range) finds the finest grid,
/// offset by a seeded random shift, with at most `count` occupied cells; each cell gives the
/// point nearest its centre, and a seeded random choice among the rest tops the draw up to
/// `count` (the occupied cells jump as the grid changes). Each halving hashes every point
/// once (25 passes in all).
fn voxel_draw(means: &[[f32; 3]], idx: &[usize], count: usize, rng: &mut SplitMix64) -> Vec<usize> {
    if count >= idx.len() {
        return idx.to_vec();
    }
    if count == 0 {
        return Vec::new();
    }
    let p = |i: usize| glam::DVec3::from(means[i].map(f64::from));
    let (lo, hi) = idx.iter().fold(
        (
            glam::DVec3::splat(f64::INFINITY),
            glam::DVec3::splat(f64::NEG_INFINITY),
        ),
        |(lo, hi), &i| (lo.min(p(i)), hi.max(p(i))),
    );
    let extent = (hi - lo).max_element().max(1e-6);
    let shift = glam::DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
    // One point per occupied cell of edge `v`: the nearest to the cell's centre.
    let cells = |v: f64| {
        let mut best: std::collections::HashMap<[i64; 3], (f64, usize)> =
            std::collections::HashMap::new();
        for &i in idx {
            let q = (p(i) - lo) / v + shift;
            let c = q.floor();
            let d2 = (q - c - glam::DVec3::splat(0.5)).length_squared();
            let key = [c.x as i64, c.y as i64, c.z as i64];
            let e = best.entry(key).or_insert((f64::INFINITY, i));
            if d2 < e.0 || (d2 == e.0 && i < e.1) {
                *e = (d2, i);
            }
        }
        let mut picked: Vec<usize> = best.into_values().map(|(_, i)| i).collect();
        picked.sort_unstable();
        picked
    };
    // Cell edges between extent / 1e6 (every point alone) and 2 × extent (one cell).
    let (mut fine, mut coarse) = ((extent * 1e-6).ln(), (2.0 * extent).ln());
    let mut picked = cells(coarse.exp());
    for _ in 0..24 {
        let mid = 0.5 * (fine + coarse);
        let c = cells(mid.exp());
        if c.len() <= count {
            coarse = mid;
            picked = c;
        } else {
            fine = mid;
        }
    }
    let mut taken = vec![false; means.len()];
    for &i in &picked {
        taken[i] = true;
    }
    let mut rest: Vec<usize> = idx.iter().copied().filter(|&i| !taken[i]).collect();
    while picked.len() < count && !rest.is_empty() {
        let j = rng.below(rest.len() as u64) as usize;
        picked.push(rest.swap_remove(j));
    }
    picked
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

/// Initial Gaussians for `params.init`: the LiDAR anchors labelled by stage `segment`, or the
/// SfM points of the dataset. SfM Gaussians take the trunk probability of their nearest anchor
/// when anchors are given (so the semantic term can act on them too).
fn initial_gaussians(
    data: &Dataset,
    params: &TrainParams,
    anchors: Option<&[Anchor]>,
    stems: &[super::dbh::StemRecord],
    dbh_params: &crate::forest::DbhParams,
) -> Result<Gaussians, StageError> {
    let mut g = match (params.init, anchors) {
        (InitSource::Lidar, Some(anchors)) => {
            let mut g = init::from_anchors(anchors, &data.train, &AnchorInit::default())
                .map_err(|e| StageError::Input(format!("anchor initialisation: {e}")))?;
            if params.sfm_fill_m > 0.0 {
                sfm_fill(&mut g, anchors, data, params.sfm_fill_m);
            }
            g
        }
        (InitSource::Lidar, None) => {
            return Err(StageError::Input(
                "LiDAR initialisation needs the anchors of stage segment".into(),
            ));
        }
        (InitSource::Sfm, _) => {
            let mut g = init::from_sfm_points(&data.points, &data.colours)
                .map_err(|e| StageError::Input(format!("SfM initialisation: {e}")))?;
            if let Some(anchors) = anchors {
                inherit_trunk_prob(&mut g, anchors);
            }
            g
        }
    };
    let before = g.len();
    // The sky dome's share of a cap: at most a tenth.
    let sky = match params.max_gaussians {
        0 => params.sky_gaussians,
        max => params.sky_gaussians.min(max / 10),
    };
    let max = params.max_gaussians.saturating_sub(sky);
    if params.max_gaussians > 0 && g.len() > max as usize {
        let band = super::dbh::in_dbh_band(&g.means, stems, dbh_params);
        cap_gaussians(&mut g, max, params.seed, Some(&band), sky);
    }
    if g.len() < before {
        // Scales from the spacing of what the cap kept (the same rule as the source's).
        match params.init {
            InitSource::Lidar => init::rescale_from_spacing(&mut g, 1, AnchorInit::default().eps),
            InitSource::Sfm => init::rescale_from_spacing(&mut g, 3, 0.0),
        }
    }
    init::add_sky(&mut g, &data.train, sky as usize);
    Ok(g)
}

/// A nearest-neighbour index of the anchors' positions; `None` when they cannot be indexed.
fn anchor_index(anchors: &[Anchor]) -> Option<crate::geom::PointIndex> {
    let pts: Vec<glam::Vec3> = anchors
        .iter()
        .map(|a| glam::Vec3::from_array(a.position))
        .collect();
    crate::geom::PointIndex::new(&pts).ok()
}

/// Appends, as non-trunk Gaussians of the SfM rule, the SfM points of `data` farther than
/// `min_dist_m` from every anchor (see `TrainParams::sfm_fill_m`).
fn sfm_fill(g: &mut Gaussians, anchors: &[Anchor], data: &Dataset, min_dist_m: f64) {
    let Some(index) = anchor_index(anchors) else {
        return;
    };
    let far = |p: &[f32; 3]| {
        index
            .nearest(glam::Vec3::from_array(*p))
            .is_none_or(|n| f64::from(n.dist2) > min_dist_m * min_dist_m)
    };
    let (points, colours): (Vec<[f32; 3]>, Vec<[u8; 3]>) = data
        .points
        .iter()
        .zip(&data.colours)
        .filter(|(p, _)| far(p))
        .map(|(p, c)| (*p, *c))
        .unzip();
    if let Ok(fill) = init::from_sfm_points(&points, &colours) {
        for i in 0..fill.len() {
            g.push(fill.get(i));
        }
    }
}

/// Sets every Gaussian's trunk probability to that of its nearest anchor.
fn inherit_trunk_prob(g: &mut Gaussians, anchors: &[Anchor]) {
    let Some(index) = anchor_index(anchors) else {
        return;
    };
    for (m, p) in g.means.iter().zip(g.trunk_prob.iter_mut()) {
        if let Some(n) = index.nearest(glam::Vec3::from_array(*m)) {
            *p = anchors[n.index as usize].trunk_prob;
        }
    }
}

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
    let (budgeted, budget_source) = with_budget(&ctx.params.train, backend.device_kind());
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
    let data = dataset::load(
        &model,
        &images,
        cfg.resolution,
        cfg.test_every,
        &SubProgress::new(ctx.progress, 0.0, 0.05),
    )?;
    // The anchors: the initialisation of the paper's method, the targets of L_geo and the
    // surface of Sylva's binding.
    let wants_anchors = params.init == InitSource::Lidar || params.semantic != TrunkTerm::Off;
    let (anchors, is_trunk, normals) = if wants_anchors {
        let (a, t, n) = read_anchors(ctx)?;
        (Some(a), t, n)
    } else {
        (None, Vec::new(), None)
    };
    // The stems of stage `segment`, whose DBH band a cap keeps dense and the trunk monitor
    // follows; none without the anchors (vanilla runs need no stage `segment`).
    let offset = read_offset(ctx)?;
    let stems = if wants_anchors {
        stems_in_model_frame(ctx, offset)?
    } else {
        Vec::new()
    };
    let mut init = initial_gaussians(
        &data,
        params,
        anchors.as_deref(),
        &stems,
        &ctx.params.segment.dbh,
    )?;
    let n_init = init.len();
    let mut cfg = cfg;
    cfg.semantic.temperature_m = ctx.params.anchors.voxel_size_m as f32;
    cfg.semantic
        .validate()
        .and_then(|_| cfg.bind.validate())
        .and_then(|_| cfg.validate_exposure())
        .map_err(|e| StageError::Input(format!("params.train: {e}")))?;
    let set = anchors
        .as_deref()
        .and_then(|a| trunk_anchors(ctx, params, a, normals.as_deref(), &is_trunk));
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
    SemanticAnchors::new(&points, normals, is_trunk)
        .map_err(|e| {
            ctx.progress
                .log(&format!("trunk term {} off: {e}", params.semantic.as_str()))
        })
        .ok()
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
    use crate::splat::model::Gaussian;

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

    fn scene(trunk: usize, other: usize) -> Gaussians {
        let mut g = Gaussians::default();
        for i in 0..trunk + other {
            let mut one = Gaussian::isotropic([i as f32, 0.0, 0.0], 0.01, [0.5; 3], 0.1);
            one.trunk_prob = if i < trunk { 0.9 } else { 0.1 };
            g.push(one);
        }
        g
    }

    fn trunk_count(g: &Gaussians) -> usize {
        g.trunk_prob.iter().filter(|&&p| p >= 0.5).count()
    }

    #[test]
    fn a_cap_keeps_a_share_for_the_trunks_and_lends_what_one_side_leaves() {
        // (trunk Gaussians, others), cap, room for Gaussians added later; then (kept, trunks kept).
        for ((trunk, other), cap, later, kept) in [
            // Few trunk Gaussians: all are kept, the others fill the cap.
            ((50, 10_000), 1000, 0, (1000, 50)),
            // Many: half the cap for each side.
            ((5000, 10_000), 1000, 0, (1000, 500)),
            // Room for 100 Gaussians added later comes from the others' share.
            ((5000, 10_000), 900, 100, (900, 500)),
            // Few others: the trunks take the rest of the cap.
            ((5000, 100), 1000, 0, (1000, 900)),
        ] {
            let mut g = scene(trunk, other);
            cap_gaussians(&mut g, cap, 7, None, later);
            assert_eq!(
                (g.len(), trunk_count(&g)),
                kept,
                "{trunk} + {other} capped at {cap}"
            );
        }
        // Under the cap, or no cap: nothing goes.
        let mut g = scene(10, 10);
        cap_gaussians(&mut g, 1000, 7, None, 0);
        assert_eq!(g.len(), 20);
        cap_gaussians(&mut g, 0, 7, None, 0);
        assert_eq!(g.len(), 20);
        // The same seed keeps the same Gaussians; another keeps others.
        let (mut a, mut b, mut c) = (scene(3000, 3000), scene(3000, 3000), scene(3000, 3000));
        cap_gaussians(&mut a, 500, 1, None, 0);
        cap_gaussians(&mut b, 500, 1, None, 0);
        cap_gaussians(&mut c, 500, 2, None, 0);
        assert_eq!(a.means, b.means);
        assert_ne!(a.means, c.means);
    }

    /// The farthest any point of `all` lies from its nearest kept Gaussian, metres.
    fn covering_radius(all: &Gaussians, kept: &Gaussians) -> f32 {
        let pts: Vec<glam::Vec3> = kept
            .means
            .iter()
            .map(|m| glam::Vec3::from_array(*m))
            .collect();
        let index = crate::geom::PointIndex::new(&pts).expect("index");
        all.means
            .iter()
            .map(|m| {
                index
                    .nearest(glam::Vec3::from_array(*m))
                    .map_or(f32::INFINITY, |n| n.dist2.sqrt())
            })
            .fold(0.0, f32::max)
    }

    #[test]
    fn a_cap_draws_a_stem_surface_evenly_and_scales_follow_the_kept_spacing() {
        // 20 000 points at random on a 15 cm stem 10 m tall; a cap of 400 keeps one in 50.
        let mut rng = SplitMix64::new(3);
        let mut g = Gaussians::default();
        for _ in 0..20_000 {
            let a = rng.uniform() * std::f64::consts::TAU;
            let z = rng.uniform() * 10.0;
            let p = [(0.15 * a.cos()) as f32, (0.15 * a.sin()) as f32, z as f32];
            let mut one = Gaussian::isotropic(p, 0.005, [0.5; 3], 0.1);
            one.trunk_prob = 0.9;
            g.push(one);
        }
        let mut drawn = g.clone();
        cap_gaussians(&mut drawn, 400, 1, None, 0);
        assert_eq!(drawn.len(), 400);
        // A random subset of the same size, for comparison.
        let mut keep = vec![false; g.len()];
        let mut left: Vec<usize> = (0..g.len()).collect();
        for _ in 0..400 {
            let j = rng.below(left.len() as u64) as usize;
            keep[left.swap_remove(j)] = true;
        }
        let mut random = g.clone();
        random.retain_mask(&keep);
        let (even, uneven) = (covering_radius(&g, &drawn), covering_radius(&g, &random));
        assert!(even < 0.7 * uneven, "even draw {even} m, random {uneven} m");
        // 9.4 m² over 400 Gaussians: about 15 cm apart; the scales follow the kept spacing.
        init::rescale_from_spacing(&mut drawn, 1, 0.0);
        let mean_sigma = drawn
            .log_scales
            .iter()
            .map(|s| f64::from(s[0]).exp())
            .sum::<f64>()
            / 400.0;
        assert!(
            (0.06..0.2).contains(&mean_sigma),
            "mean nearest spacing {mean_sigma} m"
        );
    }
}
