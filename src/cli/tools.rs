//! The one-off commands on local files: `sylva synth`, `sylva inventory`, `sylva train`.

use super::run::{fill_choice, on_off, parse_backend, parse_strategy};
use super::*;

#[derive(Debug, Args)]
#[command(group(clap::ArgGroup::new("views").required(true).args(["colmap", "photos"])))]
pub struct TrainArgs {
    /// The COLMAP project folder (images/ and sparse/0 or sparse/).
    #[arg(long, env = "SYLVA_TRAIN_COLMAP", conflicts_with = "photos")]
    pub colmap: Option<PathBuf>,
    /// Photos (JPEG, PNG, TIFF) instead of a COLMAP project: a folder or a zip/tar(.gz) of
    /// one. COLMAP (Debian's package `colmap`) makes the model first, as stage `sfm` does,
    /// into <out>/sfm/ (its report, log and model).
    #[arg(long, env = "SYLVA_TRAIN_PHOTOS")]
    pub photos: Option<PathBuf>,
    /// With --photos: the `sfm` parameters as a JSON file (the `params.sfm` object of the API;
    /// see `GET /v1/options`).
    #[arg(long, env = "SYLVA_TRAIN_SFM_PARAMS", requires = "photos")]
    pub sfm_params: Option<PathBuf>,
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
    /// LPIPS weights (a safetensors file made by scripts/lpips_weights.py): the held-out views
    /// are also measured by LPIPS. Never downloaded; without it no LPIPS is reported.
    #[arg(long, env = "SYLVA_LPIPS_WEIGHTS")]
    pub lpips_weights: Option<PathBuf>,
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
    /// 3DGS dilation. On by default, as for jobs (`params.train.antialias`).
    #[arg(long, env = "SYLVA_TRAIN_ANTIALIAS", default_value = "on")]
    pub antialias: String,
    /// With `--init sfm`, add Gaussians where the training photos see what no SfM point
    /// covers (`splat::init::fill_uncovered`: dense canopy from above, sky, walls): `on`
    /// (where the photos agree on a depth for the cell), `textured` (only where the cell has
    /// texture and its cost one clear minimum: no flat sky placed in front of the scene),
    /// `guess` (every such cell, those without an agreed depth far back in what their photo
    /// sees) or `off`. On by default
    /// (ours: Brighton's UAV photos lost their forest without it, and the guessed cells cost
    /// its held-out photos up to 1 dB at 2000 steps, issue 38).
    #[arg(long, env = "SYLVA_TRAIN_FILL", default_value = "on")]
    pub fill: String,
    /// Per-image exposure compensation, on or off (docs/splatting.md "Exposure"). On (the
    /// default) learns a colour transform per photo and measures the held-out photos on
    /// their right halves, their left halves training their exposure.
    #[arg(long, env = "SYLVA_TRAIN_EXPOSURE", default_value = "on")]
    pub exposure: String,
}

#[derive(Debug, Args)]
pub struct SynthArgs {
    /// Scene preset: tiny (1-3 trees, 30 small images), plot (one large broadleaf tree), stand
    /// (17 trees, canopy closure about 0.5), paper (stand at the paper's plot-3 size: 857
    /// photos at 1920×1080, 59.9 M LiDAR points), object (one tree in 71 close portrait
    /// phone-like frames with a sparse SfM start).
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
    /// Tag the photos with GPS positions of this horizontal noise, metres (the LiDAR file
    /// then declares EPSG:32632 so that the positions can be placed on it).
    #[arg(long, env = "SYLVA_SYNTH_GPS_NOISE_M")]
    pub gps_noise_m: Option<f64>,
    /// Scale of the SfM frame, units per metre (default: drawn in 0.2–5).
    #[arg(long, env = "SYLVA_SYNTH_SFM_SCALE")]
    pub sfm_scale: Option<f64>,
    /// Grade of the terrain, percent (default: drawn in 0–8 %).
    #[arg(long, env = "SYLVA_SYNTH_SLOPE_PCT")]
    pub slope_pct: Option<f64>,
    /// Share of the plot the LiDAR covers, in (0.05, 1] (default 1).
    #[arg(long, env = "SYLVA_SYNTH_LIDAR_COVERAGE")]
    pub lidar_coverage: Option<f64>,
    /// Scan the trees without leaves while the photos show them leafy.
    #[arg(long, env = "SYLVA_SYNTH_LIDAR_LEAF_OFF", default_value_t = false)]
    pub lidar_leaf_off: bool,
    /// Hide each tree's upper stem from the scan over a length drawn in [0.3, this] metres
    /// from its crown base up, as foliage hides it from a scanner below (default: nothing
    /// hidden).
    #[arg(long, env = "SYLVA_SYNTH_HIDDEN_STEM_M")]
    pub hidden_stem_m: Option<f64>,
    /// Crowns that interlock: each crown reaches this share farther than the spacing of the
    /// stems allows, 0–1.5 (default: none).
    #[arg(long, env = "SYLVA_SYNTH_CROWN_INTERLOCK")]
    pub crown_interlock: Option<f64>,
    /// LiDAR points delivered (default: the preset's; tiny 400 000, stand 5 200 000, paper
    /// 59 900 000).
    #[arg(long, env = "SYLVA_SYNTH_LIDAR_POINTS")]
    pub lidar_points: Option<usize>,
}

