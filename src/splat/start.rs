//! The start of training: the initial Gaussians, from the LiDAR anchors labelled by stage
//! `segment` (the paper's method) or from the SfM points (vanilla 3DGS), capped to the budget
//! by the draw of [`super::budget::cap_gaussians`], their scales taken again from what the cap
//! kept, and the sky dome added.

use super::budget::{cap_gaussians, cap_mask};
use super::dataset::Dataset;
use super::init::{
    Anchor, AnchorInit, CoverageFill, FillReport, InitError, add_sky, fill_uncovered, from_anchors,
    from_sfm_points, photometric_colours, rescale_from_spacing, seed_gaussian,
};
use super::model::Gaussians;

/// How a run starts (the initialisation part of `params.train`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Start {
    /// From the LiDAR anchors (true) or the SfM points (false).
    pub lidar: bool,
    /// With LiDAR anchors, also the SfM points farther than this from every anchor, metres
    /// (0 = none; `params.train.sfm_fill_m`).
    pub sfm_fill_m: f64,
    /// The Gaussian budget, sky dome included (0 = none).
    pub max_gaussians: u32,
    /// Gaussians of the sky dome (at most a tenth of a budget).
    pub sky_gaussians: u32,
    /// Seed of the draw.
    pub seed: u64,
}

/// Why the start failed.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error("LiDAR initialisation needs the anchors of stage segment")]
    NoAnchors,
    #[error("anchor initialisation: {0}")]
    Anchors(InitError),
    #[error("SfM initialisation: {0}")]
    Sfm(InitError),
}

/// The initial Gaussians of `start`: the LiDAR anchors, or the SfM points of `data` (which then
/// take the trunk probability of their nearest anchor when anchors are given, so the trunk
/// term can act on them too). Past the budget, [`cap_gaussians`] keeps the DBH band that
/// `band` marks (per Gaussian centre) dense.
pub fn initial_gaussians(
    data: &Dataset,
    start: &Start,
    anchors: Option<&[Anchor]>,
    band: &dyn Fn(&[[f32; 3]]) -> Vec<bool>,
) -> Result<Gaussians, StartError> {
    // The sky dome's share of a cap: at most a tenth.
    let sky = match start.max_gaussians {
        0 => start.sky_gaussians,
        max => start.sky_gaussians.min(max / 10),
    };
    let max = start.max_gaussians.saturating_sub(sky);
    let mut g = match (start.lidar, anchors) {
        (true, Some(anchors)) if start.max_gaussians > 0 && anchors.len() > max as usize => {
            capped_anchor_start(data, start, anchors, band, max, sky)?
        }
        (true, Some(anchors)) => {
            let mut g = from_anchors(anchors, &data.train, &AnchorInit::default())
                .map_err(StartError::Anchors)?;
            if start.sfm_fill_m > 0.0 {
                sfm_fill(&mut g, anchors, data, start.sfm_fill_m);
            }
            g
        }
        (true, None) => return Err(StartError::NoAnchors),
        (false, _) => {
            let mut g = from_sfm_points(&data.points, &data.colours).map_err(StartError::Sfm)?;
            if let Some(anchors) = anchors {
                inherit_trunk_prob(&mut g, anchors);
            }
            g
        }
    };
    let before = g.len();
    if start.max_gaussians > 0 && g.len() > max as usize {
        let band = band(&g.means);
        cap_gaussians(&mut g, max, start.seed, Some(&band), sky);
    }
    if g.len() < before {
        // Scales from the spacing of what the cap kept (the same rule as the source's).
        if start.lidar {
            rescale_from_spacing(&mut g, 1, AnchorInit::default().eps);
        } else {
            rescale_from_spacing(&mut g, 3, 0.0);
        }
    }
    add_sky(&mut g, &data.train, sky as usize);
    Ok(g)
}

