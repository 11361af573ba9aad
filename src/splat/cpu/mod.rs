//! CPU reference of the Gaussian-splatting rasteriser, its backward pass and the photometric
//! loss, in f64 internally (inputs and outputs are the f32 types of `splat_core`).
//!
//! Conventions: `docs/splatting.md` (Kerbl et al. 2023; Ye & Kanazawa,
//! "Mathematical Supplement for the gsplat Library", arXiv 2312.02121). The GPU kernels are
//! tested against this crate.

pub mod exposure;
pub mod linalg;
pub mod loss;
pub mod project;
pub mod raster;
pub mod sh;

#[cfg(test)]
pub(crate) mod test_scenes;
#[cfg(test)]
mod tests_fd;
#[cfg(test)]
mod tests_render;

pub use loss::LossValue;
pub use project::{Projected, ProjectedGrad};

use crate::splat::camera::{Camera, RenderOptions};
use crate::splat::model::{GaussianGrads, Gaussians, SH_FLOATS};

/// Gradient of the loss with respect to one Gaussian's parameters (f64).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamGrad {
    /// dL/dmean, per metre.
    pub mean: [f64; 3],
    /// dL/dlog_scale.
    pub log_scale: [f64; 3],
    /// dL/drotation, for the stored (unnormalised) quaternion (w, x, y, z).
    pub rotation: [f64; 4],
    /// dL/dopacity_logit.
    pub opacity_logit: f64,
    /// dL/dsh, coefficient-major like the model; zero above the active degree.
    pub sh: [f64; SH_FLOATS],
}

impl Default for ParamGrad {
    fn default() -> Self {
        ParamGrad {
            mean: [0.0; 3],
            log_scale: [0.0; 3],
            rotation: [0.0; 4],
            opacity_logit: 0.0,
            sh: [0.0; SH_FLOATS],
        }
    }
}

/// Errors of the public entry points (inconsistent inputs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CpuError {
    /// The model's per-Gaussian vectors have different lengths.
    InconsistentModel,
    /// An image or gradient buffer does not have `width · height` pixels.
    ImageSize { expected: usize, got: usize },
}

impl std::fmt::Display for CpuError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CpuError::InconsistentModel => write!(f, "model vectors have different lengths"),
            CpuError::ImageSize { expected, got } => {
                write!(f, "image has {got} pixels, expected {expected}")
            }
        }
    }
}

impl std::error::Error for CpuError {}

/// A rendered view and what its backward needs.
#[derive(Debug, Clone, PartialEq)]
pub struct Render {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Colour including the background, RGB, row-major (`y · width + x`).
    pub image: Vec<[f32; 3]>,
    /// Final transmittance per pixel (the background weight), in [1e-4, 1].
    pub final_t: Vec<f32>,
    /// Number of Gaussians blended into each pixel.
    pub n_contrib: Vec<u32>,
    /// Every Gaussian's projection (culled ones have `visible == false`).
    pub projected: Vec<Projected>,
    /// Visible Gaussians sorted front to back by depth (stable).
    pub depth_order: Vec<u32>,
    /// Expected depth per pixel, Σ T α z, metres (`raster::RasterOutput::depth`).
    pub depth: Vec<f32>,
    /// The camera, background (RGB in [0, 1]) and options it was rendered with: its backward
    /// uses the same.
    pub camera: Camera,
    pub background: [f32; 3],
    pub options: RenderOptions,
    image_f64: Vec<[f64; 3]>,
    final_t_f64: Vec<f64>,
    depth_f64: Vec<f64>,
}

impl Render {
    /// The image in f64, as composited (before rounding to f32).
    pub fn image_f64(&self) -> &[[f64; 3]] {
        &self.image_f64
    }

    /// The expected depth in f64, as composited.
    pub fn depth_f64(&self) -> &[f64] {
        &self.depth_f64
    }
}

fn check_len(expected: usize, got: usize) -> Result<(), CpuError> {
    if expected == got {
        Ok(())
    } else {
        Err(CpuError::ImageSize { expected, got })
    }
}

/// Renders `model` seen from `cam` over `background` (RGB in [0, 1]) with the default
/// [`RenderOptions`] (the reference 3DGS dilation).
pub fn render(model: &Gaussians, cam: &Camera, background: [f32; 3]) -> Result<Render, CpuError> {
    render_with(model, cam, background, RenderOptions::default())
}

