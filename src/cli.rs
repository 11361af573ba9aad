//! The command line: `serve`, `worker`, `run`. Thin: each command wires settings to the
//! library and waits.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use tokio::sync::{Notify, watch};

use crate::api::{self, AppState, Counters};
use crate::config::{ApiArgs, RetentionArgs, StoreArgs, WebhookArgs, WorkerArgs, init_tracing};
use crate::io::archive::{self, ExtractLimits};
use crate::jobs::JobStore;
use crate::pipeline::{self, PipelineParams, Stage, StageInputs};
use crate::progress::{CancelFlag, Progress};
use crate::store::BlobStore;
use crate::webhooks::{Dispatcher, Webhooks};
use crate::worker::WorkerPool;

mod keys;

/// Sylva turns a forest plot (handheld LiDAR + UAV photos with a COLMAP model) into a
/// Gaussian-splat digital twin in metric coordinates and a DBH inventory of every stem.
#[derive(Debug, Parser)]
#[command(name = "sylva", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Serve the HTTP API with in-process workers (SQLite, or PostgreSQL with --database;
    /// files under --data).
    Serve(ServeArgs),
    /// Run workers only, against the same database, so a second process can take jobs over.
    Worker(WorkerOnlyArgs),
    /// Run the pipeline in-process on local files, without a server.
    Run(RunArgs),
    /// Generate a synthetic forest plot with known truth (LiDAR, photos + COLMAP, truth).
    Synth(SynthArgs),
    /// LiDAR-only tree inventory of a point cloud: stems and DBH (trees.csv, GeoJSON).
    Inventory(InventoryArgs),
    /// Train Gaussian splatting on a COLMAP project (vanilla 3DGS from the SfM points, or
    /// resume from a splat PLY); writes splats.ply, eval.json, the loss curve and test renders.
    Train(TrainArgs),
    /// Benchmarks that print tables (not tests): `sylva bench train`, `sylva bench load`,
    /// `sylva bench soak`, `sylva bench geom`, `sylva bench method`.
    Bench(BenchArgs),
    /// A generated plot through the whole service: start the server (SQLite + local files),
    /// upload the plot through the API, follow the job, print the inventory and its accuracy,
    /// and keep serving the web page until Ctrl-C.
    Demo(DemoArgs),
    /// Retention sweep, once: expire abandoned and unused uploads, remove the files of jobs
    /// finished longer ago than --job-retention-secs, remove orphaned folders; prints what
    /// it removed. `sylva serve` also sweeps every --gc-interval-secs.
    Gc(GcArgs),
    /// Managed API keys in the job database: `sylva keys create --name N [--admin]
    /// [--quota-jobs N] [--quota-bytes B] [--expires 90d]` prints a new key once;
    /// `sylva keys list`; `sylva keys revoke ID|NAME`.
    Keys(keys::KeysArgs),
}

#[derive(Debug, Args)]
pub struct GcArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    #[command(flatten)]
    pub retention: RetentionArgs,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// Address to serve on.
    #[arg(long, env = "SYLVA_DEMO_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: std::net::SocketAddr,
    /// Seed of the generated plot (preset tiny).
    #[arg(long, env = "SYLVA_DEMO_SEED", default_value_t = 1)]
    pub seed: u64,
    /// Training steps (default: 3000 on a GPU, 500 on a software GPU such as lavapipe, 300 on
    /// the CPU reference).
    #[arg(long, env = "SYLVA_DEMO_STEPS")]
    pub steps: Option<u32>,
    /// Exit once the job has finished instead of serving on (for scripts and tests).
    #[arg(long, env = "SYLVA_DEMO_EXIT")]
    pub exit: bool,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// What to measure: train (steps per second, where the step time goes, peak memory),
    /// load (job status reads per second and latency of the HTTP API; flags marked `load:`)
    /// or soak (many small jobs through `sylva serve` and `sylva worker` processes with random
    /// cancels and one SIGKILL; jobs per hour, API latency and anything lost; flags marked
    /// `soak:`, and --jobs) or geom (read, voxel, outlier filter, normals and ICP on a real
    /// point cloud with per-phase peak memory; flags marked `geom:`) or method (the paper's
    /// ablation plus Sylva's binding on generated plots: render quality, DBH from the
    /// Gaussians and the LiDAR, trunk-surface distance; flags marked `method:`).
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
    /// Gaussians to train (a seeded subset of the SfM points; 0 = all).
    #[arg(long, env = "SYLVA_BENCH_GAUSSIANS", default_value_t = 0)]
    pub gaussians: u32,
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

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// The COLMAP project folder (images/ and sparse/0 or sparse/).
    #[arg(long, env = "SYLVA_TRAIN_COLMAP")]
    pub colmap: PathBuf,
    /// Output folder.
    #[arg(long, env = "SYLVA_TRAIN_OUT")]
    pub out: PathBuf,
    /// Optimisation steps (Kerbl et al. 2023: 30,000; the schedule scales with it).
    #[arg(long, env = "SYLVA_TRAIN_STEPS", default_value_t = 30_000)]
    pub steps: u32,
    /// Longest image side in pixels; 0 keeps the photos' size.
    #[arg(long, env = "SYLVA_TRAIN_RESOLUTION", default_value_t = 1600)]
    pub resolution: u32,
    /// `sfm` (the sparse points) or a splat PLY file to resume from.
    #[arg(long, env = "SYLVA_TRAIN_INIT", default_value = "sfm")]
    pub init: String,
    /// gpu (default) or cpu (the exact reference, for tiny scenes only).
    #[arg(long, env = "SYLVA_TRAIN_BACKEND", default_value = "gpu")]
    pub backend: String,
    /// Upper bound on the number of Gaussians; 0 = the device's default budget (none on a
    /// hardware GPU, 10000 on a software GPU such as lavapipe, 3000 on the CPU reference).
    #[arg(long, env = "SYLVA_TRAIN_MAX_GAUSSIANS", default_value_t = 0)]
    pub max_gaussians: u32,
    /// Densification: default (clone, split and prune by gradient) or mcmc (relocation under
    /// the --max-gaussians budget, which it needs).
    #[arg(long, env = "SYLVA_TRAIN_STRATEGY", default_value = "default")]
    pub strategy: String,
    /// Seed of the view order and densification sampling.
    #[arg(long, env = "SYLVA_TRAIN_SEED", default_value_t = 0)]
    pub seed: u64,
    /// Anti-aliased rasterisation, on or off: Mip-Splatting's 2-D filter (a 0.3 px² blur with
    /// opacity compensation) for training and the held-out renders; off is the reference
    /// 3DGS dilation.
    #[arg(long, env = "SYLVA_TRAIN_ANTIALIAS", default_value = "off")]
    pub antialias: String,
    /// Per-image exposure compensation, on or off (docs/splatting.md "Exposure"). On (the
    /// default) learns a colour transform per photo and measures the held-out photos on
    /// their right halves, their left halves training their exposure.
    #[arg(long, env = "SYLVA_TRAIN_EXPOSURE", default_value = "on")]
    pub exposure: String,
}

