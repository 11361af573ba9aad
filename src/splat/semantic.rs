//! The semantic geometric term L_geo (docs/method.md Stage 4, paper 3.5): Gaussians that are likely
//! trunk are pulled towards the nearest trunk anchor and their scales towards the local anchor
//! spacing, so the stems keep their LiDAR shape while the photometric loss shapes the rest.
//!
//! For Gaussian i with opacity alpha_i, inherited trunk probability P_i, mean mu_i and
//! log-scales s_i:
//!
//! - d_t, d_l: distances to the nearest trunk and leaf anchor; q_i = exp(-d_t/T) /
//!   (exp(-d_t/T) + exp(-d_l/T)) (the softmax pseudo-label of "trunk");
//! - w_i = alpha_i P_i q_i, and the candidate set S = { i : w_i >= threshold };
//! - s_target(i) = log(beta * dbar_K(i) + eps), dbar_K the mean distance to the K nearest trunk
//!   anchors, in all three axes;
//! - L_geo = (1 / sum_S w_i) sum_S w_i (|mu_i - a_nn(i)|^2 / N_pos^2 + |s_i - s_target(i)|^2),
//!   a_nn(i) the nearest trunk anchor, N_pos the diagonal of the anchors' bounding box.
//!
//! w_i, a_nn and s_target are constants of each step (no gradient flows through them); the
//! gradients go to mu_i and s_i only. The total loss adds gamma(t) L_geo with the ramp of
//! [`SemanticConfig::gamma_at`].
//!
//! This module holds the configuration, the anchor sets with the uniform grid the GPU kernel
//! searches ([`AnchorGrid`]), and the CPU twin ([`geo_targets`], [`geo_loss_and_grad`]) which
//! the CPU backend trains with and the GPU tests compare against.

use serde::{Deserialize, Serialize};

use super::model::Gaussians;
use crate::geom::PointIndex;

/// Default final weight of L_geo (docs/method.md; the paper finds 0.01–0.03 stable). The one
/// source of this default: `params.train.gamma_max` takes it too.
pub const DEFAULT_GAMMA_MAX: f64 = 0.02;
/// Default step at which the L_geo ramp starts (docs/method.md T_start).
pub const DEFAULT_GAMMA_START: u32 = 3000;
/// Default step at which the ramp reaches gamma_max (docs/method.md T_end).
pub const DEFAULT_GAMMA_END: u32 = 7000;
/// Default number K of nearest trunk anchors (docs/method.md).
pub const DEFAULT_TRUNK_K: u32 = 8;
/// Default factor beta on their mean distance (docs/method.md).
pub const DEFAULT_TRUNK_BETA: f64 = 0.5;

/// The knobs of L_geo; every default is docs/method.md Stage 4's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SemanticConfig {
    /// Apply the term at all. Default false here (vanilla 3DGS); stage `train` turns it on
    /// with `params.train.semantic` (default on there, the paper's method).
    pub enabled: bool,
    /// Final weight gamma_max of L_geo. Default 0.02 (docs/method.md; the paper finds 0.01–0.03
    /// stable).
    pub gamma_max: f32,
    /// Step at which the ramp starts (gamma = 0 before). Default 3000 (docs/method.md T_start).
    pub gamma_start: u32,
    /// Step at which the ramp reaches gamma_max. Default 7000 (docs/method.md T_end).
    pub gamma_end: u32,
    /// Softmax temperature T of the trunk score q_i, metres. Default 0.02 m: "of the order of
    /// the voxel size" (docs/method.md), and the anchors' voxel is 0.02 m (Stage 2).
    pub temperature_m: f32,
    /// Number K of nearest trunk anchors whose mean distance sets the target scale.
    /// Default 8 (docs/method.md).
    pub k: u32,
    /// Factor beta on that mean distance. Default 0.5 (docs/method.md).
    pub beta: f32,
    /// eps inside the target's log, metres. Default 1e-6 m (keeps the log finite on
    /// duplicated anchors; far below any anchor spacing).
    pub eps_m: f32,
    /// Gaussians with w_i at or above this are in the candidate set S. Default 0.5 (docs/method.md).
    pub weight_threshold: f32,
}

