//! `sylva run`: the pipeline in-process on local files, without a server.

use super::*;

fn parse_stage(s: &str) -> Result<Stage, String> {
    Stage::from_name(s).ok_or_else(|| {
        format!(
            "unknown stage {s:?}; stages: {}",
            Stage::ALL.map(|s| s.name()).join(", ")
        )
    })
}

#[derive(Debug, Args)]
#[command(group(clap::ArgGroup::new("views").required(true).args(["colmap", "photos"])))]
pub struct RunArgs {
    /// The LiDAR point cloud (LAS, LAZ, PLY, XYZ), in metres.
    #[arg(long, env = "SYLVA_LIDAR")]
    pub lidar: PathBuf,
    /// The COLMAP project: a folder (images/ and sparse/0 or sparse/) or a zip/tar(.gz) of one.
    #[arg(long, env = "SYLVA_COLMAP", conflicts_with = "photos")]
    pub colmap: Option<PathBuf>,
    /// Photos (JPEG, PNG, TIFF) instead of a COLMAP project: a folder or a zip/tar(.gz) of
    /// one. Stage `sfm` runs COLMAP on them (Debian's package `colmap`).
    #[arg(long, env = "SYLVA_PHOTOS")]
    pub photos: Option<PathBuf>,
    /// Control point pairs (CSV: sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z), at least 4.
    #[arg(long, env = "SYLVA_CONTROL_POINTS")]
    pub control_points: Option<PathBuf>,
    /// Field-measured DBH (CSV: x,y,dbh_cm) for accuracy figures.
    #[arg(long, env = "SYLVA_FIELD_DBH")]
    pub field_dbh: Option<PathBuf>,
    /// Output folder: each stage writes under <out>/<stage>/, and <out>/results.json gathers
    /// every finished stage's report.
    #[arg(long, env = "SYLVA_OUT")]
    pub out: PathBuf,
    /// Stop after this stage (ingest, sfm, register, anchors, segment, train, dbh, export).
    #[arg(long, env = "SYLVA_UNTIL", value_parser = parse_stage)]
    pub until: Option<Stage>,
    /// Start at this stage, keeping the earlier stages' outputs already in --out (each must
    /// have finished there: its folder holds a report.json). To train again with other
    /// parameters without redoing the LiDAR stages.
    #[arg(long, env = "SYLVA_FROM", value_parser = parse_stage)]
    pub from: Option<Stage>,
    /// Job parameters as a JSON file (the `params` object of the API; see `GET /v1/options`).
    #[arg(long, env = "SYLVA_PARAMS")]
    pub params: Option<PathBuf>,
    /// The CRS of the LiDAR file's coordinates (EPSG:<code>, WKT or a PROJ string), over what
    /// the file declares; overrides the params file's `crs`.
    #[arg(long, env = "SYLVA_CRS")]
    pub crs: Option<String>,
    /// Gaussians initialised from the LiDAR anchors (lidar, the paper's method) or the SfM
    /// points (sfm, vanilla 3DGS); overrides the params file.
    #[arg(long, env = "SYLVA_INIT")]
    pub init: Option<String>,
    /// What holds the trunk Gaussians: bind (Sylva's binding, the default), paper (the
    /// paper's L_geo) or off; overrides the params file.
    #[arg(long, env = "SYLVA_SEMANTIC")]
    pub semantic: Option<String>,
    /// Training steps; overrides the params file.
    #[arg(long, env = "SYLVA_STEPS")]
    pub steps: Option<u32>,
    /// Longest image side for training, pixels; overrides the params file.
    #[arg(long, env = "SYLVA_RESOLUTION")]
    pub resolution: Option<u32>,
    /// Where training runs: gpu or cpu; overrides the params file.
    #[arg(long, env = "SYLVA_BACKEND")]
    pub backend: Option<String>,
    /// Densification: default or mcmc (needs `max_gaussians`); overrides the params file.
    #[arg(long, env = "SYLVA_STRATEGY")]
    pub strategy: Option<String>,
    /// Weight of the LiDAR depth loss (0 = off); overrides the params file.
    #[arg(long, env = "SYLVA_DEPTH_WEIGHT")]
    pub depth_weight: Option<f64>,
    /// Anti-aliased rasterisation in training and the held-out renders (Mip-Splatting's 2-D
    /// filter), on or off; overrides the params file.
    #[arg(long, env = "SYLVA_ANTIALIAS")]
    pub antialias: Option<String>,
    /// Per-image exposure compensation, on (the default of `params.train.exposure`) or off;
    /// overrides the params file. On, the held-out metrics are of the photos' right halves.
    #[arg(long, env = "SYLVA_EXPOSURE")]
    pub exposure: Option<String>,
    /// Log filter in tracing's syntax.
    #[arg(long, env = "SYLVA_LOG", default_value = "warn")]
    pub log: String,
}