#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Scene preset: tiny (1-3 trees, 30 small images), plot (one large broadleaf tree), stand
    /// (17 trees, canopy closure about 0.5), object (one tree in 71 close portrait phone-like
    /// frames with a sparse SfM start).
    #[arg(long, env = "SYLVA_SYNTH_PRESET", default_value = "tiny")]
    pub preset: String,
    /// Random seed: the same seed gives byte-identical files.
    #[arg(long, env = "SYLVA_SYNTH_SEED", default_value_t = 1)]
    pub seed: u64,
    /// Output folder (lidar.laz, colmap/, control_points.csv, field_dbh.csv, truth.json,
    /// labels.bin).
    #[arg(long, env = "SYLVA_SYNTH_OUT")]
    pub out: PathBuf,
    /// LiDAR range noise, standard deviation in centimetres (default 1 cm).
    #[arg(long, env = "SYLVA_SYNTH_NOISE_CM", default_value_t = 1.0)]
    pub noise_cm: f64,
    /// Number of photos (default: the preset's).
    #[arg(long, env = "SYLVA_SYNTH_IMAGES")]
    pub images: Option<usize>,
    /// Photo width in pixels (default: the preset's).
    #[arg(long, env = "SYLVA_SYNTH_WIDTH")]
    pub width: Option<u32>,
    /// Photo height in pixels (default: the preset's).
    #[arg(long, env = "SYLVA_SYNTH_HEIGHT")]
    pub height: Option<u32>,
    /// Write the COLMAP model in binary instead of text.
    #[arg(long, env = "SYLVA_SYNTH_BINARY", default_value_t = false)]
    pub binary: bool,
    /// Trees without leaves (branches only).
    #[arg(long, env = "SYLVA_SYNTH_LEAFLESS", default_value_t = false)]
    pub leafless: bool,
    /// Write PNG photos instead of JPEG.
    #[arg(long, env = "SYLVA_SYNTH_PNG", default_value_t = false)]
    pub png: bool,
}

#[derive(Debug, Args)]
pub struct InventoryArgs {
    /// The point cloud (LAS, LAZ, PLY, E57, XYZ), in metres.
    #[arg(env = "SYLVA_INVENTORY_CLOUD")]
    pub cloud: PathBuf,
    /// Where to write the inventory CSV.
    #[arg(long, env = "SYLVA_INVENTORY_OUT", default_value = "trees.csv")]
    pub out: PathBuf,
    /// Also write the stems as GeoJSON points here.
    #[arg(long, env = "SYLVA_INVENTORY_GEOJSON")]
    pub geojson: Option<PathBuf>,
    /// Field-measured DBH (CSV x,y,dbh_cm): match trees within 1 m and print the accuracy.
    #[arg(long, env = "SYLVA_INVENTORY_FIELD")]
    pub field: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    #[command(flatten)]
    pub api: ApiArgs,
    #[command(flatten)]
    pub worker: WorkerArgs,
    #[command(flatten)]
    pub webhooks: WebhookArgs,
}

