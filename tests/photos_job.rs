//! A job from real photos, end to end through the API (issue 39): `tests/data/real_drone`
//! holds a real drone flight made small, 18 nadir photos with their own GPS tags and the
//! photogrammetric cloud of the same flight standing in for the LiDAR (see its README). A
//! server and a worker run the job from the photos and the cloud alone: stage `sfm` runs
//! COLMAP, `register` starts from the photos' GPS tags on a cloud with no ground under its
//! trees, and every later stage runs. A second job is cancelled while COLMAP runs, and no
//! COLMAP process of it may be left.
//!
//! Skips with a printed reason without the `colmap` program (Debian's package; CI requires
//! it) or a GPU adapter (lavapipe in CI).

mod common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use common::*;
use serde_json::{Value, json};

fn real_drone() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/real_drone")
}

/// The COLMAP program stage `sfm` will run, or `None` (after printing why) when missing.
fn colmap_present() -> bool {
    let program = sylva::sfm::colmap_program();
    match sylva::sfm::check_program(&program) {
        Ok(_) => true,
        Err(e) => {
            sylva::testing::skip("colmap", &e.to_string());
            false
        }
    }
}

fn gpu_present() -> bool {
    let params = sylva::pipeline::params::TrainParams::default();
    match sylva::pipeline::train::backend_for(&params) {
        Ok(_) => true,
        Err(e) => {
            sylva::testing::skip("gpu", &e.to_string());
            false
        }
    }
}

/// The ids of every process whose command line mentions `needle` (from /proc).
fn processes_mentioning(needle: &str) -> Vec<(u32, String)> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return out;
    };
    for e in entries.flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else {
            continue;
        };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        let stat = std::fs::read_to_string(e.path().join("stat")).unwrap_or_default();
        let zombie = stat
            .rsplit_once(") ")
            .is_some_and(|(_, r)| r.starts_with('Z'));
        if cmd.contains(needle) && !zombie {
            out.push((pid, cmd));
        }
    }
    out
}

async fn upload_photos(c: &reqwest::Client, base: &str, dir: &Path) -> (String, String) {
    let zip = dir.join("photos.zip");
    zip_dir(&real_drone().join("photos"), &zip);
    let photos = upload(c, base, "photos", &zip).await;
    let lidar = upload(c, base, "lidar", &real_drone().join("cloud.laz")).await;
    (lidar, photos)
}

fn report<'a>(j: &'a Value, stage_name: &str) -> &'a Value {
    &stage(j, stage_name)["metrics"]
}

/// The job from photos and the cloud alone, through the API. Stage `sfm` registers the
/// photos and `register` verifies the GPS start on the cloud without ground; then its
/// precision gate refuses, as it does on the full-size flight (the split halves of the SfM
/// points disagree on the yaw by 0.046° here, 0.033° at full size, where 0.025° is the
/// limit without control points; docs/results/photos.md). When the registration of such a
/// pair gets precise enough, this test must ask for the whole job.
#[tokio::test(flavor = "multi_thread")]
async fn a_job_from_real_drone_photos_reconstructs_and_verifies_its_gps_start() {
    if !colmap_present() {
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let data = dir.path().join("data");
    let srv = serve(&data, &[]);
    let (c, base) = (client(), srv.base.clone());
    let (lidar, photos) = upload_photos(&c, &base, dir.path()).await;
    let body = json!({ "inputs": { "lidar": lidar, "photos": photos } });
    let id = submit(&c, &base, &body).await;
    let (job, progress) = wait_job(&c, &base, &id, Duration::from_secs(1200), is_terminal).await;
    let log = log_text(&c, &base, &id).await;
    assert!(
        progress.windows(2).all(|w| w[1] >= w[0] - 1e-9),
        "progress went back: {progress:?}"
    );
    // Stage sfm: COLMAP's progress reached the log, every photo registered.
    assert!(log.contains("COLMAP matching: 100%"), "{log}");
    let sfm = report(&job, "sfm");
    assert_eq!(stage(&job, "sfm")["state"], "done", "{job}\n{log}");
    assert_eq!(sfm["photos"], 18, "{sfm}");
    assert_eq!(sfm["photos_with_gps"], 18, "{sfm}");
    assert_eq!(sfm["matching"], "exhaustive", "{sfm}");
    let registered = sfm["registered"].as_u64().unwrap_or(0);
    assert!(
        registered >= 16,
        "only {registered} of 18 photos registered: {sfm}"
    );
    let error = sfm["mean_reprojection_error_px"]
        .as_f64()
        .unwrap_or(f64::NAN);
    assert!(error > 0.0 && error < 1.5, "{sfm}");
    // Stage register: the GPS start verified on a cloud without ground, then the refusal.
    assert!(
        log.contains("a surface without ground under the canopy"),
        "{log}"
    );
    assert!(log.contains("gps start: on-cloud share"), "{log}");
    assert!(log.contains("confidence 1.00"), "{log}");
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["error"]["stage"], "register", "{job}");
    let detail = job["error"]["detail"].as_str().unwrap_or("");
    assert!(detail.contains("not precise enough"), "{detail}");
    assert!(detail.contains("control points"), "{detail}");
    println!("real_drone job: {registered}/18 registered, reprojection {error:.2} px; {detail}");
}