impl Default for SemanticConfig {
    fn default() -> Self {
        SemanticConfig {
            enabled: false,
            gamma_max: DEFAULT_GAMMA_MAX as f32,
            gamma_start: DEFAULT_GAMMA_START,
            gamma_end: DEFAULT_GAMMA_END,
            temperature_m: 0.02,
            k: DEFAULT_TRUNK_K,
            beta: DEFAULT_TRUNK_BETA as f32,
            eps_m: 1e-6,
            weight_threshold: 0.5,
        }
    }
}

/// Largest K the GPU kernel keeps in registers.
pub const MAX_K: u32 = 16;

impl SemanticConfig {
    /// gamma(t) at 1-based `step`: 0 up to `gamma_start`, linear to `gamma_max` at
    /// `gamma_end`, constant after (docs/method.md); 0 when disabled.
    pub fn gamma_at(&self, step: u32) -> f32 {
        if !self.enabled || step <= self.gamma_start {
            return 0.0;
        }
        if step >= self.gamma_end || self.gamma_end <= self.gamma_start {
            return self.gamma_max;
        }
        let f = (step - self.gamma_start) as f32 / (self.gamma_end - self.gamma_start) as f32;
        self.gamma_max * f
    }

    /// The ramp of a run of `steps` steps: the reference's 3000 → 7000 of 30 000 are moved in
    /// proportion when the run is shorter (docs/method.md), unchanged otherwise.
    pub fn scaled_to(&self, steps: u32) -> SemanticConfig {
        let mut c = self.clone();
        let reference = super::config::REFERENCE_STEPS;
        if steps < reference {
            let f = steps as f64 / reference as f64;
            c.gamma_start = (self.gamma_start as f64 * f).round() as u32;
            c.gamma_end = (self.gamma_end as f64 * f).round() as u32;
        }
        c
    }

    /// Checks the values a user can set.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.temperature_m > 0.0 && self.temperature_m.is_finite()) {
            return Err(format!(
                "semantic temperature must be > 0 m, got {}",
                self.temperature_m
            ));
        }
        if self.k == 0 || self.k > MAX_K {
            return Err(format!("semantic K must be in 1..={MAX_K}, got {}", self.k));
        }
        if !(self.beta > 0.0 && self.beta.is_finite() && self.eps_m > 0.0 && self.eps_m.is_finite())
        {
            return Err("semantic beta and eps must be > 0".into());
        }
        if !(self.gamma_max >= 0.0 && self.gamma_max.is_finite()) {
            return Err(format!("gamma_max must be ≥ 0, got {}", self.gamma_max));
        }
        Ok(())
    }
}

/// The labelled anchors L_geo pulls towards, in the training frame (metres).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SemanticAnchors {
    pub trunk: Vec<[f32; 3]>,
    /// Unit LiDAR surface normal of each trunk anchor (stage `anchors`), or empty when the
    /// anchors carry none; Sylva's binding ([`super::bind`]) needs them, L_geo does not.
    pub trunk_normals: Vec<[f32; 3]>,
    pub leaf: Vec<[f32; 3]>,
    /// N_pos: the diagonal of the bounding box of all anchors, metres (docs/method.md).
    pub n_pos: f32,
}

impl SemanticAnchors {
    /// Splits anchors into trunk and leaf by their label (`is_trunk`), N_pos from all of them;
    /// `normals` (one per point, or none) give the trunk anchors their surface normals.
    /// An error when there is no trunk anchor (nothing to pull towards) or N_pos is zero.
    pub fn new(
        points: &[[f32; 3]],
        normals: Option<&[[f32; 3]]>,
        is_trunk: &[bool],
    ) -> Result<Self, String> {
        if points.len() != is_trunk.len() || normals.is_some_and(|n| n.len() != points.len()) {
            return Err("anchor labels, normals and positions differ in count".into());
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        let (mut trunk, mut leaf, mut trunk_normals) = (Vec::new(), Vec::new(), Vec::new());
        for (i, (p, &t)) in points.iter().zip(is_trunk).enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                continue;
            }
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
            if t {
                trunk.push(*p);
                if let Some(n) = normals {
                    trunk_normals.push(unit_or_zero(n[i]));
                }
            } else {
                leaf.push(*p)
            }
        }
        if trunk.is_empty() {
            return Err("no trunk anchors: the semantic term needs the wood/leaf labels".into());
        }
        let n_pos =
            ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
        if n_pos.is_nan() || n_pos <= 0.0 {
            return Err("the anchors span no volume (N_pos = 0)".into());
        }
        Ok(SemanticAnchors {
            trunk,
            trunk_normals,
            leaf,
            n_pos,
        })
    }
}