#[derive(Debug, Args)]
pub struct WorkerOnlyArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    #[command(flatten)]
    pub worker: WorkerArgs,
    #[command(flatten)]
    pub webhooks: WebhookArgs,
}

fn parse_stage(s: &str) -> Result<Stage, String> {
    Stage::from_name(s).ok_or_else(|| {
        format!(
            "unknown stage {s:?}; stages: {}",
            Stage::ALL.map(|s| s.name()).join(", ")
        )
    })
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// The LiDAR point cloud (LAS, LAZ, PLY, XYZ), in metres.
    #[arg(long, env = "SYLVA_LIDAR")]
    pub lidar: PathBuf,
    /// The COLMAP project: a folder (images/ and sparse/0 or sparse/) or a zip/tar(.gz) of one.
    #[arg(long, env = "SYLVA_COLMAP")]
    pub colmap: PathBuf,
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
    /// Stop after this stage (ingest, register, anchors, segment, train, dbh, export).
    #[arg(long, env = "SYLVA_UNTIL", value_parser = parse_stage)]
    pub until: Option<Stage>,
    /// Job parameters as a JSON file (the `params` object of the API; see `GET /v1/options`).
    #[arg(long, env = "SYLVA_PARAMS")]
    pub params: Option<PathBuf>,
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

/// `--strategy`'s value.
fn parse_strategy(s: &str) -> anyhow::Result<crate::pipeline::params::DensifyStrategy> {
    use crate::pipeline::params::DensifyStrategy;
    match s {
        "default" => Ok(DensifyStrategy::Default),
        "mcmc" => Ok(DensifyStrategy::Mcmc),
        other => anyhow::bail!("--strategy must be default or mcmc, not {other:?}"),
    }
}

/// Applies `sylva run`'s training flags to `params`.
fn apply_train_flags(a: &RunArgs, params: &mut PipelineParams) -> anyhow::Result<()> {
    use crate::pipeline::params::{InitSource, TrainBackend, TrunkTerm};
    let t = &mut params.train;
    match a.init.as_deref() {
        None => {}
        Some("lidar") => t.init = InitSource::Lidar,
        Some("sfm") => t.init = InitSource::Sfm,
        Some(other) => anyhow::bail!("--init must be lidar or sfm, not {other:?}"),
    }
    match a.semantic.as_deref() {
        None => {}
        Some("bind") => t.semantic = TrunkTerm::Bind,
        Some("paper") => t.semantic = TrunkTerm::Paper,
        Some("off") => t.semantic = TrunkTerm::Off,
        Some(other) => anyhow::bail!("--semantic must be bind, paper or off, not {other:?}"),
    }
    match a.backend.as_deref() {
        None => {}
        Some("gpu") => t.backend = TrainBackend::Gpu,
        Some("cpu") => t.backend = TrainBackend::Cpu,
        Some(other) => anyhow::bail!("--backend must be gpu or cpu, not {other:?}"),
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
fn on_off(flag: &str, value: &str) -> anyhow::Result<bool> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => anyhow::bail!("{flag} must be on or off, not {other:?}"),
    }
}

/// Adds the summary keys of results.json: `registration`, `render` = {psnr, ssim, views} and,
/// with field data, `dbh` = {rmse_gs_cm, rmse_lidar_cm, bias_gs_cm, r2_gs, recall, matched,
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
    ] {
        if let Some(v) = v {
            results.insert(k.to_string(), v);
        }
    }
}

pub async fn main(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Serve(a) => serve(a).await.map(|_| ExitCode::SUCCESS),
        Command::Worker(a) => worker(a).await.map(|_| ExitCode::SUCCESS),
        Command::Run(a) => run(a).await,
        Command::Synth(a) => synth(a).await,
        Command::Inventory(a) => inventory(a).await,
        Command::Train(a) => train(a).await,
        Command::Bench(a) => bench(a).await,
        Command::Demo(a) => demo(a).await,
        Command::Gc(a) => gc(a).await,
        Command::Keys(a) => keys::run(a).await,
    }
}

async fn open_store(args: &StoreArgs) -> anyhow::Result<(JobStore, BlobStore)> {
    std::fs::create_dir_all(&args.data)
        .with_context(|| format!("cannot create the data directory {}", args.data.display()))?;
    let location = args.database()?;
    let db = JobStore::open(&location, 16)
        .await
        .with_context(|| format!("cannot open the job database {location}"))?;
    tracing::info!(backend = db.backend_name(), database = %location, "job database open");
    let blobs = BlobStore::open_with(&args.data, args.store.as_deref())
        .context("cannot open the blob store")?;
    match blobs.remote() {
        Some(r) => tracing::info!(backend = blobs.kind(), store = %r.url, "blob store open"),
        None => tracing::info!(backend = "local", data = %args.data.display(), "blob store open"),
    }
    Ok((db, blobs))
}

async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(s) => s,
                Err(_) => {
                    let _ = ctrl_c.await;
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = ctrl_c.await;
    }
}

