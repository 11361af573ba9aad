//! A job's 3D Tiles tileset in the clients that read it, over HTTP from `sylva serve`:
//! - the job page's viewer, which streams the tileset by level of detail (`tiles.js`);
//! - CesiumJS (npm `cesium`, installed by scripts/test into `target/test-node`; capability
//!   `cesium`), from a page on another origin (CORS, `--cors-origin`) with the caller's key,
//!   on a plot declared in UTM: it must load the tiles, draw them, and place the trees where
//!   the CRS puts them.
//!
//! Both run in Debian's headless Chromium (capability `browser`). Screenshots go to
//! `target/tmp/browser/`.

mod common;
#[allow(unused_imports)]
#[path = "common/webdriver.rs"]
mod webdriver;

use std::path::{Path, PathBuf};
use std::time::Duration;

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::IntoResponse;
use serde_json::{Value, json};

use common::*;
use webdriver::{browser_or_skip, output_dir};

/// The bearer key of the Cesium test's server.
const TOKEN: &str = "tileset-client-token";
/// EPSG code of the CRS the Cesium test's plot is declared in (UTM zone 49N).
const UTM_49N: u32 = 32649;

/// A whole job on a tiny plot within seconds (the CPU reference trainer, few steps, small
/// photos, 1500 Gaussians, as tests/crash.rs), cut into tiles of at most 200 Gaussians so
/// that the tileset has several levels.
fn params() -> Value {
    json!({
        "train": { "backend": "cpu", "steps": 60, "resolution": 48, "init": "lidar", "max_gaussians": 1500 },
        "export": { "tile_gaussians": 200 },
    })
}

