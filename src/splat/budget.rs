//! The Gaussian budget and its draw: how many Gaussians a run may hold (the speed default of
//! each device, [`default_budget`]; the memory plan of [`super::plan`] may lower it), and which
//! of the initial Gaussians a cap keeps ([`cap_gaussians`]: shares for the trunks and the stems'
//! DBH band, each part drawn evenly in space by [`voxel_draw`]).

use super::backend::DeviceKind;
use super::model::Gaussians;
use crate::rng::SplitMix64;

/// Default Gaussian budget on a software GPU (lavapipe), when no budget is
/// asked for (`params.train.max_gaussians` 0): measured on `stand` seed 1 with `sylva bench method` (docs/results/twin.md, "Budgets"),
/// where it kept a 500-step run at 80 px within a few minutes on 2 cores.
pub const SOFTWARE_GPU_BUDGET: u32 = 10_000;

/// Default Gaussian budget on the CPU reference backend (docs/results/twin.md, "Budgets"): the
/// demo's, which trains `tiny` in seconds on 2 cores.
pub const CPU_REFERENCE_BUDGET: u32 = 3_000;

/// The Gaussian budget a run gets when no budget is asked for: none on a hardware
/// GPU (the reference 3DGS has no cap; not measured here, there being no GPU on the machines
/// Sylva is tested on), [`SOFTWARE_GPU_BUDGET`] on a software one, [`CPU_REFERENCE_BUDGET`] on
/// the CPU reference.
pub fn default_budget(kind: DeviceKind) -> Option<u32> {
    match kind {
        DeviceKind::Gpu => None,
        DeviceKind::SoftwareGpu => Some(SOFTWARE_GPU_BUDGET),
        DeviceKind::CpuReference => Some(CPU_REFERENCE_BUDGET),
    }
}

/// Share of a Gaussian cap reserved for trunk Gaussians (trunk probability ≥ 0.5). The trunks
/// are a small part of a plot, yet the Gaussian DBH of stage `dbh` fits circles to the trunk
/// Gaussians of a 20 cm slice: a uniform subset of a capped initialisation leaves too few
/// there (about 10 per stem with 10 k of the 179 k anchors of `tiny`). Sylva's choice.
pub const TRUNK_SHARE_OF_CAP: f64 = 0.5;

/// Share of the trunk Gaussians' part of a cap kept for the band of the DBH slices (Gaussians
/// within reach of a stem's axis between 0.5 and 2.1 m along it, [`super::dbh::in_dbh_band`]):
/// half (Sylva's choice). The trunk surfels are what stage `dbh` measures; an even draw over
/// the whole trunk surface leaves a 20 cm slice of a 17-stem plot about 8 surfels at a cap
/// of 10 000, too few for a circle (10 inliers at least), while the rest of the trunks, which
/// only the photos see, render as well from a coarser draw.
pub const DBH_BAND_SHARE_OF_TRUNKS: f64 = 0.5;

/// Keeps at most `max` Gaussians (all when `max` is 0 or not exceeded): up to
/// [`TRUNK_SHARE_OF_CAP`] of the cap from the trunk Gaussians (of that, up to
/// [`DBH_BAND_SHARE_OF_TRUNKS`] from those `band` marks, when given), the rest from the
/// others; a share one side does not use goes to the other. Each part is drawn evenly in
/// space ([`voxel_draw`]): one Gaussian per cell of the finest grid that fits the share, the
/// grid shifted by the seed, so a slice of a stem holds surfels all round its circumference
/// rather than a random subset's clumps and gaps. Scales are left as they are: the caller
/// sets them from the spacing of what is kept ([`crate::splat::init::rescale_from_spacing`]).
///
/// `added_later` Gaussians of the others' side (the sky dome) join the model after the cap:
/// the trunks' share is of `max + added_later`, so the dome's room comes from the others.
pub fn cap_gaussians(
    g: &mut Gaussians,
    max: u32,
    seed: u64,
    band: Option<&[bool]>,
    added_later: u32,
) {
    if let Some(keep) = cap_mask(&g.means, &g.trunk_prob, max, seed, band, added_later) {
        g.retain_mask(&keep);
    }
}

