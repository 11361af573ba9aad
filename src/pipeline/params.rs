//! Parameters of every pipeline stage, one serde struct per stage, with the paper's defaults.
//!
//! A job's `params` object is a [`PipelineParams`]; unknown keys are refused so a typo never
//! silently falls back to a default. `GET /v1/options` and `sylva run --help` show these
//! structs with their defaults; the doc comments here are the descriptions users read.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::Stage;
use crate::splat::{bind, config, semantic};

/// Everything a job can be told, grouped by stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineParams {
    /// Stop after this stage and call the job succeeded (default: run every stage).
    pub until: Option<Stage>,
    /// The coordinate reference system of the LiDAR file's x, y, z: `EPSG:<code>`, OGC WKT
    /// or a PROJ string. Overrides what a LAS/LAZ file declares (default: the file's own;
    /// PLY, XYZ and E57 files declare none). A CRS in degrees is refused: Sylva measures in
    /// metres. With none, the inventory is measured as usual but trees.geojson cannot place
    /// the trees on the Earth (its geometries are null) and every output says so.
    pub crs: Option<String>,
    pub ingest: IngestParams,
    /// Stage `sfm`: COLMAP on the job's photos (unused when the job gives a COLMAP project).
    pub sfm: SfmParams,
    pub register: RegisterParams,
    pub anchors: AnchorParams,
    /// Stage `segment`: ground, wood/leaf labels, stems and their LiDAR diameters
    /// (docs/method.md Stages 3 and 5; the parameters of `sylva inventory`).
    pub segment: crate::forest::InventoryParams,
    pub train: TrainParams,
    pub dbh: DbhParams,
    pub export: ExportParams,
}

/// Stage `ingest`: read and validate the inputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct IngestParams {
    /// Fully decode every registered image to prove it is readable (default true). Turning it
    /// off only checks that the files exist, which is faster for thousands of large photos.
    pub decode_images: bool,
    /// A cloud whose bounding-box diagonal exceeds this many metres is reported as probably
    /// not in metres (e.g. millimetres). Default 5000 m: larger than any forest plot a
    /// handheld scanner covers.
    pub max_plausible_extent_m: f64,
}

impl Default for IngestParams {
    fn default() -> Self {
        Self {
            decode_images: true,
            max_plausible_extent_m: 5000.0,
        }
    }
}

/// How stage `sfm` pairs photos for matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum SfmMatching {
    /// Exhaustive for up to `exhaustive_max_photos` photos; above that spatial when at least
    /// half the photos carry EXIF GPS, else sequential (name order, as cameras number them).
    Auto,
    Exhaustive,
    Spatial,
    Sequential,
}

