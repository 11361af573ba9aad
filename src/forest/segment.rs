//! Wood/leaf segmentation (docs/method.md Stage 3, paper 3.4): eigen features of the k = 20
//! nearest neighbours, colour at weight 0.5, deterministic 2-means on standardised features,
//! trunk = the cluster with the higher mean linearity, then small-component clean-up on the
//! k-NN graph.
//!
//! On forest clouds the ground is planar and would pull the planarity feature (and the
//! clusters) towards itself although it is not wood, so callers pass a mask and only the
//! non-ground points are segmented; masked-out points get label leaf (0) and probability 0.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::ForestError;
use super::components::{GRAPH_K, KnnGraph, relabel_small_components};
use super::grid::{map_radius_covariance, voxel_centroids};
use super::kmeans::{KMeans, distance2_to_centre, kmeans, standardise};
use crate::geom::{EigenFeatures, PointIndex, covariance, symmetric_eigen3};
use crate::progress::{Progress, SubProgress};

/// Label of leaf (and everything that is not wood), docs/method.md Stage 3.
pub const LEAF: u8 = 0;
/// Label of trunk and main branches, docs/method.md Stage 3.
pub const TRUNK: u8 = 1;

/// Parameters of the wood/leaf segmentation; defaults from paper 3.4.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentParams {
    /// Neighbours per point for the covariance, the point itself included (paper 3.4: 20).
    /// The clean-up graph uses the nearest `min(k, 20)` other points.
    pub k: usize,
    /// Weight of the colour features (r, g, b in [0, 1], standardised) against the three
    /// geometric ones (paper 3.4: 0.5). Ignored when the cloud has no colour.
    pub colour_weight: f32,
    /// Same-label components smaller than this many points are relabelled (paper 3.4: 50).
    pub tau_c: usize,
    /// Most Lloyd iterations of the 2-means.
    pub max_iterations: usize,
    /// Seed of the deterministic k-means++ initialisation.
    pub seed: u64,
    /// Radii of the coarse-scale neighbourhoods, metres; each adds linearity, planarity,
    /// sphericity and verticality to the features of the 2-means (see [`coarse_features`]).
    /// Empty: docs/method.md's single k = 20 scale only. Default [0.3, 0.6]: at 0.3 m a branch
    /// is a line and a leaf (the generator's discs are 16 cm across) a plane or a blob; at
    /// 0.6 m a leaf cluster is a blob. Measured on five generated stands (1 cm noise), trunk
    /// recall / precision were 0.45 / 0.16 with k = 20 alone, 0.72 / 0.60 with [0.3],
    /// 0.84 / 0.82 with [0.15, 0.3], 0.82 / 0.98 with [0.3, 0.6] and 0.80 / 0.99 with
    /// [0.3, 0.6, 1.0] (before the stem-guided relabelling; seed 1).
    pub coarse_radii_m: Vec<f32>,
    /// Trunk labels grow along the k-NN graph into leaf-labelled points whose linearity at
    /// the first coarse scale is at least this, [0, 1] (above 1: only the fine line test below). Why: a thin
    /// branch running into a leaf cluster shares its coarse neighbourhood with the leaves
    /// and the 2-means calls it leaf, but it stays a line at 0.3 m and is connected to the
    /// wood it grows from; isolated linear bits of foliage are not. Measured on generated
    /// stand seed 1 (trunk recall / precision): none 0.84 / 0.98, 0.7: 0.85 / 0.98, 0.55:
    /// 0.87 / 0.95, 0.5: 0.88 / 0.92 (seeds 1–5: 0.879–0.883 / 0.912–0.933), 0.45:
    /// 0.89 / 0.86, 0.35: 0.92 / 0.63. 0.5 keeps precision well above 0.85 at the cost of
    /// the last points of recall: below it the growth leaks into the foliage.
    pub grow_linearity: f32,
    /// Radius of the fine line test of the growth, metres (0 turns it off). A leaf-labelled
    /// point that fails `grow_linearity` still joins a growing trunk component when the raw
    /// points within this radius form a thin line: linearity >= `fine_line_linearity` and a
    /// spread across the line (`sqrt(l2)`) of at most `fine_line_spread_m`. Why: the
    /// generator's secondary branches (radius 6–10 mm) run through leaf clusters 1.0–1.4 m
    /// across, so at 0.3 m their neighbourhood is mostly leaves; at 0.1 m (less than the
    /// 8 cm leaf discs' radius plus the branch's own length) the branch is a line again and
    /// a leaf disc a plane. Computed lazily, only for the points the growth reaches.
    pub fine_line_radius_m: f32,
    /// Least linearity of the fine line test, [0, 1] (above 1: off). Measured on generated
    /// stand seed 2 (trunk recall / precision; without the fine test 0.88 / 0.92): 0.8 with no
    /// angle condition 0.897 / 0.881 (0.75: 0.901 / 0.858, leaves leak in); with the 30°
    /// condition 0.8: 0.895 / 0.910, 0.7: 0.899 / 0.903, 0.6: 0.899 / 0.897 (0.7 and 45°:
    /// 0.900 / 0.893). Spread 0.018 / 0.025 / 0.03 m changed recall by 0.01 at most (seed 1).
    pub fine_line_linearity: f32,
    /// Largest spread across the line of the fine line test, metres: `sqrt(l2)` of a branch
    /// of radius r with range noise sigma is about `sqrt(r²/2 + sigma²)`, 1.2 cm for r = 8 mm
    /// and sigma = 1 cm (docs/method.md's handheld-scanner noise); 0.025 m admits branches up to
    /// about 3 cm radius, thicker ones are lines at 0.3 m already.
    pub fine_line_spread_m: f32,
    /// Largest angle between a candidate's fine line and the principal direction of the
    /// trunk point it grows from, degrees: a branch is straight over a few centimetres, so
    /// 30° follows its bends (the generator's bend at most ~20° per segment) and rejects
    /// leaves that pass the line test beside it at a random angle.
    pub fine_line_max_angle_deg: f32,
    /// Least linearity of a lone line point, [0, 1] (above 1: off). After the growth along
    /// lines, a leaf-labelled point whose raw points within `fine_line_radius_m` form a very
    /// thin, straight line (linearity >= this, spread across it <= `lone_line_spread_m`)
    /// becomes trunk. The growth does not start from these points: tried as its seeds they
    /// leaked into the foliage (seed 4: 0.929 / 0.746). Why: on the generated stands the
    /// wood the growth missed lies mostly 0.15–1 m from any trunk-labelled point (median
    /// 0.38 m, seed 5), in fragments of a branch cut off from the labelled wood by leaves or
    /// scan shadow, so no growth from the trunk reaches it. Measured on seed 5 (0.1 m): of the
    /// missed wood 10 % passes 0.9 / 1.5 cm, of the leaf 0.3 %; 0.7 / 2.5 cm lets 5.6 % of
    /// the leaf in.
    pub lone_line_linearity: f32,
    /// Largest spread across the line of a lone line point, metres (see `lone_line_linearity`);
    /// 0.015 m is the spread of a 6 mm branch under 1 cm range noise plus a margin.
    pub lone_line_spread_m: f32,
    /// Only leaf-labelled points whose linearity at the first coarse scale is at least this
    /// are tested as lone line points, [0, 1]: a cheap filter that spares the radius query in
    /// foliage (0 tests every leaf-labelled point).
    pub lone_line_min_coarse_linearity: f32,
    /// Voxel edge of each coarse scale as a share of its radius (0 turns the coarse scales
    /// off). 0.125: eight voxels per radius keep a neighbourhood at a few hundred voxels on a
    /// stem and a few dozen on a branch, whatever the radius; measured on seed 1, 0.1 gave the
    /// same labels (±0.1 %) in twice the time.
    pub coarse_voxel_ratio: f32,
}

