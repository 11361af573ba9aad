//! Shared test support: generated fixtures (a small LAS cloud, a COLMAP project with real
//! PNG photos, zipped), real `sylva` processes on ephemeral ports, and the job database they
//! share (SQLite, or a throwaway PostgreSQL: see [`Db`] and [`on_both_databases!`]).
#![allow(dead_code)]

pub mod postgres;
pub mod s3;

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use glam::{DVec3, Vec3};
use reqwest::{Client, RequestBuilder, Response, StatusCode};
use serde_json::{Value, json};
use sha2::{Digest, Sha256};
use sylva::io::colmap::{self, Camera, CameraModel, ColmapModel, Image, Point3D};
use sylva::io::pointcloud::{CloudFormat, PointCloud};

pub const BIN: &str = env!("CARGO_BIN_EXE_sylva");

/// Input files for one small plot.
pub struct Fixture {
    pub dir: tempfile::TempDir,
    /// `dir/data`, the data folder for the test's `sylva` processes (not created).
    pub data: PathBuf,
    pub lidar: PathBuf,
    pub lidar_points: usize,
    pub colmap_dir: PathBuf,
    pub colmap_zip: PathBuf,
    pub control_points: PathBuf,
    pub field_dbh: PathBuf,
}

/// A trunk (cylinder of radius 0.15 m) on flat ground, at georeferenced-like coordinates,
/// and a COLMAP project of 4 photos around it. Deterministic.
pub fn fixture() -> Fixture {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut positions = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            positions.push(Vec3::new(i as f32 * 0.1, j as f32 * 0.1, 0.0));
        }
    }
    for k in 0..60 {
        for a in 0..24 {
            let t = a as f32 / 24.0 * std::f32::consts::TAU;
            positions.push(Vec3::new(
                2.0 + 0.15 * t.cos(),
                2.0 + 0.15 * t.sin(),
                k as f32 * 0.05,
            ));
        }
    }
    let n = positions.len();
    let cloud = PointCloud {
        offset: DVec3::new(500_000.0, 4_000_000.0, 100.0),
        colors: Some((0..n).map(|i| [(i % 200) as u8, 90, 40]).collect()),
        intensity: None,
        positions,
        format: CloudFormat::Las,
    };
    let lidar = dir.path().join("plot.las");
    sylva::io::las::write_las(&lidar, &cloud, false).expect("write las");

    let colmap_dir = dir.path().join("project");
    let images = colmap_dir.join("images");
    let sparse = colmap_dir.join("sparse").join("0");
    std::fs::create_dir_all(&images).expect("mkdir");
    std::fs::create_dir_all(&sparse).expect("mkdir");
    let mut model = ColmapModel::default();
    model.cameras.insert(
        1,
        Camera {
            id: 1,
            model: CameraModel::Pinhole,
            width: 32,
            height: 24,
            params: vec![30.0, 30.0, 16.0, 12.0],
        },
    );
    for k in 0..4u32 {
        let name = format!("img_{k:03}.png");
        let img = image::RgbImage::from_fn(32, 24, |x, y| {
            image::Rgb([(x * 8) as u8, (y * 10) as u8, (k * 60) as u8])
        });
        img.save(images.join(&name)).expect("png");
        model.images.insert(
            k + 1,
            Image {
                id: k + 1,
                qvec: [1.0, 0.0, 0.0, 0.0],
                tvec: [k as f64 * 0.5, 0.0, 5.0],
                camera_id: 1,
                name,
                points2d: Vec::new(),
            },
        );
    }
    for p in 0..150u64 {
        model.points.push(Point3D {
            id: p + 1,
            xyz: DVec3::new((p % 10) as f64 * 0.1, (p / 10) as f64 * 0.1, 1.0),
            rgb: [100, 120, 80],
            error: 0.5,
            track: Vec::new(),
        });
    }
    colmap::write_text(&model, &sparse).expect("write model");
    let colmap_zip = dir.path().join("project.zip");
    zip_dir(&colmap_dir, &colmap_zip);

    let control_points = dir.path().join("control.csv");
    std::fs::write(
        &control_points,
        "sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z\n0,0,0,500000,4000000,100\n1,0,0,500002,4000000,100\n\
         0,1,0,500000,4000002,100\n0,0,1,500000,4000000,102\n",
    )
    .expect("write");
    let field_dbh = dir.path().join("field.csv");
    std::fs::write(&field_dbh, "tree_id,x,y,dbh_cm\n1,500002,4000002,30\n").expect("write");
    Fixture {
        data: dir.path().join("data"),
        dir,
        lidar,
        lidar_points: n,
        colmap_dir,
        colmap_zip,
        control_points,
        field_dbh,
    }
}

