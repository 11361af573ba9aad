//! `sylva bench method`: the paper's Table 5 ablation plus Sylva's arm, on generated plots
//! with known truth, at equal steps — one table a person can compare with the last one.
//!
//! Arms (`--method-arms`): `nerf` (the paper's NeRF baseline, `sylva::nerf`, trained for the
//! mean training time of the 3DGS arms before it, or `--method-nerf-seconds`), `vanilla` (SfM
//! initialisation, no trunk term), `lidar` (LiDAR
//! anchors, no term), `paper` (LiDAR and the paper's L_geo, docs/method.md Stage 4) — these three
//! the paper's Table 5, with neither SfM fill nor sky dome — `bind-lidar` (LiDAR anchors and
//! Sylva's binding), `bind-nosky` (the binding, the SfM points beyond the LiDAR filling the
//! start, `params.train.sfm_fill_m`) and `bind` (Sylva's default: that and the sky dome,
//! `params.train.sky_gaussians`), `bind-mcmc` (`bind` with the MCMC strategy,
//! `params.train.strategy`), `bind-depth` (`bind` with the LiDAR depth loss,
//! `params.train.depth_weight` = `--method-depth-weight`), `bind-exposure` (`bind` with
//! per-image exposure compensation) and `bind-dilation` (`bind` rendered with the reference
//! 3DGS dilation instead of the 2-D Mip filter, `params.train.antialias` off). The arms with
//! Sylva's binding render as Sylva's jobs do, with the Mip filter; `vanilla`, `lidar` and
//! `paper` with the reference dilation, as the reference trainer and the paper do. Stages ingest to segment run once per plot; each arm then runs train
//! and dbh in its own folder beside them. Per arm, pooled over the plots:
//!
//! - held-out PSNR and SSIM (mean over plots), Gaussians at the end, wall time of train + dbh;
//! - DBH RMSE and bias against `field_dbh.csv` for the Gaussians and for the LiDAR;
//! - the paired difference Gaussian − LiDAR per tree: mean |d| with a bootstrap 95 %
//!   interval (2000 resamples of the trees, seeded), and the mean d;
//! - the trunk-surface distance against `truth.json`: every trunk Gaussian (trunk
//!   probability ≥ 0.5, opacity ≥ `params.dbh.min_opacity`, as stage `dbh`) within ±0.1 m of the true breast-height
//!   point along the true axis and within 2 r + 10 cm of it, its distance from the true
//!   elliptical section (positive outside); mean absolute and mean signed, mm.
//!
//! Every arm trains without per-image exposure compensation (`params.train.exposure` off, the
//! reference's and the paper's setting; the generated photos share one exposure), so the
//! held-out metrics are of full images; the output says so.
//!
//! After the table, the arms of the paper's Table 3 (nerf, vanilla, paper, and Sylva's bind)
//! in its layout (PSNR, SSIM, LPIPS with `--lpips-weights`, the mean colour's PSNR, training
//! time, each arm's budget), with the paper's own figures beneath.
//!
//! `--method-long N` instead trains the `bind` arm for N steps (on the first plot) and prints
//! the trunk monitor's surface distance (against the LiDAR stems) every 1000 steps, to show
//! whether it grows with steps.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use serde_json::Value;

use sylva::forest::{TreeRow, compare_with_field};
use sylva::pipeline::params::{DensifyStrategy, InitSource, PipelineParams, TrunkTerm};
use sylva::pipeline::{self, Stage, StageInputs};
use sylva::progress::LogLines;
use sylva::rng::SplitMix64;
use sylva::splat::model::sigmoid;

