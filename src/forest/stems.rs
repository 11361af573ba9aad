//! Stem instances (docs/method.md Stage 3, "needed around it"): points in a band around breast
//! height (trunk-labelled only, or all non-ground: see [`StemParams::band_trunk_only`]) are
//! clustered in the horizontal plane; each cluster that shows a stem's circle becomes one tree
//! with an id, a base on the ground and an axis.
//!
//! Clustering is a grid flavour of DBSCAN: band points are binned into square cells of
//! `cluster_cell_m`; cells holding at least `min_cell_points` are occupied; occupied cells
//! touching (8-neighbourhood) form one cluster. It is linear in the number of points, where
//! point-wise DBSCAN is quadratic in the local density of a stem compressed onto the plane.
//!
//! The axis is a straight line fitted through circle centres of horizontal slices between
//! `axis_min_m` and `axis_max_m` above ground (least squares of x and y against z). It is
//! found in two rounds: first from the band cluster alone, then from every stem point within
//! reach of that first axis, so a leaning stem is followed below and above the band.

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ForestError;
use super::ground::Dtm;
use super::ransac::CircleParams;
use super::segment::TRUNK;
use super::stem_axis::{fit_axis, off_axis, slice_centres};
use super::stem_base::{base_on_dtm, base_on_local_ground};
use crate::progress::Progress;

/// Parameters of [`detect_stems`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct StemParams {
    /// Detection band above the DTM, metres (docs/method.md: "a band around breast height").
    pub band_min_m: f32,
    pub band_max_m: f32,
    /// Cell edge of the horizontal clustering grid, metres: gaps narrower than this inside a
    /// stem's arc are bridged; stems closer than this merge.
    pub cluster_cell_m: f32,
    /// Band points a cell needs to be occupied (drops isolated twigs and noise).
    pub min_cell_points: usize,
    /// Band points a cluster needs to be a stem candidate.
    pub min_cluster_points: usize,
    /// Share of the band's 10 cm layers a candidate must hold points in, [0, 1]: a stem is
    /// continuous through the band, a branch or a bush crossing it is not.
    pub min_vertical_fill: f32,
    /// Height range (above the DTM) of the slices that define the axis, metres.
    pub axis_min_m: f32,
    pub axis_max_m: f32,
    /// Thickness of one axis slice, metres.
    pub axis_slice_m: f32,
    /// Axes leaning more than this from the vertical are clamped to it, degrees.
    pub max_lean_deg: f32,
    /// Stem points are those within the first radius estimate plus this margin of the axis,
    /// metres.
    pub axis_margin_m: f32,
    /// Cluster only trunk-labelled points in the band (docs/method.md's wording) when true; when
    /// false (the default) every non-ground band point is clustered and the stem tests below
    /// (vertical fill, a circle in the slices) decide. Why: on dense TLS the bark of a stem
    /// is locally planar at k = 20, and the 2-means puts most of it with the leaves (TreeLS
    /// pine.laz: 5% of the 1–2 m band labelled trunk). On TreeLS pine_plot.laz trunk-only
    /// finds 11 stems, all points 16 (~15 real ones and one cut by the plot corner); on the
    /// generated plot both find all 14 with no false stem.
    pub band_trunk_only: bool,
    /// Use leaf-labelled non-ground points near the axis as well when fitting slices. The
    /// band clustering always uses trunk points only. Helps where bark is mislabelled leaf;
    /// the RANSAC fit rejects the clutter this adds.
    pub include_leaf_points: bool,
    /// Circle fitting of the axis slices.
    pub circle: CircleParams,
}

impl Default for StemParams {
    fn default() -> Self {
        Self {
            band_min_m: 1.0,
            band_max_m: 2.0,
            cluster_cell_m: 0.05,
            min_cell_points: 2,
            min_cluster_points: 30,
            min_vertical_fill: 0.6,
            axis_min_m: 0.5,
            axis_max_m: 3.0,
            axis_slice_m: 0.25,
            max_lean_deg: 30.0,
            axis_margin_m: 0.1,
            band_trunk_only: false,
            include_leaf_points: true,
            circle: CircleParams::default(),
        }
    }
}

