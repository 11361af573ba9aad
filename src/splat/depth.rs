//! LiDAR depth supervision (docs/splatting.md "LiDAR depth"): the registered LiDAR cloud seen
//! from each training view gives a sparse depth map, and a loss pulls the rendered expected
//! depth (Σ T α z, the rasterisers' fourth channel) towards it where the LiDAR has a return.
//!
//! - **Depth maps** ([`lidar_depth`]): every point is splatted as a disc of its physical
//!   footprint (the anchor voxel) into a z-buffer that keeps the nearest depth, so surfaces the
//!   cloud samples densely enough occlude what is behind them; a pixel whose depth is far
//!   behind the nearest depth within [`OCCLUSION_WINDOW_PX`] is dropped, because it is most
//!   likely a point seen through a gap between the points of a nearer surface.
//! - **Loss** ([`loss_and_grad`], GPU twin `shaders/depth_loss.wgsl`): λ / |V| Σ_{p ∈ V}
//!   |D_p − L_p| / L_p over the pixels V with a LiDAR depth L, D the rendered expected depth:
//!   relative, so that near and far surfaces count alike. Where the LiDAR sees a surface the
//!   photo's pixel is opaque, so the expected depth (which is not divided by the accumulated
//!   opacity) is the right quantity to compare, and its gradient also raises opacity there.
//! - **Metric** ([`depth_error`]): on held-out views, the mean absolute error in metres and
//!   the mean relative error over the LiDAR pixels.

use std::collections::HashMap;

use super::camera::Camera;

/// LiDAR depth maps of the training views and the loss weight, as a backend takes them.
#[derive(Debug, Clone, Default)]
pub struct DepthTargets {
    /// λ of the loss (0 turns it off).
    pub weight: f32,
    /// Per view name: one depth per pixel of the view's image, metres (0 = no LiDAR return).
    pub maps: HashMap<String, Vec<f32>>,
}

impl DepthTargets {
    /// The map of view `name`, when supervision is on.
    pub fn for_view(&self, name: &str) -> Option<&[f32]> {
        if self.weight <= 0.0 {
            return None;
        }
        self.maps.get(name).map(Vec::as_slice)
    }
}

/// Near limit of a LiDAR point in front of a camera, metres (as the rasteriser's near plane).
pub const NEAR_M: f32 = 0.01;

/// Half-width of the window in which a pixel's depth is compared with the nearest, pixels.
/// Two pixels: the gaps between the footprints of a sparse surface at the resolutions trained
/// here (Sylva's choice).
pub const OCCLUSION_WINDOW_PX: i32 = 2;

/// A pixel farther than `nearest × (1 + this)` + [`OCCLUSION_MARGIN_M`] behind the nearest depth
/// in its window is taken for a see-through point and dropped. Sylva's choice: 10 %.
pub const OCCLUSION_RATIO: f32 = 0.1;

/// See [`OCCLUSION_RATIO`], metres: 0.2 m, above the LiDAR noise and a stem's depth.
pub const OCCLUSION_MARGIN_M: f32 = 0.2;

/// The LiDAR depth map of `points` (world coordinates, metres) seen from `cam`: the camera
/// depth z of the nearest point per pixel (row-major `width × height`), 0 where no point
/// lands or the pixel is dropped as seen through a gap (see the module docs). Each point covers
/// a disc of radius max(0.5 px, fx · `footprint_m` / (2 z)).
pub fn lidar_depth(points: &[[f32; 3]], cam: &Camera, footprint_m: f32) -> Vec<f32> {
    let (w, h) = (cam.width as i32, cam.height as i32);
    let mut z = vec![f32::INFINITY; (w * h) as usize];
    for p in points {
        let t = cam.to_camera(*p);
        if t[2].is_nan() || t[2] <= NEAR_M {
            continue;
        }
        let u = cam.fx * t[0] / t[2] + cam.cx;
        let v = cam.fy * t[1] / t[2] + cam.cy;
        let r = (cam.fx * footprint_m / (2.0 * t[2])).max(0.5);
        if u + r < 0.0 || v + r < 0.0 || u - r >= w as f32 || v - r >= h as f32 {
            continue;
        }
        let (x0, x1) = ((u - r).floor() as i32, (u + r).ceil() as i32);
        let (y0, y1) = ((v - r).floor() as i32, (v + r).ceil() as i32);
        for y in y0.max(0)..y1.min(h) {
            for x in x0.max(0)..x1.min(w) {
                let (dx, dy) = (x as f32 + 0.5 - u, y as f32 + 0.5 - v);
                if dx * dx + dy * dy <= r * r {
                    let o = (y * w + x) as usize;
                    z[o] = z[o].min(t[2]);
                }
            }
        }
    }
    let k = OCCLUSION_WINDOW_PX;
    let mut out = vec![0.0f32; z.len()];
    for y in 0..h {
        for x in 0..w {
            let d = z[(y * w + x) as usize];
            if !d.is_finite() {
                continue;
            }
            let mut nearest = d;
            for yy in (y - k).max(0)..(y + k + 1).min(h) {
                for xx in (x - k).max(0)..(x + k + 1).min(w) {
                    nearest = nearest.min(z[(yy * w + xx) as usize]);
                }
            }
            if d <= nearest * (1.0 + OCCLUSION_RATIO) + OCCLUSION_MARGIN_M {
                out[(y * w + x) as usize] = d;
            }
        }
    }
    out
}

/// Pixels of `lidar` with a depth.
pub fn valid_count(lidar: &[f32]) -> usize {
    lidar.iter().filter(|&&l| l > 0.0).count()
}