/// A JSON file read as `T`; errors name the file and `what` it should hold.
pub(super) fn json_file<T: serde::de::DeserializeOwned>(
    path: &Path,
    what: &str,
) -> anyhow::Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: invalid {what}", path.display()))
}

/// `input` itself when it is a folder; an archive unpacked to `<out>/inputs/<name>`.
pub(super) async fn unpacked(input: &Path, out: &Path, name: &str) -> anyhow::Result<PathBuf> {
    if !input.is_file() {
        return Ok(input.to_path_buf());
    }
    let dest = out.join("inputs").join(name);
    if dest.exists() {
        std::fs::remove_dir_all(&dest)?;
    }
    let (src, d2) = (input.to_path_buf(), dest.clone());
    tokio::task::spawn_blocking(move || {
        archive::extract_archive(
            &src,
            &d2,
            &ExtractLimits::default(),
            &sylva::progress::NoProgress,
        )
    })
    .await?
    .with_context(|| format!("{}: cannot unpack", input.display()))?;
    Ok(dest)
}

/// `--strategy`'s value.
pub(super) fn parse_strategy(s: &str) -> anyhow::Result<sylva::pipeline::params::DensifyStrategy> {
    use sylva::pipeline::params::DensifyStrategy;
    choice(
        "--strategy",
        s,
        &[
            ("default", DensifyStrategy::Default),
            ("mcmc", DensifyStrategy::Mcmc),
        ],
    )
}

/// `--backend`'s value.
pub(super) fn parse_backend(s: &str) -> anyhow::Result<sylva::pipeline::params::TrainBackend> {
    use sylva::pipeline::params::TrainBackend;
    choice(
        "--backend",
        s,
        &[("gpu", TrainBackend::Gpu), ("cpu", TrainBackend::Cpu)],
    )
}

/// The value of flag `flag` named `value` among `choices`; anything else is an error naming the
/// flag and its choices.
fn choice<T: Copy>(flag: &str, value: &str, choices: &[(&str, T)]) -> anyhow::Result<T> {
    if let Some(&(_, v)) = choices.iter().find(|(name, _)| *name == value) {
        return Ok(v);
    }
    let names: Vec<&str> = choices.iter().map(|(name, _)| *name).collect();
    let (last, rest) = names.split_last().expect("choices");
    anyhow::bail!(
        "{flag} must be {} or {last}, not {value:?}",
        rest.join(", ")
    )
}

/// `sylva train --fill`: `on` (the defaults of [`sylva::splat::init::CoverageFill`]: only the
/// cells whose depth the photos agree on), `guess` (every uncovered cell, those without an
/// agreed depth at the 90th percentile of the depths their photo sees, the rule before the
/// sweep) or `off`.
pub(super) fn fill_choice(value: &str) -> anyhow::Result<Option<sylva::splat::init::CoverageFill>> {
    #[derive(Clone, Copy)]
    enum Fill {
        On,
        Textured,
        Guess,
        Off,
    }
    let on = sylva::splat::init::CoverageFill::default();
    let fill = choice(
        "--fill",
        value,
        &[
            ("on", Fill::On),
            ("textured", Fill::Textured),
            ("guess", Fill::Guess),
            ("off", Fill::Off),
        ],
    )?;
    Ok(match fill {
        Fill::On => Some(on),
        Fill::Textured => Some(sylva::splat::init::CoverageFill {
            textured: true,
            ..on
        }),
        Fill::Guess => Some(sylva::splat::init::CoverageFill {
            depth_percentile: Some(0.9),
            place_unseen: true,
            ..on
        }),
        Fill::Off => None,
    })
}