#[derive(Debug, Args)]
pub struct InventoryArgs {
    /// The point cloud (LAS, LAZ, PLY, E57, XYZ), in metres.
    #[arg(env = "SYLVA_INVENTORY_CLOUD")]
    pub cloud: PathBuf,
    /// Where to write the inventory CSV.
    #[arg(long, env = "SYLVA_INVENTORY_OUT", default_value = "trees.csv")]
    pub out: PathBuf,
    /// Also write the stems as GeoJSON points here (RFC 7946: WGS84 when the CRS is known).
    #[arg(long, env = "SYLVA_INVENTORY_GEOJSON")]
    pub geojson: Option<PathBuf>,
    /// Also write a GeoPackage here: the stems as points and the crowns as polygons, in the
    /// cloud's own CRS.
    #[arg(long, env = "SYLVA_INVENTORY_GPKG")]
    pub gpkg: Option<PathBuf>,
    /// Field-measured DBH (CSV x,y,dbh_cm): match trees within 1 m and print the accuracy.
    #[arg(long, env = "SYLVA_INVENTORY_FIELD")]
    pub field: Option<PathBuf>,
    /// The CRS of the cloud's coordinates (EPSG:<code>, WKT or a PROJ string), over what a
    /// LAS/LAZ file declares. Written beside the CSV as `<out>.crs.json` and used to place
    /// the GeoJSON's points in WGS84.
    #[arg(long, env = "SYLVA_INVENTORY_CRS")]
    pub crs: Option<String>,
    /// Print the plot's stand figures (stems and basal area per hectare, QMD, mean and
    /// dominant height, volume, biomass and carbon per hectare, DBH classes) and write them
    /// beside the CSV as `<out>.plot.json`.
    #[arg(long, env = "SYLVA_INVENTORY_SUMMARY", default_value_t = false)]
    pub summary: bool,
    /// Inventory parameters as a JSON file: the `segment` object of a job's params (ground,
    /// segmentation, stems, crowns, allometry such as `{"allometry": {"wood_density_g_cm3":
    /// 0.42}}`, and `summary.boundary`); see `GET /v1/options`.
    #[arg(long, env = "SYLVA_INVENTORY_PARAMS")]
    pub params: Option<PathBuf>,
}

pub(super) async fn synth(a: SynthArgs) -> anyhow::Result<ExitCode> {
    let Some(preset) = sylva::synth::Preset::from_name(&a.preset) else {
        anyhow::bail!(
            "unknown preset {:?}; presets: tiny, plot, stand, object",
            a.preset
        );
    };
    let mut p = sylva::synth::SynthParams::new(preset);
    p.seed = a.seed;
    p.noise_cm = a.noise_cm;
    p.images = a.images.or(p.images);
    p.width = a.width.or(p.width);
    p.height = a.height.or(p.height);
    p.binary = a.binary;
    p.leafless = a.leafless;
    p.png = a.png;
    p.gps_noise_m = a.gps_noise_m;
    p.sfm_scale = a.sfm_scale;
    p.slope_pct = a.slope_pct;
    p.lidar_coverage = a.lidar_coverage;
    p.lidar_leaf_off = a.lidar_leaf_off;
    p.hidden_stem_m = a.hidden_stem_m;
    p.crown_interlock = a.crown_interlock;
    if a.lidar_points == Some(0) {
        anyhow::bail!("--lidar-points must be at least 1");
    }
    p.lidar_points = a.lidar_points.or(p.lidar_points);
    let out = a.out.clone();
    let summary = tokio::task::spawn_blocking(move || {
        sylva::synth::generate(&p, &out, &ConsoleProgress::new("synth", None))
    })
    .await??;
    eprintln!();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(ExitCode::SUCCESS)
}

