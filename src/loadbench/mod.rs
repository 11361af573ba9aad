//! `sylva bench load`: how many job reads per second the HTTP API answers, and how fast.
//!
//! Status polling is most of the traffic a job service sees (scripts and web pages asking
//! "is it done yet?"), so this measures exactly that: the API is started in this process on
//! 127.0.0.1 the way `sylva serve` builds it (the same router, a job database pool of 16
//! connections, the defaults of `sylva serve`'s flags and `SYLVA_*` variables), but with no
//! worker, so the seeded jobs stay queued and every response has the same size throughout.
//! The jobs are inserted through the job store (two completed placeholder uploads, then
//! `--jobs` jobs with the default parameters). Then `--clients` concurrent clients, each with
//! its own keep-alive connection, send requests back to back for `--seconds`: a share
//! `--list-share` of them `GET /v1/jobs?limit=50`, the rest `GET /v1/jobs/{id}` of a random
//! seeded job. One table row per database and client count; latency is measured from send to
//! the last byte of the body, non-2xx answers and transport failures count as errors.
//!
//! The clients share the machine (and the async runtime) with the server, so the figures are
//! a lower bound for a server with cores of its own, and comparable between runs on the same
//! machine.

pub mod geom;
pub mod method;
pub mod postgres;
pub mod soak;
pub mod tiles;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Args, Parser};
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
pub use sylva::testing::peak_rss_mib;
use tokio::sync::{Notify, oneshot};

use sylva::api::{self, AppState, Counters};
use sylva::config::{ApiArgs, WorkerArgs};
use sylva::jobs::{
    Admission, Created, Database, JobInputs, JobStore, NewJob, UploadKind, UploadRecord, now_ms,
};
use sylva::pipeline::PipelineParams;
use sylva::store::BlobStore;

/// Connections of the job database pool: the same as `sylva serve` opens.
const POOL_CONNECTIONS: u32 = 16;
/// Longest a single request may take before it counts as an error, seconds.
const REQUEST_TIMEOUT_SECS: u64 = 30;
/// Page size of the list requests (the API's default page).
const LIST_LIMIT: u32 = 50;

/// Flags of `sylva bench load`.
#[derive(Debug, Clone, Args)]
pub struct LoadArgs {
    /// load: jobs seeded before the clients start (queued, never run). soak: jobs submitted
    /// through the API.
    #[arg(long, env = "SYLVA_BENCH_JOBS", default_value_t = 200)]
    pub jobs: u32,
    /// load: concurrent HTTP clients, each with its own connection (comma-separated for
    /// several rows).
    #[arg(long, env = "SYLVA_BENCH_CLIENTS", default_value = "16")]
    pub clients: String,
    /// load: seconds each row sends requests for.
    #[arg(long, env = "SYLVA_BENCH_SECONDS", default_value_t = 10.0)]
    pub seconds: f64,
    /// load: databases to measure, comma-separated: `sqlite` (a fresh file in a temporary
    /// folder), `postgres` (a throwaway local cluster, skipped where PostgreSQL is not
    /// installed), or a `postgres://` URL of a scratch database (its tables are created and
    /// the jobs added to it).
    #[arg(
        long = "database",
        env = "SYLVA_BENCH_DATABASE",
        default_value = "sqlite,postgres",
        hide_env_values = true
    )]
    pub databases: String,
    /// load: share of requests that list jobs (`GET /v1/jobs?limit=50`), in [0, 1]; the rest
    /// read one job (`GET /v1/jobs/{id}`). Default 0.2: pollers mostly ask about one job.
    #[arg(long, env = "SYLVA_BENCH_LIST_SHARE", default_value_t = 0.2)]
    pub list_share: f64,
}

/// One database to measure.
enum Target {
    Sqlite,
    Throwaway,
    Url(String),
}

fn parse_targets(text: &str) -> anyhow::Result<Vec<Target>> {
    text.split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| match t {
            "sqlite" => Ok(Target::Sqlite),
            "postgres" => Ok(Target::Throwaway),
            url if url.starts_with("postgres://") || url.starts_with("postgresql://") => {
                Ok(Target::Url(url.to_string()))
            }
            other => anyhow::bail!(
                "--database: {other:?} is none of sqlite, postgres or a postgres:// URL"
            ),
        })
        .collect()
}