/// Applies `sylva run`'s training flags to `params`.
fn apply_train_flags(a: &RunArgs, params: &mut PipelineParams) -> anyhow::Result<()> {
    use sylva::pipeline::params::{InitSource, TrunkTerm};
    let t = &mut params.train;
    if let Some(v) = a.init.as_deref() {
        let init = [("lidar", InitSource::Lidar), ("sfm", InitSource::Sfm)];
        t.init = choice("--init", v, &init)?;
    }
    if let Some(v) = a.semantic.as_deref() {
        let terms = [
            ("bind", TrunkTerm::Bind),
            ("paper", TrunkTerm::Paper),
            ("off", TrunkTerm::Off),
        ];
        t.semantic = choice("--semantic", v, &terms)?;
    }
    if let Some(v) = a.backend.as_deref() {
        t.backend = parse_backend(v)?;
    }
    if let Some(s) = a.strategy.as_deref() {
        t.strategy = parse_strategy(s)?;
    }
    if let Some(w) = a.depth_weight {
        t.depth_weight = w;
    }
    if let Some(e) = a.exposure.as_deref() {
        t.exposure = on_off("--exposure", e)?;
    }
    if let Some(s) = a.steps {
        t.steps = s;
    }
    if let Some(r) = a.resolution {
        t.resolution = r;
    }
    if let Some(v) = a.antialias.as_deref() {
        t.antialias = on_off("--antialias", v)?;
    }
    Ok(())
}

/// `on` or `off` of flag `flag` as a bool; anything else is an error naming the flag.
/// The value of an on/off flag.
pub(super) fn on_off(flag: &str, value: &str) -> anyhow::Result<bool> {
    choice(flag, value, &[("on", true), ("off", false)])
}

/// Adds the summary keys of results.json: `registration`, `render` = {psnr, ssim, views},
/// `plot` (the stand figures of stage `dbh`, else `segment`) and, with field data, `dbh` = {rmse_gs_cm, rmse_lidar_cm, bias_gs_cm, r2_gs, recall, matched,
/// trunk_radial_dev_mm} (the last: how far the trunk Gaussians sit from the LiDAR stems).
fn summarise(results: &mut serde_json::Map<String, serde_json::Value>) {
    let pick = |stage: &str, key: &str| {
        results
            .get(stage)
            .and_then(|r| r.get(key))
            .filter(|v| !v.is_null())
            .cloned()
    };
    let registration = results.get("register").cloned();
    let plot = pick("dbh", "plot").or_else(|| pick("segment", "plot"));
    let render = pick("train", "render");
    let dev = pick("dbh", "mean_radial_dev_mm");
    let dbh = pick("dbh", "dbh").map(|mut d| {
        if let (Some(obj), Some(dev)) = (d.as_object_mut(), dev) {
            obj.insert("trunk_radial_dev_mm".into(), dev);
        }
        d
    });
    for (k, v) in [
        ("registration", registration),
        ("render", render),
        ("dbh", dbh),
        ("plot", plot),
    ] {
        if let Some(v) = v {
            results.insert(k.to_string(), v);
        }
    }
}

fn write_results(
    out: &Path,
    results: &serde_json::Map<String, serde_json::Value>,
) -> anyhow::Result<()> {
    let path = out.join("results.json");
    let text = serde_json::to_vec_pretty(results)?;
    pipeline::write_synced(&path, &text).with_context(|| format!("cannot write {}", path.display()))
}

pub(super) async fn run(a: RunArgs) -> anyhow::Result<ExitCode> {
    let store = StoreArgs {
        data: PathBuf::new(),
        database: None,
        store: None,
        log: a.log.clone(),
        log_json: false,
    };
    init_tracing(&store);
    let mut params: PipelineParams = match &a.params {
        Some(p) => json_file(p, "parameters")?,
        None => PipelineParams::default(),
    };
    if a.until.is_some() {
        params.until = a.until;
    }
    if let Some(crs) = &a.crs {
        sylva::io::crs::Crs::parse_projected(crs).context("--crs")?;
        params.crs = Some(crs.clone());
    }
    apply_train_flags(&a, &mut params)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let colmap = match &a.colmap {
        Some(c) => Some(unpacked(c, &a.out, "colmap").await?),
        None => None,
    };
    let photos = match &a.photos {
        Some(p) => Some(unpacked(p, &a.out, "photos").await?),
        None => None,
    };
    let inputs = StageInputs {
        lidar: a.lidar.clone(),
        colmap,
        photos,
        control_points: a.control_points.clone(),
        field_dbh: a.field_dbh.clone(),
    };
    let cancel = CancelFlag::new();
    {
        let cancel = cancel.clone();
        tokio::spawn(async move {
            if tokio::signal::ctrl_c().await.is_ok() {
                eprintln!("\ninterrupted: stopping after the current step");
                cancel.cancel();
            }
        });
    }
    let mut results = serde_json::Map::new();
    let mut stages = params.stages();
    if let Some(from) = a.from {
        let Some(at) = stages.iter().position(|&s| s == from) else {
            anyhow::bail!("--from {from}: this job does not run stage {from} (stages: {stages:?})");
        };
        for &earlier in &stages[..at] {
            let report = a.out.join(earlier.name()).join(pipeline::REPORT_FILE);
            let text = std::fs::read(&report).with_context(|| {
                format!(
                    "--from {from}: stage {earlier} has not finished in {} (no {})",
                    a.out.display(),
                    report.display()
                )
            })?;
            results.insert(earlier.name().to_string(), serde_json::from_slice(&text)?);
        }
        stages.drain(..at);
    }
    for stage in stages {
        let progress = Arc::new(ConsoleProgress::new(stage.name(), Some(cancel.clone())));
        let started = Instant::now();
        let before = Resources::now_reset();
        let (inp, out, prm, p) = (
            inputs.clone(),
            a.out.clone(),
            params.clone(),
            progress.clone(),
        );
        let result = tokio::task::spawn_blocking(move || {
            pipeline::execute_stage(stage, &inp, &out, &prm, p.as_ref())
        })
        .await?;
        match result {
            Ok(outcome) => {
                progress.set(1.0);
                let wall_s = started.elapsed().as_secs_f64();
                let used = Resources::since(before, wall_s);
                eprintln!("  done in {wall_s:.1} s{}", used.describe());
                let mut report = outcome.report;
                if let Some(r) = report.as_object_mut() {
                    r.insert("resources".into(), serde_json::to_value(used)?);
                }
                results.insert(stage.name().to_string(), report);
                summarise(&mut results);
                write_results(&a.out, &results)?;
            }
            Err(e) => {
                eprintln!();
                write_results(&a.out, &results)?;
                eprintln!("error: stage {stage} failed: {e}");
                return Ok(ExitCode::FAILURE);
            }
        }
    }
    eprintln!("results: {}", a.out.join("results.json").display());
    Ok(ExitCode::SUCCESS)
}

