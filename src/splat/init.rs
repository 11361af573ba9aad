//! Initial Gaussians: from SfM points (vanilla 3DGS) or from LiDAR anchors (docs/method.md Stage 4).
//!
//! Both give one isotropic Gaussian per point with identity rotation, opacity 0.1 and a DC-only
//! colour. They differ in the scale (mean squared distance to 3 neighbours vs. distance to the
//! nearest anchor) and the colour: anchors take the median colour of their projections into the
//! training images where they are visible (the "photometric prior"), with visibility decided
//! against a coarse depth buffer of the anchors themselves.

use crate::splat::model::{Gaussian, Gaussians, SH_C0, SH_FLOATS};
use rayon::prelude::*;

use crate::rng::SplitMix64;
use crate::splat::camera::Camera;
use crate::splat::cameras::View;
use crate::splat::packed_image::{PackedImage, unpack};
use std::borrow::Cow;

/// Initial opacity, (0, 1). Reference `inverse_sigmoid(0.1 * ones)`; docs/method.md Stage 4.
pub const INIT_OPACITY: f32 = 0.1;
/// Floor of the squared neighbour distance, m². Reference `distCUDA2(...).clamp_min(1e-7)`.
pub const MIN_DIST2: f64 = 1e-7;
/// Cameras closer than this along the view axis see nothing, metres (docs/splatting.md NEAR).
const NEAR: f32 = 0.01;

/// Why no model could be built.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InitError {
    #[error("{points} points but {colours} colours; give one colour per point")]
    ColourCountMismatch { points: usize, colours: usize },
    #[error("no points to initialise from")]
    Empty,
}

/// One Gaussian with a DC colour from 8-bit RGB (reference `RGB2SH`: (c − 0.5) / C0).
pub(crate) fn seed_gaussian(
    mean: [f32; 3],
    log_scale: f32,
    rgb: [u8; 3],
    trunk_prob: f32,
) -> Gaussian {
    let mut sh = [0.0; SH_FLOATS];
    for c in 0..3 {
        sh[c] = (rgb[c] as f32 / 255.0 - 0.5) / SH_C0;
    }
    Gaussian {
        mean,
        log_scale: [log_scale; 3],
        rotation: [1.0, 0.0, 0.0, 0.0],
        opacity_logit: (INIT_OPACITY / (1.0 - INIT_OPACITY)).ln(),
        sh,
        trunk_prob,
    }
}

/// Vanilla 3DGS initialisation from SfM points: log-scale = log sqrt(mean squared distance to the
/// 3 nearest other points, floored at [`MIN_DIST2`]); trunk probability 0.
pub fn from_sfm_points(points: &[[f32; 3]], colours: &[[u8; 3]]) -> Result<Gaussians, InitError> {
    if points.len() != colours.len() {
        return Err(InitError::ColourCountMismatch {
            points: points.len(),
            colours: colours.len(),
        });
    }
    if points.is_empty() {
        return Err(InitError::Empty);
    }
    let knn = self_knn_dist2(points, 3);
    let mut g = Gaussians::default();
    for ((p, c), d) in points.iter().zip(colours).zip(&knn) {
        let mean_d2 = if d.is_empty() {
            MIN_DIST2
        } else {
            d.iter().sum::<f64>() / d.len() as f64
        };
        g.push(seed_gaussian(
            *p,
            (0.5 * mean_d2.max(MIN_DIST2).ln()) as f32,
            *c,
            0.0,
        ));
    }
    Ok(g)
}

/// Sets every Gaussian's three scales to log sqrt(mean squared distance to its `k` nearest
/// other Gaussians + `eps`) — the initial scale rule of [`from_sfm_points`] (`k` = 3) and
/// [`from_anchors`] (`k` = 1) — for Gaussians whose neighbours changed after a cap dropped
/// some: a scale from the spacing before the draw would leave holes between those kept.
pub fn rescale_from_spacing(g: &mut Gaussians, k: usize, eps: f64) {
    let knn = self_knn_dist2(&g.means, k);
    for (s, d) in g.log_scales.iter_mut().zip(&knn) {
        let mean_d2 = if d.is_empty() {
            MIN_DIST2
        } else {
            d.iter().sum::<f64>() / d.len() as f64
        };
        *s = [(0.5 * (mean_d2 + eps).max(MIN_DIST2).ln()) as f32; 3];
    }
}

/// Trunk probability that marks a background Gaussian of the sky dome ([`sky_dome`]): below
/// every label, so no trunk term takes it, and exempt from the size pruning of the density
/// control (a dome Gaussian is large by design).
pub const BACKGROUND_PROB: f32 = -1.0;