/// Stage `sfm`: structure from motion by COLMAP's command line on the job's photos
/// (docs/method.md, Stage 0). Defaults follow COLMAP 3.8's own where not said otherwise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SfmParams {
    /// COLMAP camera model (default `RADIAL`: one focal length, the principal point and two
    /// radial terms). Must be one Sylva undistorts: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
    /// RADIAL or OPENCV. Measured on Brighton's 18 drone photos at 800 px (2026-11-28,
    /// docs/results/photos.md): COLMAP's default `SIMPLE_RADIAL` (one radial term) left the
    /// model bowl-shaped against the cloud of the same flight (0.12 m below it in the middle,
    /// 0.6 m above at the edges; median distance 0.13 m after registration), `RADIAL` flat
    /// (median 0.05 m), `OPENCV` in between (0.10 m, its cameras 1.2 m from their GPS). A
    /// nadir flight without oblique views cannot tell a wide lens's distortion from a curved
    /// ground; the second radial term is what the lens needs.
    pub camera_model: String,
    /// One camera shared by photos of one size (default true: a plot is flown with one
    /// camera; fewer unknowns make the mapper steadier). Photos of several sizes always get
    /// one camera each.
    pub single_camera: bool,
    /// Longest photo side for feature extraction, pixels (default 2000: a 4000 × 2250 drone
    /// photo is halved; with it COLMAP made Brighton's model from its 18 photos in 12 minutes
    /// on 2 cores, issue 39. COLMAP's own default is 3200).
    pub max_image_size: u32,
    /// How photos are paired (default `auto`).
    pub matching: SfmMatching,
    /// `auto` matches exhaustively up to this many photos (default 60: 1,770 pairs; above it
    /// the pairs grow as n², and 857 photos would be 366,796 pairs).
    pub exhaustive_max_photos: u32,
    /// Nearest GPS neighbours each photo is matched with under spatial matching (default 30:
    /// a UAV grid with 80 % forward and 70 % side overlap sees a ground point in about 25
    /// photos; COLMAP's default is 50).
    pub spatial_neighbours: u32,
    /// Photos after each, in name order, it is matched with under sequential matching
    /// (default 10, COLMAP's own; quadratic overlap adds 2, 4, 8, … further on).
    pub sequential_overlap: u32,
    /// Smallest model the mapper keeps, in photos (default 3: COLMAP's default of 10 throws
    /// away every model of a small set; stage `sfm` keeps the largest model anyway).
    pub min_model_photos: u32,
    /// The stage fails when fewer than this share of the photos register (default 0.5); the
    /// failure lists the photos left out and why. Fewer unregistered photos are a warning.
    pub min_registered_share: f64,
    /// Use COLMAP's CUDA SIFT where the worker's COLMAP has CUDA (default false: Debian's
    /// build has none, and with none COLMAP refuses the GPU option).
    pub use_gpu: bool,
    /// CPU threads COLMAP uses (default 0: all).
    pub threads: u32,
    /// The stage fails past this many minutes of COLMAP (default 720: twelve hours; the
    /// worker's `--max-stage-secs sfm=…` stops it too).
    pub time_limit_min: f64,
    /// Keep COLMAP's database of features and matches in the stage's folder (default false:
    /// it is large, tens of MB for 18 photos, and later stages never read it).
    pub keep_database: bool,
}

impl Default for SfmParams {
    fn default() -> Self {
        Self {
            camera_model: "RADIAL".into(),
            single_camera: true,
            max_image_size: 2000,
            matching: SfmMatching::Auto,
            exhaustive_max_photos: 60,
            spatial_neighbours: 30,
            sequential_overlap: 10,
            min_model_photos: 3,
            min_registered_share: 0.5,
            use_gpu: false,
            threads: 0,
            time_limit_min: 720.0,
            keep_database: false,
        }
    }
}