/// Submits the plot in one multipart request with [`params`] and waits for the job to succeed.
async fn finished_job(c: &reqwest::Client, base: &str, plot: &Path) -> Value {
    let form = multipart(&[
        ("lidar", plot.join("lidar.laz")),
        ("colmap", plot.join("colmap.zip")),
        ("control_points", plot.join("control_points.csv")),
        ("field_dbh", plot.join("field_dbh.csv")),
    ])
    .text("params", params().to_string());
    let resp = send(c.post(format!("{base}/v1/jobs")).multipart(form)).await;
    assert_eq!(resp.status(), 202, "{:?}", resp.text().await);
    let id = id_of(&resp.json().await.expect("json"));
    let (job, _) = wait_job(c, base, &id, Duration::from_secs(900), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    job
}

/// The export report of a finished job.
async fn export_report(c: &reqwest::Client, base: &str, id: &str) -> Value {
    get_json(
        c,
        &format!("{base}/v1/jobs/{id}/artifacts/export/report.json"),
    )
    .await
}

#[tokio::test(flavor = "multi_thread")]
async fn the_job_page_streams_the_tileset_by_level_of_detail() {
    let Some(b) = browser_or_skip("tileset streaming test").await else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = serve(&dir.path().join("data"), &[]);
    let plot = synthetic_plot(dir.path(), 5);
    let c = client();
    let job = finished_job(&c, &srv.base, &plot).await;
    let id = id_of(&job);
    let report = export_report(&c, &srv.base, &id).await;
    let gaussians = report["gaussians"].as_u64().expect("gaussians");
    let tiles = report["tiles"]["tiles"].as_u64().expect("tiles");
    let levels = report["tiles"]["per_level"].as_array().map_or(0, Vec::len);
    assert!(levels >= 2, "one level only: {report}");

    b.goto(&format!("{}/#/jobs/{id}", srv.base)).await;
    b.wait_for(
        "the tileset in the viewer",
        "const t = window.Sylva.page.tiles; return t && t.stats().selected > 0 && t.stats().loading === 0",
        120,
    )
    .await;
    let source = b
        .eval("return document.querySelector('#viewer-source').textContent")
        .await;
    assert!(
        source
            .as_str()
            .unwrap_or("")
            .contains("streamed from the tileset"),
        "{source}"
    );

    // Sets the camera and the error bound, then waits until the selection has settled.
    let settle = |camera: Value, max_error: f64| {
        let b = &b;
        async move {
            b.exec(
                "const p = window.Sylva.page; p.viewer.setCamera(arguments[0]); p.tiles.setMaxError(arguments[1]);",
                json!([camera, max_error]),
            )
            .await;
            // Settled: made for this camera and bound, nothing loading, no selection pending.
            b.wait_for(
                "the tile selection to settle",
                &format!(
                    "const p = window.Sylva.page, s = p.tiles.stats(), e = p.viewer.camera().eye; \
                     return s.eye && s.maxError === {max_error} && !s.pending && s.loading === 0 \
                       && Math.hypot(s.eye[0] - e[0], s.eye[1] - e[1], s.eye[2] - e[2]) < 1e-6 ? s : null"
                ),
                120,
            )
            .await
        }
    };

    // From 5 km away, the root tile alone meets 16 px.
    let far = json!({ "distance": 5000.0, "elevation": 0.6 });
    let s = settle(far.clone(), 16.0).await;
    assert_eq!(s["selected"], 1, "{s}");
    assert_eq!(s["maxDepth"], 0, "{s}");
    assert!(s["drawn"].as_u64().unwrap_or(0) <= 200, "{s}");

    // Close to a stem, finer tiles replace the coarse ones, and only those the view needs are
    // fetched.
    let close = b
        .eval(
            "const st = window.Sylva.page.stems[0]; return { target: st.slice, distance: 4.0, elevation: 0.25 }",
        )
        .await;
    let s = settle(close, 16.0).await;
    assert!(s["maxDepth"].as_u64().unwrap_or(0) >= 1, "{s}");
    assert!(
        s["selected"].as_u64().unwrap_or(0) < tiles && s["drawn"].as_u64().unwrap_or(0) < gaussians,
        "the close view draws everything: {s}"
    );
    assert_eq!(s["failed"], 0, "{s}");
    b.screenshot(&output_dir().join("viewer-tiles-close.png"))
        .await;

    // With no error allowed, every leaf: the whole model, as the splat file has it (SPZ
    // quantisation aside: 0.24 mm steps in position, 1/16 in log-scale, 8-bit colour).
    let s = settle(far, 0.0).await;
    assert_eq!(s["drawn"].as_u64(), Some(gaussians), "{s}");
    let splat_href = format!("{}/v1/jobs/{id}/artifacts/export/splats.splat", srv.base);
    let cmp = b
        .exec(
            "return (async () => {
               const a = window.Sylva.page.splats;
               const r = await fetch(arguments[0]);
               const buf = await r.arrayBuffer();
               const f = new Float32Array(buf), u = new Uint8Array(buf), n = buf.byteLength / 32;
               const C = 0.05, grid = new Map();
               const key = (x, y, z) => `${Math.floor(x / C)},${Math.floor(y / C)},${Math.floor(z / C)}`;
               for (let i = 0; i < n; i++) {
                 const k = key(f[8 * i], f[8 * i + 1], f[8 * i + 2]);
                 if (!grid.has(k)) grid.set(k, []);
                 grid.get(k).push(i);
               }
               let pos = 0, logScale = 0, colour = 0;
               for (let j = 0; j < a.count; j++) {
                 const p = [a.positions[3 * j], a.positions[3 * j + 1], a.positions[3 * j + 2]];
                 let best = -1, bd = Infinity;
                 for (let dx = -1; dx <= 1; dx++) for (let dy = -1; dy <= 1; dy++) for (let dz = -1; dz <= 1; dz++) {
                   const k = `${Math.floor(p[0] / C) + dx},${Math.floor(p[1] / C) + dy},${Math.floor(p[2] / C) + dz}`;
                   for (const i of grid.get(k) || []) {
                     const d = Math.hypot(p[0] - f[8 * i], p[1] - f[8 * i + 1], p[2] - f[8 * i + 2]);
                     if (d < bd) { bd = d; best = i; }
                   }
                 }
                 if (best < 0) return { n, count: a.count, unmatched: j };
                 pos = Math.max(pos, bd);
                 for (let k = 0; k < 3; k++) logScale = Math.max(logScale, Math.abs(Math.log(a.scales[3 * j + k] / f[8 * best + 3 + k])));
                 for (let k = 0; k < 4; k++) colour = Math.max(colour, Math.abs(a.colors[4 * j + k] - u[32 * best + 24 + k]));
               }
               return { n, count: a.count, pos, logScale, colour };
             })().catch((e) => ({ error: String(e) }));",
            json!([splat_href]),
        )
        .await;
    assert_eq!(cmp["n"].as_u64(), Some(gaussians), "{cmp}");
    assert!(cmp["unmatched"].is_null(), "{cmp}");
    assert!(cmp["pos"].as_f64().is_some_and(|d| d < 5e-4), "{cmp}");
    assert!(
        cmp["logScale"]
            .as_f64()
            .is_some_and(|d| d <= 1.0 / 32.0 + 1e-3),
        "{cmp}"
    );
    assert!(cmp["colour"].as_f64().is_some_and(|d| d <= 2.0), "{cmp}");
}

