//! `sylva demo`: a generated plot through the whole service, as a new user runs it.

use super::*;

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

pub(super) async fn demo(a: DemoArgs) -> anyhow::Result<ExitCode> {
    // 1. A generated plot with known truth.
    let plot = generated_plot(&a).await?;
    // 2. The server, in this process, on the embedded default.
    let (server, base) = start_server(&a).await?;
    // 3. The job: GPU when there is one, else the CPU reference on a small budget.
    let params = job_params(a.steps).await;
    let http = reqwest::Client::new();
    let id = submit(&http, &base, &plot, &params).await?;
    eprintln!("job {id}: {base}/#/jobs/{id}");
    // 4. Follow it.
    let job = follow(&http, &base, &id).await?;
    if job["state"] != "succeeded" {
        eprintln!("the job did not succeed: {}", job["error"]);
    } else {
        // 5. The inventory and its quality.
        print_results(&http, &base, &id).await?;
    }
    let code = if job["state"] == "succeeded" {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    };
    if a.exit {
        server.abort();
        return Ok(code);
    }
    println!("\nthe web page: {base}/  (Ctrl-C to stop)");
    server.await??;
    Ok(code)
}

/// The demo's plot under the data folder (`sylva synth`'s `tiny` preset with `--seed`),
/// generated once, and its COLMAP project packed as `colmap.tar` for the upload.
async fn generated_plot(a: &DemoArgs) -> anyhow::Result<PathBuf> {
    let plot = a.store.data.join("demo-plot");
    if !plot.join("truth.json").is_file() {
        eprintln!("generating a synthetic plot in {} …", plot.display());
        let (dir, seed) = (plot.clone(), a.seed);
        tokio::task::spawn_blocking(move || {
            let mut p = sylva::synth::SynthParams::new(sylva::synth::Preset::Tiny);
            p.seed = seed;
            sylva::synth::generate(&p, &dir, &sylva::progress::NoProgress)
        })
        .await??;
    }
    let file = std::fs::File::create(plot.join("colmap.tar"))?;
    let mut tar = tar::Builder::new(file);
    tar.append_dir_all(".", plot.join("colmap"))?;
    tar.finish()?;
    Ok(plot)
}

/// `sylva serve` on the demo's data folder and address, in this process; returns once it
/// answers `/livez`, with its base URL.
async fn start_server(
    a: &DemoArgs,
) -> anyhow::Result<(tokio::task::JoinHandle<anyhow::Result<()>>, String)> {
    let data = a.store.data.to_string_lossy().to_string();
    let listen = a.listen.to_string();
    let cli = Cli::try_parse_from(["sylva", "serve", "--data", &data, "--listen", &listen])?;
    let Command::Serve(serve_args) = cli.command else {
        anyhow::bail!("internal: serve arguments");
    };
    let server = tokio::spawn(serve(serve_args));
    let base = format!("http://{}", a.listen);
    let http = reqwest::Client::new();
    for _ in 0..100 {
        if http
            .get(format!("{base}/livez"))
            .send()
            .await
            .is_ok_and(|r| r.status().is_success())
        {
            return Ok((server, base));
        }
        if server.is_finished() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!("the server did not start on {base} (is the port taken? use --listen)")
}

/// The job's parameters for the training device found: a real GPU trains longer and finer
/// than a software one (lavapipe) or the CPU reference; `steps` overrides the step count.
async fn job_params(steps: Option<u32>) -> serde_json::Value {
    match &sylva::gpu::probe().await {
        // A software adapter (lavapipe) gets short training; its Gaussian budget is the
        // device default (`max_gaussians` 0: splat::budget::SOFTWARE_GPU_BUDGET), an even
        // draw of about a twentieth of the ~180 k anchors.
        Some(g) if g.device_type == "cpu" => {
            eprintln!("training on {} (a software GPU: small budget)", g.name);
            serde_json::json!({"train": {"steps": steps.unwrap_or(500), "resolution": 80}})
        }
        Some(g) => {
            eprintln!("training on {}", g.name);
            serde_json::json!({"train": {"steps": steps.unwrap_or(3000), "resolution": 160}})
        }
        None => {
            eprintln!("no GPU adapter: training on the CPU reference with a small budget");
            // The CPU reference's default budget (splat::budget::CPU_REFERENCE_BUDGET).
            serde_json::json!({"train": {"backend": "cpu", "steps": steps.unwrap_or(300),
                "resolution": 80}})
        }
    }
}

/// Uploads the plot's files with `params` as one multipart job; returns the job's id.
async fn submit(
    http: &reqwest::Client,
    base: &str,
    plot: &Path,
    params: &serde_json::Value,
) -> anyhow::Result<String> {
    let part = |path: PathBuf| -> anyhow::Result<reqwest::multipart::Part> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        Ok(reqwest::multipart::Part::bytes(std::fs::read(&path)?).file_name(name))
    };
    let form = reqwest::multipart::Form::new()
        .part("lidar", part(plot.join("lidar.laz"))?)
        .part("colmap", part(plot.join("colmap.tar"))?)
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
    Ok(job["id"].as_str().unwrap_or_default().to_string())
}