pub(super) async fn inventory(a: InventoryArgs) -> anyhow::Result<ExitCode> {
    let declared = sylva::io::pointcloud::declared_crs(&a.cloud)?;
    let crs = sylva::io::crs::resolve(a.crs.as_deref(), declared)
        .with_context(|| format!("{}: the CRS", a.cloud.display()))?;
    match &crs.label {
        Some(label) => eprintln!("CRS {label}"),
        None => eprintln!("CRS unknown"),
    }
    for note in &crs.notes {
        eprintln!("note: {note}");
    }
    let params: sylva::forest::InventoryParams = match &a.params {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("cannot read {}", p.display()))?;
            serde_json::from_str(&text)
                .with_context(|| format!("{}: invalid inventory parameters", p.display()))?
        }
        None => sylva::forest::InventoryParams::default(),
    };
    let path = a.cloud.clone();
    let gpkg = a.gpkg.clone();
    let gpkg_crs = crs.clone();
    let (rows, cloud_points, summary) =
        tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
            let progress = ConsoleProgress::new("inventory", None);
            let cloud = sylva::io::pointcloud::read_point_cloud(&path, &progress)?;
            let inv = sylva::forest::inventory(&cloud, &params, &progress)?;
            if let Some(g) = &gpkg {
                sylva::forest::write_trees_gpkg(
                    g,
                    &inv.trees,
                    &inv.crowns,
                    cloud.offset,
                    &gpkg_crs,
                )?;
            }
            let summary =
                sylva::forest::PlotFile::new(inv.summary(&inv.trees, &params)?, &inv.footprint);
            Ok((inv.trees, cloud.len(), summary))
        })
        .await??;
    eprintln!();
    sylva::forest::write_trees_csv(&a.out, &rows)?;
    let sidecar = a.out.with_extension(sylva::io::crs::CRS_FILE);
    let text = serde_json::to_string_pretty(&crs)?;
    std::fs::write(&sidecar, text)
        .with_context(|| format!("cannot write {}", sidecar.display()))?;
    if let Some(g) = &a.geojson {
        sylva::forest::write_trees_geojson(g, &rows, &crs)?;
    }
    println!(
        "{} stems from {} points; inventory in {}",
        rows.len(),
        cloud_points,
        a.out.display()
    );
    if a.summary {
        let path = a.out.with_extension("plot.json");
        let text = serde_json::to_string_pretty(&summary)?;
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        for line in sylva::forest::summary_lines(&summary.summary) {
            println!("{line}");
        }
        println!("plot summary in {}", path.display());
    }
    if let Some(field) = &a.field {
        let cmp = sylva::forest::compare_with_field_file(&rows, field)?;
        for line in sylva::forest::accuracy_lines(&cmp) {
            println!("{line}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `sylva train --photos`: COLMAP on the photos into `<out>/sfm/` (as stage `sfm`), with
/// its report as `<out>/sfm/report.json`. Returns the model's folder and the photos' folder.
fn sfm_from_photos(
    photos: &Path,
    params: &sylva::pipeline::params::SfmParams,
    out: &Path,
    progress: &ConsoleProgress,
) -> anyhow::Result<(PathBuf, PathBuf)> {
    let dir = sylva::io::photos::find_photos_dir(photos)?;
    let names = sylva::io::photos::list_photos(&dir)?;
    let gps = names
        .iter()
        .filter(|n| matches!(sylva::io::gps::read_fix(&dir.join(n)), Ok(Some(_))))
        .count();
    let sfm_dir = out.join("sfm");
    if sfm_dir.exists() {
        std::fs::remove_dir_all(&sfm_dir)?;
    }
    std::fs::create_dir_all(&sfm_dir)?;
    let program = sylva::sfm::colmap_program();
    let report =
        sylva::pipeline::sfm::reconstruct_photos(&program, photos, gps, params, &sfm_dir, progress)
            .map_err(|e| anyhow::anyhow!("sfm: {e}"))?;
    std::fs::write(
        sfm_dir.join("report.json"),
        serde_json::to_vec_pretty(&report)?,
    )?;
    Ok((sfm_dir.join("sparse"), dir))
}

pub(super) async fn train(a: TrainArgs) -> anyhow::Result<ExitCode> {
    use sylva::pipeline::params::TrainParams;
    if let Some(p) = &a.lpips_weights {
        sylva::splat::eval::use_lpips_weights(p.clone());
    }
    // A weights file that cannot be used stops the command before training, not after.
    sylva::splat::eval::lpips()?;
    let backend = parse_backend(&a.backend)?;
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
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let photos = match &a.photos {
        Some(p) => Some(super::run::unpacked(p, &a.out, "photos").await?),
        None => None,
    };
    let sfm_params: sylva::pipeline::params::SfmParams = match &a.sfm_params {
        Some(p) => super::run::json_file(p, "sfm parameters")?,
        None => Default::default(),
    };
    let outcome = tokio::task::spawn_blocking(move || -> anyhow::Result<_> {
        let (sparse_dir, images) = match (&photos, &a.colmap) {
            (Some(photos), _) => {
                let progress = ConsoleProgress::new("sfm", None);
                sfm_from_photos(photos, &sfm_params, &a.out, &progress)?
            }
            (None, Some(colmap)) => {
                let project = sylva::io::colmap::find_project(colmap)?;
                let images = project.images_dir.clone().ok_or_else(|| {
                    anyhow::anyhow!(
                        "{}: no images/ folder beside the sparse model",
                        colmap.display()
                    )
                })?;
                (project.sparse_dir, images)
            }
            (None, None) => anyhow::bail!("give --colmap or --photos"),
        };
        let progress = ConsoleProgress::new("train", None);
        let model = sylva::io::colmap::read_model(&sparse_dir, &progress)?;
        let mut backend = sylva::pipeline::train::backend_for(&params)?;
        let (params, budget_source) =
            sylva::pipeline::train::with_budget(&params, backend.device_kind());
        let cfg = params.config();
        progress.log(&format!(
            "budget: {} Gaussians ({budget_source})",
            match params.max_gaussians {
                0 => "unbounded".to_string(),
                n => n.to_string(),
            }
        ));
        let data = sylva::splat::dataset::load(
            &model,
            &images,
            cfg.resolution,
            cfg.test_every,
            cfg.host_photo_mb,
            &progress,
        )?;
        let init = if a.init == "sfm" {
            let fill = fill_choice(&a.fill)?;
            let (g, filled) = sylva::splat::start::sfm_gaussians(
                &data,
                params.max_gaussians,
                params.seed,
                fill.as_ref(),
            )?;
            progress.log(&format!(
                "{} Gaussians from the SfM points{}",
                g.len(),
                if fill.is_some() {
                    format!(
                        " and the photos' uncovered cells ({} cells filled before the cap, {} \
                         at a depth the photos agree on{}; {} cells that no neighbouring photo \
                         sees and {} on whose depth they agree on nothing left to densification)",
                        filled.added,
                        filled.agreed,
                        if filled.added > filled.agreed {
                            ", the rest far back in what their photo sees"
                        } else {
                            ""
                        },
                        filled.unseen,
                        filled.ambiguous
                    )
                } else {
                    String::new()
                }
            ));
            g
        } else {
            let file =
                std::fs::File::open(&a.init).map_err(|e| anyhow::anyhow!("{}: {e}", a.init))?;
            let mut g = sylva::splat::export::read_ply(std::io::BufReader::new(file))
                .map_err(|e| anyhow::anyhow!("{}: {e}", a.init))?;
            sylva::splat::budget::cap_gaussians(&mut g, params.max_gaussians, params.seed, None, 0);
            g
        };
        let mut strategy = sylva::splat::trainer::strategy_for(&cfg)?;
        let outcome = sylva::splat::trainer::train(
            backend.as_mut(),
            &data,
            init,
            &cfg,
            strategy.as_mut(),
            &progress,
        )?;
        sylva::splat::trainer::write_outputs(&a.out, &outcome, &data)?;
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
    if let Some(l) = outcome.eval.lpips {
        println!("held-out LPIPS (AlexNet) {l:.3}");
    }
    Ok(ExitCode::SUCCESS)
}