impl Default for SegmentParams {
    fn default() -> Self {
        Self {
            k: 20,
            colour_weight: 0.5,
            tau_c: 50,
            max_iterations: 100,
            seed: 20_260_611,
            coarse_radii_m: vec![0.3, 0.6],
            coarse_voxel_ratio: 0.125,
            grow_linearity: 0.5,
            fine_line_radius_m: 0.1,
            fine_line_linearity: 0.7,
            fine_line_spread_m: 0.025,
            fine_line_max_angle_deg: 30.0,
            lone_line_linearity: 0.9,
            lone_line_spread_m: 0.015,
            lone_line_min_coarse_linearity: 0.0,
        }
    }
}

/// Per-point wood/leaf labels with the trunk probability kept for the trainer.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct WoodLeaf {
    /// [`LEAF`] or [`TRUNK`] per input point.
    pub labels: Vec<u8>,
    /// Trunk probability in [0, 1] per input point: `d_leaf / (d_leaf + d_trunk)` with the
    /// distances in standardised feature space to the two cluster centres; for a point whose
    /// label the clean-up flipped, `1 - P`, so `P >= 0.5` exactly when the label is trunk.
    pub trunk_probability: Vec<f32>,
    /// Eigen features of every input point (zero for masked-out points).
    pub features: Vec<EigenFeatures>,
    /// Coarse-scale features of every input point (zero for masked-out points; empty when
    /// the coarse scale is off).
    pub coarse: Vec<CoarseFeatures>,
    /// Points whose label the component clean-up changed.
    pub relabelled: usize,
    /// Lloyd iterations of the 2-means.
    pub iterations: usize,
    /// Points the line seeds and the growth along lines labelled trunk.
    pub grown: usize,
    /// Wall-clock seconds of each step.
    pub seconds: SegmentSeconds,
}

