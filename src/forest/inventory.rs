//! The per-tree inventory of one cloud: ground → wood/leaf → stems → DBH, with the seconds
//! each phase took. One row per stem that holds a circle; positions in the cloud's original
//! coordinates.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::allometry::{AllometryParams, tree_allometry};
use super::crowns::{CrownParams, HeightQuality, NO_TREE, TreeCrown, segment_trees_labelled};
use super::dbh::{DbhParams, measure_dbh};
use super::ground::{CsfParams, Dtm, classify_ground};
use super::segment::{SegmentParams, SegmentSeconds, segment_wood_leaf};
use super::stem_labels::{StemLabelParams, label_stem_points};
use super::stems::{Stem, StemParams, detect_stems};
use super::summary::{PlotSummary, SummaryParams, footprint, summarise};
use super::{FitQuality, ForestError, StemDbh};
use crate::io::pointcloud::PointCloud;
use crate::progress::{Progress, SubProgress};

/// Everything the inventory can be tuned with; every part has documented defaults.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct InventoryParams {
    /// Ground filter and DTM.
    pub ground: CsfParams,
    /// Wood/leaf segmentation (paper 3.4).
    pub segment: SegmentParams,
    /// Stem detection in the breast-height band.
    pub stems: StemParams,
    /// Stem-guided relabelling of the wood/leaf labels (after the stems are found).
    pub stem_labels: StemLabelParams,
    /// Breast-height slice and circle fitting (docs/method.md Stage 5).
    pub dbh: DbhParams,
    /// Individual trees from the stems: height, crown base and crown projection.
    pub crowns: CrownParams,
    /// Basal area, stem volume, biomass and carbon per tree.
    pub allometry: AllometryParams,
    /// The plot's stand figures: which DBH, and the plot boundary.
    pub summary: SummaryParams,
    /// What the cloud is (default `auto`: a plot or a tree with its ground, checked).
    pub cloud: CloudKind,
}

/// What a cloud holds, which decides where the ground is (issue 27.6).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum CloudKind {
    /// A plot or a single tree with its ground returns: the ground filter finds the ground.
    /// A cloud under 2 m tall (a slice) is refused, and so is one whose stems mostly do not
    /// stand on ground returns (`MIN_GROUNDED_STEMS`: the ground was cut away), each saying
    /// what to give instead.
    #[default]
    Auto,
    /// A height-normalised cloud (as lidR's `normalize_height` or 3DFin write it): z is the
    /// height above the ground, so the ground is the plane z = 0 and points within the ground
    /// filter's `class_threshold_m` of it are ground, whether or not there are any.
    Normalised,
    /// One tree, already segmented, with the ground cut away and z not normalised (the input
    /// TreeQSM and ITSMe take): the ground is the horizontal plane through the stem's lowest
    /// point (the [`SEGMENTED_TREE_FOOT_QUANTILE`] of the points' z, so a stray point below
    /// does not move it), no point is ground, and every height (breast height, total height)
    /// is measured from that plane. Every point above `crowns.min_height_m` is the tree's:
    /// a piece of crown the graph does not join goes to the nearest stem
    /// (`crowns.assign_unreached`). Where the plot's band tests find no stem, they are
    /// relaxed ([`StemParams::for_one_tree`]) and the largest cluster is the stem.
    SegmentedTree,
}

/// Quantile of z taken as the foot of a `segmented_tree` cloud: its lowest point, robust to
/// a few stray returns below it (0.0005: 1 point in 2000).
pub const SEGMENTED_TREE_FOOT_QUANTILE: f64 = 0.0005;

/// Least height span of a cloud for `auto`, metres: the stems are followed from the ground
/// to above breast height, so a thinner cloud is a slice.
pub const MIN_CLOUD_HEIGHT_M: f32 = 2.0;

/// Least share of the stems that must stand on ground returns under `auto`: ground points in
/// at least `GROUND_SECTORS` of 8 sectors of the ring 0.3–1.0 m around the stem base, within
/// 0.3 m of the terrain height. Where the ground was cut away the ring at the stem's foot
/// is empty, since the cloth settled on the cut; where it is there, occlusion hides a few
/// sectors at most (docs/results/inventory.md gives the shares measured).
pub const MIN_GROUNDED_STEMS: f64 = 0.5;
/// Sectors of the ring around a stem's base that must hold ground points (of 8).
const GROUND_SECTORS: usize = 3;