/// The most anchors, trunk and leaf together, the trunk term holds: 2²³ − 1, what one
/// 128 MiB storage binding holds at 16 B an anchor (lavapipe's binding limit, which the GPU
/// kernels bind the anchors in, and WebGPU's default; the same on every device, so a plot
/// trains alike everywhere). The anchors of `stand` (1.3 M) are far below it; the 11.6 M of
/// the paper-size plot (issue 41) are not. Past it, [`SemanticAnchors::thinned`].
pub const MAX_ANCHORS: usize = (128 << 20) / 16 - 1;

/// Start words of an anchor grid at most (`MAX_DIM`³ cells and one more).
const MAX_GRID_WORDS: u64 = (MAX_DIM as u64).pow(3) + 1;

impl SemanticAnchors {
    /// At most `max` anchors: the set as it is when it holds no more; otherwise an even draw in
    /// space of the leaf anchors (seeded by `seed`) to what the trunk anchors leave, and of the
    /// trunk anchors (with their normals) too when they alone are more than `max`. The leaf
    /// anchors only weigh trunk against leaf in L_geo, where a sparser set of them changes
    /// little; the trunk anchors are the surface the trunks are held to. N_pos stays.
    pub fn thinned(self, max: usize, seed: u64) -> SemanticAnchors {
        if self.trunk.len() + self.leaf.len() <= max {
            return self;
        }
        let mut rng = crate::rng::SplitMix64::new(seed);
        let draw = |points: &[[f32; 3]], count: usize, rng: &mut crate::rng::SplitMix64| {
            let idx: Vec<usize> = (0..points.len()).collect();
            let mut kept = crate::splat::budget::voxel_draw(points, &idx, count, rng);
            kept.sort_unstable();
            kept
        };
        let (trunk, trunk_normals) = if self.trunk.len() > max {
            let kept = draw(&self.trunk, max, &mut rng);
            let normals = if self.trunk_normals.len() == self.trunk.len() {
                kept.iter().map(|&i| self.trunk_normals[i]).collect()
            } else {
                self.trunk_normals.clone()
            };
            (kept.iter().map(|&i| self.trunk[i]).collect(), normals)
        } else {
            (self.trunk, self.trunk_normals)
        };
        let room = max - trunk.len();
        let leaf = draw(&self.leaf, room, &mut rng)
            .iter()
            .map(|&i| self.leaf[i])
            .collect();
        SemanticAnchors {
            trunk,
            trunk_normals,
            leaf,
            n_pos: self.n_pos,
        }
    }

    /// Bytes the set takes on the GPU: every anchor (16 B), every trunk anchor's normal
    /// (16 B) and the cell starts of its two grids (4 B a cell, at most `MAX_DIM`³ cells).
    pub fn device_bytes(&self) -> u64 {
        let words =
            |p: &[[f32; 3]]| (AnchorGrid::build(p).cell_start.len() as u64).min(MAX_GRID_WORDS);
        (self.trunk.len() + self.leaf.len()) as u64 * 16
            + self.trunk.len() as u64 * 16
            + (words(&self.trunk) + words(&self.leaf)) * 4
    }
}

/// `n` scaled to unit length, or zero when it has none (a zero normal means "unknown").
fn unit_or_zero(n: [f32; 3]) -> [f32; 3] {
    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if l.is_finite() && l > 1e-6 {
        n.map(|v| v / l)
    } else {
        [0.0; 3]
    }
}