/// Stage `register`: similarity transform from the SfM frame to the LiDAR frame (docs/method.md
/// Stage 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct RegisterParams {
    /// ICP iteration cap (default 50).
    pub icp_max_iterations: u32,
    /// ICP stops when the relative change of the RMSE falls below this (default 1e-6,
    /// Open3D's relative_rmse).
    pub icp_relative_rmse: f64,
    /// Initial correspondence distance in metres; it shrinks by 0.8 per iteration (default
    /// 1.0 m: a coarse alignment is good to decimetres).
    pub icp_max_distance_m: f64,
    /// Floor of the correspondence distance in metres (default 0.05 m).
    pub icp_min_distance_m: f64,
    /// Share of correspondences kept by the trimmed robust estimator (default 0.8: SfM
    /// clouds carry sky and mismatched points LiDAR does not see).
    pub icp_keep_fraction: f64,
    /// Estimate scale in ICP as well (similarity ICP), since SfM scale is only approximately
    /// fixed by the coarse step (docs/method.md Stage 1.2; default true).
    pub estimate_scale: bool,
    /// Use the point-to-plane objective instead of the paper's point-to-point (default false).
    pub point_to_plane: bool,
    /// The LiDAR cloud is thinned to this voxel size (metres) as the ICP target (default
    /// 0.05 m: well below SfM point noise, and fast).
    pub target_voxel_m: f64,
    /// Align automatically when no control points are given (default true: most users have
    /// none). The alignment verifies itself and, when it cannot be sure (confidence, fitness
    /// or the standard errors of the result below their floors), the stage fails saying why,
    /// listing the candidates it weighed, and asking for control points; on `stand` it reaches
    /// the registration goals and on small plots such as `tiny` it refuses
    /// (docs/results/registration.md). False: a job without control points stops at once and
    /// asks for them.
    pub automatic: bool,
    /// The automatic alignment must reach this confidence in [0, 1], or the stage refuses
    /// and asks for control points (default 0.5). The confidence comes from ICP run from each
    /// coarse candidate: how many SfM points, and how many of those standing above the
    /// ground, then lie on the LiDAR cloud, and by how much the best candidate beats the best
    /// distinct other (`geom::register::verify_candidates`).
    pub min_confidence: f64,
    /// After the automatic alignment's ICP and surface passes, at least this share of the
    /// SfM points must lie within 6 cm of the thinned LiDAR cloud, or the stage refuses
    /// (default 0.3: a floor only; right alignments of `stand` reach 0.69-0.72 and the light
    /// stand of the tests 0.37, but flat ground lets wrong ones on `tiny` reach 0.44-0.66
    /// too, so the confidence does the discriminating).
    pub min_fitness: f64,
    /// Finish with the surface refinement of [`crate::geom::surface`]: the similarity that
    /// puts the SfM points on quadric patches of the LiDAR surface (ground, stems, stones;
    /// foliage and edges fail the patch test), with the control points as extra observations.
    /// Default true: point-to-point ICP onto a thinned cloud stops centimetres and tenths of a
    /// degree short (docs/results/registration.md).
    pub refine: bool,
    /// The LiDAR cloud is thinned to this voxel size (metres) for the surface patches
    /// (default 0.01 m: the range noise of a handheld scanner; finer only adds time).
    pub refine_voxel_m: f64,
    /// Radius of the first LiDAR patch tried around each SfM point, metres (default 0.08; it
    /// doubles up to `refine_max_radius_m` where the cloud is sparse).
    pub refine_radius_m: f64,
    /// Largest patch radius, metres (default 0.32: terrain relief is still a quadric at that
    /// size).
    pub refine_max_radius_m: f64,
    /// A patch whose quadric fit leaves a larger RMS is not a surface, metres (default 0.012:
    /// measured on `tiny` seeds 1-3, 1 cm LiDAR noise leaves 0.6-1 cm on ground and stems,
    /// foliage several centimetres).
    pub refine_max_fit_rms_m: f64,
    /// Huber scale of the point-to-surface distances, metres (default 0.015: 1.5 times the
    /// ~1 cm noise of SfM points).
    pub refine_huber_m: f64,
    /// Point-to-surface distances beyond this are not used, metres (default 0.05).
    pub refine_max_distance_m: f64,
    /// Rounds of the refinement, each refitting the patches where the points moved to and
    /// solving on their tangent planes (default 3, measured best of 1, 2, 3 and 10 on `tiny`
    /// seeds 1-5; it stops early once converged).
    pub refine_rounds: u32,
    /// Random halvings of the SfM points refined again to measure the refinement's standard
    /// errors on the data (default 16; 0 keeps the normal-matrix errors alone). The report
    /// and the automatic gate take, per parameter, the larger of the two: on `tiny` the
    /// normal matrix put the yaw 1.3-1.9 times too tight (docs/results/registration.md). Sixteen
    /// splits give each standard error to about ±18 % (a chi-square of 16 degrees of
    /// freedom); with eight (±25 %) two `tiny` plots whose yaw error is 0.021-0.023° fell
    /// either side of the automatic gate depending on the draw of the halves.
    pub uncertainty_splits: u32,
    /// Standard deviation of a control point pair's coordinates, metres (default 0.015: a
    /// target picked by hand in a photo model and in a LiDAR cloud, each to about a
    /// centimetre). The pairs enter the refinement with this weight against the SfM points.
    pub control_point_sigma_m: f64,
    /// Where the automatic alignment starts (default `auto`; docs/method.md, georeferenced
    /// starts). Control points, when given, are used instead.
    pub start: RegisterStart,
    /// A georeferenced start is accepted only when the final alignment puts the camera
    /// centres within this many metres (RMS, horizontal) of their GPS positions, or within
    /// three times the GPS fit's own RMS if that is larger (default 10 m: consumer GPS on a
    /// drone is good to a few metres; an alignment that moves the photos further than that
    /// from where they were taken contradicts them).
    pub max_gps_disagreement_m: f64,
}