/// Refuses a cloud whose stems mostly do not stand on ground returns (see
/// [`MIN_GROUNDED_STEMS`]); else (stems on ground, stems).
fn check_stems_stand_on_ground(
    pts: &[Vec3],
    heights: &[f32],
    is_ground: &[bool],
    stems: &[Stem],
) -> Result<(usize, usize), ForestError> {
    if stems.is_empty() {
        return Ok((0, 0));
    }
    // The ground points near the terrain, on a 1 m grid of x, y.
    let mut grid: std::collections::HashMap<(i64, i64), Vec<u32>> = Default::default();
    for (i, p) in pts.iter().enumerate() {
        if is_ground[i] && heights[i].abs() <= 0.3 {
            grid.entry((p.x.floor() as i64, p.y.floor() as i64))
                .or_default()
                .push(i as u32);
        }
    }
    let grounded = stems
        .iter()
        .filter(|s| {
            let mut sectors = [false; 8];
            let (cx, cy) = (s.base.x.floor() as i64, s.base.y.floor() as i64);
            for gx in cx - 1..=cx + 1 {
                for gy in cy - 1..=cy + 1 {
                    for &i in grid.get(&(gx, gy)).map_or(&[][..], Vec::as_slice) {
                        let d = (pts[i as usize] - s.base).truncate();
                        let r = d.length();
                        if (0.3..=1.0).contains(&r) {
                            let a = d.y.atan2(d.x) + std::f32::consts::PI;
                            let k = ((a / std::f32::consts::TAU * 8.0) as usize).min(7);
                            sectors[k] = true;
                        }
                    }
                }
            }
            sectors.iter().filter(|&&x| x).count() >= GROUND_SECTORS
        })
        .count();
    let share = grounded as f64 / stems.len() as f64;
    if share < MIN_GROUNDED_STEMS {
        return Err(ForestError::NotAPlot(format!(
            "only {grounded} of {} stems stand on ground returns (ground points around their \
             foot): the ground seems cut away, and heights and DBH are measured from the \
             ground. Give the cloud with its ground; if z is already the height above the \
             ground, set segment.cloud = \"normalised\"; if it is one tree cut out of its \
             plot (z not normalised), set segment.cloud = \"segmented_tree\", which measures \
             from the stem's lowest point (sylva inventory --params)",
            stems.len()
        )));
    }
    Ok((grounded, stems.len()))
}

/// The 0.5 % and 99.5 % quantiles of the heights of (at most 100 000 evenly taken) points.
fn z_span(points: &[Vec3]) -> (f32, f32) {
    let step = (points.len() / 100_000).max(1);
    let mut z: Vec<f32> = points
        .iter()
        .step_by(step)
        .map(|p| p.z)
        .filter(|z| z.is_finite())
        .collect();
    if z.is_empty() {
        return (0.0, 0.0);
    }
    z.sort_unstable_by(f32::total_cmp);
    let at = |q: f64| z[((z.len() - 1) as f64 * q).round() as usize];
    (at(0.005), at(0.995))
}