/// A comma-separated list of positive whole numbers given to `flag` (--clients,
/// --method-budgets); the error names the flag and the bad item.
fn parse_positive_list(flag: &str, text: &str) -> anyhow::Result<Vec<u32>> {
    text.split(',')
        .map(|c| {
            c.trim()
                .parse::<u32>()
                .ok()
                .filter(|n| *n > 0)
                .ok_or_else(|| anyhow::anyhow!("{flag}: {c:?} is not a positive whole number"))
        })
        .collect()
}

/// A folder under the system temporary directory, removed with everything in it on drop.
struct ScratchDir(PathBuf);

impl ScratchDir {
    /// `sylva-bench-<label>-<pid>-<ms>` under the temporary directory.
    fn new(label: &str) -> anyhow::Result<Self> {
        let p = std::env::temp_dir().join(format!(
            "sylva-bench-{label}-{}-{}",
            std::process::id(),
            now_ms()
        ));
        std::fs::create_dir_all(&p).with_context(|| format!("cannot create {}", p.display()))?;
        Ok(Self(p))
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `sylva serve`'s API and worker settings with their defaults (and any `SYLVA_*` overrides
/// from the environment, as `sylva serve` would see them).
#[derive(Parser)]
struct ServeDefaults {
    #[command(flatten)]
    api: ApiArgs,
    #[command(flatten)]
    worker: WorkerArgs,
    #[command(flatten)]
    webhooks: sylva::config::WebhookArgs,
}

/// The API running in this process, without workers.
struct Server {
    addr: SocketAddr,
    db: JobStore,
    token: Option<String>,
    stop: oneshot::Sender<()>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
}

impl Server {
    async fn start(database: &Database, data: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(data)
            .with_context(|| format!("cannot create {}", data.display()))?;
        let db = JobStore::open(database, POOL_CONNECTIONS)
            .await
            .with_context(|| format!("cannot open the job database {}", database.redacted()))?;
        let blobs = BlobStore::open(data)?;
        let defaults = ServeDefaults::try_parse_from(["sylva-bench-load"])?;
        let token = defaults.api.token.first().cloned();
        let webhooks = sylva::webhooks::Webhooks::open(&db, &defaults.webhooks).await?;
        let state = AppState {
            db: db.clone(),
            blobs,
            args: Arc::new(defaults.api),
            wake: Arc::new(Notify::new()),
            counters: Arc::new(Counters::default()),
            gpu: None,
            lease: defaults.worker.lease(),
            webhooks,
            keys_exist: Default::default(),
        };
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", 0)).await?;
        let addr = listener.local_addr()?;
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            axum::serve(listener, api::router(state))
                .with_graceful_shutdown(async {
                    let _ = stopped.await;
                })
                .await
        });
        Ok(Self {
            addr,
            db,
            token,
            stop,
            task,
        })
    }

    async fn shutdown(self) {
        let _ = self.stop.send(());
        let _ = tokio::time::timeout(Duration::from_secs(5), self.task).await;
    }
}