/// `n` points spread evenly (a Fibonacci lattice) over the sphere of `radius_m` about
/// `centre`: the positions of the background Gaussians that take what the photos show beyond
/// the scene — sky, distant terrain — which would otherwise be painted by floaters in front of
/// it or left black.
pub fn sky_dome(centre: [f32; 3], radius_m: f32, n: usize) -> Vec<[f32; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f64;
            [
                centre[0] + radius_m * (r * a.cos()) as f32,
                centre[1] + radius_m * (r * a.sin()) as f32,
                centre[2] + radius_m * z as f32,
            ]
        })
        .collect()
}

/// Appends `n` background Gaussians on a dome ([`sky_dome`]) about the mean of the views'
/// camera centres, of twice the radius that holds every camera and every Gaussian of `g`:
/// isotropic, as wide as their spacing on the dome, trunk probability [`BACKGROUND_PROB`],
/// coloured like anchors by the median of their projections where nothing of `g` is in front
/// (grey where they are never seen).
pub fn add_sky(g: &mut Gaussians, views: &[View], n: usize) {
    if n == 0 || views.is_empty() {
        return;
    }
    let centres: Vec<glam::Vec3> = views
        .iter()
        .map(|v| glam::Vec3::from_array(v.camera.centre()))
        .collect();
    let centre = centres.iter().copied().sum::<glam::Vec3>() / centres.len() as f32;
    let reach = centres
        .iter()
        .copied()
        .chain(g.means.iter().map(|m| glam::Vec3::from_array(*m)))
        .filter(|p| p.is_finite())
        .map(|p| p.distance(centre))
        .fold(1.0f32, f32::max);
    let radius = 2.0 * reach;
    let dome = sky_dome(centre.to_array(), radius, n);
    let grey = [128u8; 3];
    let anchors: Vec<Anchor> = g
        .means
        .iter()
        .chain(&dome)
        .map(|&position| Anchor {
            position,
            colour: grey,
            trunk_prob: 0.0,
        })
        .collect();
    let colours = photometric_colours(&anchors, views, &AnchorInit::default());
    let spacing = radius * (4.0 * std::f32::consts::PI / n as f32).sqrt();
    for (p, c) in dome.iter().zip(&colours[g.len()..]) {
        g.push(seed_gaussian(*p, spacing.ln(), *c, BACKGROUND_PROB));
    }
}

/// Parameters of [`fill_uncovered`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoverageFill {
    /// Cells along each photo's long side; a cell is the unit of coverage. Default 32 (ours:
    /// about 10 px at 320 px and 50 px at 1600 px, so a photo adds at most 32 × 32 Gaussians).
    pub cells_long_side: u32,
    /// Percentile of the depths of the points a photo sees at which a cell is placed when the
    /// photos do not agree on a depth for it, [0, 1] (0.9 was the only rule before the sweep:
    /// what SfM misses is mostly far or textureless); `None` leaves such a cell to
    /// densification. Default `None` (measured on the real photo sets, docs/results/
    /// splatting.md "A depth the photos agree on": the guessed cells cost Brighton's UAV
    /// forest 0.7–1.0 dB at 2000 steps).
    pub depth_percentile: Option<f64>,
    /// Depths tried per cell, evenly in inverse depth (a plane sweep), from half the 2nd to
    /// the 98th percentile of the depths of the points the photo sees; 0 places every cell at
    /// `depth_percentile` (the rule before issue 38's Brighton finding). Default 32 (ours: at
    /// 320 px, adjacent candidates move a cell by well under a pixel in the neighbouring
    /// photos of both real photo sets).
    pub depth_candidates: u32,
    /// Other photos a cell is compared with: those with the nearest camera centres. The cost
    /// of a depth is the mean of the better half of theirs, so a neighbour that sees the
    /// point occluded or off its frame does not decide. Default 4 (ours).
    pub neighbours: usize,
    /// Samples along each side of the cell's square patch (bilinear). Default 5 (ours: about
    /// one sample per 2 px at 320 px).
    pub samples_per_side: u32,
    /// A depth is taken only when its cost is at most this share of the median cost over the
    /// candidates (a clear minimum; with `textured`, see there, also of more); otherwise the
    /// cell goes to `depth_percentile`. Default 0.8 (ours: a textureless cell, sky or a plain
    /// wall, costs the same at every depth).
    pub max_cost_ratio: f32,
    /// Whether a cell that none of the `neighbours` sees (at fewer than 3 of the depths) also
    /// goes to `depth_percentile` (when that is set). Default false (ours: only its own photo
    /// constrains such a Gaussian, at a depth guessed from that photo's points).
    pub place_unseen: bool,
    /// Whether a depth also needs texture and a unique minimum: the cost below
    /// `max_cost_ratio` of the cell's own texture and of every other local minimum, the
    /// minimum inside the swept range, and at least [`MIN_TEXTURE`] of texture
    /// (docs/method.md Stage 4; `sylva train --fill textured`). Default false (measured,
    /// docs/results/splatting.md "The fill's sky": +1.88 dB on the generated `object` scene at
    /// 2000 steps, level or better on the real photos at 500, but 0.04 dB short of the real
    /// trunk test's gate at 300 steps and 160 px, where the flat cells it leaves out still
    /// help).
    pub textured: bool,
}