/// Polls the job twice a second, printing each new state, stage and progress, until it
/// ends; returns its last record.
async fn follow(http: &reqwest::Client, base: &str, id: &str) -> anyhow::Result<serde_json::Value> {
    let mut last = String::new();
    loop {
        let j = get_json(http, format!("{base}/v1/jobs/{id}")).await?;
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
            return Ok(j);
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// Prints the job's `trees.csv` and the table of its quality figures.
async fn print_results(http: &reqwest::Client, base: &str, id: &str) -> anyhow::Result<()> {
    let csv = http
        .get(format!("{base}/v1/jobs/{id}/trees.csv"))
        .send()
        .await?
        .text()
        .await?;
    println!("\ntree inventory (trees.csv):\n{csv}");
    let results = get_json(http, format!("{base}/v1/jobs/{id}/results")).await?;
    let st = &results["stages"];
    let f = |v: &serde_json::Value| v.as_f64().map_or("n/a".to_string(), |x| format!("{x:.2}"));
    println!("| quality | value |\n|---|---|");
    let region = match st["train"]["render"]["region"].as_str() {
        Some("right_half") => "right halves (exposure compensation on)",
        Some(_) => "full images",
        None => "n/a",
    };
    let rows = [
        ("registration RMSE (m)", f(&st["register"]["rmse_m"])),
        ("held-out PSNR (dB)", f(&st["train"]["render"]["psnr"])),
        ("held-out SSIM", f(&st["train"]["render"]["ssim"])),
        ("held-out pixels measured", region.to_string()),
        ("mean-colour PSNR (dB)", f(&st["train"]["baseline_psnr"])),
        (
            "DBH RMSE, Gaussians (cm)",
            f(&st["dbh"]["dbh"]["rmse_gs_cm"]),
        ),
        (
            "DBH RMSE, LiDAR (cm)",
            f(&st["dbh"]["dbh"]["rmse_lidar_cm"]),
        ),
        (
            "DBH RMSE, Gaussians against LiDAR (cm)",
            f(&st["dbh"]["gs_vs_lidar"]["rmse_cm"]),
        ),
        ("trees matched", st["dbh"]["dbh"]["matched"].to_string()),
        (
            "trunk Gaussians to LiDAR stem surface, mean absolute (mm)",
            f(&st["dbh"]["mean_radial_dev_mm"]),
        ),
        (
            "trunk Gaussians to LiDAR stem surface, mean signed (mm, + outside)",
            f(&st["dbh"]["mean_surface_offset_mm"]),
        ),
        (
            "trunk term",
            st["train"]["semantic"]["term"]
                .as_str()
                .unwrap_or("n/a")
                .to_string(),
        ),
    ];
    for (quality, value) in rows {
        println!("| {quality} | {value} |");
    }
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
    Ok(())
}

/// The JSON body of a GET of `url`.
async fn get_json(http: &reqwest::Client, url: String) -> anyhow::Result<serde_json::Value> {
    Ok(http.get(url).send().await?.json().await?)
}
