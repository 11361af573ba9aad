//! The per-render parameter buffer shared by every kernel (`Params` in `shaders/common.wgsl`).

use crate::splat::camera::{Camera, RenderOptions};

/// Jacobian clamp factor of the reference: 1.3 × the half field of view (docs/splatting.md step 3).
pub const JACOBIAN_CLAMP: f32 = 1.3;
/// Tile edge, pixels (docs/splatting.md "GPU layout").
pub const TILE: u32 = 16;

/// Camera and frame parameters, laid out as WGSL `Params` (16-byte rows).
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct RenderParams {
    pub rot: [[f32; 4]; 3],
    pub trans: [f32; 4],
    pub campos: [f32; 4],
    /// fx, fy, cx, cy, pixels.
    pub focal: [f32; 4],
    pub background: [f32; 4],
    /// lim_x, lim_y (tangent of the clamped half angle), width, height (pixels).
    pub lim: [f32; 4],
    /// width, height, tiles_x, tiles_y.
    pub dims: [u32; 4],
    /// Gaussians, SH degree, intersections, and 1 with [`RenderOptions::antialias`] (else 0).
    pub counts: [u32; 4],
}

impl RenderParams {
    /// Parameters of rendering `count` Gaussians at SH degree `sh_degree` through `cam` with
    /// `options`.
    pub fn new(
        cam: &Camera,
        background: [f32; 3],
        count: u32,
        sh_degree: u32,
        options: RenderOptions,
    ) -> Self {
        let r = cam.r;
        let c = cam.centre();
        let (w, h) = (cam.width, cam.height);
        RenderParams {
            rot: [
                [r[0][0], r[0][1], r[0][2], 0.0],
                [r[1][0], r[1][1], r[1][2], 0.0],
                [r[2][0], r[2][1], r[2][2], 0.0],
            ],
            trans: [cam.t[0], cam.t[1], cam.t[2], 0.0],
            campos: [c[0], c[1], c[2], 0.0],
            focal: [cam.fx, cam.fy, cam.cx, cam.cy],
            background: [background[0], background[1], background[2], 0.0],
            lim: [
                JACOBIAN_CLAMP * (w as f32 / 2.0) / cam.fx,
                JACOBIAN_CLAMP * (h as f32 / 2.0) / cam.fy,
                w as f32,
                h as f32,
            ],
            dims: [w, h, w.div_ceil(TILE), h.div_ceil(TILE)],
            counts: [count, sh_degree.min(3), 0, u32::from(options.antialias)],
        }
    }

    /// Tiles along x and y.
    pub fn tiles(&self) -> (u32, u32) {
        (self.dims[2], self.dims[3])
    }
}