/// The depth loss of the module docs with weight `weight` and its gradient per pixel
/// (dL/dD). `depth` and `lidar` have one entry per pixel; a map with no LiDAR pixel gives 0.
pub fn loss_and_grad(depth: &[f32], lidar: &[f32], weight: f32) -> (f64, Vec<f32>) {
    let n = valid_count(lidar);
    let mut grad = vec![0.0f32; depth.len()];
    if n == 0 || weight == 0.0 {
        return (0.0, grad);
    }
    let coef = weight / n as f32;
    let mut loss = 0.0f64;
    for ((g, &d), &l) in grad.iter_mut().zip(depth).zip(lidar) {
        if l > 0.0 {
            loss += f64::from((d - l).abs() / l);
            *g = grad_at(d, l, coef);
        }
    }
    (loss * f64::from(coef), grad)
}

/// dL/dD at one LiDAR pixel: coef · sign(D − L) / L (0 at D = L), as `depth_loss.wgsl`.
pub fn grad_at(d: f32, l: f32, coef: f32) -> f32 {
    let s = if d > l {
        1.0
    } else if d < l {
        -1.0
    } else {
        0.0
    };
    coef * s / l
}

/// Held-out depth error of a rendered expected depth against a LiDAR map: (mean absolute
/// error in metres, mean relative error) over the LiDAR pixels; `None` without any.
pub fn depth_error(depth: &[f32], lidar: &[f32]) -> Option<(f64, f64)> {
    let (mut abs, mut rel, mut n) = (0.0f64, 0.0f64, 0usize);
    for (&d, &l) in depth.iter().zip(lidar) {
        if l > 0.0 {
            let e = f64::from((d - l).abs());
            abs += e;
            rel += e / f64::from(l);
            n += 1;
        }
    }
    (n > 0).then(|| (abs / n as f64, rel / n as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        crate::splat::cpu::test_scenes::camera_facing_origin([0.0, -5.0, 0.0], 40, 30, 40.0)
    }

    /// A dense wall at y = `y` spanning x, z in [−half, half], points every `step` metres.
    fn wall(y: f32, half: f32, step: f32) -> Vec<[f32; 3]> {
        let n = (2.0 * half / step) as i32;
        let mut v = Vec::new();
        for i in 0..=n {
            for j in 0..=n {
                v.push([-half + i as f32 * step, y, -half + j as f32 * step]);
            }
        }
        v
    }

    #[test]
    fn a_near_wall_hides_a_far_one_and_gaps_are_not_seen_through() {
        // Near wall 5 m away covering the middle; far wall 10 m behind, larger, sparse points
        // of the near wall (5 cm apart, footprint 5 cm) with the far one's behind.
        let mut pts = wall(0.0, 1.0, 0.05);
        pts.extend(wall(10.0, 6.0, 0.05));
        let d = lidar_depth(&pts, &cam(), 0.05);
        let c = cam();
        // Centre pixel: the near wall, 5 m.
        let centre = d[(15 * 40 + 20) as usize];
        assert!((centre - 5.0).abs() < 0.05, "centre depth {centre}");
        // Inside the near wall's silhouette no pixel shows the far wall.
        let (u0, u1) = (c.fx * -0.9 / 5.0 + c.cx, c.fx * 0.9 / 5.0 + c.cx);
        for y in 0..30 {
            for x in 0..40 {
                let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                let inside = px > u0 && px < u1 && py > u0 - c.cx + c.cy && py < u1 - c.cx + c.cy;
                let v = d[(y * 40 + x) as usize];
                if inside {
                    assert!((v - 5.0).abs() < 0.1, "pixel {x},{y}: {v}");
                }
            }
        }
        // Far from the near wall the far wall shows, at 15 m.
        let corner = d[(2 * 40 + 5) as usize];
        assert!((corner - 15.0).abs() < 0.1, "corner {corner}");
        // A far point seen through a gap in a sparse near surface is dropped: near points
        // every 0.3 m with a 2 cm footprint leave gaps.
        let mut sparse = wall(0.0, 1.0, 0.3);
        sparse.extend(wall(10.0, 6.0, 0.05));
        let d = lidar_depth(&sparse, &cam(), 0.02);
        let centre_region: Vec<f32> = (12..18)
            .flat_map(|y| (17..23).map(move |x| (y, x)))
            .map(|(y, x)| d[(y * 40 + x) as usize])
            .collect();
        assert!(
            centre_region
                .iter()
                .all(|&v| v == 0.0 || (v - 5.0).abs() < 0.1),
            "see-through depths kept: {centre_region:?}"
        );
    }

    #[test]
    fn the_loss_is_relative_and_its_gradient_matches_finite_differences() {
        let lidar = [0.0, 2.0, 10.0, 5.0];
        let depth = [3.0f32, 2.5, 9.0, 5.2];
        let (l, g) = loss_and_grad(&depth, &lidar, 0.3);
        let want = 0.3 / 3.0 * (0.5 / 2.0 + 1.0 / 10.0 + 0.2 / 5.0);
        assert!((l - want).abs() < 1e-6, "{l} vs {want}");
        assert_eq!(g[0], 0.0);
        for i in 1..4 {
            let h = 1e-3f32;
            let mut p = depth;
            p[i] += h;
            let mut m = depth;
            m[i] -= h;
            let fd = (loss_and_grad(&p, &lidar, 0.3).0 - loss_and_grad(&m, &lidar, 0.3).0)
                / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(g[i])).abs() < 1e-4,
                "pixel {i}: {fd} vs {}",
                g[i]
            );
        }
        assert_eq!(loss_and_grad(&depth, &[0.0; 4], 1.0).0, 0.0);
        let (mae, rel) = depth_error(&depth, &lidar).expect("pixels");
        assert!((mae - 1.7 / 3.0).abs() < 1e-6 && (rel - (0.25 + 0.1 + 0.04) / 3.0).abs() < 1e-6);
    }
}