/// Wall-clock seconds of the steps of [`segment_wood_leaf`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SegmentSeconds {
    /// k-d tree and k = 20 neighbourhoods (features and the clean-up graph).
    pub knn: f64,
    /// Coarse-scale features, all scales.
    pub coarse: f64,
    /// Standardisation and the 2-means.
    pub kmeans: f64,
    /// Component clean-up and growth along lines.
    pub cleanup: f64,
}

/// Segments `points` into wood and leaf. `colors` (8-bit sRGB) are used when given;
/// `include[i] == false` leaves point `i` out (label leaf, probability 0).
pub fn segment_wood_leaf(
    points: &[Vec3],
    colors: Option<&[[u8; 3]]>,
    include: Option<&[bool]>,
    params: &SegmentParams,
    progress: &dyn Progress,
) -> Result<WoodLeaf, ForestError> {
    if params.k < 3 || !params.colour_weight.is_finite() || params.colour_weight < 0.0 {
        return Err(ForestError::Params(format!(
            "segmentation needs k >= 3 and a finite colour weight >= 0 (k = {}, w = {})",
            params.k, params.colour_weight
        )));
    }
    if colors.is_some_and(|c| c.len() != points.len())
        || include.is_some_and(|m| m.len() != points.len())
    {
        return Err(ForestError::Params(
            "colours and mask must have one entry per point".into(),
        ));
    }
    let mut selected: Vec<u32> = (0..points.len() as u32)
        .filter(|&i| include.is_none_or(|m| m[i as usize]))
        .collect();
    // Work in Morton (Z-order) order of 5 cm cells: consecutive queries are neighbours in
    // space, so the k-NN search's radius hint and the caches stay warm (the order changes
    // no feature; the k-means++ seeding and warm-start subsamples are strided over it).
    spatial_sort(points, &mut selected, 0.05);
    if selected.len() < params.k.max(2) {
        return Err(ForestError::NotEnoughPoints(format!(
            "wood/leaf segmentation needs at least {} points, got {}",
            params.k.max(2),
            selected.len()
        )));
    }
    let mut seconds = SegmentSeconds::default();
    let clock = Instant::now();
    let sub: Vec<Vec3> = selected.iter().map(|&i| points[i as usize]).collect();
    let index = PointIndex::new(&sub)?;
    progress.set(0.05);

    // One k-NN pass: features and the clean-up graph.
    let k = params.k;
    let recs: Vec<(EigenFeatures, [u32; GRAPH_K])> = index.map_knn(
        &sub,
        k.max(GRAPH_K + 1),
        &SubProgress::new(progress, 0.05, 0.5),
        |i, nb| {
            let mine = &nb[..k.min(nb.len())];
            let feat = covariance(&sub, mine.iter().map(|m| m.index as usize))
                .filter(|_| mine.len() >= 3)
                .map(|(cov, _)| {
                    let e = symmetric_eigen3(cov);
                    EigenFeatures::from_eigenvalues(e.values.map(|v| v.max(0.0) as f32))
                })
                .unwrap_or_default();
            let mut g = [u32::MAX; GRAPH_K];
            for (slot, m) in g
                .iter_mut()
                .zip(nb.iter().filter(|m| m.index as usize != i))
                .take(k.min(GRAPH_K))
            {
                *slot = m.index;
            }
            (feat, g)
        },
    )?;
    // Split without a second copy of the records (92 B a point: 4.6 GB for the 50 M
    // non-ground points of a paper-size plot): the features are copied out (12 B a point),
    // then the neighbour lists are collected in place of the records.
    let features: Vec<EigenFeatures> = recs.iter().map(|r| r.0).collect();
    let neighbours: Vec<[u32; GRAPH_K]> = recs.into_iter().map(|r| r.1).collect();
    seconds.knn = clock.elapsed().as_secs_f64();
    let clock = Instant::now();

    let mut coarse: Vec<Vec<CoarseFeatures>> = Vec::new();
    if params.coarse_voxel_ratio > 0.0 {
        let n_scales = params.coarse_radii_m.len().max(1) as f64;
        for (s, &r) in params.coarse_radii_m.iter().enumerate() {
            coarse.push(coarse_features(
                &sub,
                params.coarse_voxel_ratio * r,
                r,
                &SubProgress::new(progress, 0.55 + 0.15 * s as f64 / n_scales, 0.15 / n_scales),
            )?);
        }
    }

    seconds.coarse = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    let (rows, dim) = feature_rows(&features, &coarse, colors, &selected, params.colour_weight);
    let km = kmeans(
        &rows,
        dim,
        2,
        params.max_iterations,
        params.seed,
        &SubProgress::new(progress, 0.7, 0.2),
    )?;
    let (mut labels, mut prob) = trunk_cluster(&km, &rows, dim, &features, &coarse);
    // What the clustering alone needed goes before the clean-up and the output (the rows are
    // 56 B a point with colour and two coarse scales: 2.8 GB on a paper-size plot).
    let iterations = km.iterations;
    drop(rows);
    drop(km);
    if progress.is_cancelled() {
        return Err(ForestError::Cancelled);
    }
    seconds.kmeans = clock.elapsed().as_secs_f64();
    let clock = Instant::now();
    let before = labels.clone();
    let graph = KnnGraph { neighbours };
    let relabelled = relabel_small_components(&mut labels, &graph, params.tau_c);
    for ((p, l), b) in prob.iter_mut().zip(&labels).zip(&before) {
        if l != b {
            *p = 1.0 - *p;
        }
    }
    let mut n_grown = 0;
    if let Some(first) = coarse.first() {
        let line = FineLine {
            points: &sub,
            index: &index,
            radius: params.fine_line_radius_m,
            min_linearity: params.fine_line_linearity,
            max_spread: params.fine_line_spread_m,
            min_cos: params.fine_line_max_angle_deg.to_radians().cos(),
        };
        let grown = grow_along_lines(&mut labels, &graph, first, params.grow_linearity, &line);
        for &j in &grown {
            prob[j as usize] = prob[j as usize].max(0.5);
        }
        n_grown += grown.len();
        let lone = lone_lines(
            &labels,
            first,
            &line,
            params.lone_line_linearity,
            params.lone_line_spread_m,
            params.lone_line_min_coarse_linearity,
        );
        for &j in &lone {
            labels[j as usize] = TRUNK;
            prob[j as usize] = prob[j as usize].max(0.5);
        }
        n_grown += lone.len();
    }
    seconds.cleanup = clock.elapsed().as_secs_f64();
    progress.set(1.0);
    // The neighbour graph (80 B a point) and the index go before the per-point output.
    drop(graph);
    drop(index);
    drop(before);
    // Only the last coarse scale goes to the output.
    let last_coarse = coarse.pop();
    drop(coarse);

    let mut out = WoodLeaf {
        labels: vec![LEAF; points.len()],
        trunk_probability: vec![0.0; points.len()],
        features: vec![EigenFeatures::default(); points.len()],
        coarse: if last_coarse.is_some() {
            vec![CoarseFeatures::default(); points.len()]
        } else {
            Vec::new()
        },
        relabelled,
        iterations,
        grown: n_grown,
        seconds,
    };
    for (j, &i) in selected.iter().enumerate() {
        out.labels[i as usize] = labels[j];
        out.trunk_probability[i as usize] = prob[j].clamp(0.0, 1.0);
        out.features[i as usize] = features[j];
        if let Some(c) = &last_coarse {
            out.coarse[i as usize] = c[j];
        }
    }
    Ok(out)
}

