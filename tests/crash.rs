//! A crash inside any stage loses nothing (docs/operations.md: "A killed process (SIGKILL at any
//! point) loses no accepted upload, no job, no finished stage").
//!
//! One generated plot runs through every stage once without interruption (the reference).
//! Then, for each stage in turn, a fresh job on the same server data runs under
//! `--debug-crash-at STAGE:FRACTION`, which makes the process SIGKILL itself from inside that
//! stage once the stage reports the fraction, at a point where the stage has already written
//! files into its `<stage>.partial/` folder (training is also killed half-way through its
//! optimisation, before it writes anything). The server is started again without the flag, and
//! the job must resume at that stage (earlier stages untouched), succeed, and match the
//! reference: the same artifact names and the same metrics within a tolerance. The database
//! must pass `PRAGMA integrity_check` after every crash, and every upload stays complete.
//!
//! Needs the `fault-injection` feature (scripts/test turns it on); without it this file is
//! empty, as a user's binary has no `--debug-crash-at`.
#![cfg(feature = "fault-injection")]

mod common;

use std::collections::BTreeSet;
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::ExitStatus;
use std::time::{Duration, Instant};

use common::*;
use serde_json::{Value, json};
use sylva::jobs::{JobState, JobStore, StageState};
use sylva::store::BlobStore;

/// Where each stage is killed: a progress fraction the stage reports after it has written
/// some of its files (see each stage's `progress.set` calls), and the file that proves it.
/// Training writes nothing until its last step, so it is also killed half-way through its
/// optimisation, where a real crash most likely lands.
const CRASH_POINTS: [(&str, f64, Option<&str>); 8] = [
    ("ingest", 0.5, Some("cloud.ply")),
    ("register", 1.0, Some("sparse")),
    ("anchors", 0.2, Some("fused.ply")),
    ("segment", 0.9, Some("labelled.ply")),
    ("train", 0.5, None),
    ("train", 1.0, Some("splats.ply")),
    ("dbh", 1.0, Some("trees.geojson")),
    ("export", 1.0, Some("frame.json")),
];

/// A whole job on a tiny plot within seconds: the CPU reference trainer, few steps, small
/// photos and a bounded number of Gaussians (as the CLI's whole-run test).
fn params() -> Value {
    json!({ "train": {
        "backend": "cpu", "steps": 60, "resolution": 48, "init": "lidar", "max_gaussians": 1500
    } })
}

/// Relative tolerance on a metric between the reference and a resumed run. Every stage is
/// seeded and all 175 metrics agreed exactly in every run so far; the margin is for parallel
/// reductions that may sum in another order on another machine.
const REL_TOL: f64 = 1e-3;
/// Absolute tolerance below which two metrics count as equal whatever their ratio.
const ABS_TOL: f64 = 1e-9;

/// Metric keys measured in wall-clock time, which no two runs share.
fn is_timing(key: &str) -> bool {
    let k = key.to_ascii_lowercase();
    k.contains("second")
        || k.contains("secs")
        || k.ends_with("_ms")
        || k.contains("per_s")
        || k.contains("elapsed")
        || k.contains("duration")
}

/// Compares two metric trees: the same keys and array lengths, numbers within tolerance,
/// other scalars equal (except timings and free text). Pushes every difference to `errs`;
/// returns how many numbers it compared.
fn compare(path: &str, want: &Value, got: &Value, errs: &mut Vec<String>) -> usize {
    let mut n = 0;
    match (want, got) {
        (Value::Object(a), Value::Object(b)) => {
            let (ka, kb): (BTreeSet<_>, BTreeSet<_>) = (a.keys().collect(), b.keys().collect());
            if ka != kb {
                errs.push(format!("{path}: keys {ka:?} != {kb:?}"));
            }
            for (k, va) in a {
                if is_timing(k) {
                    continue;
                }
                if let Some(vb) = b.get(k) {
                    n += compare(&format!("{path}.{k}"), va, vb, errs);
                }
            }
        }
        (Value::Array(a), Value::Array(b)) => {
            if a.len() != b.len() {
                errs.push(format!("{path}: {} items != {}", a.len(), b.len()));
            }
            for (i, (va, vb)) in a.iter().zip(b).enumerate() {
                n += compare(&format!("{path}[{i}]"), va, vb, errs);
            }
        }
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (
                a.as_f64().unwrap_or(f64::NAN),
                b.as_f64().unwrap_or(f64::NAN),
            );
            let close = (a - b).abs() <= ABS_TOL.max(REL_TOL * a.abs().max(b.abs()));
            if !close {
                errs.push(format!("{path}: {a} != {b}"));
            }
            n += 1;
        }
        // Log-like text (device names, notes) may differ; its presence is checked above.
        (Value::String(_), Value::String(_)) => {}
        (a, b) if a == b => {}
        (a, b) => errs.push(format!("{path}: {a} != {b}")),
    }
    n
}

