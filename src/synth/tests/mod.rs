//! End-to-end tests of the generator on the `tiny` preset (about a second per run with the
//! test profile's opt-level 3): the files and their formats in `outputs`, agreement with the
//! truth in `truth_checks`. Helpers shared by both live here.

mod outputs;
mod truth_checks;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3, Vec3};
use serde_json::Value;

use super::*;
use crate::forest::circle::fit_circle_weighted;
use crate::io::colmap::{ColmapModel, read_model};
use crate::io::pointcloud::read_point_cloud;
use crate::progress::NoProgress;

pub(super) fn tiny(seed: u64) -> SynthParams {
    SynthParams {
        seed,
        ..SynthParams::new(Preset::Tiny)
    }
}

pub(super) fn files(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).expect("read_dir").flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(root).expect("prefix").to_path_buf());
            }
        }
    }
    out.sort();
    out
}

pub(super) fn truth(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).expect("truth.json"))
        .expect("json")
}

pub(super) fn similarity(v: &Value) -> Similarity {
    serde_json::from_value::<SimilarityDe>(v.clone())
        .expect("similarity")
        .into()
}

#[derive(serde::Deserialize)]
pub(super) struct SimilarityDe {
    scale: f64,
    rotation: [[f64; 3]; 3],
    translation: [f64; 3],
}

impl From<SimilarityDe> for Similarity {
    fn from(s: SimilarityDe) -> Self {
        Similarity {
            scale: s.scale,
            rotation: s.rotation,
            translation: s.translation,
        }
    }
}

pub(super) fn vec3(v: &Value) -> DVec3 {
    let a: Vec<f64> = serde_json::from_value(v.clone()).expect("vec3");
    DVec3::new(a[0], a[1], a[2])
}

pub(super) fn small(seed: u64) -> SynthParams {
    SynthParams {
        lidar_points: Some(20_000),
        ..tiny(seed)
    }
}

/// Every track entry points at a 2-D point that points back, and tracks hold >= 3 images.
pub(super) fn check_tracks(m: &ColmapModel) {
    for p in &m.points {
        assert!(p.track.len() >= 3);
        for &(img, idx) in &p.track {
            let pt = m
                .images
                .get(&img)
                .and_then(|i| i.points2d.get(idx as usize))
                .expect("track target");
            assert_eq!(pt.point3d_id, Some(p.id));
        }
    }
}

/// Projects an SfM point with a written image and camera (PINHOLE or SIMPLE_RADIAL).
pub(super) fn project(
    m: &ColmapModel,
    img: &crate::io::colmap::Image,
    x: DVec3,
) -> Option<[f64; 2]> {
    let cam = m.cameras.get(&img.camera_id)?;
    let [w, qx, qy, qz] = img.qvec;
    let r = DMat3::from_quat(DQuat::from_xyzw(qx, qy, qz, w));
    let pc = r * x + DVec3::from_array(img.tvec);
    if pc.z <= 0.0 {
        return None;
    }
    let (u, v) = (pc.x / pc.z, pc.y / pc.z);
    let p = &cam.params;
    let (fx, fy, cx, cy, k) = if p.len() == 4 && cam.model.name() == "PINHOLE" {
        (p[0], p[1], p[2], p[3], 0.0)
    } else {
        (p[0], p[0], p[1], p[2], p[3])
    };
    let d = 1.0 + k * (u * u + v * v);
    Some([fx * u * d + cx, fy * v * d + cy])
}
