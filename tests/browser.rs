//! The web page in a real browser: Debian's headless Chromium driven over WebDriver
//! (chromedriver) against a running `sylva serve`. Screenshots go to
//! `target/tmp/browser/`. Without chromium and chromedriver the tests print why and pass.

mod common;
#[path = "common/webdriver.rs"]
mod webdriver;

use std::path::Path;
use std::time::Duration;

use tempfile::TempDir;

use common::*;
use serde_json::{Value, json};
use webdriver::{Browser, base64_encode, browser_or_skip, output_dir, processes_naming};

/// A script that is truthy once the jobs list says it has none.
const NO_JOBS: &str =
    "return document.querySelector('#jobs-note').textContent.startsWith('No jobs')";

/// A browser, or `None` (with the reason printed) where there is none; then a fresh folder
/// and `sylva serve` with `flags` over its `data`.
async fn browser_and_server(test: &str, flags: &[&str]) -> Option<(Browser, TempDir, Proc)> {
    let b = browser_or_skip(test).await?;
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = serve(&dir.path().join("data"), flags);
    Some((b, dir, srv))
}

/// As [`browser_and_server`], with the browser on the server's home page once `ready` (what,
/// and a script that is truthy then) holds, within 20 s.
async fn home_page(
    test: &str,
    flags: &[&str],
    (what, ready): (&str, &str),
) -> Option<(Browser, TempDir, Proc)> {
    let (b, dir, srv) = browser_and_server(test, flags).await?;
    b.goto(&format!("{}/", srv.base)).await;
    b.wait_for(what, ready, 20).await;
    Some((b, dir, srv))
}

/// Dropping a session ends its Chromium too (a killed chromedriver alone left its browsers
/// running after the test run).
#[tokio::test(flavor = "multi_thread")]
async fn a_dropped_browser_leaves_no_chromium_running() {
    let Some(b) = browser_or_skip("browser cleanup test").await else {
        return;
    };
    let profile = b.profile_dir().to_string_lossy().to_string();
    assert!(
        !processes_naming(&profile).is_empty(),
        "no Chromium names the session's profile {profile}"
    );
    drop(b);
    poll_until(Duration::from_secs(10), 100, async || {
        let left = processes_naming(&profile);
        if left.is_empty() {
            return Ok(());
        }
        Err(format!(
            "Chromium processes {left:?} still run after the session was dropped"
        ))
    })
    .await;
}