/// Flags of `sylva bench method`.
#[derive(Debug, Clone, Args)]
pub struct MethodBenchArgs {
    /// method: synthetic preset of the plots (tiny, plot, stand, object).
    #[arg(long, env = "SYLVA_BENCH_METHOD_PRESET", default_value = "stand")]
    pub method_preset: String,
    /// method: seeds of the plots, comma-separated (stand 1 and 2 hold 34 trees).
    #[arg(long, env = "SYLVA_BENCH_METHOD_SEEDS", default_value = "1,2")]
    pub method_seeds: String,
    /// method: arms, comma-separated, among nerf (the paper's NeRF baseline, src/nerf; given
    /// the 3DGS arms' wall time; not in the default list, its held-out renders take minutes on
    /// a CPU or software GPU), vanilla, lidar, paper, bind-lidar, bind-nosky, bind, bind-dilation,
    /// bind-exposure, bind-mcmc, bind-depth.
    #[arg(
        long,
        env = "SYLVA_BENCH_METHOD_ARMS",
        default_value = "vanilla,lidar,paper,bind-lidar,bind"
    )]
    pub method_arms: String,
    /// method: training steps of every arm.
    #[arg(long, env = "SYLVA_BENCH_METHOD_STEPS", default_value_t = 500)]
    pub method_steps: u32,
    /// method: several step budgets, comma-separated (e.g. 500,2000,7000): the table at each,
    /// then the default arm's held-out PSNR gain over `vanilla` at each budget (both arms are
    /// added when missing). Empty: the one budget of --method-steps.
    #[arg(long, env = "SYLVA_BENCH_METHOD_BUDGETS", default_value = "")]
    pub method_budgets: String,
    /// method: longest image side, pixels.
    #[arg(long, env = "SYLVA_BENCH_METHOD_RESOLUTION", default_value_t = 80)]
    pub method_resolution: u32,
    /// method: Gaussian cap (0 = the training device's default budget).
    #[arg(long, env = "SYLVA_BENCH_METHOD_CAP", default_value_t = 10_000)]
    pub method_cap: u32,
    /// method: weight of the LiDAR depth loss in the `bind-depth` arm.
    #[arg(long, env = "SYLVA_BENCH_METHOD_DEPTH_WEIGHT", default_value_t = 0.1)]
    pub method_depth_weight: f64,
    /// method: gpu or cpu.
    #[arg(long, env = "SYLVA_BENCH_METHOD_BACKEND", default_value = "gpu")]
    pub method_backend: String,
    /// method: the working folder (plots and runs are kept and reused).
    #[arg(
        long,
        env = "SYLVA_BENCH_METHOD_WORK",
        default_value = "target/bench-method"
    )]
    pub method_work: PathBuf,
    /// method: the `nerf` arm's wall-clock budget for training, seconds; 0 = the mean training
    /// time of the 3DGS arms listed before it on the same plot (equal wall time).
    #[arg(long, env = "SYLVA_BENCH_METHOD_NERF_SECONDS", default_value_t = 0.0)]
    pub method_nerf_seconds: f64,
    /// method: the `nerf` arm's rays per step (the paper: 4096).
    #[arg(long, env = "SYLVA_BENCH_METHOD_NERF_RAYS", default_value_t = 4096)]
    pub method_nerf_rays: usize,
    /// method: the `nerf` arm's most steps (the paper: 300,000; the wall-clock budget usually
    /// ends it first).
    #[arg(long, env = "SYLVA_BENCH_METHOD_NERF_STEPS", default_value_t = 300_000)]
    pub method_nerf_steps: u32,
    /// method: where the `nerf` arm runs, gpu or cpu; empty: as --method-backend.
    #[arg(long, env = "SYLVA_BENCH_METHOD_NERF_DEVICE", default_value = "")]
    pub method_nerf_device: String,
    /// method: LPIPS weights (a safetensors file made by scripts/lpips_weights.py): the
    /// held-out views are also measured by LPIPS (column LPIPS; n/a without it).
    #[arg(long, env = "SYLVA_LPIPS_WEIGHTS")]
    pub lpips_weights: Option<PathBuf>,
    /// method: instead of the table, train the bind arm this many steps on the first plot and
    /// print the surface distance every 1000 steps.
    #[arg(long, env = "SYLVA_BENCH_METHOD_LONG")]
    pub method_long: Option<u32>,
}

/// One arm: initialisation, trunk term, the SfM fill (metres) and sky dome (Gaussians) where
/// they differ from the defaults of `params.train`, and exposure compensation.
struct Arm {
    init: InitSource,
    term: TrunkTerm,
    fill: Option<f64>,
    sky: Option<u32>,
    strategy: DensifyStrategy,
    /// Weight of the LiDAR depth loss (`--method-depth-weight` for the `bind-depth` arm).
    depth: bool,
    /// Per-image exposure compensation (`params.train.exposure`): on in `bind-exposure` only
    /// (its PSNR and SSIM are then of the held-out right halves).
    exposure: bool,
    /// Mip-Splatting's 2-D filter (`params.train.antialias`): on in the arms with Sylva's
    /// binding but `bind-dilation`, as in Sylva's jobs.
    antialias: bool,
}

/// The arms by name (see the module doc).
fn arm(name: &str) -> anyhow::Result<Arm> {
    let paper = |init, term| Arm {
        init,
        term,
        fill: Some(0.0),
        sky: Some(0),
        strategy: DensifyStrategy::Default,
        depth: false,
        exposure: false,
        antialias: false,
    };
    Ok(match name {
        "vanilla" => paper(InitSource::Sfm, TrunkTerm::Off),
        "lidar" => paper(InitSource::Lidar, TrunkTerm::Off),
        "paper" => paper(InitSource::Lidar, TrunkTerm::Paper),
        "bind-lidar" => Arm {
            antialias: true,
            ..paper(InitSource::Lidar, TrunkTerm::Bind)
        },
        "bind-nosky" => Arm {
            sky: Some(0),
            ..arm("bind")?
        },
        "bind" => Arm {
            init: InitSource::Lidar,
            term: TrunkTerm::Bind,
            fill: None,
            sky: None,
            strategy: DensifyStrategy::Default,
            depth: false,
            exposure: false,
            antialias: true,
        },
        "bind-dilation" => Arm {
            antialias: false,
            ..arm("bind")?
        },
        "bind-exposure" => Arm {
            exposure: true,
            ..arm("bind")?
        },
        "bind-depth" => Arm {
            depth: true,
            ..arm("bind")?
        },
        "bind-mcmc" => Arm {
            strategy: DensifyStrategy::Mcmc,
            ..arm("bind")?
        },
        other => anyhow::bail!(
            "unknown arm {other:?}: vanilla, lidar, paper, bind-lidar, bind-nosky, bind, bind-dilation, bind-exposure, bind-mcmc or bind-depth"
        ),
    })
}