/// Where the automatic alignment of stage `register` starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RegisterStart {
    /// A georeferenced start when the data give one (the model's frame already is the
    /// LiDAR's CRS, else GPS positions in the photos with the LiDAR's CRS known), verified
    /// like a searched candidate; when there is none, or it fails verification, the raster
    /// search.
    Auto,
    /// Always the raster search over yaw, scale and offset.
    Search,
    /// The photos' GPS positions (EXIF), projected into the LiDAR's CRS; the stage fails
    /// when they or the CRS are missing.
    Gps,
    /// The COLMAP model's coordinates already are the LiDAR file's (e.g. aligned to
    /// projected GPS or survey positions with COLMAP's model_aligner).
    ModelFrame,
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            icp_max_iterations: 50,
            icp_relative_rmse: 1e-6,
            icp_max_distance_m: 1.0,
            icp_min_distance_m: 0.05,
            icp_keep_fraction: 0.8,
            estimate_scale: true,
            point_to_plane: false,
            target_voxel_m: 0.05,
            automatic: true,
            min_confidence: 0.5,
            min_fitness: 0.3,
            refine: true,
            refine_voxel_m: 0.01,
            refine_radius_m: 0.08,
            refine_max_radius_m: 0.32,
            refine_max_fit_rms_m: 0.012,
            refine_huber_m: 0.015,
            refine_max_distance_m: 0.05,
            refine_rounds: 3,
            uncertainty_splits: 16,
            control_point_sigma_m: 0.015,
            start: RegisterStart::Auto,
            max_gps_disagreement_m: 10.0,
        }
    }
}

/// Stage `anchors`: voxel homogenisation and statistical outlier removal (paper 3.3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct AnchorParams {
    /// Voxel edge in metres; the paper gives none, docs/method.md Stage 2.1 sets 0.02 m.
    pub voxel_size_m: f64,
    /// Neighbours for the mean-distance statistic (paper 3.3.2: k = 16).
    pub outlier_k: u32,
    /// Keep a point iff its mean neighbour distance <= mean + alpha * std (paper: 2.5).
    pub outlier_alpha: f64,
}

impl Default for AnchorParams {
    fn default() -> Self {
        Self {
            voxel_size_m: 0.02,
            outlier_k: 16,
            outlier_alpha: 2.5,
        }
    }
}

/// How the Gaussians are initialised (paper Table 5 ablation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum InitSource {
    /// From the SfM sparse points (vanilla 3DGS).
    Sfm,
    /// From the LiDAR anchors (the paper's method).
    Lidar,
}

