//! Front-to-back alpha compositing of projected Gaussians (docs/splatting.md "Forward", per pixel)
//! and its back-to-front backward.
//!
//! Coverage follows the GPU's 16×16 tiles: a Gaussian is evaluated at every pixel of every tile
//! that its screen rectangle `mean2d ± radius` touches ([`tile_rect`]), exactly like a tiled
//! rasteriser; pixels outside its rectangle but inside such a tile are evaluated too.

use crate::splat::cpu::project::{Projected, ProjectedGrad};
use rayon::prelude::*;

/// Tile edge, pixels (docs/splatting.md "GPU layout").
pub const TILE: u32 = 16;
/// Upper clamp on a Gaussian's alpha (Kerbl et al. 2023).
pub const ALPHA_MAX: f64 = 0.99;
/// Gaussians with alpha below this are skipped at a pixel.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Compositing stops before a Gaussian that would drive the transmittance below this.
pub const T_MIN: f64 = 1e-4;

/// Result of [`rasterize`], f64, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct RasterOutput {
    /// Composited colour including the background.
    pub image: Vec<[f64; 3]>,
    /// Final transmittance per pixel.
    pub final_t: Vec<f64>,
    /// Number of Gaussians blended into each pixel.
    pub n_contrib: Vec<u32>,
    /// Expected depth per pixel, Σ T_i α_i z_i over the blended Gaussians (z the camera-space
    /// depth, metres; the background adds nothing): the depth a LiDAR depth loss compares.
    pub depth: Vec<f64>,
}

/// Tiles `[x0, x1) × [y0, y1)` touched by the closed rectangle `mean2d ± radius`, clamped to the
/// tile grid of a `width × height` image; `None` when invisible or the range is empty.
/// Tile `k` spans pixel coordinates `[16k, 16k + 16)`.
pub fn tile_rect(p: &Projected, width: u32, height: u32) -> Option<[u32; 4]> {
    if !p.visible {
        return None;
    }
    let r = f64::from(p.radius);
    let span = |m: f64, n: u32| -> Option<(u32, u32)> {
        let tiles = n.div_ceil(TILE) as i64;
        let lo = (((m - r) / f64::from(TILE)).floor() as i64).max(0);
        let hi = (((m + r) / f64::from(TILE)).floor() as i64).min(tiles - 1);
        (lo <= hi).then_some((lo as u32, hi as u32 + 1))
    };
    let (x0, x1) = span(p.mean2d[0], width)?;
    let (y0, y1) = span(p.mean2d[1], height)?;
    Some([x0, y0, x1, y1])
}

/// Indices of the visible Gaussians sorted by depth, front to back (stable: ties keep index
/// order).
pub fn depth_order(projected: &[Projected]) -> Vec<u32> {
    let mut order: Vec<u32> = (0..projected.len() as u32)
        .filter(|&i| projected[i as usize].visible)
        .collect();
    order.sort_by(|&a, &b| {
        projected[a as usize]
            .depth
            .total_cmp(&projected[b as usize].depth)
    });
    order
}

/// Per-tile lists of Gaussian indices in depth order.
fn bin_tiles(projected: &[Projected], order: &[u32], width: u32, height: u32) -> Vec<Vec<u32>> {
    let tiles_x = width.div_ceil(TILE);
    let mut bins = vec![Vec::new(); (tiles_x * height.div_ceil(TILE)) as usize];
    for &i in order {
        if let Some([x0, y0, x1, y1]) = tile_rect(&projected[i as usize], width, height) {
            for ty in y0..y1 {
                for tx in x0..x1 {
                    bins[(ty * tiles_x + tx) as usize].push(i);
                }
            }
        }
    }
    bins
}

/// One Gaussian blended at one pixel.
#[derive(Debug, Clone, Copy)]
struct Hit {
    /// Gaussian index.
    index: u32,
    /// `min(0.99, opacity · gauss)`.
    alpha: f64,
    /// `exp(power)`.
    gauss: f64,
    /// `mean2d − pixel centre`, pixels.
    delta: [f64; 2],
    /// True where the 0.99 clamp is active (no gradient to opacity and shape).
    clamped: bool,
}

/// Alpha of Gaussian `index` at pixel centre `(px, py)`, `None` where skipped (power > 0 or
/// alpha < 1/255).
fn alpha_at(projected: &[Projected], index: u32, px: f64, py: f64) -> Option<Hit> {
    let p = &projected[index as usize];
    let d = [p.mean2d[0] - px, p.mean2d[1] - py];
    let [a, b, c] = p.conic;
    let power = -0.5 * (a * d[0] * d[0] + c * d[1] * d[1]) - b * d[0] * d[1];
    if power > 0.0 {
        return None;
    }
    let gauss = power.exp();
    let raw = p.opacity * gauss;
    let alpha = raw.min(ALPHA_MAX);
    (alpha >= ALPHA_MIN).then_some(Hit {
        index,
        alpha,
        gauss,
        delta: d,
        clamped: raw > ALPHA_MAX,
    })
}

/// The Gaussians blended at one pixel, front to back, with their alphas.
fn pixel_contributors(projected: &[Projected], list: &[u32], px: f64, py: f64) -> (Vec<Hit>, f64) {
    let mut t = 1.0;
    let mut out = Vec::new();
    for &i in list {
        if let Some(hit) = alpha_at(projected, i, px, py) {
            let t_next = t * (1.0 - hit.alpha);
            if t_next < T_MIN {
                break;
            }
            out.push(hit);
            t = t_next;
        }
    }
    (out, t)
}

/// One composited pixel: colour, final transmittance, contributors, expected depth.
type PixelOut = ([f64; 3], f64, u32, f64);