impl StemParams {
    /// The band tests relaxed for a cloud known to hold one tree (`segment.cloud =
    /// "segmented_tree"`), tried when the plot's tests find no stem in it: a cell needs one
    /// point, a cluster 10, and no vertical fill is asked. In a plot those tests tell a stem
    /// from a branch or a bush crossing the band; in one tree the question is only where its
    /// stem is, and the caller keeps the cluster with the most band points. Why: a sparse
    /// street scan (AdTree's tree13, 6,992 points) holds 40 points of its stem in the band, one
    /// a 5 cm cell, and foliage hides the stem above 1.3 m, so the band is 30 % filled.
    pub fn for_one_tree(&self) -> Self {
        Self {
            min_cell_points: 1,
            min_cluster_points: self.min_cluster_points.min(10),
            min_vertical_fill: 0.0,
            ..self.clone()
        }
    }
}

/// One stem: where it stands, how it leans and the points that belong to it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stem {
    /// 1-based id, stems ordered by base x, then y.
    pub id: u32,
    /// Where the axis meets the ground (local coordinates, metres): a plane fitted to the
    /// ground points around the stem, or the DTM where too few are near.
    pub base: Vec3,
    /// Unit axis direction, pointing up.
    pub axis: Vec3,
    /// Angle between the axis and the vertical, degrees.
    pub lean_deg: f32,
    /// Radius of the first slice fit, metres (a guide for the DBH slice, not the DBH).
    pub radius_estimate: f32,
    /// Trunk points of the band cluster.
    pub band_points: usize,
    /// Indices of the points within reach of the axis between `axis_min_m` - 0.3 m and
    /// `axis_max_m` above ground: the candidates for the DBH slices.
    pub points: Vec<u32>,
}

/// Finds stems among the trunk points. `heights` are heights above the DTM per point,
/// `labels` the wood/leaf labels and `is_ground` the ground mask, all one per point.
pub fn detect_stems(
    points: &[Vec3],
    heights: &[f32],
    labels: &[u8],
    is_ground: &[bool],
    dtm: &Dtm,
    params: &StemParams,
    progress: &dyn Progress,
) -> Result<Vec<Stem>, ForestError> {
    let n = points.len();
    if heights.len() != n || labels.len() != n || is_ground.len() != n {
        return Err(ForestError::Params(
            "heights, labels and ground mask need one entry per point".into(),
        ));
    }
    if !(params.cluster_cell_m > 0.0
        && params.band_max_m > params.band_min_m
        && params.axis_max_m > params.axis_min_m
        && params.axis_slice_m > 0.0)
    {
        return Err(ForestError::Params(
            "stem band, axis range, slice and cell sizes must be positive".into(),
        ));
    }
    let band: Vec<u32> = (0..n as u32)
        .filter(|&i| {
            let h = heights[i as usize];
            (labels[i as usize] == TRUNK || !params.band_trunk_only)
                && !is_ground[i as usize]
                && h >= params.band_min_m
                && h < params.band_max_m
        })
        .collect();
    let clusters = grid_clusters(points, &band, params);
    progress.set(0.2);
    // Points that may belong to a stem: non-ground, in the axis range (with slack for the
    // fallback slices and lean), trunk unless leaf points are wanted. Bucketed on a 0.5 m
    // grid for quick gathering.
    let lo = params.axis_min_m.min(params.band_min_m) - 0.3;
    let hi = params.axis_max_m.max(params.band_max_m) + 0.3;
    let candidates: Vec<u32> = (0..n as u32)
        .filter(|&i| {
            let i = i as usize;
            !is_ground[i]
                && heights[i] >= lo
                && heights[i] <= hi
                && (params.include_leaf_points || labels[i] == TRUNK)
        })
        .collect();
    let buckets = Buckets::new(points, &candidates, 0.5);
    // Each cluster is followed on its own (in parallel); ids in cluster order.
    let done = std::sync::atomic::AtomicUsize::new(0);
    let found: Vec<Option<Stem>> = clusters
        .par_iter()
        .map(|cluster| {
            if progress.is_cancelled() {
                return None;
            }
            let stem = stem_from_cluster(points, heights, cluster, &buckets, dtm, params);
            let c = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.set(0.2 + 0.8 * c as f64 / clusters.len().max(1) as f64);
            stem
        })
        .collect();
    if progress.is_cancelled() {
        return Err(ForestError::Cancelled);
    }
    let mut stems = Vec::new();
    for stem in found.into_iter().flatten() {
        stems.push(Stem {
            id: stems.len() as u32 + 1,
            ..stem
        });
    }
    let mut stems = merge_duplicates(stems);
    let ground: Vec<u32> = (0..n as u32).filter(|&i| is_ground[i as usize]).collect();
    let ground = Buckets::new(points, &ground, 0.5);
    stems.par_iter_mut().enumerate().for_each(|(k, s)| {
        s.id = k as u32 + 1;
        if let Some(base) = base_on_local_ground(points, &ground, dtm, s, params) {
            s.base = base;
        }
    });
    progress.set(1.0);
    Ok(stems)
}