/// Feature rows [L, P, S, (coarse L, P, S, verticality), (w r, w g, w b)], one per selected
/// point, standardised column-wise, then the colour weighted by `colour_weight`. Returns the
/// rows (row-major) and their width.
fn feature_rows(
    features: &[EigenFeatures],
    coarse: &[Vec<CoarseFeatures>],
    colors: Option<&[[u8; 3]]>,
    selected: &[u32],
    colour_weight: f32,
) -> (Vec<f32>, usize) {
    let geo = 3 + 4 * coarse.len();
    let dim = geo + if colors.is_some() { 3 } else { 0 };
    let mut rows = Vec::with_capacity(features.len() * dim);
    for (j, f) in features.iter().enumerate() {
        rows.extend([f.linearity, f.planarity, f.sphericity]);
        for c in coarse {
            let c = c[j];
            rows.extend([
                c.eigen.linearity,
                c.eigen.planarity,
                c.eigen.sphericity,
                c.verticality,
            ]);
        }
        if let Some(c) = colors {
            let c = c[selected[j] as usize];
            rows.extend(c.map(|v| v as f32 / 255.0));
        }
    }
    standardise(&mut rows, dim);
    if dim > geo {
        for row in rows.chunks_mut(dim) {
            row[geo..].iter_mut().for_each(|v| *v *= colour_weight);
        }
    }
    (rows, dim)
}