/// Composites a `width × height` image over `background` (RGB).
pub fn rasterize(
    projected: &[Projected],
    order: &[u32],
    width: u32,
    height: u32,
    background: [f64; 3],
) -> RasterOutput {
    let bins = bin_tiles(projected, order, width, height);
    let tiles_x = width.div_ceil(TILE);
    let rows: Vec<Vec<PixelOut>> = (0..height)
        .into_par_iter()
        .map(|y| {
            (0..width)
                .map(|x| {
                    let list = &bins[((y / TILE) * tiles_x + x / TILE) as usize];
                    let (contrib, t) =
                        pixel_contributors(projected, list, f64::from(x) + 0.5, f64::from(y) + 0.5);
                    let mut colour = [0.0; 3];
                    let mut depth = 0.0;
                    let mut tc = 1.0;
                    for hit in &contrib {
                        let p = &projected[hit.index as usize];
                        for (c, rgb) in colour.iter_mut().zip(p.rgb) {
                            *c += tc * hit.alpha * rgb;
                        }
                        depth += tc * hit.alpha * p.depth;
                        tc *= 1.0 - hit.alpha;
                    }
                    for ch in 0..3 {
                        colour[ch] += t * background[ch];
                    }
                    (colour, t, contrib.len() as u32, depth)
                })
                .collect()
        })
        .collect();
    let mut out = RasterOutput {
        image: Vec::new(),
        final_t: Vec::new(),
        n_contrib: Vec::new(),
        depth: Vec::new(),
    };
    for (colour, t, n, depth) in rows.into_iter().flatten() {
        out.image.push(colour);
        out.final_t.push(t);
        out.n_contrib.push(n);
        out.depth.push(depth);
    }
    out
}

/// Backward of [`rasterize`]: per Gaussian dL/d(mean2d, conic, rgb, opacity, depth) from
/// dL/dimage and, when given, dL/d(expected depth) per pixel (`dl_ddepth`; the depth is a
/// fourth channel whose background is 0). Walks each pixel's contributors back to front
/// starting from its final transmittance (`final_t`) and contributor count (`n_contrib`) of the
/// forward pass.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
    projected: &[Projected],
    order: &[u32],
    width: u32,
    height: u32,
    background: [f64; 3],
    final_t: &[f64],
    n_contrib: &[u32],
    dl_dimage: &[[f64; 3]],
    dl_ddepth: Option<&[f64]>,
) -> Vec<ProjectedGrad> {
    let bins = bin_tiles(projected, order, width, height);
    let tiles_x = width.div_ceil(TILE);
    let n = projected.len();
    // At most 16 row chunks (each with its own accumulator), summed in a fixed order so the
    // result does not depend on the thread count.
    let rows_per_chunk = height.div_ceil(16).max(8);
    let chunks: Vec<u32> = (0..height.div_ceil(rows_per_chunk)).collect();
    let partials: Vec<Vec<ProjectedGrad>> = chunks
        .par_iter()
        .map(|&chunk| {
            let mut acc = vec![ProjectedGrad::default(); n];
            let y_end = ((chunk + 1) * rows_per_chunk).min(height);
            for y in chunk * rows_per_chunk..y_end {
                for x in 0..width {
                    let pix = (y * width + x) as usize;
                    let list = &bins[((y / TILE) * tiles_x + x / TILE) as usize];
                    let (contrib, _) =
                        pixel_contributors(projected, list, f64::from(x) + 0.5, f64::from(y) + 0.5);
                    let count = (n_contrib[pix] as usize).min(contrib.len());
                    let g = dl_dimage[pix];
                    let gd = dl_ddepth.map_or(0.0, |d| d[pix]);
                    let mut t = final_t[pix];
                    let mut behind = background;
                    let mut behind_depth = 0.0;
                    for hit in contrib[..count].iter().rev() {
                        let Hit {
                            index: i,
                            alpha,
                            gauss,
                            delta: d,
                            clamped,
                        } = *hit;
                        let p = &projected[i as usize];
                        t /= 1.0 - alpha;
                        let ga = &mut acc[i as usize];
                        let mut dalpha = 0.0;
                        for ch in 0..3 {
                            ga.rgb[ch] += t * alpha * g[ch];
                            dalpha += t * (p.rgb[ch] - behind[ch]) * g[ch];
                            behind[ch] = alpha * p.rgb[ch] + (1.0 - alpha) * behind[ch];
                        }
                        ga.depth += t * alpha * gd;
                        dalpha += t * (p.depth - behind_depth) * gd;
                        behind_depth = alpha * p.depth + (1.0 - alpha) * behind_depth;
                        if clamped {
                            continue;
                        }
                        // alpha = o · exp(power)
                        ga.opacity += gauss * dalpha;
                        let dpower = alpha * dalpha;
                        let [a, b, c] = p.conic;
                        ga.mean2d[0] -= dpower * (a * d[0] + b * d[1]);
                        ga.mean2d[1] -= dpower * (c * d[1] + b * d[0]);
                        ga.conic[0] -= 0.5 * dpower * d[0] * d[0];
                        ga.conic[1] -= dpower * d[0] * d[1];
                        ga.conic[2] -= 0.5 * dpower * d[1] * d[1];
                    }
                }
            }
            acc
        })
        .collect();
    let mut total = vec![ProjectedGrad::default(); n];
    for part in partials {
        for (t, p) in total.iter_mut().zip(part) {
            for k in 0..2 {
                t.mean2d[k] += p.mean2d[k];
            }
            for k in 0..3 {
                t.conic[k] += p.conic[k];
                t.rgb[k] += p.rgb[k];
            }
            t.opacity += p.opacity;
            t.depth += p.depth;
        }
    }
    total
}
