//! A pinhole camera as the rasteriser sees it (see docs/splatting.md).

use serde::{Deserialize, Serialize};

/// Pinhole intrinsics (pixels) and a world→camera pose (COLMAP convention:
/// `x_cam = R x_world + t`, +z forward, x right, y down; pixel centres at i + 0.5).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    /// Focal lengths, pixels.
    pub fx: f32,
    pub fy: f32,
    /// Principal point, pixels (image origin at the top-left corner of the first pixel).
    pub cx: f32,
    pub cy: f32,
    /// World→camera rotation, row-major.
    pub r: [[f32; 3]; 3],
    /// World→camera translation, metres.
    pub t: [f32; 3],
}

/// How a view is rasterised besides its camera (docs/splatting.md "Forward", step 4). Both
/// rasterisers take it: the CPU reference ([`crate::splat::cpu::render_with`]) and the GPU one
/// (`Params.counts.w` of `shaders/common.wgsl`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct RenderOptions {
    /// Mip-Splatting's 2-D filter (Yu et al. 2024, "Mip-Splatting: Alias-free 3D Gaussian
    /// Splatting"; gsplat `rasterize_mode="antialiased"`): the screen-space blur of variance
    /// [`crate::splat::cpu::project::LOW_PASS`] (0.3 px²) keeps its size, and each Gaussian's
    /// opacity is multiplied by `ρ = sqrt(det Σ2D / det(Σ2D + 0.3 · I))`, so a Gaussian smaller
    /// than a pixel renders dimmer rather than larger and as bright, and its total light does
    /// not depend on the resolution. Default off (the reference 3DGS dilation, Kerbl et al. 2023).
    pub antialias: bool,
}

impl Camera {
    /// Camera centre in the world: -Rᵀ t.
    pub fn centre(&self) -> [f32; 3] {
        let r = &self.r;
        let t = &self.t;
        [
            -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
            -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
            -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]),
        ]
    }
    /// World point to camera coordinates.
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let r = &self.r;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + self.t[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + self.t[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + self.t[2],
        ]
    }
    /// A camera at `eye` looking at `target` with world up `up` (for tests and synthetic views).
    pub fn look_at(
        eye: [f32; 3],
        target: [f32; 3],
        up: [f32; 3],
        width: u32,
        height: u32,
        fx: f32,
    ) -> Self {
        let sub = |a: [f32; 3], b: [f32; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let cross = |a: [f32; 3], b: [f32; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let norm = |a: [f32; 3]| {
            let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-12);
            [a[0] / l, a[1] / l, a[2] / l]
        };
        let z = norm(sub(target, eye));
        // x (image right) = forward × up; y (image down) = forward × right.
        let x = norm(cross(z, up));
        let y = cross(z, x);
        let r = [x, y, z];
        let t = [
            -(r[0][0] * eye[0] + r[0][1] * eye[1] + r[0][2] * eye[2]),
            -(r[1][0] * eye[0] + r[1][1] * eye[1] + r[1][2] * eye[2]),
            -(r[2][0] * eye[0] + r[2][1] * eye[1] + r[2][2] * eye[2]),
        ];
        Camera {
            width,
            height,
            fx,
            fy: fx,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
            r,
            t,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_puts_target_on_axis_and_up_upwards() {
        let cam = Camera::look_at(
            [0.0, -5.0, 2.0],
            [0.0, 0.0, 2.0],
            [0.0, 0.0, 1.0],
            64,
            48,
            50.0,
        );
        let p = cam.to_camera([0.0, 0.0, 2.0]);
        assert!(p[0].abs() < 1e-5 && p[1].abs() < 1e-5 && (p[2] - 5.0).abs() < 1e-5);
        // A point above the target appears above the centre (negative image y).
        let q = cam.to_camera([0.0, 0.0, 3.0]);
        assert!(q[1] < 0.0);
        let c = cam.centre();
        assert!((c[1] + 5.0).abs() < 1e-5 && (c[2] - 2.0).abs() < 1e-5);
    }
}