/// One tree of the inventory: one row of trees.csv.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TreeRow {
    /// 1-based id, the stem's id.
    pub tree_id: u32,
    /// Stem position where it meets the ground, in the cloud's original coordinates, metres.
    pub x: f64,
    pub y: f64,
    /// Ground height under the stem (DTM), original coordinates, metres.
    pub ground_z: f64,
    /// DBH from the LiDAR points, centimetres.
    pub dbh_lidar_cm: f64,
    /// DBH from the Gaussians, centimetres (filled by the splatting stage; `None` here).
    pub dbh_gs_cm: Option<f64>,
    /// Points used by the circle fit (inliers).
    pub n_points: usize,
    /// RMS residual of the circle fit, millimetres.
    pub rms_mm: f64,
    /// Share of 10° sectors holding a fitted point, [0, 1].
    pub arc_coverage: f64,
    /// good, partial_arc, fallback_slice or poor.
    pub quality: String,
    /// Quality flag of the Gaussian fit (filled by stage `dbh` beside `dbh_gs_cm`; `None`
    /// here, and in rows written before it existed).
    #[serde(default)]
    pub gs_quality: Option<FitQuality>,
    /// Total height, the tree's highest point above its stem base, metres (`forest::crowns`).
    /// This and the fields below read as `None` from rows written before they existed (serde
    /// takes a missing `Option` field as `None`).
    pub height_m: Option<f64>,
    /// Crown base height above the stem base, metres.
    pub crown_base_m: Option<f64>,
    /// Crown projection area (convex hull), m².
    pub crown_area_m2: Option<f64>,
    /// Diameter of the circle of the crown projection area, metres.
    pub crown_diameter_m: Option<f64>,
    /// Basal area from the LiDAR DBH, m².
    pub basal_area_m2: Option<f64>,
    /// Stem volume, m³ (`forest::allometry`, from the LiDAR DBH and the height).
    pub volume_m3: Option<f64>,
    /// Above-ground biomass, kg (Chave et al. 2014 eq. 4 by default).
    pub agb_kg: Option<f64>,
    /// Carbon, kg.
    pub carbon_kg: Option<f64>,
    /// How the tree's top was reached, so how far its height can be trusted
    /// ([`HeightQuality`]: connected, bridged or stem_only); `None` without a height.
    #[serde(default)]
    pub height_quality: Option<HeightQuality>,
    /// The longest gap in the stem's column crossed to reach the top, metres (with
    /// `height_quality` bridged).
    #[serde(default)]
    pub crown_gap_m: Option<f64>,
}

/// Wall-clock seconds of each inventory phase.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PhaseSeconds {
    pub ground: f64,
    pub segment: f64,
    pub stems: f64,
    pub dbh: f64,
    /// The tree segmentation and crown measures.
    #[serde(default)]
    pub crowns: f64,
}

/// The inventory of one cloud with its intermediate products.
#[derive(Debug, Clone)]
pub struct Inventory {
    pub trees: Vec<TreeRow>,
    /// The stems the rows came from (local coordinates), same order as `trees`.
    pub stems: Vec<Stem>,
    /// The diameter fits, same order as `trees`.
    pub dbh: Vec<StemDbh>,
    /// Wood/leaf label per point (leaf = 0, trunk = 1; ground points are 0).
    pub labels: Vec<u8>,
    /// Trunk probability per point, [0, 1] (ground points 0).
    pub trunk_probability: Vec<f32>,
    /// Ground mask per point.
    pub is_ground: Vec<bool>,
    /// The terrain model (local coordinates).
    pub dtm: Dtm,
    pub seconds: PhaseSeconds,
    /// The wood/leaf segmentation's own steps (within `seconds.segment`).
    pub segment_seconds: SegmentSeconds,
    /// Per point: the `tree_id` of its tree, 0 for none.
    pub tree_of_point: Vec<u32>,
    /// Each tree's crown, same order as `trees`.
    pub crowns: Vec<TreeCrown>,
    /// The cloud's footprint in its file coordinates (`forest::summary::footprint`).
    pub footprint: geo::Polygon<f64>,
}

impl Inventory {
    /// The stand figures of `rows` (these trees, or the same trees with their Gaussian DBH
    /// beside) on this cloud's plot.
    pub fn summary(
        &self,
        rows: &[TreeRow],
        params: &InventoryParams,
    ) -> Result<PlotSummary, ForestError> {
        summarise(rows, &self.footprint, &params.summary, &params.allometry)
    }
}

/// The ground of a height-normalised cloud: the plane at file z = 0 (local z = −`offset_z`)
/// as a one-cell DTM, and every point within `class_threshold_m` of it as ground.
fn normalised_ground(pts: &[Vec3], offset_z: f64, p: &CsfParams) -> super::ground::GroundResult {
    let zero = (-offset_z) as f32;
    let threshold = p.class_threshold_m as f32;
    flat_ground(zero, pts.iter().map(|q| q.z - zero <= threshold).collect())
}

/// A ground that is the horizontal plane at local height `z`, with the ground mask given.
fn flat_ground(z: f32, is_ground: Vec<bool>) -> super::ground::GroundResult {
    super::ground::GroundResult {
        is_ground,
        dtm: Dtm {
            origin: [0.0, 0.0],
            cell: 1.0,
            nx: 1,
            ny: 1,
            heights: vec![z],
        },
        iterations: 0,
    }
}