/// Waits for a process to end by itself.
fn wait_exit(p: &mut Proc, timeout: Duration) -> ExitStatus {
    let deadline = Instant::now() + timeout;
    loop {
        match p.child.try_wait() {
            Ok(Some(status)) => return status,
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(50)),
            other => panic!(
                "the server did not crash within {timeout:?} ({other:?}): {}",
                p.stderr_text()
            ),
        }
    }
}

/// Names of the files a folder holds (empty when it does not exist).
fn entries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// The stages of a job straight from the database: (name, state, attempt, started, finished).
type StageRow = (String, StageState, i64, Option<i64>, Option<i64>);

async fn open_db(data: &Path) -> JobStore {
    JobStore::open_sqlite(&data.join("sylva.db"), 1)
        .await
        .expect("open the job database")
}

fn artifact_names(job: &Value) -> BTreeSet<String> {
    job["artifacts"]
        .as_array()
        .expect("artifacts")
        .iter()
        .filter_map(|a| a["name"].as_str().map(str::to_string))
        .collect()
}

struct Plot {
    _dir: tempfile::TempDir,
    files: Vec<(&'static str, PathBuf)>,
}

/// `sylva synth --preset tiny --seed 3`, with its COLMAP project zipped for upload.
fn plot() -> Plot {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = synthetic_plot(dir.path(), 3);
    let files = vec![
        ("lidar", out.join("lidar.laz")),
        ("colmap", out.join("colmap.zip")),
        ("control_points", out.join("control_points.csv")),
        ("field_dbh", out.join("field_dbh.csv")),
    ];
    Plot { _dir: dir, files }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_job_killed_inside_any_stage_resumes_there_and_matches_an_uninterrupted_run() {
    let started = Instant::now();
    let plot = plot();
    let work = tempfile::tempdir().expect("tempdir");
    let data = work.path().join("data");
    let c = client();

    // The uploads, accepted once and read by every job below.
    let srv = serve(&data, &[]);
    let mut inputs = serde_json::Map::new();
    for (kind, path) in &plot.files {
        inputs.insert(
            kind.to_string(),
            json!(upload(&c, &srv.base, kind, path).await),
        );
    }
    let body = json!({ "inputs": inputs, "params": params() });

    // The reference: the same job without interruption.
    let reference = create_job(&c, &srv.base, &body).await;
    let rid = reference["id"].as_str().expect("id").to_string();
    let (reference, _) = wait_job(&c, &srv.base, &rid, Duration::from_secs(300), is_terminal).await;
    assert_eq!(reference["state"], "succeeded", "{reference}");
    let want_names = artifact_names(&reference);
    let want_results: Value = get_json(&c, &format!("{}/v1/jobs/{rid}/results", srv.base)).await;
    for (stage, _, _) in CRASH_POINTS {
        assert!(
            want_results["stages"][stage].is_object(),
            "no metrics for {stage}: {want_results}"
        );
    }
    drop(srv);
    eprintln!("reference run done after {:?}", started.elapsed());

    let blobs = BlobStore::open(&data).expect("blob store");
    for (stage, fraction, witness) in CRASH_POINTS {
        let case = Instant::now();
        let k = sylva::pipeline::Stage::from_name(stage)
            .expect("a stage")
            .index();
        // 1. Run a fresh job until the process kills itself inside `stage`.
        let point = format!("{stage}:{fraction}");
        let mut srv = serve(&data, &["--debug-crash-at", &point]);
        let job = create_job(&c, &srv.base, &body).await;
        let id = job["id"].as_str().expect("id").to_string();
        let status = wait_exit(&mut srv, Duration::from_secs(300));
        assert_eq!(
            status.signal(),
            Some(libc::SIGKILL),
            "{stage}: not killed by SIGKILL ({status}): {}",
            srv.stderr_text()
        );
        assert!(
            srv.stderr_text()
                .contains(&format!("SIGKILL inside stage {stage} ")),
            "{stage}: {}",
            srv.stderr_text()
        );
        drop(srv);

        // 2. What the crash left: a sound database, the job running in `stage` with every
        // earlier stage done, and the stage's partial outputs on disk, not yet promoted.
        let db = open_db(&data).await;
        assert_eq!(
            db.integrity_check().await.expect("integrity_check"),
            "ok",
            "{stage}"
        );
        let rec = db.get_job(&id).await.expect("get").expect("job row kept");
        assert_eq!(rec.state, JobState::Running, "{stage}");
        assert_eq!(rec.attempt, 1, "{stage}");
        let before: Vec<StageRow> = rec
            .stages
            .iter()
            .map(|s| {
                (
                    s.name.clone(),
                    s.state,
                    s.attempt,
                    s.started_at,
                    s.finished_at,
                )
            })
            .collect();
        for (i, (name, state, ..)) in before.iter().enumerate() {
            let want = match i.cmp(&k) {
                std::cmp::Ordering::Less => StageState::Done,
                std::cmp::Ordering::Equal => StageState::Running,
                std::cmp::Ordering::Greater => StageState::Pending,
            };
            assert_eq!(*state, want, "{stage}: stage {name} after the crash");
        }
        let crashed_started = before[k].3.expect("started_at");
        drop(db);
        let job_dir = blobs.job_dir(&id);
        let partial = job_dir.join(format!("{stage}.partial"));
        assert!(partial.is_dir(), "{stage}: killed outside the stage");
        if let Some(witness) = witness {
            let written = entries(&partial);
            assert!(
                written.iter().any(|f| f == witness),
                "{stage}: killed before it wrote {witness}: {written:?}"
            );
        }
        assert!(!job_dir.join(stage).exists(), "{stage}: promoted already");

        // 3. Restart without the flag: the job resumes at `stage` and succeeds.
        let srv = serve(&data, &[]);
        let (job, progress) =
            wait_job(&c, &srv.base, &id, Duration::from_secs(300), is_terminal).await;
        assert_eq!(job["state"], "succeeded", "{stage}: {job}");
        assert_eq!(job["attempt"], 2, "{stage}: claimed once more: {job}");
        assert!(
            progress.windows(2).all(|w| w[1] >= w[0]),
            "{stage}: progress decreased: {progress:?}"
        );
        let log = log_text(&c, &srv.base, &id).await;
        assert!(
            log.contains(&format!("resumed at stage {stage} by worker")),
            "{stage}: {log}"
        );
        let db = open_db(&data).await;
        let rec = db.get_job(&id).await.expect("get").expect("job row");
        for (i, s) in rec.stages.iter().enumerate() {
            let (name, _, attempt, started, finished) = &before[i];
            assert_eq!(s.state, StageState::Done, "{stage}: {name}");
            if i < k {
                assert_eq!(
                    (s.attempt, s.started_at, s.finished_at),
                    (*attempt, *started, *finished),
                    "{stage}: finished stage {name} was run again"
                );
            } else {
                assert_eq!(s.attempt, 2, "{stage}: {name} runs in attempt 2");
            }
        }
        assert!(
            rec.stages[k].started_at > Some(crashed_started),
            "{stage}: the crashed stage was not started again"
        );
        drop(db);
        let left: Vec<String> = entries(&job_dir)
            .into_iter()
            .filter(|f| f.ends_with(".partial"))
            .collect();
        assert!(left.is_empty(), "{stage}: partial folders left: {left:?}");

        // 4. The same results as the uninterrupted run.
        assert_eq!(artifact_names(&job), want_names, "{stage}: artifacts");
        let results: Value = get_json(&c, &format!("{}/v1/jobs/{id}/results", srv.base)).await;
        let mut errs = Vec::new();
        let compared = compare(
            "stages",
            &want_results["stages"],
            &results["stages"],
            &mut errs,
        );
        assert!(
            errs.is_empty(),
            "{stage}: metrics differ:\n{}",
            errs.join("\n")
        );
        assert!(compared > 50, "{stage}: only {compared} metrics compared");
        drop(srv);
        eprintln!(
            "crash in {stage} at {fraction}: {compared} metrics compared, checked in {:?}",
            case.elapsed()
        );
    }

    // 5. Nothing accepted was lost: every upload is still complete, with its bytes intact,
    // and every job row is still there.
    let srv = serve(&data, &[]);
    for (kind, path) in &plot.files {
        let id = inputs[*kind].as_str().expect("upload id");
        let up: Value = get_json(&c, &format!("{}/v1/uploads/{id}", srv.base)).await;
        assert_eq!(up["state"], "complete", "{kind}: {up}");
        let bytes = std::fs::read(path).expect("input");
        assert_eq!(up["sha256"], sha256_hex(&bytes), "{kind}");
        let name = path.file_name().and_then(|n| n.to_str()).expect("name");
        let blob = std::fs::read(blobs.upload_blob(id, name)).expect("upload blob kept");
        assert_eq!(
            sha256_hex(&blob),
            sha256_hex(&bytes),
            "{kind}: blob changed"
        );
    }
    let list: Value = get_json(&c, &format!("{}/v1/jobs?limit=50", srv.base)).await;
    let jobs = list["jobs"].as_array().expect("jobs");
    assert_eq!(jobs.len(), 1 + CRASH_POINTS.len(), "{list}");
    assert!(jobs.iter().all(|j| j["state"] == "succeeded"), "{list}");
    drop(srv);
    let db = open_db(&data).await;
    assert_eq!(db.integrity_check().await.expect("check"), "ok");
    eprintln!("crash at every stage: {:?} in all", started.elapsed());
}