async fn serve(a: ServeArgs) -> anyhow::Result<()> {
    init_tracing(&a.store);
    a.worker.validate().map_err(anyhow::Error::msg)?;
    let (db, blobs) = open_store(&a.store).await?;
    let gpu = tokio::time::timeout(Duration::from_secs(10), crate::gpu::probe())
        .await
        .ok()
        .flatten();
    match &gpu {
        Some(g) => tracing::info!(adapter = %g.name, backend = %g.backend, "GPU adapter found"),
        None => tracing::warn!(
            "no GPU adapter found: stage train runs here only with params.train.backend = \"cpu\" (the exact reference, for tiny scenes; the demo uses it)"
        ),
    }
    let wake = Arc::new(Notify::new());
    let hooks = Webhooks::open(&db, &a.webhooks).await?;
    let state = AppState {
        db: db.clone(),
        blobs: blobs.clone(),
        args: Arc::new(a.api.clone()),
        wake: wake.clone(),
        counters: Arc::new(Counters::default()),
        gpu,
        lease: a.worker.lease(),
        webhooks: hooks.clone(),
        keys_exist: Default::default(),
    };
    // Recovery runs before the address is announced, so whoever waits for it sees a settled
    // queue.
    let (stop_tx, stop_rx) = watch::channel(false);
    let dispatcher = Dispatcher::new(db.clone(), hooks, a.webhooks.clone())
        .context("cannot build the webhook client")?;
    let dispatcher = tokio::spawn(dispatcher.run(stop_rx.clone()));
    let sweeper = (a.api.retention.gc_interval_secs > 0).then(|| {
        tokio::spawn(crate::gc::run_periodically(
            db.clone(),
            blobs.clone(),
            a.api.retention.clone(),
            Duration::from_secs(a.api.retention.gc_interval_secs),
            stop_rx.clone(),
        ))
    });
    let workers = if a.worker.workers > 0 {
        let pool = WorkerPool::new(db, blobs, a.worker.clone(), wake);
        pool.recover().await;
        Some(tokio::spawn(pool.run(stop_rx)))
    } else {
        None
    };
    let listener = tokio::net::TcpListener::bind(a.api.listen)
        .await
        .with_context(|| format!("cannot listen on {}", a.api.listen))?;
    let addr = listener.local_addr()?;
    println!("sylva listening on http://{addr}");
    let _ = std::io::stdout().flush();
    tracing::info!(%addr, auth = !a.api.token.is_empty(), "API listening");

    axum::serve(listener, api::router(state))
        .with_graceful_shutdown(shutdown_signal())
        .await?;
    let _ = stop_tx.send(true);
    if let Some(w) = workers {
        let _ = tokio::time::timeout(Duration::from_secs(5), w).await;
    }
    let _ = tokio::time::timeout(Duration::from_secs(5), dispatcher).await;
    if let Some(s) = sweeper {
        s.abort();
    }
    Ok(())
}

async fn gc(a: GcArgs) -> anyhow::Result<ExitCode> {
    init_tracing(&a.store);
    let (db, blobs) = open_store(&a.store).await?;
    let report = crate::gc::sweep(&db, &blobs, &a.retention)
        .await
        .context("retention sweep")?;
    println!(
        "uploads expired: {}\njobs purged: {}\norphaned folders removed: {}\nbytes freed: {}",
        report.uploads_expired, report.jobs_purged, report.orphans_removed, report.bytes_freed
    );
    Ok(ExitCode::SUCCESS)
}

async fn worker(a: WorkerOnlyArgs) -> anyhow::Result<()> {
    a.worker.validate().map_err(anyhow::Error::msg)?;
    init_tracing(&a.store);
    if a.worker.workers == 0 {
        anyhow::bail!("--workers must be at least 1 for `sylva worker`");
    }
    let (db, blobs) = open_store(&a.store).await?;
    let (stop_tx, stop_rx) = watch::channel(false);
    let hooks = Webhooks::open(&db, &a.webhooks).await?;
    let dispatcher = Dispatcher::new(db.clone(), hooks, a.webhooks.clone())
        .context("cannot build the webhook client")?;
    let dispatcher = tokio::spawn(dispatcher.run(stop_rx.clone()));
    let pool = WorkerPool::new(db, blobs, a.worker.clone(), Arc::new(Notify::new()));
    pool.recover().await;
    println!("sylva worker started ({} slot(s))", a.worker.workers);
    let _ = std::io::stdout().flush();
    let handle = tokio::spawn(pool.run(stop_rx));
    shutdown_signal().await;
    let _ = stop_tx.send(true);
    let _ = tokio::time::timeout(Duration::from_secs(5), handle).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), dispatcher).await;
    Ok(())
}

/// A one-line progress bar on stderr for `sylva run`.
struct ConsoleProgress {
    stage: Stage,
    cancel: CancelFlag,
    last: Mutex<(Instant, f64)>,
}