/// What the query gives one Gaussian for one step: its weight (0 outside S), the nearest trunk
/// anchor and the target log-scale.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GeoTarget {
    pub weight: f64,
    pub anchor: [f64; 3],
    pub log_scale: f64,
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// q_i from the trunk and leaf distances (leaf distance infinite when there are no leaves),
/// written as a logistic so neither exponential underflows.
pub fn trunk_score(d_trunk: f64, d_leaf: f64, temperature: f64) -> f64 {
    if !d_leaf.is_finite() {
        return 1.0;
    }
    sigmoid((d_leaf - d_trunk) / temperature)
}

/// The CPU twin of the GPU query: exact nearest neighbours by k-d tree.
pub fn geo_targets(
    model: &Gaussians,
    anchors: &SemanticAnchors,
    cfg: &SemanticConfig,
) -> Vec<GeoTarget> {
    match AnchorIndex::new(anchors) {
        Some(index) => geo_targets_indexed(model, &index, cfg),
        None => vec![GeoTarget::default(); model.len()],
    }
}

/// k-d trees over the trunk and leaf anchors, built once (anchors do not move in training).
pub struct AnchorIndex {
    trunk: Vec<glam::Vec3>,
    /// Unit normals of the trunk anchors (zero where unknown); empty without normals.
    trunk_normals: Vec<glam::Vec3>,
    leaf: Vec<glam::Vec3>,
    ti: PointIndex,
    li: Option<PointIndex>,
}

impl AnchorIndex {
    /// None when there is no trunk anchor.
    pub fn new(anchors: &SemanticAnchors) -> Option<Self> {
        let to_vec = |p: &[f32; 3]| glam::Vec3::from_array(*p);
        let trunk: Vec<glam::Vec3> = anchors.trunk.iter().map(to_vec).collect();
        let leaf: Vec<glam::Vec3> = anchors.leaf.iter().map(to_vec).collect();
        let ti = PointIndex::new(&trunk).ok()?;
        let li = PointIndex::new(&leaf).ok();
        Some(AnchorIndex {
            trunk,
            trunk_normals: anchors.trunk_normals.iter().map(to_vec).collect(),
            leaf,
            ti,
            li,
        })
    }
}

impl AnchorIndex {
    /// The nearest trunk anchor to `p`: its position and unit normal (zero when unknown).
    pub fn nearest_trunk(&self, p: glam::Vec3) -> Option<(glam::Vec3, glam::Vec3)> {
        let n = self.ti.nearest(p)?;
        let i = n.index as usize;
        Some((
            self.trunk[i],
            self.trunk_normals
                .get(i)
                .copied()
                .unwrap_or(glam::Vec3::ZERO),
        ))
    }
}

/// [`geo_targets`] with the anchors' index already built.
pub fn geo_targets_indexed(
    model: &Gaussians,
    index: &AnchorIndex,
    cfg: &SemanticConfig,
) -> Vec<GeoTarget> {
    let AnchorIndex {
        trunk,
        leaf,
        ti,
        li,
        ..
    } = index;
    let to_vec = |p: &[f32; 3]| glam::Vec3::from_array(*p);
    let k = (cfg.k as usize).min(trunk.len()).max(1);
    let t = f64::from(cfg.temperature_m);
    (0..model.len())
        .map(|i| {
            let alpha = sigmoid(f64::from(model.opacity_logits[i]));
            let p = f64::from(model.trunk_prob[i]);
            let thr = f64::from(cfg.weight_threshold);
            // w = alpha P q <= alpha P: no search needed when that is already below threshold.
            if alpha * p < thr {
                return GeoTarget::default();
            }
            let mu = to_vec(&model.means[i]);
            let nn = ti.knn(mu, k);
            let Some(first) = nn.first() else {
                return GeoTarget::default();
            };
            let pos = |n: &crate::geom::Neighbour| {
                let mut d = 0.0f64;
                let a = trunk[n.index as usize];
                for (x, y) in a.to_array().iter().zip(model.means[i]) {
                    d += f64::from(*x - y).powi(2);
                }
                d.sqrt()
            };
            let d_t = pos(first);
            let d_l = li
                .as_ref()
                .and_then(|l| l.nearest(mu))
                .map_or(f64::INFINITY, |n| {
                    let a = leaf[n.index as usize];
                    a.to_array()
                        .iter()
                        .zip(model.means[i])
                        .map(|(x, y)| f64::from(*x - y).powi(2))
                        .sum::<f64>()
                        .sqrt()
                });
            let w = alpha * p * trunk_score(d_t, d_l, t);
            if w < thr {
                return GeoTarget::default();
            }
            let dbar = nn.iter().map(pos).sum::<f64>() / nn.len() as f64;
            let a = trunk[first.index as usize].to_array();
            GeoTarget {
                weight: w,
                anchor: [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])],
                log_scale: (f64::from(cfg.beta) * dbar + f64::from(cfg.eps_m)).ln(),
            }
        })
        .collect()
}