/// The LiDAR start under a cap that the anchors exceed: the same Gaussians as making one of
/// every anchor (with the SfM fill), capping and taking the scales again, but the draw runs on
/// the anchors' positions first, so only the kept ones become Gaussians. The colours are the
/// photometric ones of every anchor (their visibility and reservoir draws as without a cap);
/// the scales come from the kept ones' spacing, as after a cap.
fn capped_anchor_start(
    data: &Dataset,
    start: &Start,
    anchors: &[Anchor],
    band: &dyn Fn(&[[f32; 3]]) -> Vec<bool>,
    max: u32,
    sky: u32,
) -> Result<Gaussians, StartError> {
    if anchors.is_empty() {
        return Err(StartError::Anchors(InitError::Empty));
    }
    let params = AnchorInit::default();
    let colours = photometric_colours(anchors, &data.train, &params);
    let fill = if start.sfm_fill_m > 0.0 {
        sfm_fill_points(anchors, data, start.sfm_fill_m)
    } else {
        (Vec::new(), Vec::new())
    };
    let means: Vec<[f32; 3]> = anchors
        .iter()
        .map(|a| a.position)
        .chain(fill.0.iter().copied())
        .collect();
    let probs: Vec<f32> = anchors
        .iter()
        .map(|a| a.trunk_prob)
        .chain(fill.0.iter().map(|_| 0.0))
        .collect();
    let band = band(&means);
    let keep = cap_mask(&means, &probs, max, start.seed, Some(&band), sky)
        .unwrap_or_else(|| vec![true; means.len()]);
    let mut g = Gaussians::default();
    for (i, a) in anchors.iter().enumerate() {
        if keep[i] {
            g.push(seed_gaussian(a.position, 0.0, colours[i], a.trunk_prob));
        }
    }
    let kept_fill: (Vec<[f32; 3]>, Vec<[u8; 3]>) = fill
        .0
        .iter()
        .zip(&fill.1)
        .enumerate()
        .filter(|(k, _)| keep[anchors.len() + k])
        .map(|(_, (p, c))| (*p, *c))
        .unzip();
    if let Ok(f) = from_sfm_points(&kept_fill.0, &kept_fill.1) {
        for i in 0..f.len() {
            g.push(f.get(i));
        }
    }
    // Scales from the spacing of what the cap kept (the anchors' own rule).
    rescale_from_spacing(&mut g, 1, params.eps);
    Ok(g)
}

/// The start of `sylva train` and the real-photo tests (SfM points only): one Gaussian per SfM point of `data`
/// (coloured from the photos where the model has no colours, [`Dataset`]), plus, with `fill`,
/// Gaussians where the training photos see what no SfM point covers
/// ([`fill_uncovered`]); capped at `max` by a draw of `seed` (0 = no cap) with the
/// scales taken again from what the cap kept. Also returns what the fill added (before the
/// cap; all zero without `fill`).
pub fn sfm_gaussians(
    data: &Dataset,
    max: u32,
    seed: u64,
    fill: Option<&CoverageFill>,
) -> Result<(Gaussians, FillReport), InitError> {
    let mut g = from_sfm_points(&data.points, &data.colours)?;
    let report = match fill {
        Some(fill) => fill_uncovered(&mut g, &data.train, fill),
        None => FillReport::default(),
    };
    let before = g.len();
    cap_gaussians(&mut g, max, seed, None, 0);
    if g.len() < before {
        rescale_from_spacing(&mut g, 3, 0.0);
    }
    Ok((g, report))
}

/// A nearest-neighbour index of the anchors' positions; `None` when they cannot be indexed.
fn anchor_index(anchors: &[Anchor]) -> Option<crate::geom::PointIndex> {
    let pts: Vec<glam::Vec3> = anchors
        .iter()
        .map(|a| glam::Vec3::from_array(a.position))
        .collect();
    crate::geom::PointIndex::new(&pts).ok()
}

/// Appends, as non-trunk Gaussians of the SfM rule, the SfM points of `data` farther than
/// `min_dist_m` from every anchor (`params.train.sfm_fill_m`).
fn sfm_fill(g: &mut Gaussians, anchors: &[Anchor], data: &Dataset, min_dist_m: f64) {
    let (points, colours) = sfm_fill_points(anchors, data, min_dist_m);
    if let Ok(fill) = from_sfm_points(&points, &colours) {
        for i in 0..fill.len() {
            g.push(fill.get(i));
        }
    }
}

/// The SfM points of `data` (with their colours) farther than `min_dist_m` from every anchor.
fn sfm_fill_points(
    anchors: &[Anchor],
    data: &Dataset,
    min_dist_m: f64,
) -> (Vec<[f32; 3]>, Vec<[u8; 3]>) {
    let Some(index) = anchor_index(anchors) else {
        return (Vec::new(), Vec::new());
    };
    let far = |p: &[f32; 3]| {
        index
            .nearest(glam::Vec3::from_array(*p))
            .is_none_or(|n| f64::from(n.dist2) > min_dist_m * min_dist_m)
    };
    data.points
        .iter()
        .zip(&data.colours)
        .filter(|(p, _)| far(p))
        .map(|(p, c)| (*p, *c))
        .unzip()
}