/// Band clusters (lists of point indices), ordered by their lowest cell.
fn grid_clusters(points: &[Vec3], band: &[u32], params: &StemParams) -> Vec<Vec<u32>> {
    use std::collections::HashMap;
    let cell = params.cluster_cell_m;
    let key = |p: Vec3| ((p.x / cell).floor() as i64, (p.y / cell).floor() as i64);
    let mut cells: HashMap<(i64, i64), Vec<u32>> = HashMap::new();
    for &i in band {
        cells.entry(key(points[i as usize])).or_default().push(i);
    }
    let mut occupied: Vec<(i64, i64)> = cells
        .iter()
        .filter(|(_, v)| v.len() >= params.min_cell_points)
        .map(|(k, _)| *k)
        .collect();
    occupied.sort_unstable();
    let mut seen: HashMap<(i64, i64), bool> = occupied.iter().map(|k| (*k, false)).collect();
    let mut out = Vec::new();
    for &start in &occupied {
        if seen.get(&start).copied().unwrap_or(true) {
            continue;
        }
        seen.insert(start, true);
        let mut stack = vec![start];
        let mut members = Vec::new();
        while let Some((x, y)) = stack.pop() {
            if let Some(v) = cells.get(&(x, y)) {
                members.extend_from_slice(v);
            }
            for dx in -1..=1 {
                for dy in -1..=1 {
                    let k = (x + dx, y + dy);
                    if seen.get(&k) == Some(&false) {
                        seen.insert(k, true);
                        stack.push(k);
                    }
                }
            }
        }
        if members.len() >= params.min_cluster_points {
            out.push(members);
        }
    }
    out
}

/// Candidate points bucketed on a coarse horizontal grid.
pub(crate) struct Buckets {
    cell: f32,
    map: std::collections::HashMap<(i64, i64), Vec<u32>>,
}

impl Buckets {
    pub(crate) fn new(points: &[Vec3], idx: &[u32], cell: f32) -> Self {
        let mut map: std::collections::HashMap<(i64, i64), Vec<u32>> = Default::default();
        for &i in idx {
            let p = points[i as usize];
            map.entry(((p.x / cell).floor() as i64, (p.y / cell).floor() as i64))
                .or_default()
                .push(i);
        }
        Buckets { cell, map }
    }
    /// Points whose horizontal position lies within `r` of `c` (a superset filter by cell).
    pub(crate) fn near(&self, c: Vec2, r: f32) -> Vec<u32> {
        let (x0, x1) = (
            ((c.x - r) / self.cell).floor() as i64,
            ((c.x + r) / self.cell).floor() as i64,
        );
        let (y0, y1) = (
            ((c.y - r) / self.cell).floor() as i64,
            ((c.y + r) / self.cell).floor() as i64,
        );
        let mut out = Vec::new();
        for x in x0..=x1 {
            for y in y0..=y1 {
                if let Some(v) = self.map.get(&(x, y)) {
                    out.extend_from_slice(v);
                }
            }
        }
        out
    }
}