impl Default for CoverageFill {
    fn default() -> Self {
        CoverageFill {
            cells_long_side: 32,
            depth_percentile: None,
            depth_candidates: 32,
            neighbours: 4,
            samples_per_side: 5,
            max_cost_ratio: 0.8,
            place_unseen: false,
            textured: false,
        }
    }
}

/// What [`fill_uncovered`] added.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FillReport {
    /// Gaussians added.
    pub added: usize,
    /// Of those, the ones placed at a depth on which the photos agreed; the rest sit at the
    /// fallback percentile depth.
    pub agreed: usize,
    /// Uncovered cells left to densification because no neighbouring photo sees them (without
    /// [`CoverageFill::place_unseen`]).
    pub unseen: usize,
    /// Uncovered cells left to densification because the photos agree on no depth for them
    /// and there is no fallback depth ([`CoverageFill::depth_percentile`] `None`).
    pub ambiguous: usize,
}

/// Where the photos put an uncovered cell ([`Sweep::place`]).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Placement {
    /// At this depth, metres: a clear minimum of the matching cost.
    Agreed(f32),
    /// Seen by a neighbouring photo, but no depth stands out (textureless), or no sweep.
    Ambiguous,
    /// No neighbouring photo sees the cell's patch.
    Unseen,
}

/// Adds a Gaussian wherever a training photo sees something that no Gaussian of `g` projects
/// to, and says how many it added.
///
/// An SfM model has no points where matching fails: dense canopy from above, bark in shadow,
/// sky and walls. Gaussians grow into such a hole only slowly by densification, so the
/// photos' forest came out as a flat wash (Brighton's UAV photos: no SfM point in the left
/// third of a held-out photo, issue 38). Each photo in turn is cut into a grid of cells
/// (`cells_long_side` along its long side); every cell no Gaussian projects into — the
/// Gaussians added for earlier photos included, so a hole seen by many photos is filled once
/// — gets one Gaussian on the ray through its centre, coloured by the cell's mean pixel,
/// isotropic with σ half the cell's footprint at its depth, at the initial opacity. Photos
/// that see no point are skipped.
///
/// The depth is the one on which the photos agree (`Sweep::place`): a plane sweep over
/// `depth_candidates` depths, comparing the cell's patch with where it lands in the
/// `neighbours` photos nearest this one. Where no depth stands out (a textureless cell) the
/// cell goes to the `depth_percentile` depth of the points the photo sees, or is left to
/// densification when that is `None`; so is a cell that no neighbouring photo sees, unless
/// `place_unseen`. A single depth per
/// photo put a closed canopy seen from above at the ground beneath it, where the other photos
/// saw it in the wrong place (Brighton at 2000 steps, docs/results/splatting.md).
pub fn fill_uncovered(g: &mut Gaussians, views: &[View], params: &CoverageFill) -> FillReport {
    let mut report = FillReport::default();
    let centres: Vec<glam::Vec3> = views
        .iter()
        .map(|v| glam::Vec3::from_array(v.camera.centre()))
        .collect();
    for (vi, view) in views.iter().enumerate() {
        let cam = &view.camera;
        let (w, h) = (
            view.image.width.min(cam.width),
            view.image.height.min(cam.height),
        );
        let cell = w.max(h).div_ceil(params.cells_long_side.max(1)).max(1);
        let (gw, gh) = (w.div_ceil(cell) as usize, h.div_ceil(cell) as usize);
        let projected: Vec<(usize, f32)> = g
            .means
            .par_iter()
            .filter_map(|m| {
                let (x, y, z) = project_pixel(cam, *m, w, h)?;
                Some(((y / cell) as usize * gw + (x / cell) as usize, z))
            })
            .collect();
        if projected.is_empty() {
            continue;
        }
        let mut covered = vec![false; gw * gh];
        let mut depths: Vec<f32> = Vec::with_capacity(projected.len());
        for &(c, z) in &projected {
            covered[c] = true;
            depths.push(z);
        }
        depths.sort_unstable_by(f32::total_cmp);
        let at = |q: f64| depths[((depths.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize];
        let fallback = params.depth_percentile.map(at);
        let sweep = Sweep::new(
            0.5 * at(0.02),
            at(0.98),
            params.depth_candidates,
            nearest_views(&centres, vi, params.neighbours),
        );
        // The photos decoded once for the view (borrowed when held decoded). One that cannot
        // be decoded adds nothing here; training meets the same photo and fails with its error.
        let Ok(own) = view.image.image() else {
            continue;
        };
        let Ok(others) = sweep
            .neighbours
            .iter()
            .map(|&j| views[j].image.image().map(|img| (&views[j].camera, img)))
            .collect::<Result<Vec<_>, _>>()
        else {
            continue;
        };
        let cells: Vec<usize> = (0..covered.len()).filter(|&c| !covered[c]).collect();
        // Per cell: None without pixels, else (Gaussian or None, agreed, unseen, ambiguous).
        type Placed = Option<(Option<(glam::Vec3, f32, [u8; 3])>, bool, bool, bool)>;
        let placed: Vec<Placed> = cells
            .par_iter()
            .map(|&c| {
                let (cx, cy) = ((c % gw) as u32 * cell, (c / gw) as u32 * cell);
                let colour = cell_colour(&own, cx, cy, cell)?;
                let (cw, ch) = (cell.min(w - cx) as f32, cell.min(h - cy) as f32);
                let (px, py) = (cx as f32 + 0.5 * cw, cy as f32 + 0.5 * ch);
                let place = sweep.place((cam, &own), &others, [px, py], cw.min(ch), params);
                let depth = match place {
                    Placement::Agreed(d) => Some(d),
                    Placement::Ambiguous => fallback,
                    Placement::Unseen => fallback.filter(|_| params.place_unseen),
                };
                let unseen = place == Placement::Unseen && depth.is_none();
                let ambiguous = place == Placement::Ambiguous && depth.is_none();
                let agreed = matches!(place, Placement::Agreed(_));
                let gaussian = depth.map(|depth| {
                    let pc = [
                        (px - cam.cx) / cam.fx * depth,
                        (py - cam.cy) / cam.fy * depth,
                        depth,
                    ];
                    let mean = glam::Vec3::from_array(camera_to_world(cam, pc));
                    (mean, depth, colour)
                });
                Some((gaussian, agreed, unseen, ambiguous))
            })
            .collect();
        for (gaussian, agreed, unseen, ambiguous) in placed.into_iter().flatten() {
            report.unseen += usize::from(unseen);
            report.ambiguous += usize::from(ambiguous);
            let Some((mean, depth, colour)) = gaussian else {
                continue;
            };
            let sigma = 0.5 * cell as f32 * depth / cam.fx.abs().max(f32::MIN_POSITIVE);
            g.push(seed_gaussian(mean.to_array(), sigma.ln(), colour, 0.0));
            report.added += 1;
            report.agreed += usize::from(agreed);
        }
    }
    report
}

/// Indices of the `k` views other than `i` whose camera centres are nearest view `i`'s.
fn nearest_views(centres: &[glam::Vec3], i: usize, k: usize) -> Vec<usize> {
    let mut others: Vec<(f32, usize)> = centres
        .iter()
        .enumerate()
        .filter(|&(j, c)| j != i && c.is_finite())
        .map(|(j, c)| (c.distance_squared(centres[i]), j))
        .collect();
    others.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    others.into_iter().take(k).map(|(_, j)| j).collect()
}

/// The candidate depths of one photo's cells and the photos they are compared in.
struct Sweep {
    depths: Vec<f32>,
    neighbours: Vec<usize>,
}

impl Sweep {
    /// `n` depths evenly spaced in inverse depth over [`near`, `far`] metres (none when the
    /// range is empty or not finite, or `n` is 0).
    fn new(near: f32, far: f32, n: u32, neighbours: Vec<usize>) -> Self {
        let ok = near.is_finite() && far.is_finite() && near > NEAR && far > near;
        let depths = if !ok || n == 0 || neighbours.is_empty() {
            Vec::new()
        } else if n == 1 {
            vec![far]
        } else {
            let (a, b) = (1.0 / near, 1.0 / far);
            (0..n)
                .map(|k| 1.0 / (a + (b - a) * k as f32 / (n - 1) as f32))
                .collect()
        };
        Sweep { depths, neighbours }
    }

    /// Where the photos put the square patch of side `side` px about pixel `centre` of `view`:
    /// at the candidate depth (metres) where it looks most alike in the neighbouring views, when
    /// that stands out — its cost at most `max_cost_ratio` of the median over the candidates
    /// that any neighbour sees; [`Placement::Unseen`] when fewer than 3 candidates are seen by
    /// any neighbour. The cost at a depth is the mean absolute difference of the two patches, each
    /// less its own mean colour (robust to the photos' exposure), over the better half of the
    /// neighbours that see the whole patch; the patch is taken as a plane facing this photo.
    fn place(
        &self,
        (cam, img): (&Camera, &PackedImage),
        others: &[(&Camera, Cow<'_, PackedImage>)],
        centre: [f32; 2],
        side: f32,
        params: &CoverageFill,
    ) -> Placement {
        if self.depths.is_empty() {
            return Placement::Ambiguous;
        }
        let n = params.samples_per_side.max(2);
        let step = side / n as f32;
        let offsets: Vec<[f32; 2]> = (0..n * n)
            .map(|k| {
                [
                    centre[0] + ((k % n) as f32 + 0.5) * step - 0.5 * side,
                    centre[1] + ((k / n) as f32 + 0.5) * step - 0.5 * side,
                ]
            })
            .collect();
        let Some(own) = offsets
            .iter()
            .map(|p| opaque_sample(img, cam, p[0], p[1]))
            .collect::<Option<Vec<[f32; 3]>>>()
        else {
            return Placement::Ambiguous;
        };
        let own = less_mean(own);
        let mut costs: Vec<Option<f32>> = Vec::with_capacity(self.depths.len());
        for &d in &self.depths {
            let points: Vec<[f32; 3]> = offsets
                .iter()
                .map(|p| {
                    camera_to_world(
                        cam,
                        [
                            (p[0] - cam.cx) / cam.fx * d,
                            (p[1] - cam.cy) / cam.fy * d,
                            d,
                        ],
                    )
                })
                .collect();
            let mut per_view: Vec<f32> = others
                .iter()
                .filter_map(|(oc, other)| {
                    let theirs: Vec<[f32; 3]> = points
                        .iter()
                        .map(|&p| {
                            let c = oc.to_camera(p);
                            if c[2].is_nan() || c[2] < NEAR {
                                return None;
                            }
                            opaque_sample(
                                other,
                                oc,
                                oc.fx * c[0] / c[2] + oc.cx,
                                oc.fy * c[1] / c[2] + oc.cy,
                            )
                        })
                        .collect::<Option<_>>()?;
                    let theirs = less_mean(theirs);
                    let sad: f32 = own
                        .iter()
                        .zip(&theirs)
                        .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).abs()).sum::<f32>())
                        .sum();
                    Some(sad / (3 * own.len()) as f32)
                })
                .collect();
            if per_view.is_empty() {
                costs.push(None);
                continue;
            }
            per_view.sort_unstable_by(f32::total_cmp);
            let better = per_view.len().div_ceil(2);
            costs.push(Some(per_view[..better].iter().sum::<f32>() / better as f32));
        }
        let mut seen: Vec<f32> = costs.iter().flatten().copied().collect();
        if seen.len() < 3 {
            return Placement::Unseen;
        }
        seen.sort_unstable_by(f32::total_cmp);
        let median = seen[seen.len() / 2];
        let (k, best) = costs
            .iter()
            .enumerate()
            .filter_map(|(k, c)| Some((k, (*c)?)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, f32::INFINITY));
        let placed = if params.textured {
            textured_match(&own, n, &costs, k, best, median, params.max_cost_ratio)
        } else {
            median > 0.0 && best <= params.max_cost_ratio * median
        };
        if !placed {
            return Placement::Ambiguous;
        }
        // Between the candidates: the vertex of the parabola through the best cost and its two
        // neighbours, in inverse depth (where the candidates are evenly spaced).
        let (before, after) = (
            k.checked_sub(1).and_then(|i| costs[i]),
            costs.get(k + 1).copied().flatten(),
        );
        let shift = match (before, after) {
            (Some(a), Some(b)) if a + b - 2.0 * best > 0.0 => {
                (0.5 * (a - b) / (a + b - 2.0 * best)).clamp(-0.5, 0.5)
            }
            _ => 0.0,
        };
        let inverse = |i: usize| 1.0 / self.depths[i];
        let step = if self.depths.len() > 1 {
            inverse(1) - inverse(0)
        } else {
            0.0
        };
        Placement::Agreed(1.0 / (inverse(k) + shift * step))
    }
}

/// RGB (0–255) of photo `img` (seen by `cam`) at continuous pixel (`x`, `y`) by bilinear
/// interpolation, when every pixel it draws on is opaque (inside an undistorted photo) and it
/// lies inside the camera.
fn opaque_sample(img: &PackedImage, cam: &Camera, x: f32, y: f32) -> Option<[f32; 3]> {
    let (w, h) = (
        img.width.min(cam.width) as f32,
        img.height.min(cam.height) as f32,
    );
    if !(x >= 0.0 && y >= 0.0 && x <= w && y <= h) {
        return None;
    }
    let s = img.sample_bilinear(f64::from(x), f64::from(y))?;
    (s[3] >= 254.5).then_some([s[0], s[1], s[2]])
}

/// The tests of [`CoverageFill::textured`] for the least cost `best` at candidate `k` of
/// `costs` (median `median`), the cell's own samples `own` (an `n` × `n` grid, less its mean):
/// a match better than a flat patch, the only local minimum, inside the swept range, on at
/// least [`MIN_TEXTURE`] of texture.
fn textured_match(
    own: &[[f32; 3]],
    n: u32,
    costs: &[Option<f32>],
    k: usize,
    best: f32,
    median: f32,
    ratio: f32,
) -> bool {
    // The cost of this patch against a flat one (its own texture): a depth is a match only
    // where it beats that by the same margin. Without this, a textureless cell (sky, a plain
    // wall) whose neighbours' patches cross an edge at some depths and plain sky at others has
    // a clear minimum that is no depth at all (the generated `object` scene: 2 953
    // sky-coloured Gaussians of 3 973 placed in front of the scene, issue 38). Its texture is
    // what a plane (a constant and a gradient per channel) leaves of it: a ramp alone, as a
    // sky's, lines up with itself at any depth.
    let texture = detail(own, n);
    // And the minimum must be the only one: a smooth ramp (a sky's gradient) matches itself at
    // every depth where the neighbours' patches stay on it, so its cost curve holds several
    // minima about as low (Lowe's ratio test, on the curve's local minima).
    let local_minimum = |i: usize, c: f32| {
        let left = i.checked_sub(1).and_then(|j| costs[j]);
        let right = costs.get(i + 1).copied().flatten();
        left.is_none_or(|l| l >= c) && right.is_none_or(|r| r >= c)
    };
    let second = costs
        .iter()
        .enumerate()
        .filter_map(|(i, c)| Some((i, (*c)?)))
        .filter(|&(i, c)| i != k && local_minimum(i, c))
        .map(|(_, c)| c)
        .min_by(f32::total_cmp)
        .unwrap_or(f32::INFINITY);
    let floor = median.min(texture).min(second);
    // A minimum at the end of the swept range (or beside a depth no neighbour sees) may lie
    // beyond it: a sky's cost falls toward the far end, where the parallax vanishes.
    let interior = k > 0 && costs[k - 1].is_some() && costs.get(k + 1).copied().flatten().is_some();
    // Strictly below, and on more texture than the photos' 8-bit steps make: a flat patch
    // costs 0 wherever it lands on flat sky, and a gradient quantised to steps of one grey
    // level leaves a residual of a fraction of one.
    interior && texture >= MIN_TEXTURE && best < ratio * floor
}

/// Least texture ([`detail`]) a cell needs for a depth, grey levels: one step of an 8-bit
/// photo (ours; a quantised smooth gradient leaves about a quarter of one).
pub const MIN_TEXTURE: f32 = 1.0;

/// Mean absolute residual of `s` (an `n` × `n` grid of samples, row-major, each channel of
/// zero mean) about its least-squares plane per channel, grey levels (0–255): the texture that
/// a gradient does not explain.
fn detail(s: &[[f32; 3]], n: u32) -> f32 {
    let n = n as usize;
    if n < 2 || s.len() != n * n {
        return 0.0;
    }
    // Centred grid coordinates: the plane's constant, u and v terms are orthogonal.
    let c = |i: usize| i as f32 - 0.5 * (n - 1) as f32;
    let suu: f32 = (0..n).map(|i| c(i) * c(i)).sum::<f32>() * n as f32;
    let mut total = 0.0f32;
    for k in 0..3 {
        let (mut su, mut sv) = (0.0f32, 0.0f32);
        for (j, p) in s.iter().enumerate() {
            su += p[k] * c(j % n);
            sv += p[k] * c(j / n);
        }
        let (bu, bv) = (su / suu, sv / suu);
        total += s
            .iter()
            .enumerate()
            .map(|(j, p)| (p[k] - bu * c(j % n) - bv * c(j / n)).abs())
            .sum::<f32>();
    }
    total / (3 * s.len()) as f32
}

/// The samples less their mean colour, per channel.
fn less_mean(mut s: Vec<[f32; 3]>) -> Vec<[f32; 3]> {
    let n = s.len().max(1) as f32;
    let mean: [f32; 3] = std::array::from_fn(|k| s.iter().map(|p| p[k]).sum::<f32>() / n);
    for p in &mut s {
        for k in 0..3 {
            p[k] -= mean[k];
        }
    }
    s
}

/// The pixel (column, row) and depth (metres) of world point `p` in `cam`, when it lies at
/// least [`NEAR`] in front of the camera and inside the `w` × `h` image.
fn project_pixel(
    cam: &crate::splat::camera::Camera,
    p: [f32; 3],
    w: u32,
    h: u32,
) -> Option<(u32, u32, f32)> {
    let c = cam.to_camera(p);
    if c[2].is_nan() || c[2] < NEAR {
        return None;
    }
    let x = cam.fx * c[0] / c[2] + cam.cx;
    let y = cam.fy * c[1] / c[2] + cam.cy;
    let inside = x >= 0.0 && y >= 0.0 && x < w as f32 && y < h as f32;
    inside.then_some((x as u32, y as u32, c[2]))
}

/// Camera coordinates back to the world: Rᵀ (p − t).
fn camera_to_world(cam: &crate::splat::camera::Camera, p: [f32; 3]) -> [f32; 3] {
    let d = [p[0] - cam.t[0], p[1] - cam.t[1], p[2] - cam.t[2]];
    std::array::from_fn(|k| cam.r[0][k] * d[0] + cam.r[1][k] * d[1] + cam.r[2][k] * d[2])
}

/// Mean colour of the opaque pixels of the `cell`-px square at (`x0`, `y0`); `None` when it
/// holds none (outside an undistorted photo).
fn cell_colour(img: &PackedImage, x0: u32, y0: u32, cell: u32) -> Option<[u8; 3]> {
    let (mut sum, mut n) = ([0u64; 3], 0u64);
    for y in y0..(y0 + cell).min(img.height) {
        for x in x0..(x0 + cell).min(img.width) {
            let p = unpack(img.pixels[(y * img.width + x) as usize]);
            if p[3] > 0 {
                for c in 0..3 {
                    sum[c] += u64::from(p[c]);
                }
                n += 1;
            }
        }
    }
    (n > 0).then(|| sum.map(|s| (s / n) as u8))
}

/// A LiDAR anchor: position (metres), its own colour (fallback) and trunk probability P_i.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    pub position: [f32; 3],
    pub colour: [u8; 3],
    pub trunk_prob: f32,
}

