//! The COLMAP model a structure-from-motion run would have produced: the true cameras and
//! surface points expressed in an arbitrary SfM frame (a random similarity of the world),
//! with small pose and point noise, keypoint noise, tracks and consistent 2-D point indices.
//!
//! Points3D are surface points found through random pixels of every image and kept when at
//! least [`MIN_TRACK`] cameras see them (in the frame, not occluded: a ray cast from each
//! camera centre). Their colour is the rendered pixel's.

use std::collections::BTreeMap;

use glam::{DMat3, DQuat, DVec3, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use super::camera::{Intrinsics, View};
use super::rng::{Stream, domain};
use super::scene::Scene;
use crate::io::colmap::{Camera, ColmapModel, Image, Point2D, Point3D};

/// Cameras that must see a point for it to become a points3D entry (issue: at least 3).
pub const MIN_TRACK: usize = 3;
/// Keypoint localisation noise, pixels (typical SIFT sub-pixel accuracy).
pub const KEYPOINT_NOISE_PX: f64 = 0.3;
/// Camera rotation noise per metre of `sfm_noise`, degrees (0.02° at the 1 cm default).
const ROT_NOISE_DEG_PER_M: f64 = 2.0;

/// x' = scale · R x + t.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Similarity {
    pub scale: f64,
    /// Rows of R.
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

impl Similarity {
    pub fn new(scale: f64, r: DMat3, t: DVec3) -> Similarity {
        let rows = r.transpose();
        Similarity {
            scale,
            rotation: [
                rows.x_axis.to_array(),
                rows.y_axis.to_array(),
                rows.z_axis.to_array(),
            ],
            translation: t.to_array(),
        }
    }

    pub fn matrix(&self) -> DMat3 {
        DMat3::from_cols_array_2d(&self.rotation).transpose()
    }

    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.matrix() * p * self.scale + DVec3::from_array(self.translation)
    }

    pub fn inverse(&self) -> Similarity {
        let rt = self.matrix().transpose();
        let s = 1.0 / self.scale;
        Similarity::new(s, rt, -(rt * DVec3::from_array(self.translation)) * s)
    }

    /// A random similarity: scale log-uniform in [0.2, 5], uniform rotation, offset in
    /// [-50, 50]³ SfM units (the "scale 0.2–5, any rotation, any offset").
    pub fn random(rng: &mut Stream) -> Similarity {
        let scale = rng.range(0.2f64.ln(), 5.0f64.ln()).exp();
        let q =
            DQuat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize();
        let t = DVec3::new(
            rng.range(-50.0, 50.0),
            rng.range(-50.0, 50.0),
            rng.range(-50.0, 50.0),
        );
        Similarity::new(scale, DMat3::from_quat(q), t)
    }
}

/// A surface point found through a pixel of image `view`, with that pixel's colour.
#[derive(Debug, Clone, Copy)]
pub struct Candidate {
    pub view: usize,
    pub point: Vec3,
    pub rgb: [u8; 3],
}

/// Picks `count` random pixels of view `k` and returns the surface points behind them.
pub fn candidates(
    scene: &Scene,
    cam: &Intrinsics,
    view: &View,
    k: usize,
    count: usize,
    pixels: &[u8],
    seed: u64,
) -> Vec<Candidate> {
    let mut rng = Stream::new(seed, domain::KEYPOINTS, k as u64);
    let inv = view.rot.transpose();
    let o = view.center.as_vec3();
    let mut out = Vec::with_capacity(count);
    for _ in 0..count {
        let (u, v) = (
            rng.range(0.0, cam.width as f64),
            rng.range(0.0, cam.height as f64),
        );
        let d = (inv * cam.ray(u, v)).as_vec3().normalize();
        if let Some(hit) = scene.intersect(o, d, 0.0, 1.0e3) {
            let idx = (v as usize * cam.width as usize + u as usize) * 3;
            let rgb = pixels
                .get(idx..idx + 3)
                .map_or([0; 3], |p| [p[0], p[1], p[2]]);
            out.push(Candidate {
                view: k,
                point: o + d * hit.t,
                rgb,
            });
        }
    }
    out
}

/// Settings of the export.
pub struct ExportParams {
    /// Target number of points3D (kept ones are thinned evenly to at most this).
    pub points3d: usize,
    /// Noise on points and camera centres, metres (scene units before scaling).
    pub noise_m: f64,
    pub seed: u64,
}