/// L_geo and its gradients with respect to the means and log-scales, with `targets` held
/// constant (docs/method.md: w_i is a constant weight). Zero loss and gradients when S is empty.
pub fn geo_loss_and_grad(
    model: &Gaussians,
    targets: &[GeoTarget],
    n_pos: f32,
) -> (f64, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let n = model.len();
    let mut d_mu = vec![[0.0; 3]; n];
    let mut d_s = vec![[0.0; 3]; n];
    let total_w: f64 = targets.iter().map(|t| t.weight).sum();
    if total_w <= 0.0 {
        return (0.0, d_mu, d_s);
    }
    let inv_n2 = 1.0 / f64::from(n_pos).powi(2);
    let mut loss = 0.0;
    for (i, t) in targets.iter().enumerate().take(n) {
        if t.weight <= 0.0 {
            continue;
        }
        let g = t.weight / total_w;
        for a in 0..3 {
            let dm = f64::from(model.means[i][a]) - t.anchor[a];
            let ds = f64::from(model.log_scales[i][a]) - t.log_scale;
            loss += g * (dm * dm * inv_n2 + ds * ds);
            d_mu[i][a] = g * 2.0 * dm * inv_n2;
            d_s[i][a] = g * 2.0 * ds;
        }
    }
    (loss, d_mu, d_s)
}

/// A uniform grid over one anchor set, as the GPU kernel searches it: points sorted by cell,
/// `cell_start[c]..cell_start[c + 1]` the points of cell c (x fastest).
#[derive(Debug, Clone, PartialEq)]
pub struct AnchorGrid {
    /// Corner of cell (0, 0, 0), metres.
    pub origin: [f32; 3],
    /// Cell edge, metres.
    pub cell: f32,
    pub dims: [u32; 3],
    pub cell_start: Vec<u32>,
    pub points: Vec<[f32; 3]>,
    /// Index in the input of each point of `points` (to carry per-anchor data such as normals).
    pub order: Vec<u32>,
}

/// Finest grid resolution per axis; bounds the cell table at 128³ entries.
const MAX_DIM: u32 = 128;
/// The grid is refined while occupied cells hold at least this many anchors on average.
const TARGET_PER_CELL: f64 = 8.0;

