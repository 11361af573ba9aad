//! Wood/leaf segmentation (METHOD.md Stage 3, paper 3.4): eigen features of the k = 20
//! nearest neighbours, colour at weight 0.5, deterministic 2-means on standardised features,
//! trunk = the cluster with the higher mean linearity, then small-component clean-up on the
//! k-NN graph.
//!
//! On forest clouds the ground is planar and would pull the planarity feature (and the
//! clusters) towards itself although it is not wood, so callers pass a mask and only the
//! non-ground points are segmented; masked-out points get label leaf (0) and probability 0.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use super::ForestError;
use super::components::{GRAPH_K, KnnGraph, relabel_small_components};
use super::kmeans::{distance2_to_centre, kmeans, standardise};
use crate::geom::{EigenFeatures, PointIndex, covariance, symmetric_eigen3};
use crate::progress::{Progress, SubProgress};

/// Label of leaf (and everything that is not wood), METHOD.md Stage 3.
pub const LEAF: u8 = 0;
/// Label of trunk and main branches, METHOD.md Stage 3.
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
}

impl Default for SegmentParams {
    fn default() -> Self {
        Self {
            k: 20,
            colour_weight: 0.5,
            tau_c: 50,
            max_iterations: 100,
            seed: 20_260_611,
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
    /// Points whose label the component clean-up changed.
    pub relabelled: usize,
    /// Lloyd iterations of the 2-means.
    pub iterations: usize,
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
    let selected: Vec<u32> = (0..points.len() as u32)
        .filter(|&i| include.is_none_or(|m| m[i as usize]))
        .collect();
    if selected.len() < params.k.max(2) {
        return Err(ForestError::NotEnoughPoints(format!(
            "wood/leaf segmentation needs at least {} points, got {}",
            params.k.max(2),
            selected.len()
        )));
    }
    let sub: Vec<Vec3> = selected.iter().map(|&i| points[i as usize]).collect();
    let index = PointIndex::new(&sub)?;
    progress.set(0.05);

    // One k-NN pass: features and the clean-up graph.
    let k = params.k;
    let recs: Vec<(EigenFeatures, [u32; GRAPH_K])> = index.map_knn(
        &sub,
        k.max(GRAPH_K + 1),
        &SubProgress::new(progress, 0.05, 0.65),
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
    let (features, neighbours): (Vec<EigenFeatures>, Vec<[u32; GRAPH_K]>) =
        recs.into_iter().unzip();

    // Feature rows [L, P, S, (w r, w g, w b)], standardised column-wise, then weighted.
    let dim = if colors.is_some() { 6 } else { 3 };
    let mut rows = Vec::with_capacity(sub.len() * dim);
    for (j, f) in features.iter().enumerate() {
        rows.extend([f.linearity, f.planarity, f.sphericity]);
        if let Some(c) = colors {
            let c = c[selected[j] as usize];
            rows.extend(c.map(|v| v as f32 / 255.0));
        }
    }
    standardise(&mut rows, dim);
    if dim == 6 {
        for row in rows.chunks_mut(dim) {
            row[3..].iter_mut().for_each(|v| *v *= params.colour_weight);
        }
    }
    let km = kmeans(
        &rows,
        dim,
        2,
        params.max_iterations,
        params.seed,
        &SubProgress::new(progress, 0.7, 0.2),
    )?;
    // Trunk = the cluster with the higher mean linearity.
    let (mut lin, mut cnt) = ([0.0f64; 2], [0usize; 2]);
    for (f, &a) in features.iter().zip(&km.assignment) {
        lin[a as usize] += f.linearity as f64;
        cnt[a as usize] += 1;
    }
    let mean = |c: usize| lin[c] / cnt[c].max(1) as f64;
    let trunk_cluster = usize::from(mean(1) > mean(0));
    let mut labels: Vec<u8> = km
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
    let mut prob: Vec<f32> = rows
        .chunks(dim)
        .map(|row| {
            let dt = distance2_to_centre(&km, dim, row, trunk_cluster).sqrt();
            let dl = distance2_to_centre(&km, dim, row, 1 - trunk_cluster).sqrt();
            if dt + dl > 0.0 { dl / (dt + dl) } else { 0.5 }
        })
        .collect();
    if progress.is_cancelled() {
        return Err(ForestError::Cancelled);
    }
    let before = labels.clone();
    let relabelled = relabel_small_components(&mut labels, &KnnGraph { neighbours }, params.tau_c);
    for ((p, l), b) in prob.iter_mut().zip(&labels).zip(&before) {
        if l != b {
            *p = 1.0 - *p;
        }
    }
    progress.set(1.0);

    let mut out = WoodLeaf {
        labels: vec![LEAF; points.len()],
        trunk_probability: vec![0.0; points.len()],
        features: vec![EigenFeatures::default(); points.len()],
        relabelled,
        iterations: km.iterations,
    };
    for (j, &i) in selected.iter().enumerate() {
        out.labels[i as usize] = labels[j];
        out.trunk_probability[i as usize] = prob[j].clamp(0.0, 1.0);
        out.features[i as usize] = features[j];
    }
    Ok(out)
}