/// Builds the model in the SfM frame given by `world_to_sfm` (scene frame → SfM).
pub fn build_model(
    scene: &Scene,
    cam: &Intrinsics,
    views: &[View],
    cands: &[Candidate],
    world_to_sfm: &Similarity,
    p: &ExportParams,
) -> ColmapModel {
    // Tracks: every camera that sees the candidate, with its true pixel position.
    let tracks: Vec<Vec<(usize, [f64; 2])>> = cands
        .par_iter()
        .map(|c| {
            let pw = c.point.as_dvec3();
            views
                .iter()
                .enumerate()
                .filter_map(|(k, v)| {
                    let uv = cam.project(v.to_camera(pw))?;
                    (cam.inside(uv) && scene.visible(v.center.as_vec3(), c.point, 0.01))
                        .then_some((k, uv))
                })
                .collect()
        })
        .collect();
    let kept: Vec<usize> = (0..cands.len())
        .filter(|&i| tracks[i].len() >= MIN_TRACK)
        .collect();
    let chosen: Vec<usize> = if kept.len() > p.points3d {
        (0..p.points3d)
            .map(|k| kept[k * kept.len() / p.points3d])
            .collect()
    } else {
        kept
    };

    // Cameras in the SfM frame, with pose noise.
    let q = world_to_sfm.matrix();
    let s = world_to_sfm.scale;
    let mut images: BTreeMap<u32, Image> = BTreeMap::new();
    let mut poses: Vec<(DMat3, DVec3)> = Vec::with_capacity(views.len());
    for (k, v) in views.iter().enumerate() {
        let mut rng = Stream::new(p.seed, domain::SFM, 1 + k as u64);
        let sigma = (ROT_NOISE_DEG_PER_M * p.noise_m).to_radians();
        let wobble = DMat3::from_quat(DQuat::from_scaled_axis(
            DVec3::new(rng.normal(), rng.normal(), rng.normal()) * sigma,
        ));
        let rot = wobble * v.rot * q.transpose();
        let c = world_to_sfm.apply(v.center)
            + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * (p.noise_m * s);
        let t = -(rot * c);
        let mut qv = DQuat::from_mat3(&rot).normalize();
        if qv.w < 0.0 {
            qv = -qv;
        }
        poses.push((rot, t));
        images.insert(
            k as u32 + 1,
            Image {
                id: k as u32 + 1,
                qvec: [qv.w, qv.x, qv.y, qv.z],
                tvec: t.to_array(),
                camera_id: 1,
                name: v.name.clone(),
                points2d: Vec::new(),
            },
        );
    }

    let mut points = Vec::with_capacity(chosen.len());
    for (n, &ci) in chosen.iter().enumerate() {
        let mut rng = Stream::new(p.seed, domain::TRACK, ci as u64);
        let c = &cands[ci];
        let noisy =
            c.point.as_dvec3() + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * p.noise_m;
        let xyz = world_to_sfm.apply(noisy);
        let id = n as u64 + 1;
        let mut track = Vec::with_capacity(tracks[ci].len());
        let mut err = 0.0;
        for &(k, uv) in &tracks[ci] {
            let obs = [
                (uv[0] + rng.normal() * KEYPOINT_NOISE_PX).clamp(0.0, cam.width as f64 - 1e-3),
                (uv[1] + rng.normal() * KEYPOINT_NOISE_PX).clamp(0.0, cam.height as f64 - 1e-3),
            ];
            let (rot, t) = poses[k];
            if let Some(proj) = cam.project(rot * xyz + t) {
                err += (proj[0] - obs[0]).hypot(proj[1] - obs[1]);
            }
            if let Some(img) = images.get_mut(&(k as u32 + 1)) {
                track.push((img.id, img.points2d.len() as u32));
                img.points2d.push(Point2D {
                    xy: obs,
                    point3d_id: Some(id),
                });
            }
        }
        let error = err / track.len().max(1) as f64;
        points.push(Point3D {
            id,
            xyz,
            rgb: c.rgb,
            error,
            track,
        });
    }

    // Keypoints without a 3-D point, as real detectors produce (about one in ten).
    for img in images.values_mut() {
        let mut rng = Stream::new(p.seed, domain::KEYPOINTS, 1 << 32 | img.id as u64);
        for _ in 0..img.points2d.len() / 10 {
            let xy = [
                rng.range(0.0, cam.width as f64),
                rng.range(0.0, cam.height as f64),
            ];
            img.points2d.push(Point2D {
                xy,
                point3d_id: None,
            });
        }
    }
    let camera = Camera {
        id: 1,
        model: cam.model,
        width: cam.width as u64,
        height: cam.height as u64,
        params: cam.params(),
    };
    ColmapModel {
        cameras: BTreeMap::from([(1, camera)]),
        images,
        points,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn similarity_inverse_round_trips() {
        let mut rng = Stream::new(3, 0, 0);
        for _ in 0..20 {
            let s = Similarity::random(&mut rng);
            assert!((0.2..=5.0).contains(&s.scale));
            let p = DVec3::new(12.5, -3.0, 7.25);
            let back = s.inverse().apply(s.apply(p));
            assert!((back - p).length() < 1e-9);
        }
    }
}
