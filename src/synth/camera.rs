//! UAV camera simulator: intrinsics with known distortion, flight plans (orbits for single
//! trees, grid plus oblique rings for stands, paper 2.2) and images rendered by ray casting
//! the scene under sun and sky light with cast shadows and a one-ray sky-visibility term.
//!
//! Camera frame as COLMAP: x right, y down, z forward; pixel (i, j) covers [i, i+1) × [j, j+1)
//! with the origin at the top-left corner of the image. Images are rendered in parallel, one
//! task per image, each writing its own file, so the output does not depend on scheduling.

use glam::{DMat3, DVec3, Vec3};

use super::layout::Plot;
use super::presets::Flight;
use super::rng::{Stream, domain};
use super::scene::{Material, Scene, linear_to_srgb};
use crate::io::colmap::CameraModel;

/// Horizontal field of view, degrees (a DJI Mavic 3E wide camera is 84° diagonal ≈ 72°
/// horizontal).
pub const HFOV_DEG: f64 = 72.0;
/// Reach of the ambient-occlusion ray, metres: nearby foliage and stems darken a surface;
/// the canopy's shadow on the ground comes from the sun ray.
pub const AO_RANGE_M: f32 = 3.0;
/// SIMPLE_RADIAL k1 used for the rendered images (mild barrel distortion).
pub const DEFAULT_K1: f64 = -0.04;

/// Intrinsics of the one camera all images share.
#[derive(Debug, Clone, Copy)]
pub struct Intrinsics {
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    /// Focal length, pixels.
    pub f: f64,
    pub cx: f64,
    pub cy: f64,
    /// Radial distortion (SIMPLE_RADIAL only; 0 for PINHOLE).
    pub k1: f64,
}

impl Intrinsics {
    pub fn new(width: u32, height: u32, pinhole: bool) -> Intrinsics {
        // The field of view spans the longer side, so portrait frames (`object`) are a phone
        // held upright rather than a wider lens.
        let f = 0.5 * width.max(height) as f64 / (0.5 * HFOV_DEG.to_radians()).tan();
        Intrinsics {
            model: if pinhole {
                CameraModel::Pinhole
            } else {
                CameraModel::SimpleRadial
            },
            width,
            height,
            f,
            cx: 0.5 * width as f64,
            cy: 0.5 * height as f64,
            k1: if pinhole { 0.0 } else { DEFAULT_K1 },
        }
    }

    /// COLMAP parameters: PINHOLE (fx, fy, cx, cy) or SIMPLE_RADIAL (f, cx, cy, k).
    pub fn params(&self) -> Vec<f64> {
        match self.model {
            CameraModel::Pinhole => vec![self.f, self.f, self.cx, self.cy],
            _ => vec![self.f, self.cx, self.cy, self.k1],
        }
    }

    /// Pixel position of a camera-frame point, if in front of the camera.
    pub fn project(&self, pc: DVec3) -> Option<[f64; 2]> {
        if pc.z <= 1e-6 {
            return None;
        }
        let (x, y) = (pc.x / pc.z, pc.y / pc.z);
        let d = 1.0 + self.k1 * (x * x + y * y);
        Some([self.f * x * d + self.cx, self.f * y * d + self.cy])
    }

    /// True when pixel position `uv` lies inside the image.
    pub fn inside(&self, uv: [f64; 2]) -> bool {
        uv[0] >= 0.0 && uv[1] >= 0.0 && uv[0] < self.width as f64 && uv[1] < self.height as f64
    }

    /// Unit camera-frame direction through pixel position (u, v) (fixed-point undistortion).
    pub fn ray(&self, u: f64, v: f64) -> DVec3 {
        let (xd, yd) = ((u - self.cx) / self.f, (v - self.cy) / self.f);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..12 {
            let d = 1.0 + self.k1 * (x * x + y * y);
            x = xd / d;
            y = yd / d;
        }
        DVec3::new(x, y, 1.0).normalize()
    }
}

/// One camera pose in the scene frame.
#[derive(Debug, Clone)]
pub struct View {
    pub name: String,
    pub center: DVec3,
    /// World→camera rotation (rows: right, down, forward).
    pub rot: DMat3,
}

impl View {
    /// A camera at `center` looking at `target`; `up` decides the roll.
    pub fn look_at(name: String, center: DVec3, target: DVec3, up: DVec3) -> View {
        let fwd = (target - center).normalize_or(DVec3::NEG_Z);
        let right = fwd
            .cross(up)
            .try_normalize()
            .unwrap_or_else(|| fwd.any_orthonormal_vector());
        let down = fwd.cross(right);
        View {
            name,
            center,
            rot: DMat3::from_cols(right, down, fwd).transpose(),
        }
    }

    pub fn to_camera(&self, p: DVec3) -> DVec3 {
        self.rot * (p - self.center)
    }
}