/// Parameters of the anchor initialisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorInit {
    /// eps of s = log sqrt(d² + eps), m². Default 1e-7 (the reference's distance floor; docs/method.md
    /// leaves eps open).
    pub eps: f64,
    /// Cell size of the coarse per-image depth buffer, pixels. Default 8 (about the spacing of
    /// voxel-downsampled anchors in a 1–2 MP image; ours).
    pub depth_cell_px: u32,
    /// An anchor is visible when its depth is within this relative margin of its cell's nearest
    /// anchor. Default 0.03 (ours).
    pub depth_tolerance: f32,
    /// Colour samples kept per anchor (reservoir sampling); the median is taken over them.
    /// Default 16 (ours; bounds memory at millions of anchors).
    pub max_samples: usize,
    /// Seed of the reservoir sampling. Default 0.
    pub seed: u64,
}

impl Default for AnchorInit {
    fn default() -> Self {
        AnchorInit {
            eps: MIN_DIST2,
            depth_cell_px: 8,
            depth_tolerance: 0.03,
            max_samples: 16,
            seed: 0,
        }
    }
}

/// Anchor initialisation (paper 3.3.3): s = log sqrt(d² + eps) with d to the nearest other
/// anchor; colour = per-channel median of the anchor's visible projections into `views`,
/// falling back to its own colour; trunk probability from the anchor.
pub fn from_anchors(
    anchors: &[Anchor],
    views: &[View],
    params: &AnchorInit,
) -> Result<Gaussians, InitError> {
    if anchors.is_empty() {
        return Err(InitError::Empty);
    }
    let positions: Vec<[f32; 3]> = anchors.iter().map(|a| a.position).collect();
    let nearest = self_knn_dist2(&positions, 1);
    let colours = photometric_colours(anchors, views, params);
    let mut g = Gaussians::default();
    for ((a, d), c) in anchors.iter().zip(&nearest).zip(colours) {
        let d2 = d.first().copied().unwrap_or(0.0);
        g.push(seed_gaussian(
            a.position,
            (0.5 * (d2 + params.eps).max(f64::MIN_POSITIVE).ln()) as f32,
            c,
            a.trunk_prob,
        ));
    }
    Ok(g)
}