/// Labels from the 2-means: trunk is the cluster with the higher mean linearity (fine plus
/// coarse scales). The trunk probability of a row is its distance to the leaf centre over
/// the sum of its distances to both (0.5 when it sits on both).
fn trunk_cluster(
    km: &KMeans,
    rows: &[f32],
    dim: usize,
    features: &[EigenFeatures],
    coarse: &[Vec<CoarseFeatures>],
) -> (Vec<u8>, Vec<f32>) {
    let (mut lin, mut cnt) = ([0.0f64; 2], [0usize; 2]);
    for (j, (f, &a)) in features.iter().zip(&km.assignment).enumerate() {
        let coarse_lin: f32 = coarse.iter().map(|c| c[j].eigen.linearity).sum();
        lin[a as usize] += (f.linearity + coarse_lin) as f64;
        cnt[a as usize] += 1;
    }
    let mean = |c: usize| lin[c] / cnt[c].max(1) as f64;
    let trunk_cluster = usize::from(mean(1) > mean(0));
    let labels: Vec<u8> = km
        .assignment
        .iter()
        .map(|&a| {
            if a as usize == trunk_cluster {
                TRUNK
            } else {
                LEAF
            }
        })
        .collect();
    let prob: Vec<f32> = rows
        .chunks(dim)
        .map(|row| {
            let dt = distance2_to_centre(km, dim, row, trunk_cluster).sqrt();
            let dl = distance2_to_centre(km, dim, row, 1 - trunk_cluster).sqrt();
            if dt + dl > 0.0 { dl / (dt + dl) } else { 0.5 }
        })
        .collect();
    (labels, prob)
}

/// Shape of a point's surroundings at the coarse scale: eigen features of the voxel centroids
/// within `radius` of its voxel's centroid, and the verticality `|e1 · z|` of the principal
/// direction (1 for a vertical line, 0 for a horizontal one).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CoarseFeatures {
    pub eigen: EigenFeatures,
    pub verticality: f32,
    /// Spread across the principal direction, `sqrt(l2)`, metres: about a branch's radius
    /// (plus noise) on a branch, larger in foliage.
    pub spread_m: f32,
    /// Voxels in the neighbourhood.
    pub voxels: u32,
    /// Extent along the principal direction, `sqrt(l1)`, metres.
    pub extent_m: f32,
}