/// The draw of [`cap_gaussians`] on centres `means` with trunk probabilities `trunk_prob`
/// (one each): which to keep, or `None` when all stay. Lets a start draw its anchors before
/// it makes Gaussians of them (`super::start`), so millions of anchors never become
/// Gaussians only to be dropped.
pub fn cap_mask(
    means: &[[f32; 3]],
    trunk_prob: &[f32],
    max: u32,
    seed: u64,
    band: Option<&[bool]>,
    added_later: u32,
) -> Option<Vec<bool>> {
    let n = means.len().min(trunk_prob.len());
    if max == 0 || n <= max as usize {
        return None;
    }
    let max = max as usize;
    let in_band = |i: usize| band.is_some_and(|b| b.get(i).copied().unwrap_or(false));
    let (trunk, other): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| trunk_prob[i] >= 0.5);
    let (trunk_band, trunk_rest): (Vec<usize>, Vec<usize>) =
        trunk.iter().partition(|&&i| in_band(i));
    let share_of = max + added_later as usize;
    let reserve = ((share_of as f64 * TRUNK_SHARE_OF_CAP) as usize)
        .min(trunk.len())
        .min(max);
    let from_other = (max - reserve).min(other.len());
    let from_trunk = (max - from_other).min(trunk.len());
    let band_reserve =
        ((from_trunk as f64 * DBH_BAND_SHARE_OF_TRUNKS) as usize).min(trunk_band.len());
    let from_rest = (from_trunk - band_reserve).min(trunk_rest.len());
    let from_band = from_trunk - from_rest;
    let mut rng = SplitMix64::new(seed);
    let mut keep = vec![false; n];
    for (part, count) in [
        (&trunk_band, from_band),
        (&trunk_rest, from_rest),
        (&other, from_other),
    ] {
        for i in voxel_draw(means, part, count, &mut rng) {
            keep[i] = true;
        }
    }
    Some(keep)
}