/// Per anchor, the median colour of its projections into the views where it is visible, or its
/// own colour where it is visible in none.
pub fn photometric_colours(
    anchors: &[Anchor],
    views: &[View],
    params: &AnchorInit,
) -> Vec<[u8; 3]> {
    // One flat reservoir of `keep` samples per anchor (3 B each) with its fill and the count
    // of views that saw the anchor: 53 B an anchor at the default 16 samples, for the millions
    // of anchors of a paper-size plot (a vector per anchor took twice that).
    let keep = params.max_samples.clamp(1, usize::from(u8::MAX));
    let mut samples = vec![[0u8; 3]; anchors.len() * keep];
    let mut filled = vec![0u8; anchors.len()];
    let mut seen = vec![0u64; anchors.len()];
    let mut rng = SplitMix64::new(params.seed);
    for view in views {
        for (i, c) in visible_colours(anchors, view, params) {
            seen[i] += 1;
            let f = usize::from(filled[i]);
            if f < keep {
                samples[i * keep + f] = c;
                filled[i] += 1;
            } else {
                let j = rng.below(seen[i]) as usize;
                if j < keep {
                    samples[i * keep + j] = c;
                }
            }
        }
    }
    anchors
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let s = samples[i * keep..i * keep + usize::from(filled[i])].to_vec();
            median_colour(s).unwrap_or(a.colour)
        })
        .collect()
}

