//! The parameters, result and errors of [`super::generate`]: one documented struct whose
//! every field names its unit and default.

use std::path::PathBuf;

use serde::Serialize;

use super::presets::Preset;
use crate::io::IoError;

/// Parameters of one synthetic plot. Every `None` takes the preset's value.
#[derive(Debug, Clone, Serialize)]
pub struct SynthParams {
    pub preset: Preset,
    /// Seed of every random draw.
    pub seed: u64,
    /// LiDAR range noise sigma, centimetres (default 1.0: a handheld SLAM unit's ~1 cm).
    pub noise_cm: f64,
    /// Number of images (tiny 30, plot and stand 100).
    pub images: Option<usize>,
    /// Image width and height, pixels (tiny 160×120, plot and stand 640×360).
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Write the COLMAP model in binary (default text).
    pub binary: bool,
    /// Trees without leaves (like the paper's plot 2 magnolia).
    pub leafless: bool,
    /// PNG images instead of JPEG (quality 92).
    pub png: bool,
    /// LiDAR points delivered (tiny 400 000, plot 3 000 000, stand 5 200 000).
    pub lidar_points: Option<usize>,
    /// Target number of points3D (tiny 12 000, plot 15 000, stand 20 000).
    pub points3d: Option<usize>,
    /// Number of trees (preset: tiny 1–3, plot 1, stand 17).
    pub trees: Option<usize>,
    /// PINHOLE cameras instead of SIMPLE_RADIAL with k = -0.04 (default false).
    pub pinhole: bool,
    /// Samples per pixel: 1, 2 or 4 (default 1).
    pub samples_per_pixel: u32,
    /// Noise of SfM points, camera centres and control point picking, centimetres (default
    /// 1.0); camera rotations get 0.02° per centimetre.
    pub sfm_noise_cm: f64,
    /// LiDAR maximum range, metres (default 80, below a VLP-16's 100 m for dark bark).
    pub max_range_m: f64,
    /// Store LiDAR colour from the surface albedo (default true).
    pub lidar_rgb: bool,
    /// Offset from scene to LiDAR file coordinates, metres (default 500000, 4000000, 50: a
    /// UTM-like easting/northing that exercises f64 handling).
    pub geo_offset: [f64; 3],
    /// DBH of the first trees, centimetres, in place of the species' draw (default empty:
    /// every tree drawn). Entries beyond the plot's number of trees are unused; the other
    /// draws stay as they were, so the remaining trees keep their own sizes. Tests use it to
    /// put the ends of a DBH range (the 8 and 60 cm of the forest tests) into a plot.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stem_dbh_cm: Vec<f64>,
    /// GPS positions in the photos' EXIF, with this horizontal noise sigma in metres (1.5 ×
    /// that vertically), as a drone's consumer GPS gives (default none: no GPS tags). The
    /// LiDAR file then declares EPSG:32632 (UTM 32N, where the default `geo_offset` lies at
    /// about 9° E, 36.1° N), so that the positions can be placed on the cloud. JPEG only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gps_noise_m: Option<f64>,
    /// Scale of the SfM frame, SfM units per metre, in place of the random draw (log-uniform
    /// in 0.2–5; the registration tests' "SfM scale off by 10× and 0.1×").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sfm_scale: Option<f64>,
    /// Grade of the terrain's planar part, percent (default: drawn in 0–8 %; a steep slope
    /// is 30–60 %).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub slope_pct: Option<f64>,
    /// Share of the plot the LiDAR covers, in (0, 1] (default 1): the scan keeps the points
    /// whose x lies in that share of its x extent from the low end, as if the scanner walked
    /// only part of the photographed area.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lidar_coverage: Option<f64>,
    /// Scan the trees without their leaves while the photos show them leafy (a leaf-off scan
    /// against leaf-on photos; default false).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub lidar_leaf_off: bool,
    /// Hide each tree's upper stem from the scan over a length drawn uniformly in
    /// [0.3, this] metres from its crown base up: every return of that tree (stem, branches,
    /// leaves) in the band is dropped, so its crown reaches the cloud as a piece apart from
    /// its stem, as from a scanner below dense foliage (default none: nothing hidden, so
    /// existing figures stand). 0.3–10 m; 3 m is the largest gap measured in the independent
    /// generator of issue 40 (0.3–3 m).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hidden_stem_m: Option<f64>,
    /// Crowns that interlock: the trees are placed as without it, then built with their crown
    /// reach × (1 + this), so neighbours' branches grow into each other (default none; 0–1.5;
    /// 0.5 makes the crowns of `stand` overlap by about a third of their radius).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crown_interlock: Option<f64>,
}