impl AnchorGrid {
    /// A grid over `points` whose cells hold about [`TARGET_PER_CELL`] anchors each where there
    /// are anchors (at most [`MAX_DIM`] cells per axis). An empty set gives a 1-cell empty grid.
    pub fn build(points: &[[f32; 3]]) -> AnchorGrid {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        if points.is_empty() {
            return AnchorGrid {
                origin: [0.0; 3],
                cell: 1.0,
                dims: [1, 1, 1],
                cell_start: vec![0, 0],
                points: Vec::new(),
                order: Vec::new(),
            };
        }
        let extent = (0..3)
            .map(|a| hi[a] - lo[a])
            .fold(0.0f32, f32::max)
            .max(1e-3);
        let mut best = extent;
        let mut d = MAX_DIM;
        while d >= 1 {
            let cell = extent / d as f32 * (1.0 + 1e-4);
            let mut cells: Vec<u64> = points
                .iter()
                .map(|p| {
                    let c = |a: usize| ((p[a] - lo[a]) / cell) as u64;
                    (c(2) * 1024 + c(1)) * 1024 + c(0)
                })
                .collect();
            cells.sort_unstable();
            cells.dedup();
            if points.len() as f64 / cells.len() as f64 >= TARGET_PER_CELL || d == 1 {
                best = cell;
                break;
            }
            d /= 2;
        }
        let cell = best;
        let dims: [u32; 3] =
            std::array::from_fn(|a| (((hi[a] - lo[a]) / cell) as u32 + 1).clamp(1, MAX_DIM));
        let index = |p: &[f32; 3]| -> usize {
            let c = |a: usize| (((p[a] - lo[a]) / cell) as u32).min(dims[a] - 1) as usize;
            (c(2) * dims[1] as usize + c(1)) * dims[0] as usize + c(0)
        };
        let n_cells = dims.iter().map(|&d| d as usize).product::<usize>();
        let mut counts = vec![0u32; n_cells + 1];
        for p in points {
            counts[index(p) + 1] += 1;
        }
        for c in 1..counts.len() {
            counts[c] += counts[c - 1];
        }
        let mut fill = counts.clone();
        let mut sorted = vec![[0.0f32; 3]; points.len()];
        let mut order = vec![0u32; points.len()];
        for (i, p) in points.iter().enumerate() {
            let c = index(p);
            sorted[fill[c] as usize] = *p;
            order[fill[c] as usize] = i as u32;
            fill[c] += 1;
        }
        AnchorGrid {
            origin: lo,
            cell,
            dims,
            cell_start: counts,
            points: sorted,
            order,
        }
    }
}