/// Exactly `count` of the points `idx` of `means` (all when there are no more), spread evenly:
/// a bisection of the log cell edge (24 halvings, to 1e-6 of its range) finds the finest grid,
/// offset by a seeded random shift, with at most `count` occupied cells; each cell gives the
/// point nearest its centre, and a seeded random choice among the rest tops the draw up to
/// `count` (the occupied cells jump as the grid changes). Each halving hashes every point
/// once (25 passes in all).
pub fn voxel_draw(
    means: &[[f32; 3]],
    idx: &[usize],
    count: usize,
    rng: &mut SplitMix64,
) -> Vec<usize> {
    if count >= idx.len() {
        return idx.to_vec();
    }
    if count == 0 {
        return Vec::new();
    }
    let p = |i: usize| glam::DVec3::from(means[i].map(f64::from));
    let (lo, hi) = idx.iter().fold(
        (
            glam::DVec3::splat(f64::INFINITY),
            glam::DVec3::splat(f64::NEG_INFINITY),
        ),
        |(lo, hi), &i| (lo.min(p(i)), hi.max(p(i))),
    );
    let extent = (hi - lo).max_element().max(1e-6);
    let shift = glam::DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
    // One point per occupied cell of edge `v`: the nearest to the cell's centre.
    let cells = |v: f64| {
        let mut best: std::collections::HashMap<[i64; 3], (f64, usize)> =
            std::collections::HashMap::new();
        for &i in idx {
            let q = (p(i) - lo) / v + shift;
            let c = q.floor();
            let d2 = (q - c - glam::DVec3::splat(0.5)).length_squared();
            let key = [c.x as i64, c.y as i64, c.z as i64];
            let e = best.entry(key).or_insert((f64::INFINITY, i));
            if d2 < e.0 || (d2 == e.0 && i < e.1) {
                *e = (d2, i);
            }
        }
        let mut picked: Vec<usize> = best.into_values().map(|(_, i)| i).collect();
        picked.sort_unstable();
        picked
    };
    // Cell edges between extent / 1e6 (every point alone) and 2 × extent (one cell).
    let (mut fine, mut coarse) = ((extent * 1e-6).ln(), (2.0 * extent).ln());
    let mut picked = cells(coarse.exp());
    for _ in 0..24 {
        let mid = 0.5 * (fine + coarse);
        let c = cells(mid.exp());
        if c.len() <= count {
            coarse = mid;
            picked = c;
        } else {
            fine = mid;
        }
    }
    let mut taken = vec![false; means.len()];
    for &i in &picked {
        taken[i] = true;
    }
    let mut rest: Vec<usize> = idx.iter().copied().filter(|&i| !taken[i]).collect();
    while picked.len() < count && !rest.is_empty() {
        let j = rng.below(rest.len() as u64) as usize;
        picked.push(rest.swap_remove(j));
    }
    picked
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::init;
    use crate::splat::model::Gaussian;

    fn scene(trunk: usize, other: usize) -> Gaussians {
        let mut g = Gaussians::default();
        for i in 0..trunk + other {
            let mut one = Gaussian::isotropic([i as f32, 0.0, 0.0], 0.01, [0.5; 3], 0.1);
            one.trunk_prob = if i < trunk { 0.9 } else { 0.1 };
            g.push(one);
        }
        g
    }

    fn trunk_count(g: &Gaussians) -> usize {
        g.trunk_prob.iter().filter(|&&p| p >= 0.5).count()
    }

    #[test]
    fn a_cap_keeps_a_share_for_the_trunks_and_lends_what_one_side_leaves() {
        // (trunk Gaussians, others), cap, room for Gaussians added later; then (kept, trunks kept).
        for ((trunk, other), cap, later, kept) in [
            // Few trunk Gaussians: all are kept, the others fill the cap.
            ((50, 10_000), 1000, 0, (1000, 50)),
            // Many: half the cap for each side.
            ((5000, 10_000), 1000, 0, (1000, 500)),
            // Room for 100 Gaussians added later comes from the others' share.
            ((5000, 10_000), 900, 100, (900, 500)),
            // Few others: the trunks take the rest of the cap.
            ((5000, 100), 1000, 0, (1000, 900)),
        ] {
            let mut g = scene(trunk, other);
            cap_gaussians(&mut g, cap, 7, None, later);
            assert_eq!(
                (g.len(), trunk_count(&g)),
                kept,
                "{trunk} + {other} capped at {cap}"
            );
        }
        // Under the cap, or no cap: nothing goes.
        let mut g = scene(10, 10);
        cap_gaussians(&mut g, 1000, 7, None, 0);
        assert_eq!(g.len(), 20);
        cap_gaussians(&mut g, 0, 7, None, 0);
        assert_eq!(g.len(), 20);
        // The same seed keeps the same Gaussians; another keeps others.
        let (mut a, mut b, mut c) = (scene(3000, 3000), scene(3000, 3000), scene(3000, 3000));
        cap_gaussians(&mut a, 500, 1, None, 0);
        cap_gaussians(&mut b, 500, 1, None, 0);
        cap_gaussians(&mut c, 500, 2, None, 0);
        assert_eq!(a.means, b.means);
        assert_ne!(a.means, c.means);
    }

    /// The farthest any point of `all` lies from its nearest kept Gaussian, metres.
    fn covering_radius(all: &Gaussians, kept: &Gaussians) -> f32 {
        let pts: Vec<glam::Vec3> = kept
            .means
            .iter()
            .map(|m| glam::Vec3::from_array(*m))
            .collect();
        let index = crate::geom::PointIndex::new(&pts).expect("index");
        all.means
            .iter()
            .map(|m| {
                index
                    .nearest(glam::Vec3::from_array(*m))
                    .map_or(f32::INFINITY, |n| n.dist2.sqrt())
            })
            .fold(0.0, f32::max)
    }

    #[test]
    fn a_cap_draws_a_stem_surface_evenly_and_scales_follow_the_kept_spacing() {
        // 20 000 points at random on a 15 cm stem 10 m tall; a cap of 400 keeps one in 50.
        let mut rng = SplitMix64::new(3);
        let mut g = Gaussians::default();
        for _ in 0..20_000 {
            let a = rng.uniform() * std::f64::consts::TAU;
            let z = rng.uniform() * 10.0;
            let p = [(0.15 * a.cos()) as f32, (0.15 * a.sin()) as f32, z as f32];
            let mut one = Gaussian::isotropic(p, 0.005, [0.5; 3], 0.1);
            one.trunk_prob = 0.9;
            g.push(one);
        }
        let mut drawn = g.clone();
        cap_gaussians(&mut drawn, 400, 1, None, 0);
        assert_eq!(drawn.len(), 400);
        // A random subset of the same size, for comparison.
        let mut keep = vec![false; g.len()];
        let mut left: Vec<usize> = (0..g.len()).collect();
        for _ in 0..400 {
            let j = rng.below(left.len() as u64) as usize;
            keep[left.swap_remove(j)] = true;
        }
        let mut random = g.clone();
        random.retain_mask(&keep);
        let (even, uneven) = (covering_radius(&g, &drawn), covering_radius(&g, &random));
        assert!(even < 0.7 * uneven, "even draw {even} m, random {uneven} m");
        // 9.4 m² over 400 Gaussians: about 15 cm apart; the scales follow the kept spacing.
        init::rescale_from_spacing(&mut drawn, 1, 0.0);
        let mean_sigma = drawn
            .log_scales
            .iter()
            .map(|s| f64::from(s[0]).exp())
            .sum::<f64>()
            / 400.0;
        assert!(
            (0.06..0.2).contains(&mean_sigma),
            "mean nearest spacing {mean_sigma} m"
        );
    }
}