fn read_json(path: &Path) -> anyhow::Result<Value> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_slice(&bytes).with_context(|| format!("{}: invalid JSON", path.display()))
}

/// Generates plot `seed` (once) and runs stages ingest to segment on it (once).
fn prepare_plot(
    preset: sylva::synth::Preset,
    seed: u64,
    dir: &Path,
) -> anyhow::Result<StageInputs> {
    let plot = dir.join("plot");
    if !plot.join("truth.json").is_file() {
        eprintln!("generating {} …", plot.display());
        let mut p = sylva::synth::SynthParams::new(preset);
        p.seed = seed;
        sylva::synth::generate(&p, &plot, &sylva::progress::NoProgress)?;
    }
    let inputs = StageInputs::of_synth_plot(&plot);
    let shared = dir.join("shared");
    let params = PipelineParams::default();
    for &stage in Stage::Train.predecessors() {
        if !shared
            .join(stage.name())
            .join(pipeline::REPORT_FILE)
            .is_file()
        {
            eprintln!("  {stage} on seed {seed}");
            pipeline::execute_stage(stage, &inputs, &shared, &params, &LogLines(stage.name()))
                .map_err(|e| anyhow::anyhow!("stage {stage} on seed {seed}: {e}"))?;
        }
    }
    Ok(inputs)
}

/// A run folder whose shared stages link to the plot's.
fn arm_dir(dir: &Path, name: &str) -> anyhow::Result<PathBuf> {
    let out = dir.join(name);
    std::fs::create_dir_all(&out)?;
    for &stage in Stage::Train.predecessors() {
        let link = out.join(stage.name());
        if !link.exists() {
            std::os::unix::fs::symlink(dir.join("shared").join(stage.name()), &link)?;
        }
    }
    Ok(out)
}

/// What one arm measured on one plot.
#[derive(Debug, Default, Clone)]
struct ArmResult {
    psnr: f64,
    ssim: f64,
    /// Held-out LPIPS (NaN without weights).
    lpips: f64,
    /// Held-out PSNR of the mean training colour, dB.
    baseline_psnr: f64,
    /// Held-out expected depth against the LiDAR: mean absolute error, m.
    depth_mae: f64,
    gaussians: u64,
    seconds: f64,
    /// Training alone, seconds (the train stage's report; the NeRF's training loop).
    train_seconds: f64,
    /// The NeRF arm's steps and rays per step (0 for the 3DGS arms).
    nerf_steps: u32,
    nerf_rays: usize,
    /// Per matched tree: (field, LiDAR, Gaussian) DBH, cm; the Gaussian one may be missing.
    trees: Vec<(f64, f64, Option<f64>)>,
    /// Per trunk Gaussian in a true breast-height slice: signed distance from the true stem, m.
    offsets: Vec<f64>,
}