/// Stage `train`: LiDAR-guided semantic Gaussian splatting (paper 3.5).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct TrainParams {
    /// Optimisation steps (Kerbl et al. 2023: 30,000).
    pub steps: u32,
    /// Initialisation source (default lidar, the paper's method).
    pub init: InitSource,
    /// LiDAR initialisation: SfM points farther than this from every anchor join the anchors
    /// as (non-trunk) Gaussians, so that what the photos see beyond the LiDAR — the canopy top
    /// a handheld scanner under it misses, terrain outside the scan — starts with Gaussians
    /// too; metres, 0 = the anchors alone (the paper's initialisation). Default 0.1 (Sylva's:
    /// five anchor voxels, so the SfM noise about surfaces the LiDAR has does not double them).
    pub sfm_fill_m: f64,
    /// Background Gaussians on a dome beyond the scene (`splat::init::add_sky`), for the sky
    /// and distant terrain the photos show: without them the optimiser paints the sky with
    /// floaters in front of the trees, or leaves it black. Counted in `max_gaussians` (at most
    /// a tenth of it). Default 1000 (Sylva's: about 6.4° apart); 0 = none (reference 3DGS and
    /// the paper).
    pub sky_gaussians: u32,
    /// What holds the trunk Gaussians: "bind" (default: Sylva's binding, surfels held on the
    /// LiDAR stem surface from step 0, docs/method.md Stage 4 "Sylva's binding"), "paper" (the
    /// paper's term L_geo exactly as docs/method.md writes it, for the ablation) or "off".
    pub semantic: TrunkTerm,
    /// Sylva's binding: largest offset of a trunk Gaussian's centre from the LiDAR surface
    /// along its normal, metres (default 0: the photos cannot place a stem to a pixel, and
    /// push the fitted Gaussians to the inner edge of any band; see `splat::bind`).
    pub bind_band_m: f64,
    /// Sylva's binding: largest standard deviation of a trunk surfel along the normal, metres
    /// (default 0.005: half the LiDAR noise).
    pub bind_normal_scale_m: f64,
    /// Final weight of L_geo (paper: 0.02; 0.01-0.03 is stable).
    pub gamma_max: f64,
    /// Step where the L_geo ramp starts (paper: 3000 of 30,000; moved in proportion when
    /// `steps` is smaller, docs/method.md).
    pub gamma_start: u32,
    /// Step where the L_geo ramp reaches gamma_max (paper: 7000 of 30,000; scaled likewise).
    pub gamma_end: u32,
    /// Trunk anchors averaged for the target scale (docs/method.md: K = 8).
    pub trunk_k: u32,
    /// Target scale factor on the mean trunk-anchor distance (docs/method.md: beta = 0.5).
    pub trunk_beta: f64,
    /// Longest image side in pixels used for training; 0 keeps the full resolution.
    pub resolution: u32,
    /// Upper bound on the number of Gaussians, at initialisation (an even draw in space of
    /// the anchors or points, half of it reserved for trunk Gaussians and half of that for the
    /// stems' DBH band: see `splat::budget::cap_gaussians`) and during densification; 0
    /// (default) = the budget of the device that trains (`splat::budget::default_budget`: none
    /// on a hardware GPU, 10 000 on a software one such as lavapipe, 3 000 on the CPU
    /// reference; measured in docs/results/twin.md, "Budgets"). On a GPU the memory plan
    /// lowers it to what fits (`gpu_memory_mb`).
    pub max_gaussians: u32,
    /// The GPU memory a run may plan with, MB (MiB); 0 (default) = the device's own, as its
    /// Vulkan driver reports it (the largest device-local heap). From it stage `train` plans the
    /// Gaussian budget and where the photos live (all on the GPU, or a cache streamed from host
    /// memory; `splat::plan`, docs/splatting.md "Memory plan"). Ignored by the CPU reference.
    pub gpu_memory_mb: u64,
    /// Host memory the decoded photos may take, MB (MiB); past it they are kept compressed
    /// (lossless PNG) and decoded for each upload or measurement (`splat::photo`; default
    /// `splat::photo::DEFAULT_HOST_PHOTO_MB`, 4096: the paper's 857 photos at 1920×1080 are
    /// 6.8 GiB decoded, about 3 GiB compressed).
    pub host_photo_mb: u64,
    /// Weight λ of the LiDAR depth loss (`splat::depth`): the rendered expected depth of each
    /// training view is pulled towards the registered LiDAR anchors' depth there,
    /// λ · mean |D − L| / L over the pixels with a LiDAR return (occlusion-aware maps); 0 =
    /// off (default: the reference 3DGS and the paper have none). Needs the LiDAR anchors.
    pub depth_weight: f64,
    /// How the set of Gaussians changes during training: "default" (the reference adaptive
    /// density control: clone, split and prune by gradient; Kerbl et al. 2023) or "mcmc"
    /// (relocation of dead Gaussians and growth to `max_gaussians`, with position noise;
    /// Kheradmand et al. 2024, `splat::mcmc`), which needs a budget.
    pub strategy: DensifyStrategy,
    /// Where the steps run: the GPU (default) or the CPU reference, which is exact but only
    /// fit for tiny scenes.
    pub backend: TrainBackend,
    /// Seed of view order, densification sampling and subsets (default 0).
    pub seed: u64,
    /// Anti-aliased rasterisation: Mip-Splatting's 2-D filter (Yu et al. 2024; gsplat's
    /// "antialiased" mode), a 0.3 px² screen-space blur whose opacity compensation dims
    /// Gaussians smaller than a pixel instead of enlarging them, for training and the
    /// held-out renders alike. Default true (Sylva's; the reference 3DGS dilation, without
    /// compensation, is `false`): the dilation draws a trunk's sub-pixel Gaussians wider than
    /// the surface they stand on, the photos pull them inside it, and the DBH measured on
    /// them comes out small; measured in docs/results/twin.md (issue 40, "The Gaussian DBH
    /// on unseen seeds"). The exported splat files do not record it; viewers render them
    /// with their own filter.
    pub antialias: bool,
    /// Per-image exposure compensation (docs/splatting.md "Exposure"; the reference trainer's
    /// `train_test_exp`): each photo gets a learned affine colour transform applied to its
    /// render before the loss. Default true (Sylva's: real photos of a forest change exposure
    /// and white balance from shot to shot; the reference trainer leaves it off). With it,
    /// the held-out photos' left halves train as well and the held-out PSNR and SSIM are
    /// measured on their right halves (`render.region` says `right_half`).
    pub exposure: bool,
    /// Exposure learning rate at the first step, per step (default 0.01, reference
    /// `exposure_lr_init`).
    pub exposure_lr_init: f64,
    /// Exposure learning rate at the last step; log-linear in between (default 0.001,
    /// reference `exposure_lr_final`).
    pub exposure_lr_final: f64,
    /// Steps over which the exposure rate ramps in (default 0, reference
    /// `exposure_lr_delay_steps`; the reference README suggests 5000 of 30,000 with rates
    /// 0.001 and 0.0001 and a multiplier of 0.001); moved in proportion when `steps` is
    /// smaller.
    pub exposure_lr_delay_steps: u32,
    /// Multiplier of the exposure rate at step 0 during the ramp, in [0, 1] (default 0,
    /// reference `exposure_lr_delay_mult`).
    pub exposure_lr_delay_mult: f64,
}