impl SynthParams {
    /// The preset's defaults with seed 0.
    pub fn new(preset: Preset) -> SynthParams {
        SynthParams {
            preset,
            seed: 0,
            noise_cm: 1.0,
            images: None,
            width: None,
            height: None,
            binary: false,
            leafless: false,
            png: false,
            lidar_points: None,
            points3d: None,
            trees: None,
            pinhole: false,
            samples_per_pixel: 1,
            sfm_noise_cm: 1.0,
            max_range_m: 80.0,
            lidar_rgb: true,
            geo_offset: [500_000.0, 4_000_000.0, 50.0],
            stem_dbh_cm: Vec::new(),
            gps_noise_m: None,
            sfm_scale: None,
            slope_pct: None,
            lidar_coverage: None,
            lidar_leaf_off: false,
            hidden_stem_m: None,
            crown_interlock: None,
        }
    }
}

impl Default for SynthParams {
    fn default() -> Self {
        SynthParams::new(Preset::Tiny)
    }
}

/// Errors of [`generate`].
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("invalid synth parameters: {0}")]
    InvalidParams(String),
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("{path}: cannot encode image: {source}")]
    Image {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },
    #[error("cannot serialise truth.json: {0}")]
    Json(#[source] serde_json::Error),
    #[error("cancelled")]
    Cancelled,
}

/// Seconds spent in one phase.
#[derive(Debug, Clone, Serialize)]
pub struct PhaseTiming {
    pub phase: &'static str,
    pub seconds: f64,
}

/// What [`generate`] produced.
#[derive(Debug, Clone, Serialize)]
pub struct SynthSummary {
    pub preset: &'static str,
    pub seed: u64,
    pub trees: usize,
    pub stones: usize,
    pub shrubs: usize,
    pub primitives: usize,
    pub lidar_points: usize,
    pub lidar_rays: u64,
    pub images: usize,
    pub width: u32,
    pub height: u32,
    pub points3d: usize,
    pub control_points: usize,
    pub canopy_closure: f64,
    pub timings: Vec<PhaseTiming>,
}

/// Refuses parameters outside their documented ranges.
pub(crate) fn check(params: &SynthParams) -> Result<(), SynthError> {
    let bad = |m: &str| Err(SynthError::InvalidParams(m.to_string()));
    if !(params.noise_cm.is_finite() && params.noise_cm >= 0.0 && params.noise_cm <= 100.0) {
        return bad("noise_cm must be in [0, 100]");
    }
    if !(params.sfm_noise_cm.is_finite()
        && params.sfm_noise_cm >= 0.0
        && params.sfm_noise_cm <= 100.0)
    {
        return bad("sfm_noise_cm must be in [0, 100]");
    }
    if params.images.is_some_and(|n| !(3..=5000).contains(&n)) {
        return bad("images must be between 3 and 5000");
    }
    if params.width.is_some_and(|w| !(16..=8192).contains(&w))
        || params.height.is_some_and(|h| !(16..=8192).contains(&h))
    {
        return bad("width and height must be between 16 and 8192 pixels");
    }
    if params
        .lidar_points
        .is_some_and(|n| !(1_000..=200_000_000).contains(&n))
    {
        return bad("lidar_points must be between 1000 and 200 million");
    }
    if params.trees.is_some_and(|n| !(1..=500).contains(&n)) {
        return bad("trees must be between 1 and 500");
    }
    if !(params.max_range_m.is_finite() && params.max_range_m > 1.0) {
        return bad("max_range_m must exceed 1 m");
    }
    if !params
        .geo_offset
        .iter()
        .all(|v| v.is_finite() && v.abs() < 1e8)
    {
        return bad("geo_offset must be finite and below 1e8 m");
    }
    if !params
        .stem_dbh_cm
        .iter()
        .all(|d| d.is_finite() && (2.0..=300.0).contains(d))
    {
        return bad("stem_dbh_cm must be between 2 and 300 cm");
    }
    if params
        .gps_noise_m
        .is_some_and(|v| !(v.is_finite() && (0.0..=100.0).contains(&v)))
    {
        return bad("gps_noise_m must be in [0, 100]");
    }
    if params.gps_noise_m.is_some() && params.png {
        return bad("gps_noise_m needs JPEG photos (the GPS goes into their EXIF)");
    }
    if params
        .sfm_scale
        .is_some_and(|v| !(v.is_finite() && (1e-3..=1e3).contains(&v)))
    {
        return bad("sfm_scale must be between 0.001 and 1000");
    }
    if params
        .slope_pct
        .is_some_and(|v| !(v.is_finite() && (0.0..=100.0).contains(&v)))
    {
        return bad("slope_pct must be in [0, 100]");
    }
    if params
        .lidar_coverage
        .is_some_and(|v| !(v.is_finite() && v > 0.05 && v <= 1.0))
    {
        return bad("lidar_coverage must be in (0.05, 1]");
    }
    if params
        .hidden_stem_m
        .is_some_and(|v| !(v.is_finite() && (0.3..=10.0).contains(&v)))
    {
        return bad("hidden_stem_m must be between 0.3 and 10 m");
    }
    if params
        .crown_interlock
        .is_some_and(|v| !(v.is_finite() && (0.0..=1.5).contains(&v)))
    {
        return bad("crown_interlock must be between 0 and 1.5");
    }
    Ok(())
}