fn stem_from_cluster(
    points: &[Vec3],
    heights: &[f32],
    cluster: &[u32],
    buckets: &Buckets,
    dtm: &Dtm,
    params: &StemParams,
) -> Option<Stem> {
    // Vertical continuity through the band.
    let layers = ((params.band_max_m - params.band_min_m) / 0.1)
        .ceil()
        .max(1.0) as usize;
    let mut filled = vec![false; layers];
    for &i in cluster {
        let k = ((heights[i as usize] - params.band_min_m) / 0.1) as usize;
        filled[k.min(layers - 1)] = true;
    }
    if (filled.iter().filter(|f| **f).count() as f32) < params.min_vertical_fill * layers as f32 {
        return None;
    }
    // Round 1: the band cluster alone.
    let band_params = StemParams {
        axis_min_m: params.band_min_m,
        axis_max_m: params.band_max_m,
        ..params.clone()
    };
    let first = slice_centres(points, heights, cluster, &band_params);
    let (origin, axis) = fit_axis(&first, params.max_lean_deg)?;
    let mut radii: Vec<f32> = first.iter().map(|c| c.2).collect();
    radii.sort_by(f32::total_cmp);
    let r0 = radii[radii.len() / 2];
    // Round 2: every candidate within reach of the first axis, over the full axis range.
    let reach = r0 + params.axis_margin_m;
    let slack = (params.axis_max_m - params.band_min_m) * params.max_lean_deg.to_radians().tan();
    let near: Vec<u32> = buckets
        .near(origin.truncate(), reach + slack.min(1.0))
        .into_iter()
        .filter(|&i| off_axis(points[i as usize], origin, axis) <= reach)
        .collect();
    let second = slice_centres(points, heights, &near, params);
    let (origin, axis) = if second.len() >= 2 {
        fit_axis(&second, params.max_lean_deg)?
    } else {
        (origin, axis)
    };
    let near: Vec<u32> = near
        .into_iter()
        .filter(|&i| off_axis(points[i as usize], origin, axis) <= reach)
        .collect();
    let base = base_on_dtm(origin, axis, dtm);
    Some(Stem {
        id: 0,
        base,
        axis,
        lean_deg: axis.z.clamp(-1.0, 1.0).acos().to_degrees(),
        radius_estimate: r0,
        band_points: cluster.len(),
        points: near,
    })
}

/// Two band clusters of one stem (split by a gap in its arc) give two stems whose axes pass
/// within the larger radius of each other at breast height: keep the one from more band
/// points, and give it the union of both point sets.
fn merge_duplicates(mut stems: Vec<Stem>) -> Vec<Stem> {
    stems.sort_by_key(|s| std::cmp::Reverse(s.band_points));
    let at = |s: &Stem| s.base + s.axis * (1.3 / s.axis.z.max(0.1));
    let mut out: Vec<Stem> = Vec::new();
    for s in stems {
        let p = at(&s);
        match out.iter_mut().find(|o| {
            at(o).truncate().distance(p.truncate()) < o.radius_estimate.max(s.radius_estimate)
        }) {
            Some(o) => {
                o.points.extend_from_slice(&s.points);
                o.points.sort_unstable();
                o.points.dedup();
            }
            None => out.push(s),
        }
    }
    out.sort_by(|a, b| {
        a.base
            .x
            .total_cmp(&b.base.x)
            .then(a.base.y.total_cmp(&b.base.y))
    });
    out
}