/// (anchor index, pixel colour) for every anchor visible in `view`.
fn visible_colours(anchors: &[Anchor], view: &View, params: &AnchorInit) -> Vec<(usize, [u8; 3])> {
    let cam = &view.camera;
    let (w, h) = (
        view.image.width.min(cam.width),
        view.image.height.min(cam.height),
    );
    let cell = params.depth_cell_px.max(1);
    let (gw, gh) = (w.div_ceil(cell) as usize, h.div_ceil(cell) as usize);
    // (pixel x, pixel y, depth) of anchors in front of the camera and inside the image.
    let projected: Vec<Option<(u32, u32, f32)>> = anchors
        .par_iter()
        .map(|a| project_pixel(cam, a.position, w, h))
        .collect();
    // A photo that cannot be decoded colours nothing here; training meets the same photo and
    // fails with its error.
    let Ok(img) = view.image.image() else {
        return Vec::new();
    };
    let mut depth = vec![f32::INFINITY; gw * gh];
    for &(x, y, z) in projected.iter().flatten() {
        let c = &mut depth[(y / cell) as usize * gw + (x / cell) as usize];
        *c = c.min(z);
    }
    let tol = 1.0 + params.depth_tolerance.max(0.0);
    projected
        .iter()
        .enumerate()
        .filter_map(|(i, pr)| {
            let (x, y, z) = (*pr)?;
            if z > depth[(y / cell) as usize * gw + (x / cell) as usize] * tol {
                return None;
            }
            let px = unpack(img.pixels[(y * img.width + x) as usize]);
            (px[3] > 0).then_some((i, [px[0], px[1], px[2]]))
        })
        .collect()
}

/// Per-channel median (upper middle for an even count); `None` for no samples.
fn median_colour(mut s: Vec<[u8; 3]>) -> Option<[u8; 3]> {
    if s.is_empty() {
        return None;
    }
    let mid = s.len() / 2;
    Some(std::array::from_fn(|c| {
        s.sort_unstable_by_key(|p| p[c]);
        s[mid][c]
    }))
}

/// For every point, the squared distances (m²) to its `k` nearest other points, in input order
/// (fewer than `k` when there are not that many; none when the points cannot be indexed).
pub(crate) fn self_knn_dist2(points: &[[f32; 3]], k: usize) -> Vec<Vec<f64>> {
    let positions: Vec<glam::Vec3> = points.iter().map(|p| glam::Vec3::from_array(*p)).collect();
    let Ok(index) = crate::geom::PointIndex::new(&positions) else {
        return vec![Vec::new(); points.len()];
    };
    positions
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            index
                .knn(*p, k + 1)
                .into_iter()
                .filter(|n| n.index as usize != i)
                .take(k)
                .map(|n| f64::from(n.dist2))
                .collect()
        })
        .collect()
}

#[cfg(test)]
#[path = "init_tests.rs"]
mod tests;