/// Zips every file under `dir` (names relative to it).
pub fn zip_dir(dir: &Path, out: &Path) {
    let f = std::fs::File::create(out).expect("create zip");
    let mut z = zip::ZipWriter::new(f);
    let opts = zip::write::SimpleFileOptions::default();
    let mut stack = vec![dir.to_path_buf()];
    let mut files = Vec::new();
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("read_dir") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                stack.push(p);
            } else {
                files.push(p);
            }
        }
    }
    files.sort();
    for p in files {
        let name = p
            .strip_prefix(dir)
            .expect("prefix")
            .to_string_lossy()
            .replace('\\', "/");
        z.start_file(name, opts).expect("start_file");
        z.write_all(&std::fs::read(&p).expect("read"))
            .expect("write");
    }
    z.finish().expect("finish zip");
}

/// `sylva synth --preset tiny --seed SEED` into `dir/plot`, with its COLMAP project zipped
/// (`colmap.zip`) for upload; returns the plot folder.
#[allow(dead_code)]
pub fn synthetic_plot(dir: &Path, seed: u64) -> PathBuf {
    let plot = synth_plot(dir, seed);
    zip_dir(&plot.join("colmap"), &plot.join("colmap.zip"));
    plot
}

/// `sylva synth --preset tiny --seed SEED` into `dir/plot`; returns the plot folder.
pub fn synth_plot(dir: &Path, seed: u64) -> PathBuf {
    let plot = dir.join("plot");
    let seed = seed.to_string();
    let synth = ["synth", "--preset", "tiny", "--seed", &seed, "--out"];
    succeeds(Command::new(BIN).args(synth).arg(&plot));
    plot
}