/// What holds the trunk Gaussians during training (the ablation's arms).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum TrunkTerm {
    /// Sylva's binding (the default): trunk surfels projected onto the LiDAR surface after
    /// every optimiser step.
    Bind,
    /// The paper's L_geo as docs/method.md specifies it.
    Paper,
    /// Nothing (LiDAR initialisation alone, or vanilla 3DGS with `init = "sfm"`).
    Off,
}

impl TrunkTerm {
    /// The name used in params and on the command line.
    pub fn as_str(self) -> &'static str {
        match self {
            TrunkTerm::Bind => "bind",
            TrunkTerm::Paper => "paper",
            TrunkTerm::Off => "off",
        }
    }
}

/// How the set of Gaussians changes during training.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum DensifyStrategy {
    /// Clone, split and prune by gradient (Kerbl et al. 2023).
    Default,
    /// Relocate dead Gaussians and grow to the budget (Kheradmand et al. 2024).
    Mcmc,
}

/// Where training runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum TrainBackend {
    Gpu,
    Cpu,
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            steps: 30_000,
            init: InitSource::Lidar,
            sfm_fill_m: 0.1,
            sky_gaussians: 1000,
            semantic: TrunkTerm::Bind,
            bind_band_m: bind::DEFAULT_BAND_M,
            bind_normal_scale_m: bind::DEFAULT_NORMAL_SCALE_M,
            gamma_max: semantic::DEFAULT_GAMMA_MAX,
            gamma_start: semantic::DEFAULT_GAMMA_START,
            gamma_end: semantic::DEFAULT_GAMMA_END,
            trunk_k: semantic::DEFAULT_TRUNK_K,
            trunk_beta: semantic::DEFAULT_TRUNK_BETA,
            resolution: 1600,
            max_gaussians: 0,
            gpu_memory_mb: 0,
            host_photo_mb: crate::splat::photo::DEFAULT_HOST_PHOTO_MB,
            strategy: DensifyStrategy::Default,
            depth_weight: 0.0,
            backend: TrainBackend::Gpu,
            seed: 0,
            antialias: true,
            exposure: true,
            exposure_lr_init: config::DEFAULT_LR_EXPOSURE_INIT,
            exposure_lr_final: config::DEFAULT_LR_EXPOSURE_FINAL,
            exposure_lr_delay_steps: config::DEFAULT_LR_EXPOSURE_DELAY_STEPS,
            exposure_lr_delay_mult: config::DEFAULT_LR_EXPOSURE_DELAY_MULT,
        }
    }
}