/// `sylva train --photos`: COLMAP, then a short training, held out above the mean colour.
#[test]
fn train_from_real_drone_photos_alone_beats_the_mean_colour() {
    if !colmap_present() || !gpu_present() {
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let out = dir.path().join("twin");
    let run = std::process::Command::new(BIN)
        .args(["train", "--photos"])
        .arg(real_drone().join("photos"))
        .arg("--out")
        .arg(&out)
        .args([
            "--steps",
            "300",
            "--resolution",
            "160",
            "--max-gaussians",
            "4000",
        ])
        .args(["--seed", "1", "--exposure", "off"])
        .env("LP_NUM_THREADS", "1")
        .output()
        .expect("sylva train");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(run.status.success(), "{text}");
    let sfm = read_json(&out.join("sfm").join("report.json"));
    assert!(sfm["registered"].as_u64().unwrap_or(0) >= 16, "{sfm}");
    assert!(out.join("sfm").join("sparse").join("cameras.txt").is_file());
    let eval = read_json(&out.join("eval.json"));
    let psnr = eval["psnr"].as_f64().unwrap_or(0.0);
    // The mean colour's PSNR, as the command prints it.
    let mean = text
        .split("(mean colour ")
        .nth(1)
        .and_then(|t| t.split(" dB").next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no mean colour in the output: {text}"));
    println!(
        "train --photos on real_drone: held-out {psnr:.2} dB against the mean colour's {mean:.2} dB"
    );
    assert!(
        psnr > mean + 1.0,
        "held out {psnr:.2} dB, mean colour {mean:.2} dB\n{text}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn cancelling_during_sfm_leaves_no_colmap_process() {
    if !colmap_present() {
        return;
    }
    let dir = tempfile::tempdir().expect("tmp");
    let data = dir.path().join("data");
    let srv = serve(&data, &[]);
    let _worker = worker(&data, &[]);
    let (c, base) = (client(), srv.base.clone());
    let (lidar, photos) = upload_photos(&c, &base, dir.path()).await;
    let body = json!({
        "inputs": { "lidar": lidar, "photos": photos },
        "params": { "until": "sfm" },
    });
    let id = submit(&c, &base, &body).await;
    let needle = data.display().to_string();
    // Wait until COLMAP runs for this job.
    poll_until(Duration::from_secs(300), 100, async || {
        let running = processes_mentioning(&needle)
            .into_iter()
            .filter(|(_, cmd)| cmd.contains("feature_extractor") || cmd.contains("_matcher"))
            .count();
        if running > 0 {
            Ok(())
        } else {
            Err(format!(
                "no COLMAP process of the job yet: {}",
                get_job(&c, &base, &id).await
            ))
        }
    })
    .await;
    let resp = send(c.post(format!("{base}/v1/jobs/{id}/cancel"))).await;
    assert!(resp.status().is_success(), "{:?}", resp.text().await);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(120), is_terminal).await;
    assert_eq!(job["state"], "canceled", "{job}");
    // The group got SIGTERM then SIGKILL within a few seconds of the cancel reaching it.
    let left = poll_until(Duration::from_secs(30), 200, async || {
        let left: Vec<(u32, String)> = processes_mentioning(&needle)
            .into_iter()
            .filter(|(_, cmd)| !cmd.contains(" serve ") && !cmd.contains(" worker "))
            .collect();
        if left.is_empty() {
            Ok(left)
        } else {
            Err(format!("COLMAP processes left after the cancel: {left:?}"))
        }
    })
    .await;
    assert!(left.is_empty());
}