/// Runs `cmd` to its end and returns its output, failing the test (with its stdout and
/// stderr) unless it succeeded.
pub fn succeeds(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("run the command");
    assert!(
        out.status.success(),
        "{:?} failed ({}): {}\n{}",
        cmd.get_args().collect::<Vec<_>>(),
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `cmd` to its end and returns its stderr, failing the test if it succeeded.
pub fn fails(cmd: &mut Command) -> String {
    let out = cmd.output().expect("run the command");
    assert!(
        !out.status.success(),
        "{:?} succeeded",
        cmd.get_args().collect::<Vec<_>>()
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A tool the tests run: `$VAR` (its path, or `none` to go without), else
/// `target/test-venv/bin/NAME` (where scripts/test installs it), else NAME on the PATH; `Err`
/// says why there is none.
pub fn test_tool(var: &str, name: &str) -> Result<PathBuf, String> {
    if let Ok(v) = std::env::var(var) {
        if v == "none" {
            return Err(format!("{var}=none"));
        }
        return Ok(PathBuf::from(v));
    }
    let mut dirs = vec![Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-venv/bin")];
    if let Some(path) = std::env::var_os("PATH") {
        dirs.extend(std::env::split_paths(&path));
    }
    dirs.into_iter().map(|d| d.join(name)).find(|p| p.is_file()).ok_or_else(|| {
        format!(
            "{name} is not installed (scripts/test installs it into target/test-venv; or set {var})"
        )
    })
}

/// `sylva bench ARGS…` with authentication off, whatever the environment says: its stdout
/// and stderr, failing the test (with both) unless it succeeded.
pub fn bench(args: &[&str]) -> (String, String) {
    let out = Command::new(BIN)
        .arg("bench")
        .args(args)
        .env_remove("SYLVA_TOKEN")
        .output()
        .expect("run sylva bench");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        out.status.success(),
        "exit {}:\n{stdout}\n{stderr}",
        out.status
    );
    (stdout, stderr)
}

/// The cells of the first row of the Markdown table that `text` starts with, once its header
/// and rule lines are asserted to be `header` and `rule`.
pub fn table_row<'a>(text: &'a str, header: &str, rule: &str) -> Vec<&'a str> {
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(header), "{text}");
    assert_eq!(lines.next(), Some(rule));
    let row = lines.next().expect("one row").split('|').map(str::trim);
    row.filter(|c| !c.is_empty()).collect()
}

/// The JSON document in the file at `path`.
pub fn read_json(path: &Path) -> Value {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    serde_json::from_slice(&bytes).expect("json")
}

/// A running `sylva` process, killed when dropped.
pub struct Proc {
    pub child: Child,
    pub base: String,
    pub stderr: PathBuf,
}

impl Proc {
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
    pub fn stderr_text(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A `sylva ARGS… --data DATA` command with no `SYLVA_*` variables from the test's
/// environment.
pub fn sylva_command(args: &[&str], data: &Path) -> Command {
    let mut cmd = Command::new(BIN);
    for (k, _) in std::env::vars() {
        if k.starts_with("SYLVA_") {
            cmd.env_remove(k);
        }
    }
    cmd.args(args).arg("--data").arg(data);
    cmd
}

/// An HTTP client that sends `Authorization: Bearer KEY` with every request.
pub fn keyed_client(key: &str) -> Client {
    let mut h = reqwest::header::HeaderMap::new();
    h.insert(
        reqwest::header::AUTHORIZATION,
        format!("Bearer {key}").parse().expect("header"),
    );
    Client::builder()
        .default_headers(h)
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client")
}

/// `sylva serve` on an ephemeral port: the command, and the line it prints once it listens.
const SERVE: (&[&str], &str) = (&["serve", "--listen", "127.0.0.1:0"], "sylva listening on");
/// `sylva worker`: the command, and the line it prints once it polls.
const WORKER: (&[&str], &str) = (&["worker"], "sylva worker started");

/// Starts `sylva COMMAND… EXTRA…` and waits for its ready line.
fn spawn((command, ready): (&[&str], &str), extra: &[&str], data: &Path) -> Proc {
    spawn_with_env(&[command, extra].concat(), data, ready, &[])
}

fn spawn_with_env(
    args: &[&str],
    data: &Path,
    ready_prefix: &str,
    env: &[(String, String)],
) -> Proc {
    let stderr = data.join(format!("stderr-{}.log", uuid::Uuid::new_v4().simple()));
    std::fs::create_dir_all(data).expect("data dir");
    let mut child = sylva_command(args, data)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .env("SYLVA_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&stderr).expect("stderr file"))
        .spawn()
        .expect("spawn sylva");
    let stdout = child.stdout.take().expect("stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) if line.starts_with(ready_prefix) => {
                let base = line
                    .split_whitespace()
                    .find(|w| w.starts_with("http://"))
                    .unwrap_or("")
                    .to_string();
                return Proc {
                    child,
                    base,
                    stderr,
                };
            }
            Ok(_) => {}
            Err(_) => {
                let _ = child.kill();
                panic!(
                    "sylva {args:?} did not start: {}",
                    std::fs::read_to_string(&stderr).unwrap_or_default()
                );
            }
        }
    }
}

/// `sylva serve` on an ephemeral port with `extra` flags.
pub fn serve(data: &Path, extra: &[&str]) -> Proc {
    spawn(SERVE, extra, data)
}

/// `sylva worker` with `extra` flags.
pub fn worker(data: &Path, extra: &[&str]) -> Proc {
    spawn(WORKER, extra, data)
}

/// The job database (and blob store) a test's `sylva` processes share.
pub enum Db {
    /// SQLite and local files under the data directory (the default; no flag).
    Sqlite,
    /// A fresh database on the test PostgreSQL (`--database postgres://...`) and, where the
    /// test S3 server is installed, a fresh bucket (`--store s3://...`): then every process
    /// also gets a data directory of its own, as if it ran on its own machine.
    Postgres(postgres::TestDatabase, Option<s3::TestBucket>),
}

impl Db {
    pub fn sqlite() -> Db {
        Db::Sqlite
    }

    /// `None` (with the reason printed) where PostgreSQL is not installed.
    pub fn postgres() -> Option<Db> {
        let pg = postgres::database()?;
        Some(Db::Postgres(pg, s3::bucket()))
    }

    /// The test bucket, when blobs live in one.
    pub fn bucket(&self) -> Option<&s3::TestBucket> {
        match self {
            Db::Postgres(_, b) => b.as_ref(),
            Db::Sqlite => None,
        }
    }

    fn with_flags<'a>(&'a self, extra: &[&'a str]) -> Vec<&'a str> {
        let mut args = extra.to_vec();
        if let Db::Postgres(pg, bucket) = self {
            args.extend(["--database", pg.url.as_str()]);
            if let Some(b) = bucket {
                args.extend(["--store", b.url.as_str()]);
            }
        }
        args
    }

    fn env(&self) -> Vec<(String, String)> {
        self.bucket().map(|b| b.env.clone()).unwrap_or_default()
    }

    /// The data directory of one process: `data` itself, or with an object store a fresh
    /// folder under it (nothing local is shared between processes then).
    fn machine_dir(&self, data: &Path) -> PathBuf {
        match self.bucket() {
            Some(_) => data.join(format!("machine-{}", uuid::Uuid::new_v4().simple())),
            None => data.to_path_buf(),
        }
    }

    /// Fails unless the process says it opened this kind of database and blob store.
    fn check_backend(&self, p: Proc) -> Proc {
        let name = match self {
            Db::Sqlite => "\"sqlite\"",
            Db::Postgres(..) => "\"postgres\"",
        };
        let store = if self.bucket().is_some() {
            "s3"
        } else {
            "local"
        };
        let text = p.stderr_text();
        assert!(
            text.lines()
                .any(|l| l.contains("job database open") && l.contains(name)),
            "expected a {name} job database: {text}"
        );
        assert!(
            text.lines()
                .any(|l| l.contains("blob store open") && l.contains(store)),
            "expected a {store} blob store: {text}"
        );
        p
    }

    /// Starts `sylva COMMAND… EXTRA…` on this database and checks that it opened it.
    fn spawn(&self, (command, ready): (&[&str], &str), extra: &[&str], data: &Path) -> Proc {
        let args = [command, &self.with_flags(extra)].concat();
        let p = spawn_with_env(&args, &self.machine_dir(data), ready, &self.env());
        self.check_backend(p)
    }

    /// `sylva serve` on this database.
    pub fn serve(&self, data: &Path, extra: &[&str]) -> Proc {
        self.spawn(SERVE, extra, data)
    }

    /// `sylva keys create --name NAME EXTRA…` on this database: the new key.
    pub fn create_key(&self, data: &Path, name: &str, extra: &[&str]) -> String {
        let mut args = vec!["--name", name];
        args.extend_from_slice(extra);
        let key = self.keys(data, "create", &args).trim().to_string();
        assert!(key.starts_with("sylva_") && key.len() == 70, "{key:?}");
        key
    }

    /// `sylva keys ACTION ARGS…` on this database; its output, failing the test on an error.
    pub fn keys(&self, data: &Path, action: &str, args: &[&str]) -> String {
        let mut all = vec!["keys", action];
        all.extend_from_slice(args);
        if let Db::Postgres(pg, _) = self {
            all.extend(["--database", pg.url.as_str()]);
        }
        let out = succeeds(&mut sylva_command(&all, data));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// `sylva worker` on this database.
    pub fn worker(&self, data: &Path, extra: &[&str]) -> Proc {
        self.spawn(WORKER, extra, data)
    }
}

/// Runs the async test body `$name(db: Db)` once per job database, as the tests
/// `$name::sqlite` and `$name::postgres` (which skips, saying why, without PostgreSQL).
#[allow(unused_macros)]
macro_rules! on_both_databases {
    ($name:ident) => {
        mod $name {
            #[tokio::test(flavor = "multi_thread")]
            async fn sqlite() {
                super::$name(super::common::Db::sqlite()).await;
            }

            #[tokio::test(flavor = "multi_thread")]
            async fn postgres() {
                if let Some(db) = super::common::Db::postgres() {
                    super::$name(db).await;
                }
            }
        }
    };
}
#[allow(unused_imports)]
pub(crate) use on_both_databases;

/// An HTTP client with a 60 s timeout.
pub fn client() -> Client {
    Client::builder()
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client")
}

/// Hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Sends a request; its answer (the test fails when none comes).
pub async fn send(req: RequestBuilder) -> Response {
    req.send().await.expect("send the request")
}

/// Sends a request; the JSON body of its answer, whatever its status.
pub async fn send_json(req: RequestBuilder) -> Value {
    send(req).await.json().await.expect("a JSON answer")
}

/// `v["id"]`: the id of a created upload, job or key.
pub fn id_of(v: &Value) -> String {
    v["id"].as_str().expect("id").to_string()
}

/// The `detail` of a problem document.
pub fn detail(p: &Value) -> &str {
    p["detail"].as_str().expect("detail")
}

/// Asserts a problem+json answer with `status`; returns the problem.
pub async fn expect_problem(resp: Response, status: StatusCode) -> Value {
    assert_eq!(resp.status(), status, "unexpected status");
    let ct = resp
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(
        ct.starts_with("application/problem+json"),
        "content type {ct}"
    );
    let v: Value = resp.json().await.expect("problem body");
    assert_eq!(v["status"], status.as_u16());
    assert!(v["type"].as_str().is_some_and(|t| !t.is_empty()));
    v
}

/// Sends a request and asserts a problem+json answer with `status`; returns the problem.
pub async fn send_problem(req: RequestBuilder, status: StatusCode) -> Value {
    expect_problem(send(req).await, status).await
}

/// Opens an upload of `size` bytes of `kind` named `name`, without a checksum; the JSON
/// answer, whatever its status.
pub async fn open_upload(c: &Client, base: &str, kind: &str, name: &str, size: u64) -> Value {
    let body = json!({ "kind": kind, "filename": name, "size": size });
    send_json(c.post(format!("{base}/v1/uploads")).json(&body)).await
}

/// PUTs part `n` of upload `id`; the answer.
pub async fn put_part(
    c: &Client,
    base: &str,
    id: &str,
    n: usize,
    body: impl Into<reqwest::Body>,
) -> Response {
    send(
        c.put(format!("{base}/v1/uploads/{id}/parts/{n}"))
            .body(body),
    )
    .await
}

/// Asks to complete upload `id`; the answer.
pub async fn complete_upload(c: &Client, base: &str, id: &str) -> Response {
    send(c.post(format!("{base}/v1/uploads/{id}/complete"))).await
}

/// Uploads `bytes` as `kind` named `name` through the resumable API, in the parts the server
/// asks for (with their SHA-256 when `checksum`); the upload's id and the answer to `complete`.
pub async fn upload_bytes(
    c: &Client,
    base: &str,
    (kind, name): (&str, &str),
    bytes: &[u8],
    checksum: bool,
) -> (String, Response) {
    let mut body = json!({ "kind": kind, "filename": name, "size": bytes.len() });
    if checksum {
        body["sha256"] = json!(sha256_hex(bytes));
    }
    let created: Value = send(c.post(format!("{base}/v1/uploads")).json(&body))
        .await
        .error_for_status()
        .expect("201")
        .json()
        .await
        .expect("json");
    let id = id_of(&created);
    let part = created["part_size"].as_u64().expect("part_size") as usize;
    for (n, chunk) in bytes.chunks(part).enumerate() {
        let r = put_part(c, base, &id, n, chunk.to_vec()).await;
        assert_eq!(r.status(), StatusCode::OK, "part {n} of {name}");
    }
    let done = complete_upload(c, base, &id).await;
    (id, done)
}

/// Uploads a file in parts through the resumable API; returns the upload id.
pub async fn upload(c: &Client, base: &str, kind: &str, path: &Path) -> String {
    let bytes = std::fs::read(path).expect("read input");
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let (id, done) = upload_bytes(c, base, (kind, name), &bytes, true).await;
    assert_eq!(done.status(), StatusCode::OK, "{:?}", done.text().await);
    id
}

/// Uploads the fixture's lidar and colmap; returns the job's `inputs` object.
pub async fn upload_inputs(c: &Client, base: &str, fx: &Fixture) -> Value {
    let lidar = upload(c, base, "lidar", &fx.lidar).await;
    let colmap = upload(c, base, "colmap", &fx.colmap_zip).await;
    json!({ "lidar": lidar, "colmap": colmap })
}

/// A multipart form with a part for each `(name, path)`: the file's bytes under its own name.
pub fn multipart<P: AsRef<Path>>(files: &[(&str, P)]) -> reqwest::multipart::Form {
    files
        .iter()
        .fold(reqwest::multipart::Form::new(), |form, (name, path)| {
            let path = path.as_ref();
            let bytes = std::fs::read(path).expect("read input");
            let file = path.file_name().and_then(|n| n.to_str()).unwrap_or("f");
            let part = reqwest::multipart::Part::bytes(bytes).file_name(file.to_string());
            form.part(name.to_string(), part)
        })
}

/// A client of the server `srv`, its base URL, and the fixture's lidar and colmap uploaded
/// through it (a job's `inputs`).
pub async fn client_with_inputs(srv: &Proc, fx: &Fixture) -> (Client, String, Value) {
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, fx).await;
    (c, base, inputs)
}

/// The body of a job over `inputs` that runs the stages up to `until`.
pub fn job_until(inputs: &Value, until: &str) -> Value {
    json!({ "inputs": inputs, "params": { "until": until } })
}

/// Creates a job, asserting 202; the job.
pub async fn create_job(c: &Client, base: &str, body: &Value) -> Value {
    let resp = send(c.post(format!("{base}/v1/jobs")).json(body)).await;
    assert_eq!(
        resp.status(),
        StatusCode::ACCEPTED,
        "{:?}",
        resp.text().await
    );
    resp.json().await.expect("job json")
}

/// Creates a job, asserting 202; its id.
pub async fn submit(c: &Client, base: &str, body: &Value) -> String {
    id_of(&create_job(c, base, body).await)
}

/// GET `url` and its JSON body.
#[allow(dead_code)]
pub async fn get_json(c: &Client, url: &str) -> Value {
    send_json(c.get(url)).await
}

/// The job `id`, asserting a 2xx answer.
pub async fn get_job(c: &Client, base: &str, id: &str) -> Value {
    send(c.get(format!("{base}/v1/jobs/{id}")))
        .await
        .error_for_status()
        .expect("200")
        .json()
        .await
        .expect("json")
}

/// Calls `probe` every `every_ms` milliseconds until it gives `Ok`; fails the test with its
/// last `Err` once `timeout` has passed.
pub async fn poll_until<T>(
    timeout: Duration,
    every_ms: u64,
    mut probe: impl AsyncFnMut() -> Result<T, String>,
) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        match probe().await {
            Ok(v) => return v,
            Err(why) => assert!(Instant::now() < deadline, "timed out: {why}"),
        }
        tokio::time::sleep(Duration::from_millis(every_ms)).await;
    }
}

/// Polls a job until `done(job)` holds; returns the job and every progress value seen.
pub async fn wait_job(
    c: &Client,
    base: &str,
    id: &str,
    timeout: Duration,
    done: impl Fn(&Value) -> bool,
) -> (Value, Vec<f64>) {
    let mut seen = Vec::new();
    let job = poll_until(timeout, 50, async || {
        let j = get_job(c, base, id).await;
        seen.push(j["progress"].as_f64().expect("progress"));
        if done(&j) {
            Ok(j)
        } else {
            Err(format!("waiting for job {id}: {j}"))
        }
    })
    .await;
    (job, seen)
}

/// Whether a job has ended: succeeded, failed or canceled.
pub fn is_terminal(j: &Value) -> bool {
    matches!(
        j["state"].as_str(),
        Some("succeeded" | "failed" | "canceled")
    )
}

/// The stage `name` of a job (null when it has none).
pub fn stage<'a>(j: &'a Value, name: &str) -> &'a Value {
    j["stages"]
        .as_array()
        .and_then(|s| s.iter().find(|s| s["name"] == name))
        .unwrap_or(&Value::Null)
}