fn run_arm(
    dir: &Path,
    inputs: &StageInputs,
    name: &str,
    a: &MethodBenchArgs,
    steps: u32,
) -> anyhow::Result<ArmResult> {
    let arm = arm(name)?;
    let mut params = PipelineParams::default();
    params.train.init = arm.init;
    params.train.sfm_fill_m = arm.fill.unwrap_or(params.train.sfm_fill_m);
    params.train.sky_gaussians = arm.sky.unwrap_or(params.train.sky_gaussians);
    params.train.semantic = arm.term;
    params.train.strategy = arm.strategy;
    if arm.depth {
        params.train.depth_weight = a.method_depth_weight;
    }
    params.train.exposure = arm.exposure;
    params.train.antialias = arm.antialias;
    params.train.steps = steps;
    params.train.resolution = a.method_resolution;
    params.train.max_gaussians = a.method_cap;
    params.train.backend = match a.method_backend.as_str() {
        "cpu" => sylva::pipeline::params::TrainBackend::Cpu,
        _ => sylva::pipeline::params::TrainBackend::Gpu,
    };
    let weight = if arm.depth {
        format!("-w{}", a.method_depth_weight)
    } else {
        String::new()
    };
    // The filter is in the name: folders of runs made before the Mip filter became the
    // binding arms' default (rendered with the dilation) are not reused for them.
    let filter = if arm.antialias { "-mip" } else { "" };
    let out = arm_dir(
        dir,
        &format!(
            "{name}-{steps}-{}-{}{weight}{filter}",
            a.method_resolution, a.method_cap
        ),
    )?;
    let start = Instant::now();
    for stage in [Stage::Train, Stage::Dbh] {
        if !out.join(stage.name()).join(pipeline::REPORT_FILE).is_file() {
            pipeline::execute_stage(stage, inputs, &out, &params, &LogLines(stage.name()))
                .map_err(|e| anyhow::anyhow!("arm {name}, stage {stage}: {e}"))?;
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    let train = read_json(&out.join("train").join(pipeline::REPORT_FILE))?;
    let dbh = read_json(&out.join("dbh").join(pipeline::REPORT_FILE))?;
    let stems = read_json(&dir.join("shared/segment/stems.json"))?;
    let rows: Vec<TreeRow> = serde_json::from_value(stems["trees"].clone())?;
    let gs_of = |id: u32| {
        dbh["trees"].as_array().and_then(|t| {
            t.iter()
                .find(|r| r["tree_id"].as_u64() == Some(u64::from(id)))
                .and_then(|r| r["dbh_gs_cm"].as_f64())
        })
    };
    let field_path = inputs
        .field_dbh
        .as_deref()
        .context("the plot has no field_dbh.csv")?;
    let field = sylva::io::tables::read_field_dbh(field_path)?;
    let cmp = compare_with_field(&rows, &field, sylva::forest::accuracy::MATCH_DISTANCE_M);
    let trees = cmp
        .matches
        .iter()
        .map(|m| (m.dbh_field_cm, m.dbh_lidar_cm, gs_of(m.tree_id)))
        .collect();
    let offset: Vec<f64> = serde_json::from_value(train["offset"].clone())?;
    let offsets = truth_offsets(
        &out.join("train/splats.ply"),
        &dir.join("plot/truth.json"),
        DVec3::new(offset[0], offset[1], offset[2]),
        params.dbh.min_opacity as f32,
    )?;
    Ok(ArmResult {
        psnr: train["render"]["psnr"].as_f64().unwrap_or(f64::NAN),
        ssim: train["render"]["ssim"].as_f64().unwrap_or(f64::NAN),
        lpips: train["render"]["lpips"].as_f64().unwrap_or(f64::NAN),
        baseline_psnr: train["baseline_psnr"].as_f64().unwrap_or(f64::NAN),
        depth_mae: train["depth"]["heldout_mae_m"].as_f64().unwrap_or(f64::NAN),
        gaussians: train["gaussians"]["final"].as_u64().unwrap_or(0),
        seconds,
        train_seconds: train["seconds"].as_f64().unwrap_or(f64::NAN),
        nerf_steps: 0,
        nerf_rays: 0,
        trees,
        offsets,
    })
}

/// Signed distances (m, + outside) of the trunk Gaussians in each true stem's breast-height
/// slice from the true elliptical section (see the module doc).
fn truth_offsets(
    splats: &Path,
    truth: &Path,
    offset: DVec3,
    min_opacity: f32,
) -> anyhow::Result<Vec<f64>> {
    let file = std::fs::File::open(splats).with_context(|| splats.display().to_string())?;
    let g = sylva::splat::export::read_ply(std::io::BufReader::new(file))?;
    let truth = read_json(truth)?;
    let v3 = |v: &Value| -> Option<DVec3> {
        Some(DVec3::new(v[0].as_f64()?, v[1].as_f64()?, v[2].as_f64()?))
    };
    let mut out = Vec::new();
    for t in truth["trees"].as_array().into_iter().flatten() {
        let (Some(bh), Some(axis), Some(major)) = (
            v3(&t["breast_height_point"]),
            v3(&t["axis"]),
            v3(&t["section_major_axis"]),
        ) else {
            continue;
        };
        let (Some(a), Some(b)) = (
            t["section_semi_axes_m"][0].as_f64(),
            t["section_semi_axes_m"][1].as_f64(),
        ) else {
            continue;
        };
        let axis = axis.normalize_or(DVec3::Z);
        let major = (major - axis * major.dot(axis)).normalize_or(DVec3::X);
        let minor = axis.cross(major);
        for i in 0..g.len() {
            if g.trunk_prob[i] < 0.5 || sigmoid(g.opacity_logits[i]) < min_opacity {
                continue;
            }
            let p = DVec3::from_array(g.means[i].map(f64::from)) + offset;
            let d = p - bh;
            let along = d.dot(axis);
            let radial = d - axis * along;
            let r = radial.length();
            if along.abs() > 0.1 || r > 2.0 * a + 0.1 || r < 1e-9 {
                continue;
            }
            let (c, s) = (radial.dot(major) / r, radial.dot(minor) / r);
            let r_true = a * b / ((b * c).powi(2) + (a * s).powi(2)).sqrt();
            out.push(r - r_true);
        }
    }
    Ok(out)
}

/// Mean of `v` (NaN when empty).
fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// Bootstrap 95 % interval of the mean of `v` (2000 resamples, seeded).
fn bootstrap_ci(v: &[f64]) -> (f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let mut rng = SplitMix64::new(0x5ee_d0b0);
    let mut means: Vec<f64> = (0..2000)
        .map(|_| {
            (0..v.len())
                .map(|_| v[rng.below(v.len() as u64) as usize])
                .sum::<f64>()
                / v.len() as f64
        })
        .collect();
    means.sort_by(f64::total_cmp);
    (means[49], means[1949])
}

fn rmse_bias(pairs: &[(f64, f64)]) -> (f64, f64) {
    let d: Vec<f64> = pairs.iter().map(|(est, truth)| est - truth).collect();
    (
        mean(&d.iter().map(|x| x * x).collect::<Vec<_>>()).sqrt(),
        mean(&d),
    )
}

/// Runs the benchmark and prints its table.
pub fn run(a: &MethodBenchArgs) -> anyhow::Result<()> {
    if let Some(p) = &a.lpips_weights {
        sylva::splat::eval::use_lpips_weights(p.clone());
    }
    sylva::splat::eval::lpips()?;
    let preset = sylva::synth::Preset::from_name(&a.method_preset).with_context(|| {
        format!(
            "--method-preset {:?}: tiny, plot, stand or object",
            a.method_preset
        )
    })?;
    let seeds: Vec<u64> = a
        .method_seeds
        .split(',')
        .map(|s| s.trim().parse())
        .collect::<Result<_, _>>()
        .context("--method-seeds: comma-separated integers")?;
    let mut arms: Vec<String> = a
        .method_arms
        .split(',')
        .map(|s| s.trim().to_string())
        .collect();
    let budgets: Vec<u32> = if a.method_budgets.trim().is_empty() {
        vec![a.method_steps]
    } else {
        super::parse_positive_list("--method-budgets", &a.method_budgets)?
    };
    if budgets.len() > 1 {
        for must in [GAIN_BASE, GAIN_ARM] {
            if !arms.iter().any(|n| n == must) {
                arms.push(must.to_string());
            }
        }
    }
    for name in &arms {
        if name != NERF {
            arm(name)?;
        }
    }
    let plots: Vec<(PathBuf, StageInputs)> = seeds
        .iter()
        .map(|&s| {
            let dir = a.method_work.join(format!("{}-{s}", a.method_preset));
            prepare_plot(preset, s, &dir).map(|i| (dir, i))
        })
        .collect::<anyhow::Result<_>>()?;
    if let Some(long) = a.method_long {
        return run_long(a, &plots, long);
    }
    let mut gains = Vec::new();
    for &steps in &budgets {
        let psnr = print_table(a, &plots, &arms, steps)?;
        let of = |name: &str| psnr.iter().find(|(n, _)| n == name).map(|(_, v)| v.clone());
        if let (Some(base), Some(arm)) = (of(GAIN_BASE), of(GAIN_ARM)) {
            gains.push((steps, base, arm));
        }
    }
    if budgets.len() > 1 {
        println!(
            "\nthe default arm ({GAIN_ARM}) against {GAIN_BASE}, held-out PSNR per budget (each plot's difference, then their mean)\n"
        );
        println!("| steps | {GAIN_BASE} dB | {GAIN_ARM} dB | gain dB | gain per plot dB |");
        println!("|---|---|---|---|---|");
        for (steps, base, arm) in gains {
            let d: Vec<f64> = arm.iter().zip(&base).map(|(x, y)| x - y).collect();
            println!(
                "| {steps} | {:.2} | {:.2} | {:+.2} | {} |",
                mean(&base),
                mean(&arm),
                mean(&d),
                d.iter()
                    .map(|x| format!("{x:+.2}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    Ok(())
}

/// The arm a budget sweep compares ([`run`] with `--method-budgets`): Sylva's default.
const GAIN_ARM: &str = "bind";
/// What [`GAIN_ARM`] is compared with: vanilla 3DGS from the SfM points.
const GAIN_BASE: &str = "vanilla";

/// Runs every arm on every plot at `steps` and prints the table; returns each arm's held-out
/// PSNR per plot, dB.
fn print_table(
    a: &MethodBenchArgs,
    plots: &[(PathBuf, StageInputs)],
    arms: &[String],
    steps: u32,
) -> anyhow::Result<Vec<(String, Vec<f64>)>> {
    let mut per_arm = Vec::new();
    println!(
        "\n{} seeds {} — {} steps at {} px, cap {} Gaussians, backend {}\n",
        a.method_preset, a.method_seeds, steps, a.method_resolution, a.method_cap, a.method_backend
    );
    println!(
        "exposure compensation off in every arm but bind-exposure, whose PSNR and SSIM are of the held-out right halves; the others' are of the full held-out images\n"
    );
    println!(
        "| arm | PSNR dB | SSIM | LPIPS | depth MAE m | DBH RMSE GS cm | bias GS cm | DBH RMSE LiDAR cm | bias LiDAR cm | mean abs(GS − LiDAR) cm [95 % CI] | mean GS − LiDAR cm | trees GS / matched | surface abs mm | surface signed mm | Gaussians | wall s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    // Per plot, the training seconds of the 3DGS arms so far (the NeRF's equal wall time).
    let mut gs_seconds: Vec<Vec<f64>> = vec![Vec::new(); plots.len()];
    let mut results: Vec<(String, Vec<ArmResult>)> = Vec::new();
    for name in arms {
        let mut all = Vec::new();
        for (k, (dir, inputs)) in plots.iter().enumerate() {
            eprintln!("arm {name} on {}", dir.display());
            let r = if name == NERF {
                let budget = if a.method_nerf_seconds > 0.0 {
                    a.method_nerf_seconds
                } else if gs_seconds[k].is_empty() {
                    anyhow::bail!(
                        "the nerf arm's equal wall time needs a 3DGS arm listed before it, or --method-nerf-seconds"
                    );
                } else {
                    mean(&gs_seconds[k])
                };
                run_nerf_arm(dir, inputs, a, budget)?
            } else {
                let r = run_arm(dir, inputs, name, a, steps)?;
                gs_seconds[k].push(r.train_seconds);
                r
            };
            all.push(r);
        }
        results.push((name.clone(), all.clone()));
        per_arm.push((name.clone(), all.iter().map(|r| r.psnr).collect()));
        let trees: Vec<(f64, f64, Option<f64>)> =
            all.iter().flat_map(|r| r.trees.iter().copied()).collect();
        let gs: Vec<(f64, f64)> = trees.iter().filter_map(|t| Some((t.2?, t.0))).collect();
        let lidar: Vec<(f64, f64)> = trees.iter().map(|t| (t.1, t.0)).collect();
        let diff: Vec<f64> = trees.iter().filter_map(|t| Some(t.2? - t.1)).collect();
        let abs_diff: Vec<f64> = diff.iter().map(|d| d.abs()).collect();
        let (ci_lo, ci_hi) = bootstrap_ci(&abs_diff);
        let (rg, bg) = rmse_bias(&gs);
        let (rl, bl) = rmse_bias(&lidar);
        let offsets: Vec<f64> = all.iter().flat_map(|r| r.offsets.iter().copied()).collect();
        let abs_off: Vec<f64> = offsets.iter().map(|o| o.abs()).collect();
        let f = |x: f64| {
            if x.is_finite() {
                format!("{x:.2}")
            } else {
                "n/a".into()
            }
        };
        let f3 = |x: f64| {
            if x.is_finite() {
                format!("{x:.3}")
            } else {
                "n/a".into()
            }
        };
        // Millimetres, one decimal, signed when asked; n/a without any trunk Gaussian.
        let f1 = |x: f64, signed: bool| match (x.is_finite(), signed) {
            (false, _) => "n/a".to_string(),
            (true, true) => format!("{x:+.1}"),
            (true, false) => format!("{x:.1}"),
        };
        println!(
            "| {name} | {} | {:.3} | {} | {} | {} | {} | {} | {} | {} [{}, {}] | {} | {} / {} | {} | {} | {} | {:.0} |",
            f(mean(&all.iter().map(|r| r.psnr).collect::<Vec<_>>())),
            mean(&all.iter().map(|r| r.ssim).collect::<Vec<_>>()),
            f3(mean(&all.iter().map(|r| r.lpips).collect::<Vec<_>>())),
            f(mean(&all.iter().map(|r| r.depth_mae).collect::<Vec<_>>())),
            f(rg),
            f(bg),
            f(rl),
            f(bl),
            f(mean(&abs_diff)),
            f(ci_lo),
            f(ci_hi),
            f(mean(&diff)),
            gs.len(),
            trees.len(),
            f1(mean(&abs_off) * 1000.0, false),
            f1(mean(&offsets) * 1000.0, true),
            all.iter().map(|r| r.gaussians).sum::<u64>(),
            all.iter().map(|r| r.seconds).sum::<f64>(),
        );
    }
    print_paper_layout(a, &results, steps);
    Ok(per_arm)
}

/// The arm that trains the paper's NeRF baseline ([`run_nerf_arm`]).
const NERF: &str = "nerf";

/// One method on one of the paper's plots: PSNR dB, SSIM, LPIPS, minutes.
type PaperFigures = (f64, f64, f64, f64);

/// The paper's Table 3, per plot: NeRF, 3DGS, the paper's (its LPIPS 0.318 is a figure, not
/// an approximation of 1/π).
#[allow(clippy::approx_constant)]
const PAPER_TABLE3: [(&str, [PaperFigures; 3]); 3] = [
    (
        "NeRF",
        [
            (23.46, 0.639, 0.271, 684.0),
            (23.69, 0.734, 0.177, 747.0),
            (22.06, 0.665, 0.387, 2579.0),
        ],
    ),
    (
        "3DGS",
        [
            (24.70, 0.749, 0.280, 72.0),
            (23.95, 0.831, 0.164, 95.0),
            (23.38, 0.717, 0.334, 198.0),
        ],
    ),
    (
        "Ours",
        [
            (25.48, 0.772, 0.266, 70.0),
            (25.14, 0.884, 0.114, 88.0),
            (24.21, 0.736, 0.318, 204.0),
        ],
    ),
];

/// The arms in the paper's Table 3 layout (PSNR, SSIM, LPIPS, time) with the paper's own
/// figures beneath, and each arm's budget.
fn print_paper_layout(a: &MethodBenchArgs, results: &[(String, Vec<ArmResult>)], steps: u32) {
    let label = |name: &str| match name {
        NERF => "NeRF",
        "vanilla" => "3DGS",
        "paper" => "Ours (the paper's method)",
        "bind" => "Sylva (default arm)",
        _ => "",
    };
    let rows: Vec<&(String, Vec<ArmResult>)> = results
        .iter()
        .filter(|(n, _)| !label(n).is_empty())
        .collect();
    if rows.is_empty() {
        return;
    }
    println!(
        "
the paper's Table 3 layout: {} seeds {} at {} px, held-out views, this machine\n",
        a.method_preset, a.method_seeds, a.method_resolution
    );
    println!(
        "| method | arm | PSNR dB | SSIM | LPIPS | mean colour PSNR dB | training s | budget |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    let f = |x: f64, d: usize| {
        if x.is_finite() {
            format!("{x:.d$}")
        } else {
            "n/a".into()
        }
    };
    for (name, all) in rows {
        let m = |g: fn(&ArmResult) -> f64| mean(&all.iter().map(g).collect::<Vec<_>>());
        let budget = if name == NERF {
            let steps: Vec<String> = all.iter().map(|r| r.nerf_steps.to_string()).collect();
            format!(
                "{} steps of {} rays (per plot) on the {}, {}",
                steps.join(", "),
                all.first().map_or(0, |r| r.nerf_rays),
                nerf_device(a),
                if a.method_nerf_seconds > 0.0 {
                    format!("{:.0} s per plot", a.method_nerf_seconds)
                } else {
                    "the 3DGS arms' mean training time per plot".to_string()
                }
            )
        } else {
            format!("{steps} steps, cap {} Gaussians", a.method_cap)
        };
        println!(
            "| {} | {name} | {} | {} | {} | {} | {} | {budget} |",
            label(name),
            f(m(|r| r.psnr), 2),
            f(m(|r| r.ssim), 3),
            f(m(|r| r.lpips), 3),
            f(m(|r| r.baseline_psnr), 2),
            f(all.iter().map(|r| r.train_seconds).sum::<f64>(), 0),
        );
    }
    println!(
        "
the paper's Table 3 (plots 1 / 2 / 3; 1920×1080 photos, RTX 4060; NeRF 300,000 steps, 3DGS and its method 30,000)\n"
    );
    println!("| method | PSNR dB | SSIM | LPIPS | time min |");
    println!("|---|---|---|---|---|");
    for (name, plots) in PAPER_TABLE3 {
        let join =
            |g: fn(&PaperFigures) -> String| plots.iter().map(g).collect::<Vec<_>>().join(" / ");
        println!(
            "| {name} | {} | {} | {} | {} |",
            join(|p| format!("{:.2}", p.0)),
            join(|p| format!("{:.3}", p.1)),
            join(|p| format!("{:.3}", p.2)),
            join(|p| format!("{:.0}", p.3)),
        );
    }
}

/// Where the NeRF arm runs: `--method-nerf-device`, else `--method-backend`.
fn nerf_device(a: &MethodBenchArgs) -> &str {
    if a.method_nerf_device.is_empty() {
        &a.method_backend
    } else {
        &a.method_nerf_device
    }
}

/// Trains the paper's NeRF baseline (src/nerf, the paper's settings but the rays per step and
/// the steps of `--method-nerf-rays` and `--method-nerf-steps`) for `budget` seconds on the
/// plot's photos at the arms' resolution and split, and measures its held-out views. Kept in
/// `<plot>/nerf-<seconds>-<px>-<rays>/result.json` and reused.
fn run_nerf_arm(
    dir: &Path,
    inputs: &StageInputs,
    a: &MethodBenchArgs,
    budget: f64,
) -> anyhow::Result<ArmResult> {
    let out = dir.join(format!(
        "{NERF}-{:.0}-{}-{}-{}",
        budget,
        a.method_resolution,
        a.method_nerf_rays,
        nerf_device(a)
    ));
    let saved = out.join("result.json");
    if let Ok(v) = read_json(&saved) {
        let g = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
        return Ok(ArmResult {
            psnr: g("psnr"),
            ssim: g("ssim"),
            lpips: g("lpips"),
            baseline_psnr: g("baseline_psnr"),
            depth_mae: f64::NAN,
            seconds: g("seconds"),
            train_seconds: g("train_seconds"),
            nerf_steps: v["steps"].as_u64().unwrap_or(0) as u32,
            nerf_rays: v["rays"].as_u64().unwrap_or(0) as usize,
            ..ArmResult::default()
        });
    }
    let start = Instant::now();
    let mut params = PipelineParams::default();
    params.train.resolution = a.method_resolution;
    let cfg = params.train.config();
    let model = sylva::io::colmap::read_model(
        &dir.join("shared/register/sparse"),
        &sylva::progress::NoProgress,
    )?;
    let colmap = inputs
        .colmap
        .as_deref()
        .context("the plot has no COLMAP project")?;
    let images = sylva::io::colmap::find_project(colmap)?
        .images_dir
        .context("the plot's COLMAP project has no images/")?;
    let data = sylva::splat::dataset::load(
        &model,
        &images,
        cfg.resolution,
        cfg.test_every,
        cfg.host_photo_mb,
        &sylva::progress::NoProgress,
    )?;
    let nerf_cfg = sylva::nerf::NerfConfig {
        rays: a.method_nerf_rays,
        steps: a.method_nerf_steps,
        seconds: Some(budget),
        device: match nerf_device(a) {
            "cpu" => sylva::nerf::NerfDevice::Cpu,
            _ => sylva::nerf::NerfDevice::Gpu,
        },
        ..sylva::nerf::NerfConfig::default()
    };
    let trained = sylva::nerf::train(&data, &nerf_cfg, &LogLines("nerf"))?;
    let (eval, baseline) = sylva::nerf::evaluate(&trained.nerf, &data)?;
    let r = ArmResult {
        psnr: f64::from(eval.psnr),
        ssim: f64::from(eval.ssim),
        lpips: eval.lpips.map_or(f64::NAN, f64::from),
        baseline_psnr: f64::from(baseline),
        depth_mae: f64::NAN,
        seconds: start.elapsed().as_secs_f64(),
        train_seconds: trained.train_seconds,
        nerf_steps: trained.steps,
        nerf_rays: trained.rays_per_step,
        ..ArmResult::default()
    };
    std::fs::create_dir_all(&out)?;
    std::fs::write(
        &saved,
        serde_json::to_vec_pretty(&serde_json::json!({
            "psnr": r.psnr, "ssim": r.ssim,
            "lpips": eval.lpips, "baseline_psnr": r.baseline_psnr, "seconds": r.seconds, "train_seconds": r.train_seconds,
            "steps": r.nerf_steps, "rays": r.nerf_rays, "budget_seconds": budget,
            "eval": eval,
        }))?,
    )?;
    Ok(r)
}

/// The long run of the bind arm: its loss.csv holds the trunk monitor's columns.
fn run_long(
    a: &MethodBenchArgs,
    plots: &[(PathBuf, StageInputs)],
    steps: u32,
) -> anyhow::Result<()> {
    let Some((dir, inputs)) = plots.first() else {
        anyhow::bail!("no plot");
    };
    let r = run_arm(dir, inputs, "bind", a, steps)?;
    let out = dir.join(format!(
        "bind-{steps}-{}-{}",
        a.method_resolution, a.method_cap
    ));
    let csv = std::fs::read_to_string(out.join("train/loss.csv"))?;
    println!(
        "\nbind arm, {steps} steps at {} px, cap {}, on {}: trunk monitor every 1000 steps\n",
        a.method_resolution,
        a.method_cap,
        dir.display()
    );
    println!("| step | Gaussians | slice Gaussians | surface abs mm | surface signed mm |");
    println!("|---|---|---|---|---|");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name);
    let (Some(cs), Some(cn), Some(cc), Some(ca), Some(co)) = (
        col("step"),
        col("n_gaussians"),
        col("slice_count"),
        col("surface_abs_mm"),
        col("surface_offset_mm"),
    ) else {
        anyhow::bail!("loss.csv has no trunk monitor columns");
    };
    for line in lines {
        let v: Vec<&str> = line.split(',').collect();
        let step: u32 = v.get(cs).and_then(|s| s.parse().ok()).unwrap_or(0);
        if v.get(ca).is_some_and(|s| !s.is_empty()) && (step.is_multiple_of(1000) || step == steps)
        {
            println!(
                "| {step} | {} | {} | {} | {} |",
                v.get(cn).unwrap_or(&""),
                v.get(cc).unwrap_or(&""),
                v.get(ca).unwrap_or(&""),
                v.get(co).unwrap_or(&"")
            );
        }
    }
    let abs: Vec<f64> = r.offsets.iter().map(|o| o.abs()).collect();
    println!(
        "\nat the end, against truth.json: {:.1} mm absolute, {:+.1} mm signed over {} slice Gaussians; PSNR {:.2} dB",
        mean(&abs) * 1000.0,
        mean(&r.offsets) * 1000.0,
        r.offsets.len(),
        r.psnr
    );
    Ok(())
}