/// Coarse-scale features of every point of `points`.
///
/// Why a second scale: with handheld-scanner range noise of about 1 cm (docs/method.md), the
/// k = 20 neighbourhood of a dense cloud spans 2–3 cm, so its shape is mostly noise: bark,
/// twigs and leaves all look like blobs or small planes. At ~15 cm a branch is a line, a
/// stem a curved sheet and a leaf cluster a blob or a disc, whatever the noise. The cloud is
/// first homogenised on a grid of edge `voxel` (centroid per voxel, as docs/method.md Stage 2.1
/// does for the anchors), so the neighbourhood is measured in space, not in point counts,
/// and dense near-scanner patches do not dominate; each point takes its voxel's features.
pub fn coarse_features(
    points: &[Vec3],
    voxel: f32,
    radius: f32,
    progress: &dyn Progress,
) -> Result<Vec<CoarseFeatures>, ForestError> {
    if !(voxel > 0.0 && radius > voxel && radius.is_finite()) {
        return Err(ForestError::Params(format!(
            "coarse features need 0 < voxel < radius (voxel {voxel} m, radius {radius} m)"
        )));
    }
    let (member, centres) = voxel_centroids(points, voxel);
    let per_voxel: Vec<CoarseFeatures> =
        map_radius_covariance(&centres, radius, progress, |n, cov| {
            if n < 3 {
                return CoarseFeatures::default();
            }
            let e = symmetric_eigen3(cov);
            CoarseFeatures {
                eigen: EigenFeatures::from_eigenvalues(e.values.map(|v| v.max(0.0) as f32)),
                verticality: e.vectors[0].z.abs() as f32,
                spread_m: e.values[1].max(0.0).sqrt() as f32,
                voxels: n as u32,
                extent_m: e.values[0].max(0.0).sqrt() as f32,
            }
        })?;
    Ok(member.iter().map(|&v| per_voxel[v as usize]).collect())
}

/// Sorts `indices` by the Morton code of their points' cells of edge `cell` metres (stable:
/// ties keep their order).
fn spatial_sort(points: &[Vec3], indices: &mut [u32], cell: f32) {
    let Some(lo) = indices
        .iter()
        .map(|&i| points[i as usize])
        .reduce(|a, b| a.min(b))
    else {
        return;
    };
    // Spread the low 21 bits of v so that two zero bits follow each.
    fn spread(v: u64) -> u64 {
        let mut x = v & 0x1f_ffff;
        x = (x | x << 32) & 0x1f_0000_0000_ffff;
        x = (x | x << 16) & 0x1f_0000_ff00_00ff;
        x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
        x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
        x = (x | x << 2) & 0x1249_2492_4924_9249;
        x
    }
    let code = |i: u32| {
        let c = ((points[i as usize] - lo) / cell).max(Vec3::ZERO);
        spread(c.x as u64) | spread(c.y as u64) << 1 | spread(c.z as u64) << 2
    };
    let mut keyed: Vec<(u64, u32)> = indices.par_iter().map(|&i| (code(i), i)).collect();
    keyed.par_sort_by_key(|k| k.0);
    for (slot, (_, i)) in indices.iter_mut().zip(keyed) {
        *slot = i;
    }
}

/// The fine line test of the growth (see [`SegmentParams::fine_line_radius_m`]).
struct FineLine<'a> {
    points: &'a [Vec3],
    index: &'a PointIndex,
    radius: f32,
    min_linearity: f32,
    max_spread: f32,
    /// Cosine of the largest angle between a candidate's line and its parent's.
    min_cos: f32,
}