/// The flight: `n` views with names `img_0001.jpg` (or .png) in flight order.
pub fn plan_flight(plot: &Plot, flight: Flight, n: usize, seed: u64, ext: &str) -> Vec<View> {
    let mut rng = Stream::new(seed, domain::FLIGHT, 0);
    let top = plot
        .trees
        .iter()
        .map(|t| t.base.z + t.height_m)
        .fold(f64::NEG_INFINITY, f64::max);
    let height = plot.trees.iter().map(|t| t.height_m).fold(0.0, f64::max);
    let extent = plot
        .trees
        .iter()
        .map(|t| t.base.truncate().length() + t.crown_radius_m)
        .fold(plot.radius_m, f64::max);
    let name = |k: usize| format!("img_{:04}.{ext}", k + 1);
    let mut views = Vec::with_capacity(n);
    let ring =
        |views: &mut Vec<View>, rng: &mut Stream, count: usize, radius: f64, alt: f64, aim: f64| {
            let phase = rng.range(0.0, std::f64::consts::TAU);
            for i in 0..count {
                let a = phase
                    + std::f64::consts::TAU * i as f64 / count as f64
                    + rng.range(-0.03, 0.03);
                let (x, y) = (radius * a.cos(), radius * a.sin());
                let c = DVec3::new(
                    x,
                    y,
                    plot.scene.terrain.height(x, y).max(0.0) + alt + rng.range(-0.3, 0.3),
                );
                let target = DVec3::new(rng.range(-0.5, 0.5), rng.range(-0.5, 0.5), aim);
                views.push(View::look_at(name(views.len()), c, target, DVec3::Z));
            }
        };
    match flight {
        Flight::Orbit => {
            let rings: &[(f64, f64, f64)] = if n >= 60 {
                &[(0.35, 5.0, 0.3), (0.8, 8.0, 0.45), (1.3, 11.0, 0.45)]
            } else {
                &[(0.35, 5.0, 0.3), (1.1, 9.0, 0.45)]
            };
            let mut left = n;
            for (k, &(alt, dr, aim)) in rings.iter().enumerate() {
                let count = if k + 1 == rings.len() {
                    left
                } else {
                    n / rings.len()
                };
                left -= count;
                ring(
                    &mut views,
                    &mut rng,
                    count,
                    extent + dr,
                    alt * height,
                    aim * height,
                );
            }
        }
        Flight::Walk => {
            // Two laps (close at the stem, a step back looking up), each frame with the
            // wobble of a hand-held phone; the stem of the first tree is the centre.
            let base = plot.trees.first().map_or(DVec3::ZERO, |t| t.base);
            let near = n / 2;
            for (lap, count) in [(0usize, near), (1, n - near)] {
                let phase = rng.range(0.0, std::f64::consts::TAU);
                for i in 0..count {
                    let a = phase
                        + std::f64::consts::TAU * i as f64 / count.max(1) as f64
                        + rng.range(-0.04, 0.04);
                    let r = if lap == 0 { 2.2 } else { 3.6 } + rng.range(-0.3, 0.3);
                    let (x, y) = (base.x + r * a.cos(), base.y + r * a.sin());
                    let ground = plot.scene.terrain.height(x, y);
                    let c = DVec3::new(x, y, ground + rng.range(1.4, 1.75));
                    let aim = if lap == 0 {
                        rng.range(0.8, 2.0)
                    } else {
                        rng.range(2.0, 0.6 * height.max(3.5))
                    };
                    let target = DVec3::new(
                        base.x + rng.range(-0.3, 0.3),
                        base.y + rng.range(-0.3, 0.3),
                        base.z + aim,
                    );
                    views.push(View::look_at(name(views.len()), c, target, DVec3::Z));
                }
            }
        }
        Flight::GridOblique => {
            let n_grid = (0.36 * n as f64).round() as usize;
            let cols = (n_grid as f64).sqrt().ceil().max(1.0) as usize;
            let rows = n_grid.div_ceil(cols);
            let alt = top + 18.0;
            for r in 0..rows {
                for c in 0..cols {
                    if views.len() == n_grid {
                        break;
                    }
                    let cc = if r % 2 == 0 { c } else { cols - 1 - c };
                    let x = -plot.radius_m + 2.0 * plot.radius_m * (cc as f64 + 0.5) / cols as f64;
                    let y = -plot.radius_m + 2.0 * plot.radius_m * (r as f64 + 0.5) / rows as f64;
                    let center =
                        DVec3::new(x + rng.range(-0.5, 0.5), y + rng.range(-0.5, 0.5), alt);
                    // Nearly nadir, a few degrees off so the views are not all parallel.
                    let target =
                        center + DVec3::new(rng.range(-0.08, 0.08), rng.range(-0.08, 0.08), -1.0);
                    views.push(View::look_at(name(views.len()), center, target, DVec3::Y));
                }
            }
            let rest = n - views.len();
            let inner = rest / 2;
            ring(
                &mut views,
                &mut rng,
                inner,
                extent + 4.0,
                height + 6.0,
                0.3 * height,
            );
            ring(
                &mut views,
                &mut rng,
                rest - inner,
                extent + 10.0,
                height + 12.0,
                0.2 * height,
            );
        }
    }
    views
}