/// Inserts two completed placeholder uploads and `n` queued jobs reading them; returns the
/// job ids.
async fn seed(db: &JobStore, n: u32) -> anyhow::Result<Vec<String>> {
    let now = now_ms();
    let upload = |kind: UploadKind, filename: &str| UploadRecord {
        id: api::uploads::new_id(),
        kind,
        filename: filename.to_string(),
        size: 0,
        sha256: None,
        part_size: 1,
        complete: false,
        inspection: None,
        created_at: now,
        // Far enough out that no sweep of expired uploads touches them during the run.
        expires_at: now + 86_400_000,
        completed_at: None,
        parts: Vec::new(),
        owner: String::new(),
        expired: false,
    };
    let lidar = upload(UploadKind::Lidar, "bench.laz");
    let colmap = upload(UploadKind::Colmap, "bench.tar");
    // SHA-256 of zero bytes: the placeholders are empty.
    let empty_sha = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855";
    let inspection = serde_json::json!({ "placeholder": "sylva bench load" });
    for u in [&lidar, &colmap] {
        db.create_upload(u).await?;
        db.complete_upload(&u.id, empty_sha, &inspection).await?;
    }
    let inputs = JobInputs {
        lidar: lidar.id,
        colmap: Some(colmap.id),
        photos: None,
        control_points: None,
        field_dbh: None,
    };
    let params = PipelineParams::default();
    let value = serde_json::to_value(&params)?;
    let stages = params.stages();
    let mut ids = Vec::with_capacity(n as usize);
    for i in 0..n {
        let (id, hash) = (api::uploads::new_id(), format!("sylva-bench-load-{i}"));
        let job = NewJob {
            id: &id,
            inputs: &inputs,
            params: &value,
            stages: &stages,
            idempotency_key: None,
            request_hash: &hash,
            owner: "",
            webhook: None,
        };
        let created = db.create_job(&job, Admission::queue(i64::MAX)).await?;
        ids.push(match created {
            Created::New(id) | Created::Existing(id) => id,
        });
    }
    Ok(ids)
}

/// What one client saw.
#[derive(Default)]
struct Tally {
    /// Latency of every request, microseconds.
    latencies_us: Vec<u64>,
    errors: u64,
}

async fn client(
    base: Arc<str>,
    ids: Arc<Vec<String>>,
    seed: u64,
    until: Instant,
    list_share: f64,
    token: Option<String>,
) -> anyhow::Result<Tally> {
    let http = reqwest::Client::builder()
        .timeout(Duration::from_secs(REQUEST_TIMEOUT_SECS))
        .pool_max_idle_per_host(1)
        .build()?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut tally = Tally::default();
    while Instant::now() < until {
        let draw = f64::from(rng.next_u32()) / f64::from(u32::MAX);
        let url = if draw < list_share || ids.is_empty() {
            format!("{base}/v1/jobs?limit={LIST_LIMIT}")
        } else {
            let i = rng.next_u32() as usize % ids.len();
            format!("{base}/v1/jobs/{}", ids[i])
        };
        let mut req = http.get(url);
        if let Some(t) = &token {
            req = req.bearer_auth(t);
        }
        let t0 = Instant::now();
        let ok = match req.send().await {
            Ok(resp) => {
                let success = resp.status().is_success();
                resp.bytes().await.is_ok() && success
            }
            Err(_) => false,
        };
        tally
            .latencies_us
            .push(u64::try_from(t0.elapsed().as_micros()).unwrap_or(u64::MAX));
        if !ok {
            tally.errors += 1;
        }
    }
    Ok(tally)
}

/// One row of the table.
struct Row {
    requests: usize,
    per_second: f64,
    p50_ms: f64,
    p99_ms: f64,
    errors: u64,
}

/// The `q`-quantile (nearest rank) of sorted values, in milliseconds from microseconds.
pub(crate) fn quantile_ms(sorted_us: &[u64], q: f64) -> f64 {
    if sorted_us.is_empty() {
        return 0.0;
    }
    let rank = (q * sorted_us.len() as f64).ceil() as usize;
    sorted_us[rank.clamp(1, sorted_us.len()) - 1] as f64 / 1000.0
}

async fn drive(
    server: &Server,
    ids: &Arc<Vec<String>>,
    clients: u32,
    seconds: f64,
    list_share: f64,
) -> anyhow::Result<Row> {
    let base: Arc<str> = format!("http://{}", server.addr).into();
    let start = Instant::now();
    let until = start + Duration::from_secs_f64(seconds);
    let tasks: Vec<_> = (0..clients)
        .map(|c| {
            tokio::spawn(client(
                base.clone(),
                ids.clone(),
                u64::from(c),
                until,
                list_share,
                server.token.clone(),
            ))
        })
        .collect();
    let mut all = Vec::new();
    let mut errors = 0;
    for t in tasks {
        let tally = t.await??;
        all.extend(tally.latencies_us);
        errors += tally.errors;
    }
    let elapsed = start.elapsed().as_secs_f64();
    all.sort_unstable();
    Ok(Row {
        requests: all.len(),
        per_second: all.len() as f64 / elapsed.max(1e-9),
        p50_ms: quantile_ms(&all, 0.50),
        p99_ms: quantile_ms(&all, 0.99),
        errors,
    })
}