/// [`render`] with `options` (e.g. Mip-Splatting's 2-D filter, [`RenderOptions::antialias`]).
pub fn render_with(
    model: &Gaussians,
    cam: &Camera,
    background: [f32; 3],
    options: RenderOptions,
) -> Result<Render, CpuError> {
    if !model.is_consistent() {
        return Err(CpuError::InconsistentModel);
    }
    let projected = project::project_all(model, cam, options);
    let order = raster::depth_order(&projected);
    let out = raster::rasterize(
        &projected,
        &order,
        cam.width,
        cam.height,
        background.map(f64::from),
    );
    Ok(Render {
        width: cam.width,
        height: cam.height,
        camera: *cam,
        background,
        image: out.image.iter().map(|p| p.map(|v| v as f32)).collect(),
        final_t: out.final_t.iter().map(|&t| t as f32).collect(),
        n_contrib: out.n_contrib,
        projected,
        depth_order: order,
        depth: out.depth.iter().map(|&d| d as f32).collect(),
        options,
        image_f64: out.image,
        final_t_f64: out.final_t,
        depth_f64: out.depth,
    })
}

/// Backward of [`render`] in f64; see [`render_backward`].
pub fn render_backward_f64(
    model: &Gaussians,
    render: &Render,
    dl_dimage: &[[f64; 3]],
    dl_ddepth: Option<&[f64]>,
) -> Result<(Vec<ParamGrad>, Vec<f64>), CpuError> {
    if !model.is_consistent() || render.projected.len() != model.len() {
        return Err(CpuError::InconsistentModel);
    }
    check_len(render.image.len(), dl_dimage.len())?;
    if let Some(d) = dl_ddepth {
        check_len(render.image.len(), d.len())?;
    }
    let pgrads = raster::rasterize_backward(
        &render.projected,
        &render.depth_order,
        render.width,
        render.height,
        render.background.map(f64::from),
        &render.final_t_f64,
        &render.n_contrib,
        dl_dimage,
        dl_ddepth,
    );
    let (half_w, half_h) = (
        0.5 * f64::from(render.width),
        0.5 * f64::from(render.height),
    );
    let mut grads = Vec::with_capacity(model.len());
    let mut stat = Vec::with_capacity(model.len());
    for (i, g) in pgrads.iter().enumerate() {
        grads.push(project::project_backward(
            model,
            i,
            &render.camera,
            render.options,
            g,
        ));
        stat.push(if render.projected[i].visible {
            (g.mean2d[0] * half_w).hypot(g.mean2d[1] * half_h)
        } else {
            0.0
        });
    }
    Ok((grads, stat))
}

/// Gradients of a loss with respect to every parameter, given `dl_dimage` = dL/d`render.image`
/// (per pixel RGB), for the `model` that produced `render` (with the camera, background and options
/// it holds), and, when given, `dl_ddepth` = dL/d`render.depth`.
/// Also returns the densification statistic per Gaussian: `|dL/dmean2d|` with the pixel
/// gradient scaled by `(0.5 · width, 0.5 · height)` (the reference's NDC gradient), 0 when culled.
pub fn render_backward(
    model: &Gaussians,
    render: &Render,
    dl_dimage: &[[f32; 3]],
    dl_ddepth: Option<&[f32]>,
) -> Result<(GaussianGrads, Vec<f32>), CpuError> {
    let g64: Vec<[f64; 3]> = dl_dimage.iter().map(|p| p.map(f64::from)).collect();
    let d64: Option<Vec<f64>> = dl_ddepth.map(|d| d.iter().map(|&v| f64::from(v)).collect());
    let (grads, stat) = render_backward_f64(model, render, &g64, d64.as_deref())?;
    let mut out = GaussianGrads::zeros(model.len());
    for (i, g) in grads.iter().enumerate() {
        out.means[i] = g.mean.map(|v| v as f32);
        out.log_scales[i] = g.log_scale.map(|v| v as f32);
        out.rotations[i] = g.rotation.map(|v| v as f32);
        out.opacity_logits[i] = g.opacity_logit as f32;
        out.sh[i] = g.sh.map(|v| v as f32);
    }
    Ok((out, stat.iter().map(|&s| s as f32).collect()))
}

/// The training loss of `rendered` against `target` (both `width · height` RGB pixels,
/// row-major) and dL/drendered.
pub fn loss_and_grad(
    rendered: &[[f32; 3]],
    target: &[[f32; 3]],
    width: u32,
    height: u32,
) -> Result<(LossValue, Vec<[f32; 3]>), CpuError> {
    let (x, y) = (to_f64(rendered), to_f64(target));
    let (value, grad) = loss_and_grad_f64(&x, &y, width, height)?;
    Ok((value, grad.iter().map(|p| p.map(|v| v as f32)).collect()))
}

/// [`loss_and_grad`] in f64.
pub fn loss_and_grad_f64(
    rendered: &[[f64; 3]],
    target: &[[f64; 3]],
    width: u32,
    height: u32,
) -> Result<(LossValue, Vec<[f64; 3]>), CpuError> {
    let n = width as usize * height as usize;
    check_len(n, rendered.len())?;
    check_len(n, target.len())?;
    Ok(loss::loss_f64(
        rendered,
        target,
        width as usize,
        height as usize,
        true,
    ))
}

fn to_f64(img: &[[f32; 3]]) -> Vec<[f64; 3]> {
    img.iter().map(|p| p.map(f64::from)).collect()
}