/// Sun and sky (linear radiance units; the paper's data was taken in soft, uniform light, so
/// the sky term is strong).
#[derive(Debug, Clone, Copy)]
pub struct Lighting {
    /// Unit direction towards the sun.
    pub sun_dir: Vec3,
    pub sun: Vec3,
    pub sky_zenith: Vec3,
    pub sky_horizon: Vec3,
    /// Diffuse sky light reaching a surface (the hemisphere average: nearly white under a
    /// hazy sky, bluer than the sun).
    pub ambient: Vec3,
}

impl Lighting {
    /// Sun elevation 40–65°, any azimuth.
    pub fn from_seed(seed: u64) -> Lighting {
        let mut rng = Stream::new(seed, domain::FLIGHT, 1);
        let el = rng.range(40.0, 65.0).to_radians();
        let az = rng.range(0.0, std::f64::consts::TAU);
        Lighting {
            sun_dir: Vec3::new(
                (el.cos() * az.cos()) as f32,
                (el.cos() * az.sin()) as f32,
                el.sin() as f32,
            ),
            sun: Vec3::new(1.9, 1.8, 1.65),
            sky_zenith: Vec3::new(0.30, 0.45, 0.80),
            sky_horizon: Vec3::new(0.72, 0.78, 0.86),
            ambient: Vec3::new(0.60, 0.63, 0.68),
        }
    }

    fn sky(&self, d: Vec3) -> Vec3 {
        let t = d.z.clamp(0.0, 1.0).sqrt();
        self.sky_horizon * (1.0 - t) + self.sky_zenith * t
    }
}

/// Linear radiance seen along the ray (o, d).
pub fn shade(scene: &Scene, light: &Lighting, o: Vec3, d: Vec3) -> Vec3 {
    let Some(hit) = scene.intersect(o, d, 0.0, 1.0e4) else {
        return light.sky(d);
    };
    let s = scene.surface(o, d, hit);
    let p = s.point + s.normal * 2e-3;
    let ndl = s.normal.dot(light.sun_dir);
    // One sun ray: from the lit side, or through a leaf (leaves let some light through).
    let direct = if ndl > 0.0 {
        if scene.occluded(p, light.sun_dir, 0.0, 1.0e4) {
            0.0
        } else {
            ndl
        }
    } else if s.material == Material::Leaf
        && !scene.occluded(s.point - s.normal * 2e-3, light.sun_dir, 0.0, 1.0e4)
    {
        -0.35 * ndl
    } else {
        0.0
    };
    // Local ambient occlusion: one ray towards the upper sky, within AO_RANGE_M.
    let up = (s.normal + Vec3::Z * 1.5).normalize();
    let sky_vis = if scene.occluded(p, up, 0.0, AO_RANGE_M) {
        0.35
    } else {
        1.0
    };
    let ambient = light.ambient * (sky_vis * (0.6 + 0.4 * s.normal.z.max(0.0)));
    let c = s.albedo * (light.sun * direct + ambient * 1.2);
    // Aerial perspective over long distances.
    let haze = 1.0 - (-hit.t / 600.0).exp();
    c * (1.0 - haze) + light.sky_horizon * haze
}

/// Sub-pixel sample offsets for 1, 2 or 4 samples per pixel (rotated grid).
pub fn sample_offsets(spp: u32) -> &'static [(f64, f64)] {
    match spp {
        0 | 1 => &[(0.5, 0.5)],
        2 | 3 => &[(0.25, 0.25), (0.75, 0.75)],
        _ => &[
            (0.375, 0.125),
            (0.875, 0.375),
            (0.125, 0.625),
            (0.625, 0.875),
        ],
    }
}

/// Renders one view to 8-bit sRGB, row-major RGB.
pub fn render(scene: &Scene, light: &Lighting, cam: &Intrinsics, view: &View, spp: u32) -> Vec<u8> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut buf = vec![0u8; w * h * 3];
    let offsets = sample_offsets(spp);
    let inv = view.rot.transpose();
    let o = view.center.as_vec3();
    for j in 0..h {
        for i in 0..w {
            let mut acc = Vec3::ZERO;
            for &(du, dv) in offsets {
                let d = (inv * cam.ray(i as f64 + du, j as f64 + dv))
                    .as_vec3()
                    .normalize();
                acc += shade(scene, light, o, d);
            }
            let rgb = linear_to_srgb(acc / offsets.len() as f32);
            buf[(j * w + i) * 3..(j * w + i) * 3 + 3].copy_from_slice(&rgb);
        }
    }
    buf
}