/// Stage `dbh`: diameter at breast height from the Gaussians (paper 3.6). The slice height and
/// thickness are those of `segment.dbh`, so both diameters come from the same slice.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct DbhParams {
    /// Minimum opacity of a Gaussian used in the fit. Default 0.005, the reference prune
    /// threshold: every Gaussian the model keeps, its opacity weighting the algebraic fit
    /// (docs/method.md Stage 5.3). The paper's 0.1 is the initial opacity itself: on short runs
    /// it cut at random (Sylva's binding on `tiny` seed 1, 500 steps at 80 px: 3–9 of the
    /// 38–50 trunk surfels per slice kept, no fit), and a bound surfel is no floater.
    pub min_opacity: f64,
    /// RANSAC inlier distance in metres (docs/method.md: of the order of 1-2 cm).
    pub ransac_threshold_m: f64,
}

impl Default for DbhParams {
    fn default() -> Self {
        Self {
            min_opacity: 0.005,
            ransac_threshold_m: 0.015,
        }
    }
}

/// Stage `export`: splat files and the inventory in the LiDAR file's own coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ExportParams {
    /// Also write the compact (quantised) splat file for web viewers (default true).
    pub compact: bool,
    /// Also write the splats as a 3D Tiles 1.1 tileset (`tileset.json` and `tiles/`: glTF
    /// tiles with levels of detail, georeferenced to ECEF when the CRS is known;
    /// `splat::tiles`; default true).
    pub tiles: bool,
    /// Most Gaussians in one tile of the tileset (default 50 000,
    /// `splat::tiles::TileParams`'s: 3.2 MB of SPZ at SH degree 3). Fewer make smaller
    /// tiles and more levels, for weak clients or slow links; at least 1.
    pub tile_gaussians: u32,
}

impl Default for ExportParams {
    fn default() -> Self {
        Self {
            compact: true,
            tiles: true,
            tile_gaussians: crate::splat::tiles::TileParams::default().max_per_tile as u32,
        }
    }
}

impl TrainParams {
    /// The trainer's configuration: the reference schedule scaled to `steps`, with these
    /// parameters' resolution, cap, seed and exposure compensation.
    pub fn config(&self) -> crate::splat::config::TrainConfig {
        let semantic = crate::splat::semantic::SemanticConfig {
            enabled: self.semantic == TrunkTerm::Paper,
            gamma_max: self.gamma_max as f32,
            gamma_start: self.gamma_start,
            gamma_end: self.gamma_end,
            k: self.trunk_k,
            beta: self.trunk_beta as f32,
            ..Default::default()
        };
        let bind = crate::splat::bind::BindConfig {
            enabled: self.semantic == TrunkTerm::Bind,
            band_m: self.bind_band_m as f32,
            normal_scale_m: self.bind_normal_scale_m as f32,
            ..Default::default()
        };
        let mut cfg = crate::splat::config::TrainConfig {
            steps: self.steps,
            semantic,
            bind,
            exposure: self.exposure,
            lr_exposure_init: self.exposure_lr_init as f32,
            lr_exposure_final: self.exposure_lr_final as f32,
            lr_exposure_delay_steps: self.exposure_lr_delay_steps,
            lr_exposure_delay_mult: self.exposure_lr_delay_mult as f32,
            ..Default::default()
        }
        .scaled_to(self.steps);
        cfg.resolution = (self.resolution > 0).then_some(self.resolution);
        cfg.host_photo_mb = self.host_photo_mb;
        cfg.max_gaussians = (self.max_gaussians > 0).then_some(self.max_gaussians as usize);
        cfg.strategy = match self.strategy {
            DensifyStrategy::Default => crate::splat::config::StrategyKind::Default,
            DensifyStrategy::Mcmc => crate::splat::config::StrategyKind::Mcmc,
        };
        cfg.seed = self.seed;
        cfg.antialias = self.antialias;
        cfg
    }
}