impl Progress for ConsoleProgress {
    fn set(&self, fraction: f64) {
        let f = fraction.clamp(0.0, 1.0);
        if let Ok(mut last) = self.last.lock()
            && f > last.1
            && (last.0.elapsed() > Duration::from_millis(100) || f >= 1.0)
        {
            *last = (Instant::now(), f);
            let filled = (f * 30.0).round() as usize;
            eprint!(
                "\r{:>9} [{}{}] {:>3.0}%",
                self.stage.name(),
                "#".repeat(filled),
                ".".repeat(30 - filled),
                f * 100.0
            );
        }
    }
    fn log(&self, message: &str) {
        eprintln!("\r{:>9}: {message}", self.stage.name());
    }
    fn is_cancelled(&self) -> bool {
        self.cancel.is_cancelled()
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

async fn run(a: RunArgs) -> anyhow::Result<ExitCode> {
    let store = StoreArgs {
        data: PathBuf::new(),
        database: None,
        store: None,
        log: a.log.clone(),
        log_json: false,
    };
    init_tracing(&store);
    let mut params: PipelineParams = match &a.params {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("cannot read {}", p.display()))?;
            serde_json::from_str(&text)
                .with_context(|| format!("{}: invalid parameters", p.display()))?
        }
        None => PipelineParams::default(),
    };
    if a.until.is_some() {
        params.until = a.until;
    }
    apply_train_flags(&a, &mut params)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let colmap = if a.colmap.is_file() {
        let dest = a.out.join("inputs").join("colmap");
        if dest.exists() {
            std::fs::remove_dir_all(&dest)?;
        }
        let src = a.colmap.clone();
        let d2 = dest.clone();
        tokio::task::spawn_blocking(move || {
            archive::extract_archive(
                &src,
                &d2,
                &ExtractLimits::default(),
                &crate::progress::NoProgress,
            )
        })
        .await?
        .with_context(|| format!("{}: cannot unpack", a.colmap.display()))?;
        dest
    } else {
        a.colmap.clone()
    };
    let inputs = StageInputs {
        lidar: a.lidar.clone(),
        colmap,
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
    for stage in params.stages() {
        let progress = Arc::new(ConsoleProgress {
            stage,
            cancel: cancel.clone(),
            last: Mutex::new((Instant::now(), -1.0)),
        });
        let started = Instant::now();
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
                eprintln!("  done in {:.1} s", started.elapsed().as_secs_f64());
                results.insert(stage.name().to_string(), outcome.report);
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

/// A progress line on stderr for one-off commands.
struct LineProgress {
    label: &'static str,
    last: Mutex<(Instant, f64)>,
}

impl LineProgress {
    fn new(label: &'static str) -> Self {
        Self {
            label,
            last: Mutex::new((Instant::now(), -1.0)),
        }
    }
}

impl Progress for LineProgress {
    fn set(&self, fraction: f64) {
        if let Ok(mut last) = self.last.lock()
            && fraction > last.1 + 0.01
            && last.0.elapsed() > Duration::from_millis(200)
        {
            *last = (Instant::now(), fraction);
            eprint!(
                "\r{}: {:>3.0}%",
                self.label,
                fraction.clamp(0.0, 1.0) * 100.0
            );
        }
    }
    fn log(&self, message: &str) {
        eprintln!("\r{}: {message}", self.label);
    }
}

async fn synth(a: SynthArgs) -> anyhow::Result<ExitCode> {
    let Some(preset) = crate::synth::Preset::from_name(&a.preset) else {
        anyhow::bail!(
            "unknown preset {:?}; presets: tiny, plot, stand, object",
            a.preset
        );
    };
    let mut p = crate::synth::SynthParams::new(preset);
    p.seed = a.seed;
    p.noise_cm = a.noise_cm;
    p.images = a.images.or(p.images);
    p.width = a.width.or(p.width);
    p.height = a.height.or(p.height);
    p.binary = a.binary;
    p.leafless = a.leafless;
    p.png = a.png;
    let out = a.out.clone();
    let summary = tokio::task::spawn_blocking(move || {
        crate::synth::generate(&p, &out, &LineProgress::new("synth"))
    })
    .await??;
    eprintln!();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(ExitCode::SUCCESS)
}

async fn inventory(a: InventoryArgs) -> anyhow::Result<ExitCode> {
    let path = a.cloud.clone();
    let (rows, cloud_points) = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
        let progress = LineProgress::new("inventory");
        let cloud = crate::io::pointcloud::read_point_cloud(&path, &progress)?;
        let inv = crate::forest::inventory(
            &cloud,
            &crate::forest::InventoryParams::default(),
            &progress,
        )?;
        Ok((inv.trees, cloud.len()))
    })
    .await??;
    eprintln!();
    crate::forest::write_trees_csv(&a.out, &rows)?;
    if let Some(g) = &a.geojson {
        crate::forest::write_trees_geojson(g, &rows)?;
    }
    println!(
        "{} stems from {} points; inventory in {}",
        rows.len(),
        cloud_points,
        a.out.display()
    );
    if let Some(field) = &a.field {
        let cmp = crate::forest::compare_with_field_file(&rows, field)?;
        for line in crate::forest::accuracy_lines(&cmp) {
            println!("{line}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

async fn train(a: TrainArgs) -> anyhow::Result<ExitCode> {
    use crate::pipeline::params::{TrainBackend, TrainParams};
    let backend = match a.backend.as_str() {
        "gpu" => TrainBackend::Gpu,
        "cpu" => TrainBackend::Cpu,
        other => anyhow::bail!("--backend must be gpu or cpu, not {other:?}"),
    };
    let params = TrainParams {
        steps: a.steps,
        resolution: a.resolution,
        max_gaussians: a.max_gaussians,
        strategy: parse_strategy(&a.strategy)?,
        backend,
        seed: a.seed,
        antialias: on_off("--antialias", &a.antialias)?,
        exposure: on_off("--exposure", &a.exposure)?,
        ..TrainParams::default()
    };
    let outcome = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
        let progress = LineProgress::new("train");
        let project = crate::io::colmap::find_project(&a.colmap)?;
        let images = project.images_dir.clone().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: no images/ folder beside the sparse model",
                a.colmap.display()
            )
        })?;
        let model = crate::io::colmap::read_model(&project.sparse_dir, &progress)?;
        let mut backend = crate::pipeline::train::backend_for(&params)?;
        let (params, budget_source) =
            crate::pipeline::train::with_budget(&params, backend.device_kind());
        let cfg = params.config();
        progress.log(&format!(
            "budget: {} Gaussians ({budget_source})",
            match params.max_gaussians {
                0 => "unbounded".to_string(),
                n => n.to_string(),
            }
        ));
        let data = crate::splat::dataset::load(
            &model,
            &images,
            cfg.resolution,
            cfg.test_every,
            &progress,
        )?;
        let mut init = if a.init == "sfm" {
            crate::splat::init::from_sfm_points(&data.points, &data.colours)?
        } else {
            let file =
                std::fs::File::open(&a.init).map_err(|e| anyhow::anyhow!("{}: {e}", a.init))?;
            crate::splat::export::read_ply(std::io::BufReader::new(file))
                .map_err(|e| anyhow::anyhow!("{}: {e}", a.init))?
        };
        let before = init.len();
        crate::pipeline::train::cap_gaussians(
            &mut init,
            params.max_gaussians,
            params.seed,
            None,
            0,
        );
        if a.init == "sfm" && init.len() < before {
            crate::splat::init::rescale_from_spacing(&mut init, 3, 0.0);
        }
        let mut strategy = crate::splat::trainer::strategy_for(&cfg)?;
        let outcome = crate::splat::trainer::train(
            backend.as_mut(),
            &data,
            init,
            &cfg,
            strategy.as_mut(),
            &progress,
        )?;
        crate::splat::trainer::write_outputs(&a.out, &outcome, &data)?;
        Ok(outcome)
    })
    .await??;
    eprintln!();
    println!(
        "held-out PSNR {:.2} dB, SSIM {:.3} over {} views, {} (mean colour {:.2} dB); {} Gaussians; {:.2} steps/s on {}",
        outcome.eval.psnr,
        outcome.eval.ssim,
        outcome.eval.views.len(),
        outcome.eval.region.describe(),
        outcome.baseline_psnr,
        outcome.model.len(),
        outcome.steps_per_second,
        outcome.device
    );
    Ok(ExitCode::SUCCESS)
}