impl FineLine<'_> {
    fn enabled(&self) -> bool {
        self.radius > 0.0 && self.min_linearity <= 1.0 && self.max_spread > 0.0
    }

    /// Whether the points within `radius` of point `i` form a thin line, and their principal
    /// direction (zero when there are too few points).
    fn line(&self, i: usize) -> (bool, Vec3) {
        let (lin, spread, dir) = self.shape(i);
        (lin >= self.min_linearity && spread <= self.max_spread, dir)
    }

    /// Linearity, spread across the principal direction (`sqrt(l2)`, metres) and principal
    /// direction of the points within `radius` of point `i`; (0, inf, zero) when fewer than
    /// five.
    fn shape(&self, i: usize) -> (f32, f32, Vec3) {
        let none = (0.0, f32::INFINITY, Vec3::ZERO);
        let nb = self.index.within(self.points[i], self.radius);
        if nb.len() < 5 {
            return none;
        }
        covariance(self.points, nb.iter().map(|m| m.index as usize)).map_or(none, |(cov, _)| {
            let e = symmetric_eigen3(cov);
            let f = EigenFeatures::from_eigenvalues(e.values.map(|v| v.max(0.0) as f32));
            (
                f.linearity,
                e.values[1].max(0.0).sqrt() as f32,
                e.vectors[0].as_vec3(),
            )
        })
    }
}

/// Leaf-labelled points that are very thin lines at the fine radius (see
/// [`SegmentParams::lone_line_linearity`]), sorted; tested in parallel.
fn lone_lines(
    labels: &[u8],
    coarse: &[CoarseFeatures],
    line: &FineLine,
    min_linearity: f32,
    max_spread: f32,
    min_coarse_linearity: f32,
) -> Vec<u32> {
    if line.radius <= 0.0 || min_linearity > 1.0 || max_spread <= 0.0 {
        return Vec::new();
    }
    (0..labels.len() as u32)
        .into_par_iter()
        .filter(|&j| {
            let ju = j as usize;
            labels[ju] != TRUNK
                && coarse
                    .get(ju)
                    .is_some_and(|c| c.eigen.linearity >= min_coarse_linearity)
                && {
                    let (lin, spread, _) = line.shape(ju);
                    lin >= min_linearity && spread <= max_spread
                }
        })
        .collect()
}