/// Runs the benchmark and prints its table on stdout (progress and skips on stderr).
pub async fn run(a: &LoadArgs) -> anyhow::Result<()> {
    use std::io::Write;
    let targets = parse_targets(&a.databases)?;
    let clients = parse_positive_list("--clients", &a.clients)?;
    if !(a.seconds.is_finite() && a.seconds > 0.0) {
        anyhow::bail!("--seconds must be a positive number of seconds");
    }
    if !(0.0..=1.0).contains(&a.list_share) {
        anyhow::bail!("--list-share must lie in [0, 1]");
    }
    if a.jobs == 0 {
        anyhow::bail!("--jobs must be at least 1");
    }
    let scratch = ScratchDir::new("load")?;
    let mut printed_header = false;
    for (i, target) in targets.iter().enumerate() {
        // The cluster (if any) outlives the server that uses it: declared first, dropped last.
        let mut cluster = None;
        let (label, database) = match target {
            Target::Sqlite => (
                "sqlite".to_string(),
                Database::Sqlite(scratch.0.join(format!("{i}")).join("sylva.db")),
            ),
            Target::Url(url) => ("postgres".to_string(), Database::parse(url)?),
            Target::Throwaway => {
                eprintln!("starting a throwaway PostgreSQL cluster…");
                let started = tokio::task::spawn_blocking(postgres::Cluster::start).await?;
                let c = match started {
                    Ok(c) => c,
                    Err(e) => {
                        eprintln!("skipping PostgreSQL: {e}");
                        continue;
                    }
                };
                let url = c.create_database("sylva_bench")?;
                let label = format!("postgres {}", c.version()).trim().to_string();
                cluster = Some(c);
                (label, Database::parse(&url)?)
            }
        };
        let server = Server::start(&database, &scratch.0.join(format!("{i}"))).await?;
        eprintln!("{label}: seeding {} jobs…", a.jobs);
        let ids = Arc::new(seed(&server.db, a.jobs).await?);
        for &n in &clients {
            let row = drive(&server, &ids, n, a.seconds, a.list_share).await?;
            if !printed_header {
                println!(
                    "| database | clients | requests | requests/s | p50 ms | p99 ms | errors |"
                );
                println!("|---|---|---|---|---|---|---|");
                printed_header = true;
            }
            println!(
                "| {label} | {n} | {} | {:.0} | {:.2} | {:.2} | {} |",
                row.requests, row.per_second, row.p50_ms, row.p99_ms, row.errors
            );
            let _ = std::io::stdout().flush();
        }
        server.shutdown().await;
        drop(cluster);
    }
    if !printed_header {
        anyhow::bail!("no database could be measured");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_rank() {
        let v: Vec<u64> = (1..=100).map(|x| x * 1000).collect();
        assert_eq!(quantile_ms(&v, 0.5), 50.0);
        assert_eq!(quantile_ms(&v, 0.99), 99.0);
        assert_eq!(quantile_ms(&[], 0.5), 0.0);
    }

    #[test]
    fn database_list_is_checked() {
        assert!(parse_targets("sqlite,postgres").is_ok());
        assert!(parse_targets("postgres://u@h/db").is_ok());
        assert!(parse_targets("mysql").is_err());
        assert!(parse_positive_list("--clients", "1,16").is_ok());
        assert!(parse_positive_list("--clients", "0").is_err());
        let e = parse_positive_list("--method-budgets", "500,0").expect_err("zero steps");
        assert!(e.to_string().contains("--method-budgets"), "{e}");
        assert_eq!(
            parse_positive_list("--method-budgets", " 500, 2000").expect("budgets"),
            [500, 2000]
        );
    }
}