async fn bench(a: BenchArgs) -> anyhow::Result<ExitCode> {
    use crate::pipeline::params::{TrainBackend, TrainParams};
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
    if a.what != "train" {
        anyhow::bail!(
            "unknown benchmark {:?}; available: train, load, soak, geom, method",
            a.what
        );
    }
    let backend = match a.backend.as_str() {
        "gpu" => TrainBackend::Gpu,
        "cpu" => TrainBackend::Cpu,
        other => anyhow::bail!("--backend must be gpu or cpu, not {other:?}"),
    };
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
    tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
        let tmp = std::env::temp_dir().join(format!("sylva-bench-{}", std::process::id()));
        let colmap = match &a.colmap {
            Some(c) => c.clone(),
            None => {
                let preset = crate::synth::Preset::from_name(&a.preset)
                    .ok_or_else(|| anyhow::anyhow!("unknown preset {:?}", a.preset))?;
                let p = crate::synth::SynthParams::new(preset);
                eprintln!("generating a synthetic {} plot…", a.preset);
                crate::synth::generate(&p, &tmp, &crate::progress::NoProgress)?;
                tmp.join("colmap")
            }
        };
        let project = crate::io::colmap::find_project(&colmap)?;
        let images = project
            .images_dir
            .clone()
            .ok_or_else(|| anyhow::anyhow!("{}: no images/ folder", colmap.display()))?;
        let model = crate::io::colmap::read_model(&project.sparse_dir, &crate::progress::NoProgress)?;
        println!(
            "| device | resolution (px) | images | Gaussians | tiles per Gaussian | steps/s | s/step | projection ms | sort ms | raster ms | loss ms | backward ms | optimiser ms | peak RSS MiB |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
        for res in resolutions {
            let params = TrainParams {
                steps: a.steps,
                resolution: res,
                max_gaussians: a.gaussians,
                backend,
                ..TrainParams::default()
            };
            let mut cfg = params.config();
            // Time the steps themselves: no densification, no evaluation views.
            cfg.densify_until = 0;
            cfg.test_every = 0;
            let data = crate::splat::dataset::load(&model, &images, cfg.resolution, 0, &crate::progress::NoProgress)?;
            let mut init = crate::splat::init::from_sfm_points(&data.points, &data.colours)?;
            let before = init.len();
            crate::pipeline::train::cap_gaussians(&mut init, params.max_gaussians, params.seed, None, 0);
            if init.len() < before {
                crate::splat::init::rescale_from_spacing(&mut init, 3, 0.0);
            }
            let n = init.len();
            let mut backend = if a.raster_pixels > 0 && backend == TrainBackend::Gpu {
                let mut ctx = crate::splat::gpu::GpuContext::new()?;
                ctx.raster_pixels = a.raster_pixels;
                Box::new(crate::splat::gpu::GpuBackend::with_context(ctx, [0.0; 3])?)
                    as Box<dyn crate::splat::backend::Backend>
            } else {
                crate::pipeline::train::backend_for(&params)?
            };
            backend.set_timed(true);
            let mut strategy = crate::splat::trainer::default_strategy(&cfg);
            let out = crate::splat::trainer::train(
                backend.as_mut(),
                &data,
                init,
                &cfg,
                &mut strategy,
                &crate::progress::NoProgress,
            )?;
            let t = out.phase_times;
            let steps = f64::from(cfg.steps);
            let first = data.train.first().map(|v| (v.camera.width, v.camera.height)).unwrap_or((0, 0));
            println!(
                "| {} | {}×{} | {} | {} | {} | {:.2} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} |",
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
                crate::loadbench::peak_rss_mib()
            );
        }
        let _ = std::fs::remove_dir_all(&tmp);
        Ok(())
    })
    .await??;
    Ok(ExitCode::SUCCESS)
}