/// Growth of the trunk label from every trunk point into graph neighbours that are lines:
/// `coarse` linearity >= `min_linearity`, or the fine line test with the candidate's line
/// within the largest angle of its parent's principal direction (a twig goes on straight
/// through a leaf cluster; a leaf seen edge-on beside it is a line at any angle). Level by
/// level, all candidates of one level tested in parallel, the fine test only where the
/// coarse one fails; a candidate that fails only the angle is tried again from each new
/// parent. The result is the set of points reachable from a trunk point through points that
/// pass, so it does not depend on the order. Returns the points that became trunk, sorted.
fn grow_along_lines(
    labels: &mut [u8],
    graph: &KnnGraph,
    coarse: &[CoarseFeatures],
    min_linearity: f32,
    line: &FineLine,
) -> Vec<u32> {
    let fine = line.enabled();
    if min_linearity > 1.0 && !fine {
        return Vec::new();
    }
    let n = labels.len();
    // 0 untested, 1 passed, 2 failed for good (neither test), 3 a line, angle not yet met.
    let mut state = vec![0u8; n];
    // Fine-scale principal direction, computed once where needed (NaN: not yet).
    let mut dir = vec![Vec3::NAN; n];
    let mut frontier: Vec<u32> = (0..n as u32)
        .filter(|&i| labels[i as usize] == TRUNK)
        .collect();
    let mut grown = Vec::new();
    while !frontier.is_empty() {
        // (candidate, parent) pairs.
        let mut pairs: Vec<(u32, u32)> = frontier
            .iter()
            .filter_map(|&i| graph.neighbours.get(i as usize).map(|nb| (i, nb)))
            .flat_map(|(i, nb)| {
                nb.iter()
                    .copied()
                    .take_while(|j| *j != u32::MAX)
                    .map(move |j| (j, i))
            })
            .filter(|&(j, _)| {
                (j as usize) < n
                    && labels[j as usize] != TRUNK
                    && matches!(state[j as usize], 0 | 3)
            })
            .collect();
        pairs.sort_unstable();
        pairs.dedup();
        let mut cand: Vec<u32> = pairs.iter().map(|p| p.0).collect();
        cand.dedup();
        // Candidates' own tests (state 3 keeps its earlier result).
        let tests: Vec<(u32, u8, Vec3)> = cand
            .par_iter()
            .filter(|&&j| state[j as usize] == 0)
            .map(|&j| {
                let ju = j as usize;
                if coarse
                    .get(ju)
                    .is_some_and(|c| c.eigen.linearity >= min_linearity)
                {
                    return (j, 1, Vec3::NAN);
                }
                if !fine {
                    return (j, 2, Vec3::NAN);
                }
                let (thin, d) = line.line(ju);
                (j, if thin { 3 } else { 2 }, d)
            })
            .collect();
        for (j, st, d) in tests {
            state[j as usize] = st;
            if st == 3 {
                dir[j as usize] = d;
            }
        }
        // Parents' directions where a line candidate needs them.
        let mut parents: Vec<u32> = pairs
            .iter()
            .filter(|&&(j, i)| state[j as usize] == 3 && dir[i as usize].is_nan())
            .map(|p| p.1)
            .collect();
        parents.sort_unstable();
        parents.dedup();
        let pdirs: Vec<Vec3> = parents
            .par_iter()
            .map(|&i| line.line(i as usize).1)
            .collect();
        for (&i, d) in parents.iter().zip(pdirs) {
            dir[i as usize] = d;
        }
        frontier.clear();
        for &(j, i) in &pairs {
            let ju = j as usize;
            let ok = match state[ju] {
                1 => true,
                3 => dir[ju].dot(dir[i as usize]).abs() >= line.min_cos,
                _ => false,
            };
            if ok && labels[ju] != TRUNK {
                state[ju] = 1;
                labels[ju] = TRUNK;
                frontier.push(j);
            }
        }
        grown.extend_from_slice(&frontier);
    }
    grown.sort_unstable();
    grown
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A twig (a 4 mm-noisy line) beside a leaf disc (a plane) and a blob, all labelled
    /// leaf: the lone-line test relabels the twig's inner points and none of the others.
    #[test]
    fn lone_lines_take_a_thin_twig_and_leave_planes_and_blobs() {
        let mut unit = crate::testing::centred_unit(7);
        let mut pts = Vec::new();
        // Twig along x, 1 m long, 600 points, ±4 mm across.
        for i in 0..600 {
            let x = i as f32 / 600.0;
            pts.push(Vec3::new(x, 0.008 * unit(), 0.008 * unit()));
        }
        // Leaf disc: 0.3 m square in the plane z = 0, 1 m away.
        for i in 0..900 {
            pts.push(Vec3::new(
                2.0 + 0.01 * (i % 30) as f32 + 0.002 * unit(),
                0.01 * (i / 30) as f32,
                0.003 * unit(),
            ));
        }
        // Blob: 0.1 m cube of 500 points.
        for _ in 0..500 {
            pts.push(Vec3::new(0.1 * unit(), 2.0 + 0.1 * unit(), 0.1 * unit()));
        }
        let index = PointIndex::new(&pts).expect("index");
        let params = SegmentParams::default();
        let line = FineLine {
            points: &pts,
            index: &index,
            radius: params.fine_line_radius_m,
            min_linearity: params.fine_line_linearity,
            max_spread: params.fine_line_spread_m,
            min_cos: 1.0,
        };
        let labels = vec![LEAF; pts.len()];
        let coarse = vec![CoarseFeatures::default(); pts.len()];
        let lone = lone_lines(
            &labels,
            &coarse,
            &line,
            params.lone_line_linearity,
            params.lone_line_spread_m,
            params.lone_line_min_coarse_linearity,
        );
        // Away from its ends (where the 0.1 m ball holds half a line) the twig passes.
        let inner = (60u32..540)
            .filter(|i| lone.binary_search(i).is_ok())
            .count();
        assert!(inner >= 470, "{inner} of 480 inner twig points");
        assert!(
            lone.iter().all(|&j| j < 600),
            "a plane or blob point passed"
        );
        // Off: nothing.
        let off = lone_lines(&labels, &coarse, &line, 1.1, 0.015, 0.0);
        assert!(off.is_empty());
        // Already trunk: not returned.
        let trunk = vec![TRUNK; pts.len()];
        assert!(lone_lines(&trunk, &coarse, &line, 0.9, 0.015, 0.0).is_empty());
    }
}