impl PipelineParams {
    /// The stages a job with these parameters runs, in order.
    pub fn stages(&self) -> Vec<Stage> {
        let last = self.until.unwrap_or(Stage::Export);
        Stage::ALL.iter().copied().filter(|s| *s <= last).collect()
    }

    /// JSON Schema of the params object (shown by `GET /v1/options`).
    pub fn schema() -> serde_json::Value {
        serde_json::to_value(schemars::schema_for!(PipelineParams)).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn antialias_reaches_the_training_config() {
        let p: PipelineParams =
            serde_json::from_value(serde_json::json!({"train": {"antialias": false}}))
                .expect("valid params");
        assert!(!p.train.config().antialias);
        assert!(!p.train.config().render_options().antialias);
        // On by default for jobs (the library's reference `TrainConfig` keeps the dilation).
        assert!(PipelineParams::default().train.config().antialias);
        assert!(
            PipelineParams::default()
                .train
                .config()
                .render_options()
                .antialias
        );
        assert!(!crate::splat::config::TrainConfig::default().antialias);
    }

    #[test]
    fn unknown_keys_are_refused() {
        let r: Result<PipelineParams, _> =
            serde_json::from_value(serde_json::json!({"anchors": {"voxel": 0.1}}));
        assert!(r.is_err());
    }

    #[test]
    fn partial_params_keep_defaults() {
        let p: PipelineParams =
            serde_json::from_value(serde_json::json!({"anchors": {"voxel_size_m": 0.05}}))
                .expect("valid params");
        assert_eq!(p.anchors.voxel_size_m, 0.05);
        assert_eq!(p.anchors.outlier_k, 16);
        assert_eq!(p.train.steps, 30_000);
        assert!(p.train.exposure);
    }

    #[test]
    fn exposure_is_on_for_jobs_and_reaches_the_trainer() {
        let on = TrainParams::default().config();
        assert!(on.exposure);
        assert_eq!((on.lr_exposure_init, on.lr_exposure_final), (0.01, 0.001));
        let p: PipelineParams = serde_json::from_value(serde_json::json!({"train": {
            "exposure": false, "steps": 3000, "exposure_lr_delay_steps": 5000,
            "exposure_lr_delay_mult": 0.001}}))
        .expect("valid params");
        let off = p.train.config();
        assert!(!off.exposure);
        // The ramp moves with the schedule: 5000 of 30 000 steps is 500 of 3000.
        assert_eq!(off.lr_exposure_delay_steps, 500);
        assert!((off.lr_exposure_delay_mult - 0.001).abs() < 1e-9);
        let bad = TrainParams {
            exposure_lr_init: -1.0,
            ..TrainParams::default()
        };
        assert!(bad.config().validate_exposure().is_err());
    }

    #[test]
    fn until_limits_the_stages() {
        let p = PipelineParams {
            until: Some(Stage::Anchors),
            ..Default::default()
        };
        assert_eq!(
            p.stages(),
            vec![Stage::Ingest, Stage::Sfm, Stage::Register, Stage::Anchors]
        );
        assert_eq!(PipelineParams::default().stages().len(), 8);
    }

    #[test]
    fn schema_describes_every_stage() {
        let s = PipelineParams::schema().to_string();
        for stage in Stage::ALL {
            assert!(s.contains(stage.name()), "{} missing", stage.name());
        }
    }
}