/// npm's CesiumJS build under `target/test-node`, where scripts/test installed it.
fn cesium_build() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("target/test-node/node_modules/cesium/Build/Cesium");
    if dir.join("Cesium.js").is_file() {
        return Some(dir);
    }
    sylva::testing::skip(
        "cesium",
        &format!("no {} (scripts/test installs npm's cesium)", dir.display()),
    );
    None
}

/// Content type of a file of the Cesium build, by extension.
fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "html" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript",
        "css" => "text/css",
        "json" => "application/json",
        "wasm" => "application/wasm",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "svg" => "image/svg+xml",
        "xml" => "application/xml",
        _ => "application/octet-stream",
    }
}

/// A static server for the Cesium page (`/`, tests/cesium/index.html) and the Cesium build
/// (`/cesium/…`), on its own port so that the page's origin is not the API's. Returns its
/// origin.
async fn cesium_page_server(build: PathBuf) -> String {
    let page = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/cesium/index.html");
    let file = move |path: PathBuf| async move {
        match tokio::fs::read(&path).await {
            Ok(body) => (
                [(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static(content_type(&path)),
                )],
                body,
            )
                .into_response(),
            Err(_) => StatusCode::NOT_FOUND.into_response(),
        }
    };
    let app = axum::Router::new()
        .route("/", axum::routing::get(move || file(page.clone())))
        .route(
            "/cesium/{*path}",
            axum::routing::get(
                move |axum::extract::Path(rel): axum::extract::Path<String>| {
                    let safe = !rel.split('/').any(|c| c == ".." || c.is_empty());
                    let path = build.join(&rel);
                    async move {
                        if safe {
                            file(path).await
                        } else {
                            StatusCode::NOT_FOUND.into_response()
                        }
                    }
                },
            ),
        );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(async move {
        let _ = axum::serve(listener, app).await;
    });
    format!("http://{addr}")
}

/// The synthetic plot with its LiDAR declared in UTM zone 49N, so that the tileset is placed
/// on the Earth.
fn georeferenced_plot(dir: &Path) -> PathBuf {
    let plot = synthetic_plot(dir, 3);
    let laz = plot.join("lidar.laz");
    let cloud = sylva::io::pointcloud::read_point_cloud(&laz, &sylva::progress::NoProgress)
        .expect("read lidar");
    let utm = sylva::io::crs::Crs::from_epsg(UTM_49N).expect("utm");
    sylva::io::las::write_las_with_crs(&laz, &cloud, true, Some(&utm)).expect("write lidar");
    plot
}

/// Pixels whose colour differs by more than 24 (summed over R, G, B) between two screenshots
/// of the same size.
fn differing_pixels(a: &Path, b: &Path) -> (usize, usize) {
    let a = image::open(a).expect("screenshot").to_rgb8();
    let b = image::open(b).expect("screenshot").to_rgb8();
    assert_eq!(a.dimensions(), b.dimensions());
    let n = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| {
            (0..3)
                .map(|k| (i32::from(p[k]) - i32::from(q[k])).abs())
                .sum::<i32>()
                > 24
        })
        .count();
    (n, a.pixels().len())
}