async fn demo(a: DemoArgs) -> anyhow::Result<ExitCode> {
    // 1. A generated plot with known truth.
    let plot = a.store.data.join("demo-plot");
    if !plot.join("truth.json").is_file() {
        eprintln!("generating a synthetic plot in {} …", plot.display());
        let (dir, seed) = (plot.clone(), a.seed);
        tokio::task::spawn_blocking(move || {
            let mut p = crate::synth::SynthParams::new(crate::synth::Preset::Tiny);
            p.seed = seed;
            crate::synth::generate(&p, &dir, &crate::progress::NoProgress)
        })
        .await??;
    }
    let colmap_tar = plot.join("colmap.tar");
    {
        let file = std::fs::File::create(&colmap_tar)?;
        let mut tar = tar::Builder::new(file);
        tar.append_dir_all(".", plot.join("colmap"))?;
        tar.finish()?;
    }
    // 2. The server, in this process, on the embedded default.
    let data = a.store.data.to_string_lossy().to_string();
    let listen = a.listen.to_string();
    let cli = Cli::try_parse_from(["sylva", "serve", "--data", &data, "--listen", &listen])?;
    let Command::Serve(serve_args) = cli.command else {
        anyhow::bail!("internal: serve arguments");
    };
    let server = tokio::spawn(serve(serve_args));
    let base = format!("http://{}", a.listen);
    let http = reqwest::Client::new();
    let mut ready = false;
    for _ in 0..100 {
        if http
            .get(format!("{base}/livez"))
            .send()
            .await
            .is_ok_and(|r| r.status().is_success())
        {
            ready = true;
            break;
        }
        if server.is_finished() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    if !ready {
        anyhow::bail!("the server did not start on {base} (is the port taken? use --listen)");
    }
    // 3. The job: GPU when there is one, else the CPU reference on a small budget.
    let gpu = crate::gpu::probe().await;
    let params = match &gpu {
        // A software adapter (lavapipe) gets short training; its Gaussian budget is the
        // device default (`max_gaussians` 0: pipeline::train::SOFTWARE_GPU_BUDGET), an even
        // draw of about a twentieth of the ~180 k anchors.
        Some(g) if g.device_type == "cpu" => {
            eprintln!("training on {} (a software GPU: small budget)", g.name);
            serde_json::json!({"train": {"steps": a.steps.unwrap_or(500), "resolution": 80}})
        }
        Some(g) => {
            eprintln!("training on {}", g.name);
            serde_json::json!({"train": {"steps": a.steps.unwrap_or(3000), "resolution": 160}})
        }
        None => {
            eprintln!("no GPU adapter: training on the CPU reference with a small budget");
            // The CPU reference's default budget (pipeline::train::CPU_REFERENCE_BUDGET).
            serde_json::json!({"train": {"backend": "cpu", "steps": a.steps.unwrap_or(300),
                "resolution": 80}})
        }
    };
    let part = |path: PathBuf| -> anyhow::Result<reqwest::multipart::Part> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        Ok(reqwest::multipart::Part::bytes(std::fs::read(&path)?).file_name(name))
    };
    let form = reqwest::multipart::Form::new()
        .part("lidar", part(plot.join("lidar.laz"))?)
        .part("colmap", part(colmap_tar.clone())?)
        .part("control_points", part(plot.join("control_points.csv"))?)
        .part("field_dbh", part(plot.join("field_dbh.csv"))?)
        .text("params", params.to_string());
    let resp = http
        .post(format!("{base}/v1/jobs"))
        .multipart(form)
        .send()
        .await?;
    if !resp.status().is_success() {
        anyhow::bail!("job refused: {}", resp.text().await.unwrap_or_default());
    }
    let job: serde_json::Value = resp.json().await?;
    let id = job["id"].as_str().unwrap_or_default().to_string();
    eprintln!("job {id}: {base}/#/jobs/{id}");
    // 4. Follow it.
    let mut last = String::new();
    let job = loop {
        let j: serde_json::Value = http
            .get(format!("{base}/v1/jobs/{id}"))
            .send()
            .await?
            .json()
            .await?;
        let line = format!(
            "{} {} {:.0}%",
            j["state"].as_str().unwrap_or("?"),
            j["stage"].as_str().unwrap_or(""),
            j["progress"].as_f64().unwrap_or(0.0) * 100.0
        );
        if line != last {
            eprintln!("  {line}");
            last = line;
        }
        if matches!(
            j["state"].as_str(),
            Some("succeeded" | "failed" | "canceled")
        ) {
            break j;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    };
    if job["state"] != "succeeded" {
        eprintln!("the job did not succeed: {}", job["error"]);
    } else {
        // 5. The inventory and its quality.
        let csv = http
            .get(format!("{base}/v1/jobs/{id}/trees.csv"))
            .send()
            .await?
            .text()
            .await?;
        println!("\ntree inventory (trees.csv):\n{csv}");
        let results: serde_json::Value = http
            .get(format!("{base}/v1/jobs/{id}/results"))
            .send()
            .await?
            .json()
            .await?;
        let st = &results["stages"];
        let f = |v: &serde_json::Value| v.as_f64().map_or("n/a".to_string(), |x| format!("{x:.2}"));
        println!("| quality | value |\n|---|---|");
        println!(
            "| registration RMSE (m) | {} |",
            f(&st["register"]["rmse_m"])
        );
        println!(
            "| held-out PSNR (dB) | {} |",
            f(&st["train"]["render"]["psnr"])
        );
        println!("| held-out SSIM | {} |", f(&st["train"]["render"]["ssim"]));
        println!(
            "| held-out pixels measured | {} |",
            match st["train"]["render"]["region"].as_str() {
                Some("right_half") => "right halves (exposure compensation on)",
                Some(_) => "full images",
                None => "n/a",
            }
        );
        println!(
            "| mean-colour PSNR (dB) | {} |",
            f(&st["train"]["baseline_psnr"])
        );
        println!(
            "| DBH RMSE, Gaussians (cm) | {} |",
            f(&st["dbh"]["dbh"]["rmse_gs_cm"])
        );
        println!(
            "| DBH RMSE, LiDAR (cm) | {} |",
            f(&st["dbh"]["dbh"]["rmse_lidar_cm"])
        );
        println!(
            "| DBH RMSE, Gaussians against LiDAR (cm) | {} |",
            f(&st["dbh"]["gs_vs_lidar"]["rmse_cm"])
        );
        println!("| trees matched | {} |", st["dbh"]["dbh"]["matched"]);
        println!(
            "| trunk Gaussians to LiDAR stem surface, mean absolute (mm) | {} |",
            f(&st["dbh"]["mean_radial_dev_mm"])
        );
        println!(
            "| trunk Gaussians to LiDAR stem surface, mean signed (mm, + outside) | {} |",
            f(&st["dbh"]["mean_surface_offset_mm"])
        );
        println!(
            "| trunk term | {} |",
            st["train"]["semantic"]["term"].as_str().unwrap_or("n/a")
        );
        let tr = &st["train"];
        println!(
            "| training budget | {} steps at {} px, {} Gaussians ({}), {} |",
            tr["steps"],
            tr["resolution"]
                .as_array()
                .map_or("n/a".to_string(), |r| format!(
                    "{}×{}",
                    r.first().unwrap_or(&serde_json::Value::Null),
                    r.get(1).unwrap_or(&serde_json::Value::Null)
                )),
            match tr["budget"]["max_gaussians"].as_u64() {
                Some(0) | None => "unbounded".to_string(),
                Some(n) => format!("at most {n}"),
            },
            tr["budget"]["source"].as_str().unwrap_or("n/a"),
            tr["device"].as_str().unwrap_or("n/a")
        );
        println!("| training time (s) | {} |", f(&tr["seconds"]));
    }
    let ok = job["state"] == "succeeded";
    if a.exit {
        server.abort();
        return Ok(if ok {
            ExitCode::SUCCESS
        } else {
            ExitCode::FAILURE
        });
    }
    println!("\nthe web page: {base}/  (Ctrl-C to stop)");
    server.await??;
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

#[cfg(test)]
mod tests {
    use super::on_off;

    #[test]
    fn on_off_flags_parse_and_name_the_flag_on_error() {
        assert!(on_off("--antialias", "on").expect("on"));
        assert!(!on_off("--antialias", "off").expect("off"));
        let err = on_off("--antialias", "yes").expect_err("not on/off");
        assert!(err.to_string().contains("--antialias"), "{err}");
    }
}
