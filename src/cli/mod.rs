//! The command line: `serve`, `worker`, `run`. Thin: each command wires settings to the
//! library and waits.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use tokio::sync::{Notify, watch};

use sylva::api::{self, AppState, Counters};
use sylva::config::{ApiArgs, RetentionArgs, StoreArgs, WebhookArgs, WorkerArgs, init_tracing};
use sylva::io::archive::{self, ExtractLimits};
use sylva::jobs::JobStore;
use sylva::pipeline::{self, PipelineParams, Stage, StageInputs};
use sylva::progress::{CancelFlag, Progress};
use sylva::store::BlobStore;
use sylva::webhooks::{Dispatcher, Webhooks};
use sylva::worker::WorkerPool;

mod bench;
mod demo;
mod keys;
mod progress;
mod run;
mod tools;

pub use bench::BenchArgs;
pub use demo::DemoArgs;
use progress::ConsoleProgress;
pub use run::RunArgs;
pub use tools::{InventoryArgs, SynthArgs, TrainArgs};

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

pub async fn main(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Serve(a) => serve(a).await.map(|_| ExitCode::SUCCESS),
        Command::Worker(a) => worker(a).await.map(|_| ExitCode::SUCCESS),
        Command::Run(a) => run::run(a).await,
        Command::Synth(a) => tools::synth(a).await,
        Command::Inventory(a) => tools::inventory(a).await,
        Command::Train(a) => tools::train(a).await,
        Command::Bench(a) => bench::bench(a).await,
        Command::Demo(a) => demo::demo(a).await,
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
    api::cors_layer(&a.api.cors_origin).map_err(anyhow::Error::msg)?;
    let (db, blobs) = open_store(&a.store).await?;
    let gpu = tokio::time::timeout(Duration::from_secs(10), sylva::gpu::probe())
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
        tokio::spawn(sylva::gc::run_periodically(
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
    let report = sylva::gc::sweep(&db, &blobs, &a.retention)
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