#[tokio::test(flavor = "multi_thread")]
async fn cesiumjs_loads_the_tileset_from_the_job_artifact_url_and_places_it_on_the_earth() {
    let Some(build) = cesium_build() else {
        return;
    };
    let Some(b) = browser_or_skip("CesiumJS tileset test").await else {
        return;
    };
    let origin = cesium_page_server(build).await;
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = serve(
        &dir.path().join("data"),
        &["--token", TOKEN, "--cors-origin", &origin],
    );
    let plot = georeferenced_plot(dir.path());
    let c = keyed_client(TOKEN);
    let job = finished_job(&c, &srv.base, &plot).await;
    let id = id_of(&job);
    let tileset = format!("{}/v1/jobs/{id}/artifacts/export/tileset.json", srv.base);

    // The preflight a browser sends before a keyed request from the page's origin, and
    // another origin, which gets no CORS header.
    let pre = send(
        reqwest::Client::new()
            .request(reqwest::Method::OPTIONS, &tileset)
            .header("origin", &origin)
            .header("access-control-request-method", "GET")
            .header("access-control-request-headers", "authorization"),
    )
    .await;
    assert!(pre.status().is_success(), "{pre:?}");
    let h = pre.headers();
    assert_eq!(
        h.get("access-control-allow-origin")
            .and_then(|v| v.to_str().ok()),
        Some(origin.as_str()),
        "{h:?}"
    );
    let allowed = h
        .get("access-control-allow-headers")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    assert!(allowed.contains("authorization"), "{h:?}");
    let other = send(c.get(&tileset).header("origin", "http://elsewhere.example")).await;
    assert_eq!(other.status(), 200);
    assert!(
        other.headers().get("access-control-allow-origin").is_none(),
        "{:?}",
        other.headers()
    );

    b.set_window_size(1000, 700).await;
    let url = format!(
        "{origin}/?tileset={}&token={TOKEN}",
        tileset.replace(':', "%3A").replace('/', "%2F")
    );
    b.goto(&url).await;
    let state = b
        .wait_for(
            "CesiumJS to load the tileset",
            "const s = window.state; if (s.error || s.failed.length) return s; \
             return s.ready && s.loaded > 0 && window.tileset.tilesLoaded && s.frames > 5 ? s : null",
            180,
        )
        .await;
    assert!(state["error"].is_null(), "{state}");
    assert_eq!(state["failed"], json!([]), "{state}");

    // Each tree, from the tileset's metadata through the root transform as CesiumJS applies it,
    // where the CRS puts the inventory's position.
    let csv = send(c.get(format!("{}/v1/jobs/{id}/trees.csv", srv.base)))
        .await
        .text()
        .await
        .expect("csv");
    let mut rows = csv::Reader::from_reader(csv.as_bytes());
    let heads = rows.headers().expect("header").clone();
    let col = |n: &str| heads.iter().position(|h| h == n).expect(n);
    let (tid, x, y, z) = (col("tree_id"), col("x"), col("y"), col("ground_z"));
    let utm = sylva::io::crs::Crs::from_epsg(UTM_49N).expect("utm");
    let trees = state["trees"].as_array().expect("trees");
    let mut n = 0;
    for r in rows.records() {
        let r = r.expect("row");
        let num = |i: usize| r[i].parse::<f64>().expect("number");
        let mut ll = [(num(x), num(y))];
        utm.to_wgs84(&mut ll).expect("to wgs84");
        let t = trees
            .iter()
            .find(|t| t["id"] == r[tid])
            .unwrap_or_else(|| panic!("tree {} not in the tileset: {state}", &r[tid]));
        let lat = t["lat"].as_f64().expect("lat");
        let lon = t["lon"].as_f64().expect("lon");
        let north = (lat - ll[0].1).to_radians() * 6_371_000.0;
        let east = (lon - ll[0].0).to_radians() * 6_371_000.0 * lat.to_radians().cos();
        let up = t["height"].as_f64().expect("height") - num(z);
        let off = (north * north + east * east + up * up).sqrt();
        assert!(off < 0.01, "tree {}: {off:.4} m off ({t})", &r[tid]);
        n += 1;
    }
    assert!(n >= 3 && n == trees.len(), "{n} trees in the CSV, {state}");

    // The splats are drawn: the frame with the tileset differs from the frame without it.
    let shots = output_dir();
    let (on, off) = (
        shots.join("cesium-tileset.png"),
        shots.join("cesium-no-tileset.png"),
    );
    let shown = async |show: bool, path: &Path| {
        let frames = b
            .exec(
                "window.tileset.show = arguments[0]; return window.state.frames",
                json!([show]),
            )
            .await
            .as_u64()
            .unwrap_or(0);
        b.wait_for(
            "CesiumJS to draw",
            &format!(
                "return window.state.frames > {} && window.tileset.tilesLoaded",
                frames + 3
            ),
            60,
        )
        .await;
        b.screenshot(path).await;
    };
    shown(false, &off).await;
    shown(true, &on).await;
    let (differ, total) = differing_pixels(&on, &off);
    assert!(
        differ * 100 > total,
        "the tileset changed {differ} of {total} pixels (see {})",
        on.display()
    );
}