/// Submits the plot in one multipart request and waits for the job to succeed.
async fn finished_segment_job(base: &str, plot: &Path) -> Value {
    let c = client();
    let form = multipart(&[
        ("lidar", plot.join("lidar.laz")),
        ("colmap", plot.join("colmap.zip")),
        ("control_points", plot.join("control_points.csv")),
        ("field_dbh", plot.join("field_dbh.csv")),
    ]);
    let form = form.text("params", r#"{"until":"segment"}"#);
    let resp = send(c.post(format!("{base}/v1/jobs")).multipart(form)).await;
    assert_eq!(resp.status(), 202, "{:?}", resp.text().await);
    let job: Value = resp.json().await.expect("json");
    let id = id_of(&job);
    let (job, _) = wait_job(&c, base, &id, Duration::from_secs(600), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    job
}

/// A job whose automatic registration refuses (its photos show another plot) says why and
/// lists the candidate alignments it weighed, one row each, as the job's problem carries them.
#[tokio::test(flavor = "multi_thread")]
async fn a_refused_registration_lists_the_candidates_it_weighed() {
    let Some((b, dir, srv)) = browser_and_server("refused registration test", &[]).await else {
        return;
    };
    let lidar = synthetic_plot(&dir.path().join("a"), 11);
    let photos = synthetic_plot(&dir.path().join("b"), 12);
    let form = multipart(&[
        ("lidar", lidar.join("lidar.laz")),
        ("colmap", photos.join("colmap.zip")),
    ])
    .text("params", r#"{"until":"register"}"#);
    let c = client();
    let resp = send(c.post(format!("{}/v1/jobs", srv.base)).multipart(form)).await;
    assert_eq!(resp.status(), 202, "{:?}", resp.text().await);
    let id = id_of(&resp.json().await.expect("json"));
    let (job, _) = wait_job(&c, &srv.base, &id, Duration::from_secs(600), is_terminal).await;
    assert_eq!(job["state"], "failed", "{job}");
    let n = job["error"]["candidates"].as_array().map_or(0, Vec::len);
    assert!(n > 0, "the refusal carries no candidates: {job}");

    b.goto(&format!("{}/#/jobs/{id}", srv.base)).await;
    b.wait_for(
        "the candidates table",
        &format!("return document.querySelectorAll('#job-candidates tbody tr').length === {n}"),
        30,
    )
    .await;
    let text = b
        .eval("return document.querySelector('#job-error').textContent")
        .await;
    let text = text.as_str().unwrap_or_default();
    assert!(
        text.contains("supply control points") && text.contains("Candidate alignments weighed"),
        "{text}"
    );
    b.screenshot(&output_dir().join("refused-registration.png"))
        .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn job_page_lists_the_trees_draws_the_twin_and_plots_a_stem_slice() {
    let Some((b, dir, srv)) = browser_and_server("job page test", &[]).await else {
        return;
    };
    let plot = synthetic_plot(dir.path(), 1);
    let job = finished_segment_job(&srv.base, &plot).await;
    let id = job["id"].as_str().expect("id");
    let csv = send(client().get(format!("{}/v1/jobs/{id}/trees.csv", srv.base))).await;
    let csv = csv.text().await.expect("text");
    let ids: Vec<String> = csv
        .lines()
        .skip(1)
        .filter_map(|l| l.split(',').next().map(str::to_string))
        .collect();
    assert!(!ids.is_empty(), "{csv}");
    let shots = output_dir();

    b.goto(&format!("{}/#/jobs/{id}", srv.base)).await;

    // The inventory table lists every tree of trees.csv.
    let n = ids.len();
    b.wait_for(
        "the inventory table",
        &format!("return document.querySelectorAll('#trees tbody tr').length === {n}"),
        60,
    )
    .await;
    let shown = b
        .eval("return [...document.querySelectorAll('#trees tbody tr')].map(r => r.dataset.tree)")
        .await;
    assert_eq!(shown, json!(ids));
    // The stand figures come from the server's plot summary (LiDAR DBH), with a bar per 5 cm
    // DBH class and a dot per tree in the height-DBH scatter.
    b.wait_for(
        "the plot summary and its charts",
        "return !document.querySelector('#inventory-charts').hidden",
        60,
    )
    .await;
    let header = b
        .eval("return document.querySelector('#inventory-summary').textContent + ' | ' + document.querySelector('#inventory-plot').textContent")
        .await;
    let header = header.as_str().unwrap_or_default().to_string();
    assert!(
        header.contains("LiDAR DBH") && header.contains("stems/ha"),
        "{header}"
    );
    let results = send(client().get(format!("{}/v1/jobs/{id}/results", srv.base)))
        .await
        .json::<serde_json::Value>()
        .await
        .expect("results");
    let classes = results["plot"]["dbh_classes"]
        .as_array()
        .map_or(0, Vec::len);
    assert!(classes > 0, "{results}");
    let bars = b
        .eval("return document.querySelectorAll('#dbh-histogram rect').length")
        .await;
    assert_eq!(bars, json!(classes));
    let dots = b
        .eval("return document.querySelectorAll('#height-dbh circle').length")
        .await;
    assert_eq!(dots, json!(n));
    // Sorting by DBH, both ways.
    let dbh_col = "return [...document.querySelectorAll('#trees tbody tr')].map(r => Number(r.children[4].textContent))";
    b.click("#trees th[data-col=dbh_lidar_cm]").await;
    let up: Vec<f64> = serde_json::from_value(b.eval(dbh_col).await).expect("numbers");
    assert!(up.windows(2).all(|w| w[0] <= w[1]), "ascending: {up:?}");
    b.click("#trees th[data-col=dbh_lidar_cm]").await;
    let down: Vec<f64> = serde_json::from_value(b.eval(dbh_col).await).expect("numbers");
    assert!(
        down.windows(2).all(|w| w[0] >= w[1]),
        "descending: {down:?}"
    );

    // The stage timeline and the live log.
    let stages = b
        .eval("return [...document.querySelectorAll('#timeline tr')].map(r => [r.dataset.stage, r.children[1].textContent, r.children[3].textContent])")
        .await;
    let stages = stages.as_array().expect("rows");
    // ingest, sfm (nothing to do: the job gave a COLMAP project), register, anchors, segment.
    assert_eq!(stages.len(), 5, "{stages:?}");
    for s in stages {
        assert_eq!(s[1], "done", "{s}");
        assert!(!s[2].as_str().unwrap_or("").is_empty(), "no duration: {s}");
    }
    let some_lines = "return document.querySelectorAll('#log > span').length > 3";
    b.wait_for("log lines", some_lines, 30).await;
    let reg = b
        .eval("return document.querySelector('#registration').textContent")
        .await;
    assert!(
        reg.as_str().unwrap_or("").contains("control_points"),
        "{reg}"
    );

    // The viewer draws the anchors (no splats yet) with one label per stem.
    b.wait_for(
        "the viewer",
        "return window.Sylva.page.viewer && window.Sylva.page.viewer.splats && document.querySelectorAll('.stem-label').length > 0",
        60,
    )
    .await;
    let labels = b
        .eval("return [...document.querySelectorAll('.stem-label')].map(l => l.textContent)")
        .await;
    assert_eq!(labels.as_array().map(Vec::len), Some(n), "{labels}");
    assert!(labels[0].as_str().unwrap_or("").contains(" cm"), "{labels}");
    let px = b
        .eval("return window.Sylva.page.viewer.drawnPixels()")
        .await;
    let drawn = px["drawn"].as_f64().unwrap_or(0.0);
    let total = px["total"].as_f64().unwrap_or(1.0);
    assert!(
        drawn / total > 0.02,
        "the canvas is mostly background: {px}"
    );
    b.screenshot(&shots.join("job.png")).await;

    // A click on a stem label shows its 1.3 m slice with the LiDAR circle and points.
    b.click(&format!(".stem-label[data-stem=\"{}\"]", ids[0]))
        .await;
    let panel = "return !document.querySelector('#stem-panel').hidden";
    b.wait_for("the stem panel", panel, 10).await;
    let slice = b
        .eval("const s = document.querySelector('#stem-plot svg'); return { circle: s.querySelectorAll('circle.fit-lidar').length, points: s.querySelectorAll('circle:not([class])').length, title: document.querySelector('#stem-title').textContent }")
        .await;
    assert_eq!(slice["circle"], 1, "{slice}");
    assert!(slice["points"].as_u64().unwrap_or(0) > 10, "{slice}");
    assert_eq!(slice["title"], format!("Tree {}", ids[0]));
    b.screenshot_element("#viewer-card", &shots.join("viewer-stem.png"))
        .await;

    // The CSV download hands over the inventory file.
    let dl = b
        .eval(
            "return new Promise(resolve => {
               const click = HTMLAnchorElement.prototype.click, make = URL.createObjectURL;
               let blob = null;
               URL.createObjectURL = (b) => { blob = b; return make(b); };
               HTMLAnchorElement.prototype.click = function () {
                 HTMLAnchorElement.prototype.click = click;
                 URL.createObjectURL = make;
                 blob.text().then(text => resolve({ name: this.download, text }));
               };
               document.querySelector('#dl-csv').click();
             })",
        )
        .await;
    assert!(dl["name"].as_str().unwrap_or("").ends_with(".csv"), "{dl}");
    assert_eq!(dl["text"], csv);

    // The jobs list shows the finished job.
    // A fresh load of the page (a hash change alone would keep the scroll position).
    b.goto(&format!("{}/", srv.base)).await;
    b.wait_for(
        "the jobs list",
        &format!("const r = document.querySelector('tr[data-job=\"{id}\"] .badge'); return r && r.dataset.state === 'succeeded'"),
        30,
    )
    .await;
    b.screenshot(&shots.join("jobs.png")).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn upload_through_the_form_creates_a_job_followed_live_and_retries_a_failed_part() {
    // Small parts so the LiDAR file goes in several.
    let flags = ["--part-size", "262144"];
    let empty = ("the empty jobs list", NO_JOBS);
    let Some((b, dir, srv)) = home_page("upload test", &flags, empty).await else {
        return;
    };
    let plot = synthetic_plot(dir.path(), 1);
    // The first PUT of a part fails as a dropped connection would.
    b.eval("const open = XMLHttpRequest.prototype.open, send = XMLHttpRequest.prototype.send;
         window.__failed = 0;
         XMLHttpRequest.prototype.open = function (m, u) { this.__part = m === 'PUT' && u.includes('/parts/'); return open.apply(this, arguments); };
         XMLHttpRequest.prototype.send = function (body) {
           if (this.__part && window.__failed < 1) { window.__failed++; setTimeout(() => this.onerror(new ProgressEvent('error')), 20); return; }
           return send.call(this, body);
         };")
    .await;
    let path = |f: &str| plot.join(f).to_string_lossy().to_string();
    b.send_keys("#in-lidar", &path("lidar.laz")).await;
    b.send_keys("#in-colmap", &path("colmap.zip")).await;
    b.send_keys("#in-control", &path("control_points.csv"))
        .await;
    b.eval("document.querySelector('#in-until').value = 'ingest'")
        .await;
    b.click("#upload-submit").await;

    let id = b
        .wait_for(
            "the job page",
            "const m = location.hash.match(/^#\\/jobs\\/([0-9a-f]{32})/); return m && m[1]",
            120,
        )
        .await;
    let id = id.as_str().expect("id").to_string();
    // Followed live over server-sent events: no reload happens on the page.
    b.wait_for(
        "the job to succeed on the page",
        "return document.querySelector('#job-state').dataset.state === 'succeeded'",
        120,
    )
    .await;
    let stats = b.eval("return window.Sylva.uploadStats").await;
    assert!(stats["retries"].as_u64().unwrap_or(0) >= 1, "{stats}");
    let lidar_parts = std::fs::metadata(plot.join("lidar.laz"))
        .expect("size")
        .len()
        .div_ceil(262_144);
    assert!(
        stats["parts"].as_u64().unwrap_or(0) > lidar_parts,
        "{stats}"
    );
    assert_eq!(stats["jobs"], json!([id]));
    b.screenshot(&output_dir().join("uploaded-job.png")).await;

    let job = get_job(&client(), &srv.base, &id).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    for k in ["lidar", "colmap", "control_points"] {
        assert!(job["inputs"][k].as_str().is_some(), "{job}");
    }
    assert_eq!(job["params"]["until"], "ingest");
}

/// Writes `n` splats in the antimatter15 layout: a ring of coloured, rotated ellipsoids.
fn splat_file(n: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(32 * n);
    for i in 0..n {
        let t = i as f32 / n as f32 * std::f32::consts::TAU;
        let (x, y, z) = (2.0 * t.cos(), 2.0 * t.sin(), 0.5 + 0.3 * (3.0 * t).sin());
        for v in [x, y, z, 0.08, 0.04, 0.02] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&[(i * 7 % 256) as u8, 180, (255 - i % 256) as u8, 230]);
        // Rotation about z by t: (w, x, y, z) = (cos t/2, 0, 0, sin t/2), as u8 = q·128 + 128.
        let q = [(t / 2.0).cos(), 0.0, 0.0, (t / 2.0).sin()];
        out.extend(q.map(|c| (c * 128.0 + 128.0).clamp(0.0, 255.0) as u8));
    }
    out
}

#[tokio::test(flavor = "multi_thread")]
async fn splat_files_are_parsed_and_drawn() {
    let flags = ["--workers", "0"];
    let scripts = (
        "the page scripts",
        "return window.SylvaViewer && window.Sylva",
    );
    let Some((b, _dir, _srv)) = home_page("splat viewer test", &flags, scripts).await else {
        return;
    };
    let n = 400;
    let bytes = splat_file(n);
    let v = b
        .exec(
            "const raw = atob(arguments[0]);
             const buf = new Uint8Array(raw.length);
             for (let i = 0; i < raw.length; i++) buf[i] = raw.charCodeAt(i);
             const s = SylvaViewer.parseSplat(buf.buffer);
             const wrap = document.createElement('div');
             wrap.className = 'viewer-wrap';
             wrap.id = 'splat-test';
             const canvas = document.createElement('canvas');
             canvas.style.width = '640px'; canvas.style.height = '400px';
             const labels = document.createElement('div');
             labels.className = 'labels';
             wrap.append(canvas, labels);
             document.body.prepend(wrap);
             const v = SylvaViewer.create(canvas, labels);
             v.setSplats(s);
             v.frame();
             v.setStems([{ id: 7, base: [0, 0, 0], axis: [0, 0, 1], height: 3, slice: [0, 0, 1.3], radius: 0.2, text: '#7 · 40.0 cm' }]);
             return { count: s.count, p: Array.from(s.positions.slice(0, 6)), sc: Array.from(s.scales.slice(0, 3)),
                      c: Array.from(s.colors.slice(4, 8)), q: Array.from(s.rotations.slice(0, 4)), px: v.drawnPixels() };",
            json!([base64_encode(&bytes)]),
        )
        .await;
    assert_eq!(v["count"], n, "{v}");
    let p: Vec<f32> = serde_json::from_value(v["p"].clone()).expect("positions");
    let t1 = std::f32::consts::TAU / n as f32;
    let want = [
        2.0,
        0.0,
        0.5,
        2.0 * t1.cos(),
        2.0 * t1.sin(),
        0.5 + 0.3 * (3.0 * t1).sin(),
    ];
    for (a, b) in p.iter().zip(want) {
        assert!((a - b).abs() < 1e-5, "{p:?} vs {want:?}");
    }
    assert_eq!(
        v["sc"],
        json!([0.08f32 as f64, 0.04f32 as f64, 0.02f32 as f64])
    );
    assert_eq!(v["c"], json!([7, 180, 254, 230]));
    // cos 0 = 1 is stored as 255, the largest byte: (255 - 128) / 128.
    let q: Vec<f64> = serde_json::from_value(v["q"].clone()).expect("rotation");
    assert_eq!(q, [127.0 / 128.0, 0.0, 0.0, 0.0]);
    let drawn = v["px"]["drawn"].as_f64().unwrap_or(0.0);
    assert!(drawn > 500.0, "nothing drawn: {v}");
    b.screenshot_element("#splat-test", &output_dir().join("splats.png"))
        .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn the_page_asks_once_for_a_token_when_the_server_needs_one() {
    let flags = ["--workers", "0", "--token", "s3cret-token"];
    let dialog = (
        "the token dialog",
        "return !document.querySelector('#token-dialog').hidden",
    );
    let Some((b, _dir, _srv)) = home_page("token test", &flags, dialog).await else {
        return;
    };
    b.send_keys("#token-input", "s3cret-token").await;
    b.click("#token-form button[type=submit]").await;
    b.wait_for("the jobs list", NO_JOBS, 20).await;
    let kept = b.eval("return sessionStorage.getItem('sylva-token')").await;
    assert_eq!(kept, "s3cret-token");
    let dialog_hidden = b
        .eval("return document.querySelector('#token-dialog').hidden")
        .await;
    assert_eq!(dialog_hidden, true);
}