/// Sets every Gaussian's trunk probability to that of its nearest anchor.
fn inherit_trunk_prob(g: &mut Gaussians, anchors: &[Anchor]) {
    let Some(index) = anchor_index(anchors) else {
        return;
    };
    for (m, p) in g.means.iter().zip(g.trunk_prob.iter_mut()) {
        if let Some(n) = index.nearest(glam::Vec3::from_array(*m)) {
            *p = anchors[n.index as usize].trunk_prob;
        }
    }
}

/// `g` spread to `n` Gaussians (nothing happens when it has as many or more): each Gaussian
/// becomes ⌈n / len⌉ copies, each moved by a seeded normal offset of its own scale and
/// shrunk by the cube root of the copies (so the copies fill about the volume the one did),
/// then [`cap_gaussians`] draws `n` of them evenly. For benchmarks that need a model of a
/// given size from a sparse start (`sylva bench train --gaussians`, benches/gpu_check.sh), not
/// for training a twin: the stage starts from the LiDAR anchors.
pub fn spread_to(g: &mut Gaussians, n: usize, seed: u64) {
    let have = g.len();
    if have == 0 || n <= have {
        return;
    }
    let copies = n.div_ceil(have);
    let shrink = (copies as f32).cbrt().ln();
    let mut rng = crate::rng::SplitMix64::new(seed);
    let mut out = Gaussians {
        sh_degree: g.sh_degree,
        ..Gaussians::default()
    };
    for i in 0..have {
        let one = g.get(i);
        let sigma = one.log_scale.map(f32::exp);
        for _ in 0..copies {
            let mut c = one;
            for ((m, s), sig) in c.mean.iter_mut().zip(&mut c.log_scale).zip(sigma) {
                *m += sig * rng.normal() as f32;
                *s -= shrink;
            }
            out.push(c);
        }
    }
    cap_gaussians(&mut out, n as u32, seed, None, 0);
    *g = out;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::cpu::test_scenes::{random_scene, ring_dataset};

    #[test]
    fn a_capped_anchor_start_makes_the_gaussians_of_capping_them_all() {
        // 4000 anchors in the ring scene's volume (a quarter of them trunk), SfM points around
        // them for the fill, a cap of 600 with a sky dome of 40 and a DBH band.
        let truth = random_scene(3, 60, 0);
        let mut data = ring_dataset(&truth, 16);
        let mut rng = crate::rng::SplitMix64::new(5);
        let mut u = |a: f64| ((rng.uniform() - 0.5) * 2.0 * a) as f32;
        let anchors: Vec<Anchor> = (0..4000)
            .map(|i| Anchor {
                position: [u(1.0), u(1.0), u(1.0)],
                colour: [(i % 251) as u8, 90, 40],
                trunk_prob: if i % 4 == 0 { 0.9 } else { 0.1 },
            })
            .collect();
        data.points = (0..300).map(|_| [u(2.5), u(2.5), u(2.5)]).collect();
        data.colours = vec![[200, 180, 160]; 300];
        let band = |m: &[[f32; 3]]| m.iter().map(|p| p[2] < -0.5).collect::<Vec<bool>>();
        let start = Start {
            lidar: true,
            sfm_fill_m: 0.2,
            max_gaussians: 600,
            sky_gaussians: 40,
            seed: 9,
        };
        let got = initial_gaussians(&data, &start, Some(&anchors), &band).expect("start");
        // The old way: every anchor a Gaussian, the fill, the cap, the scales again, the dome.
        let mut want = from_anchors(&anchors, &data.train, &AnchorInit::default()).expect("all");
        sfm_fill(&mut want, &anchors, &data, start.sfm_fill_m);
        let b = band(&want.means);
        cap_gaussians(&mut want, 560, start.seed, Some(&b), 40);
        rescale_from_spacing(&mut want, 1, AnchorInit::default().eps);
        add_sky(&mut want, &data.train, 40);
        assert_eq!(got.len(), 600);
        assert!(
            got.trunk_prob.iter().filter(|&&p| p >= 0.5).count() > 200,
            "the trunks' share"
        );
        assert_eq!(got, want);
    }
}