/// What one stage of `sylva run` took: wall and CPU seconds, and the process's peak resident
/// memory during it (Linux: VmHWM of /proc/self/status, reset before each stage through
/// /proc/self/clear_refs; CPU time from /proc/self/stat in USER_HZ ticks, 100 a second).
/// `None` where /proc does not say.
#[derive(Debug, Clone, Copy, serde::Serialize)]
struct Resources {
    wall_s: f64,
    cpu_s: Option<f64>,
    peak_rss_mb: Option<f64>,
}

impl Resources {
    /// The CPU seconds so far, after resetting the peak resident memory.
    fn now_reset() -> Option<f64> {
        // "5" resets the peak resident set size (Linux 4.0 and later); harmless elsewhere.
        let _ = std::fs::write("/proc/self/clear_refs", "5");
        cpu_seconds()
    }

    fn since(cpu_before: Option<f64>, wall_s: f64) -> Resources {
        Resources {
            wall_s,
            cpu_s: cpu_seconds().zip(cpu_before).map(|(a, b)| a - b),
            peak_rss_mb: peak_rss_mb(),
        }
    }

    fn describe(&self) -> String {
        let mut s = String::new();
        if let Some(c) = self.cpu_s {
            s += &format!(", {c:.1} CPU s");
        }
        if let Some(m) = self.peak_rss_mb {
            s += &format!(", peak memory {m:.0} MB");
        }
        s
    }
}

/// User + system CPU seconds of this process (/proc/self/stat fields 14 and 15).
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) may hold spaces: count from the closing parenthesis.
    let rest = &stat[stat.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Peak resident memory since the last reset, MB (VmHWM).
fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::{fill_choice, on_off};

    #[test]
    fn fill_choices_parse_and_name_the_flag_on_error() {
        let on = fill_choice("on").expect("on").expect("a fill");
        assert_eq!(on.depth_percentile, None);
        let guess = fill_choice("guess").expect("guess").expect("a fill");
        assert_eq!(guess.depth_percentile, Some(0.9));
        assert!(guess.place_unseen);
        assert_eq!(guess.depth_candidates, on.depth_candidates);
        assert!(
            fill_choice("textured")
                .expect("textured")
                .expect("a fill")
                .textured
        );
        assert!(!on.textured);
        assert!(fill_choice("off").expect("off").is_none());
        let err = fill_choice("yes").expect_err("not a choice");
        assert!(
            err.to_string()
                .contains("--fill must be on, textured, guess or off"),
            "{err}"
        );
    }

    #[test]
    fn on_off_flags_parse_and_name_the_flag_on_error() {
        assert!(on_off("--antialias", "on").expect("on"));
        assert!(!on_off("--antialias", "off").expect("off"));
        let err = on_off("--antialias", "yes").expect_err("not on/off");
        assert!(err.to_string().contains("--antialias"), "{err}");
    }
}