/// The lines of job `id`'s log.
pub async fn log_lines(c: &Client, base: &str, id: &str) -> Vec<Value> {
    let v = send_json(c.get(format!("{base}/v1/jobs/{id}/log"))).await;
    v["lines"].as_array().cloned().unwrap_or_default()
}

/// The messages of job `id`'s log, one a line.
pub async fn log_text(c: &Client, base: &str, id: &str) -> String {
    let lines = log_lines(c, base, id).await;
    let messages: Vec<&str> = lines.iter().filter_map(|x| x["message"].as_str()).collect();
    messages.join("\n")
}

/// (METHOD, path) pairs of openapi.yaml's `paths`.
pub fn openapi_operations() -> std::collections::BTreeSet<(String, String)> {
    let text = sylva::api::service::OPENAPI_YAML;
    let mut ops = std::collections::BTreeSet::new();
    let mut in_paths = false;
    let mut path = None;
    for line in text.lines() {
        if !line.starts_with(' ') && !line.is_empty() {
            in_paths = line.starts_with("paths:");
            continue;
        }
        if !in_paths {
            continue;
        }
        if let Some(p) = line.strip_prefix("  /").and_then(|l| l.strip_suffix(':')) {
            path = Some(format!("/{p}"));
        } else if let Some(m) = line.strip_prefix("    ").and_then(|l| l.strip_suffix(':'))
            && ["get", "put", "post", "delete", "head", "patch", "options"].contains(&m)
            && let Some(p) = &path
        {
            ops.insert((m.to_uppercase(), p.clone()));
        }
    }
    ops
}

/// A Python venv with laspy + lazrs under target/, or None (with the reason printed).
pub fn laspy_python() -> Option<PathBuf> {
    let venv = Path::new(env!("CARGO_TARGET_TMPDIR")).join("laspy-venv");
    let python = venv.join("bin/python");
    let ready = |p: &Path| {
        Command::new(p)
            .args(["-c", "import laspy, lazrs"])
            .status()
            .is_ok_and(|s| s.success())
    };
    if python.is_file() && ready(&python) {
        return Some(python);
    }
    let made = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .status();
    if !made.is_ok_and(|s| s.success()) {
        sylva::testing::skip("pypi", "cannot create a Python venv (python3 -m venv)");
        return None;
    }
    let pip = Command::new(venv.join("bin/pip"))
        .args(["install", "-q", "laspy==2.6.1", "lazrs==0.7.0"])
        .status();
    if !pip.is_ok_and(|s| s.success()) || !ready(&python) {
        sylva::testing::skip("pypi", "cannot install laspy and lazrs from PyPI");
        return None;
    }
    Some(python)
}