/// A test scene with known geometry, for the CPU and GPU tests and benchmarks: a trunk (600
/// anchors on a cylinder of radius 0.15 m, 3 m tall, with their outward normals) and 600 leaf
/// anchors above it, and `n`
/// Gaussians near them (trunk ones with P in [0.6, 1], leaf ones below 0.3; every tenth moved
/// 3 m off the anchors' box).
pub fn test_scene(seed: u64, n: usize) -> (Gaussians, SemanticAnchors) {
    let mut rng = crate::rng::SplitMix64::new(seed);
    let mut r = move || rng.uniform() as f32;
    let mut pts = Vec::new();
    let mut lab = Vec::new();
    for _ in 0..600 {
        let th = r() * std::f32::consts::TAU;
        pts.push([0.15 * th.cos(), 0.15 * th.sin(), r() * 3.0]);
        lab.push(true);
    }
    for _ in 0..600 {
        pts.push([r() * 4.0 - 2.0, r() * 4.0 - 2.0, 2.0 + r() * 2.0]);
        lab.push(false);
    }
    let anchors = SemanticAnchors {
        n_pos: 0.0,
        ..Default::default()
    };
    let normals: Vec<[f32; 3]> = pts
        .iter()
        .zip(&lab)
        .map(|(p, &t)| {
            if t {
                [p[0], p[1], 0.0]
            } else {
                [0.0, 0.0, 1.0]
            }
        })
        .collect();
    let anchors = SemanticAnchors::new(&pts, Some(&normals), &lab).unwrap_or(anchors);
    let mut g = Gaussians::default();
    for i in 0..n {
        let j = (i * 7) % pts.len();
        let base = pts[j];
        let off = if i % 10 == 9 { 3.0 } else { 0.0 };
        g.push(super::model::Gaussian {
            mean: [
                base[0] + 0.05 * (r() - 0.5) + off,
                base[1] + 0.05 * (r() - 0.5),
                base[2] + 0.05 * (r() - 0.5),
            ],
            log_scale: [r() * -3.0 - 2.0, r() * -3.0 - 2.0, r() * -3.0 - 2.0],
            opacity_logit: r() * 6.0 - 1.0,
            trunk_prob: if lab[j] { 0.6 + 0.4 * r() } else { 0.3 * r() },
            ..super::model::Gaussian::isotropic([0.0; 3], 0.01, [0.5; 3], 0.5)
        });
    }
    (g, anchors)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_set_past_the_limit_keeps_its_trunk_and_an_even_draw_of_its_leaves() {
        let mut rng = crate::rng::SplitMix64::new(4);
        let mut pt = || std::array::from_fn(|_| rng.uniform() as f32 * 10.0);
        let points: Vec<[f32; 3]> = (0..5000).map(|_| pt()).collect();
        let is_trunk: Vec<bool> = (0..5000).map(|i| i % 10 == 0).collect();
        let normals: Vec<[f32; 3]> = (0..5000)
            .map(|i| [(i as f32).cos(), (i as f32).sin(), 0.0])
            .collect();
        let set = SemanticAnchors::new(&points, Some(&normals), &is_trunk).expect("set");
        let n_pos = set.n_pos;
        // Under the limit: as it is.
        assert_eq!(set.clone().thinned(5000, 1), set);
        // Past it: every trunk anchor, leaves to the limit, the normals with their anchors.
        let thin = set.clone().thinned(2000, 1);
        assert_eq!(thin.trunk, set.trunk);
        assert_eq!(thin.trunk_normals, set.trunk_normals);
        assert_eq!(thin.leaf.len(), 1500);
        assert!(thin.leaf.iter().all(|p| set.leaf.contains(p)));
        assert_eq!(thin.n_pos, n_pos);
        // Fewer room than trunk anchors: the trunk is drawn too, its normals follow.
        let thinner = set.clone().thinned(300, 1);
        assert_eq!((thinner.trunk.len(), thinner.leaf.len()), (300, 0));
        for (p, n) in thinner.trunk.iter().zip(&thinner.trunk_normals) {
            let i = points.iter().position(|q| q == p).expect("an input anchor");
            assert_eq!(*n, unit_or_zero(normals[i]));
        }
        // The GPU bytes: 16 per anchor, 16 per trunk normal, the grids' starts.
        let grids = thin.device_bytes() - (2000 + 500) * 16;
        assert!(grids > 0 && grids <= 2 * (MAX_GRID_WORDS * 4), "{grids}");
    }

    #[test]
    fn gamma_ramps_as_the_paper_and_scales_with_short_runs() {
        let c = SemanticConfig {
            enabled: true,
            ..Default::default()
        };
        assert_eq!(c.gamma_at(3000), 0.0);
        assert!((c.gamma_at(5000) - 0.01).abs() < 1e-7);
        assert_eq!(c.gamma_at(7000), 0.02);
        assert_eq!(c.gamma_at(29_000), 0.02);
        let s = c.scaled_to(3000);
        assert_eq!((s.gamma_start, s.gamma_end), (300, 700));
        assert_eq!(SemanticConfig::default().gamma_at(9000), 0.0, "disabled");
    }

    #[test]
    fn gradient_agrees_with_finite_differences() {
        let (mut g, anchors) = test_scene(3, 200);
        let cfg = SemanticConfig::default();
        let targets = geo_targets(&g, &anchors, &cfg);
        let in_s = targets.iter().filter(|t| t.weight > 0.0).count();
        assert!(in_s > 20, "only {in_s} Gaussians in S");
        let (_, d_mu, d_s) = geo_loss_and_grad(&g, &targets, anchors.n_pos);
        // The centres and the log-scales, with their analytic gradients.
        type Field = fn(&mut Gaussians) -> &mut Vec<[f32; 3]>;
        let fields: [(&str, Field, &[[f64; 3]]); 2] = [
            ("mu", |g| &mut g.means, &d_mu),
            ("s", |g| &mut g.log_scales, &d_s),
        ];
        let h = 1e-3f32;
        let mut checked = 0;
        for i in (0..g.len()).filter(|&i| targets[i].weight > 0.0).take(15) {
            for a in 0..3 {
                for (name, field, analytic) in fields {
                    let x = field(&mut g)[i][a];
                    field(&mut g)[i][a] = x + h;
                    let up = geo_loss_and_grad(&g, &targets, anchors.n_pos).0;
                    field(&mut g)[i][a] = x - h;
                    let dn = geo_loss_and_grad(&g, &targets, anchors.n_pos).0;
                    field(&mut g)[i][a] = x;
                    let fd = (up - dn) / (2.0 * f64::from(h));
                    assert!(
                        (fd - analytic[i][a]).abs() <= 1e-6 + 1e-3 * fd.abs(),
                        "{name} {i} {a}: {fd} vs {}",
                        analytic[i][a]
                    );
                }
                checked += 1;
            }
        }
        assert_eq!(checked, 45);
    }

    #[test]
    fn targets_follow_the_definition() {
        let (g, anchors) = test_scene(5, 300);
        let cfg = SemanticConfig::default();
        let targets = geo_targets(&g, &anchors, &cfg);
        for (i, t) in targets.iter().enumerate() {
            let alpha = sigmoid(f64::from(g.opacity_logits[i]));
            let p = f64::from(g.trunk_prob[i]);
            if t.weight == 0.0 {
                continue;
            }
            assert!(t.weight >= 0.5 && t.weight <= alpha * p + 1e-12);
            // The nearest trunk anchor by brute force.
            let d = |a: &[f32; 3]| {
                (0..3)
                    .map(|k| f64::from(a[k] - g.means[i][k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            };
            let best = anchors.trunk.iter().map(d).fold(f64::INFINITY, f64::min);
            let got = (0..3)
                .map(|k| (t.anchor[k] - f64::from(g.means[i][k])).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!((got - best).abs() < 1e-6);
            let mut all: Vec<f64> = anchors.trunk.iter().map(d).collect();
            all.sort_by(f64::total_cmp);
            let dbar = all[..8].iter().sum::<f64>() / 8.0;
            assert!((t.log_scale - (0.5 * dbar + 1e-6).ln()).abs() < 1e-6);
        }
        // Leaf Gaussians (P <= 0.3) never enter S.
        for (i, t) in targets.iter().enumerate() {
            if g.trunk_prob[i] < 0.5 {
                assert_eq!(t.weight, 0.0);
            }
        }
    }

    #[test]
    fn a_gradient_step_pulls_trunk_gaussians_to_the_trunk() {
        let (mut g, anchors) = test_scene(9, 300);
        let cfg = SemanticConfig::default();
        let targets = geo_targets(&g, &anchors, &cfg);
        let (before, d_mu, d_s) = geo_loss_and_grad(&g, &targets, anchors.n_pos);
        let total: f64 = targets.iter().map(|t| t.weight).sum();
        for i in 0..g.len() {
            let w = targets[i].weight / total;
            if w == 0.0 {
                continue;
            }
            for a in 0..3 {
                // A step of 0.2 in the natural scale of each term lowers the loss.
                g.means[i][a] -=
                    (0.2 * d_mu[i][a] / w * f64::from(anchors.n_pos).powi(2) / 2.0) as f32;
                g.log_scales[i][a] -= (0.2 * d_s[i][a] / w / 2.0) as f32;
            }
        }
        let (after, _, _) = geo_loss_and_grad(&g, &targets, anchors.n_pos);
        assert!(after < 0.7 * before, "{before} -> {after}");
    }

    #[test]
    fn grid_cells_hold_their_points() {
        let (_, anchors) = test_scene(1, 1);
        let grid = AnchorGrid::build(&anchors.trunk);
        assert_eq!(grid.points.len(), anchors.trunk.len());
        assert_eq!(
            *grid.cell_start.last().unwrap_or(&0) as usize,
            grid.points.len()
        );
        for z in 0..grid.dims[2] {
            for y in 0..grid.dims[1] {
                for x in 0..grid.dims[0] {
                    let c = ((z * grid.dims[1] + y) * grid.dims[0] + x) as usize;
                    for p in
                        &grid.points[grid.cell_start[c] as usize..grid.cell_start[c + 1] as usize]
                    {
                        let cell = [x, y, z];
                        for a in 0..3 {
                            let lo = grid.origin[a] + cell[a] as f32 * grid.cell;
                            assert!(p[a] >= lo - 1e-5 && p[a] <= lo + grid.cell + 1e-5);
                        }
                    }
                }
            }
        }
        assert!(AnchorGrid::build(&[]).points.is_empty());
    }

    #[test]
    fn bad_inputs_are_refused() {
        assert!(SemanticAnchors::new(&[[0.0; 3]], None, &[false]).is_err());
        assert!(
            SemanticAnchors::new(&[[0.0; 3]], None, &[true]).is_err(),
            "N_pos = 0"
        );
        let bad = SemanticConfig {
            k: 0,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        assert!(SemanticConfig::default().validate().is_ok());
    }
}