/// The ground of one segmented tree: the horizontal plane through its lowest point (see
/// [`CloudKind::SegmentedTree`]); no point is ground.
fn segmented_tree_ground(pts: &[Vec3]) -> super::ground::GroundResult {
    let mut z: Vec<f32> = pts.iter().map(|p| p.z).collect();
    let k = ((z.len().saturating_sub(1)) as f64 * SEGMENTED_TREE_FOOT_QUANTILE).round() as usize;
    let foot = if z.is_empty() {
        0.0
    } else {
        *z.select_nth_unstable_by(k, f32::total_cmp).1
    };
    flat_ground(foot, vec![false; pts.len()])
}

/// Runs ground → segmentation (non-ground points only) → stems → DBH on `cloud`.
pub fn inventory(
    cloud: &PointCloud,
    params: &InventoryParams,
    progress: &dyn Progress,
) -> Result<Inventory, ForestError> {
    params.allometry.validate()?;
    let pts = &cloud.positions;
    if pts.len() < params.segment.k.max(3) {
        return Err(ForestError::NotEnoughPoints(format!(
            "an inventory needs at least {} points, the cloud has {}",
            params.segment.k.max(3),
            pts.len()
        )));
    }
    let mut seconds = PhaseSeconds::default();
    let t = Instant::now();
    let (z_lo, z_hi) = z_span(pts);
    if params.cloud == CloudKind::Auto && z_hi - z_lo < MIN_CLOUD_HEIGHT_M {
        return Err(ForestError::NotAPlot(format!(
            "the cloud is only {:.2} m tall (z {:.2} to {:.2} m): a slice, not a plot or a \
             tree. Sylva finds the stems from the ground up and cuts its own breast-height \
             slice, so it needs the whole cloud, with the ground and the stems to at least \
             {MIN_CLOUD_HEIGHT_M} m",
            z_hi - z_lo,
            cloud.offset.z + f64::from(z_lo),
            cloud.offset.z + f64::from(z_hi)
        )));
    }
    let ground = match params.cloud {
        CloudKind::Auto => {
            progress.log("ground: cloth simulation");
            classify_ground(pts, &params.ground, &SubProgress::new(progress, 0.0, 0.1))?
        }
        CloudKind::Normalised => {
            progress.log("ground: z = 0 (a height-normalised cloud)");
            normalised_ground(pts, cloud.offset.z, &params.ground)
        }
        CloudKind::SegmentedTree => {
            progress.log("ground: the plane through the stem's lowest point (one segmented tree)");
            segmented_tree_ground(pts)
        }
    };
    let heights = ground.dtm.heights_above(pts);
    seconds.ground = t.elapsed().as_secs_f64();

    let t = Instant::now();
    progress.log("wood/leaf segmentation of the non-ground points");
    let include: Vec<bool> = ground.is_ground.iter().map(|g| !g).collect();
    let mut wood = segment_wood_leaf(
        pts,
        cloud.colors.as_deref(),
        Some(&include),
        &params.segment,
        &SubProgress::new(progress, 0.1, 0.7),
    )?;
    seconds.segment = t.elapsed().as_secs_f64();
    // The per-point features are not needed past the segmentation (40 B a point: 2.4 GB on a
    // paper-size plot, held through the stems and crowns otherwise).
    wood.features = Vec::new();
    wood.coarse = Vec::new();

    let t = Instant::now();
    progress.log("stems in the breast-height band");
    let stems = detect_stems(
        pts,
        &heights,
        &wood.labels,
        &ground.is_ground,
        &ground.dtm,
        &params.stems,
        &SubProgress::new(progress, 0.8, 0.1),
    )?;
    let stems = if stems.is_empty() && params.cloud == CloudKind::SegmentedTree {
        progress.log(
            "no stem passed the plot's band tests; the cloud is one tree, so its band's \
             largest cluster is taken as its stem (the tests relaxed: StemParams::for_one_tree)",
        );
        let relaxed = detect_stems(
            pts,
            &heights,
            &wood.labels,
            &ground.is_ground,
            &ground.dtm,
            &params.stems.for_one_tree(),
            &SubProgress::new(progress, 0.9, 0.0),
        )?;
        relaxed
            .into_iter()
            .max_by_key(|s| s.band_points)
            .map(|s| Stem { id: 1, ..s })
            .into_iter()
            .collect()
    } else {
        stems
    };
    if params.cloud == CloudKind::Auto {
        let (grounded, n) = check_stems_stand_on_ground(pts, &heights, &ground.is_ground, &stems)?;
        if n > 0 {
            progress.log(&format!("{grounded} of {n} stems stand on ground returns"));
        }
    }
    label_stem_points(
        pts,
        &heights,
        &ground.is_ground,
        &stems,
        &mut wood.labels,
        &mut wood.trunk_probability,
        &params.stem_labels,
    );
    seconds.stems = t.elapsed().as_secs_f64();

    let t = Instant::now();
    progress.log(&format!("DBH of {} stems", stems.len()));
    let total = stems.len().max(1);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let fits: Vec<Option<StemDbh>> = stems
        .par_iter()
        .map(|stem| {
            if progress.is_cancelled() {
                return None;
            }
            let d = measure_dbh(pts, stem, &params.dbh);
            let k = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.set(0.9 + 0.05 * k as f64 / total as f64);
            d
        })
        .collect();
    if progress.is_cancelled() {
        return Err(ForestError::Cancelled);
    }
    seconds.dbh = t.elapsed().as_secs_f64();

    // Every stem seeds its tree, also one without a diameter, so that its crown is not
    // handed to a neighbour; rows are written for the stems with a diameter.
    let t = Instant::now();
    progress.log("trees: crowns and heights");
    let crown_params = CrownParams {
        assign_unreached: params.crowns.assign_unreached
            || params.cloud == CloudKind::SegmentedTree,
        ..params.crowns.clone()
    };
    let seg = segment_trees_labelled(
        pts,
        &heights,
        &ground.is_ground,
        Some(&wood.labels),
        &stems,
        &crown_params,
        &SubProgress::new(progress, 0.95, 0.05),
    )?;
    let mut kept = Vec::new();
    let mut dbh = Vec::new();
    let mut trees = Vec::new();
    let mut crowns = Vec::new();
    // Row id of each stem index (0: no row).
    let mut row_of_stem = vec![0u32; stems.len()];
    for (k, ((stem, d), crown)) in stems.into_iter().zip(fits).zip(seg.trees).enumerate() {
        let Some(d) = d else {
            continue;
        };
        let id = trees.len() as u32 + 1;
        row_of_stem[k] = id;
        let dbh_cm = d.diameter_m * 100.0;
        let height = (crown.points > 0).then_some(crown.height_m);
        let allometry = tree_allometry(dbh_cm, height, &params.allometry);
        let with_area = crown.hull.len() >= 3;
        trees.push(TreeRow {
            tree_id: id,
            x: cloud.offset.x + stem.base.x as f64,
            y: cloud.offset.y + stem.base.y as f64,
            ground_z: cloud.offset.z + stem.base.z as f64,
            dbh_lidar_cm: dbh_cm,
            dbh_gs_cm: None,
            n_points: d.circle.fit.n,
            rms_mm: d.circle.fit.rms * 1000.0,
            arc_coverage: d.circle.arc_coverage,
            quality: d.quality.as_str().to_string(),
            gs_quality: None,
            height_m: height,
            crown_base_m: crown.crown_base_m,
            crown_area_m2: with_area.then_some(crown.crown_area_m2),
            crown_diameter_m: with_area.then_some(crown.crown_diameter_m),
            basal_area_m2: Some(allometry.basal_area_m2),
            volume_m3: allometry.volume_m3,
            agb_kg: allometry.agb_kg,
            carbon_kg: allometry.carbon_kg,
            height_quality: height.map(|_| crown.height_quality()),
            crown_gap_m: height.and(crown.gap_m),
        });
        kept.push(Stem { id, ..stem });
        dbh.push(d);
        crowns.push(crown);
    }
    let tree_of_point = seg
        .tree_of_point
        .iter()
        .map(|&t| {
            if t == NO_TREE {
                0
            } else {
                row_of_stem.get(t as usize).copied().unwrap_or(0)
            }
        })
        .collect();
    seconds.crowns = t.elapsed().as_secs_f64();
    progress.set(1.0);
    Ok(Inventory {
        trees,
        stems: kept,
        dbh,
        labels: wood.labels,
        trunk_probability: wood.trunk_probability,
        is_ground: ground.is_ground,
        dtm: ground.dtm,
        seconds,
        segment_seconds: wood.seconds,
        tree_of_point,
        crowns,
        footprint: footprint(pts, cloud.offset),
    })
}
