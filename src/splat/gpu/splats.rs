//! The Gaussian model and its gradients on the GPU: one storage buffer per parameter.

use crate::splat::model::{GaussianGrads, Gaussians, SH_FLOATS};

use crate::splat::gpu::buffers::{chunked_uploaded, chunked_zeroed, read_buffer};
use crate::splat::gpu::chunks::ChunkPlan;
use crate::splat::gpu::context::{GpuContext, GpuError};

/// A [`Gaussians`] model on the GPU (`trunk_prob` stays on the CPU: it is not trained).
/// Each buffer may exceed one storage binding: kernels bind it in [`GpuSplats::plan`] chunks.
/// Layout per buffer: flat `f32`, `means` 3, `log_scales` 3, `rotations` 4 (w, x, y, z),
/// `opacity_logits` 1, `sh` 48 (coefficient-major) floats per Gaussian.
pub struct GpuSplats {
    pub means: wgpu::Buffer,
    pub log_scales: wgpu::Buffer,
    pub rotations: wgpu::Buffer,
    pub opacity_logits: wgpu::Buffer,
    pub sh: wgpu::Buffer,
    /// Number of Gaussians.
    pub count: u32,
    /// Active SH degree (0..=3).
    pub sh_degree: u32,
    /// How kernels split the Gaussians into chunks that fit one binding.
    pub plan: ChunkPlan,
}

fn check_count(n: usize) -> Result<u32, GpuError> {
    u32::try_from(n)
        .ok()
        .filter(|&c| c < u32::MAX / SH_FLOATS as u32)
        .ok_or_else(|| GpuError::Invalid(format!("{n} Gaussians is too many for one GPU model")))
}

impl GpuSplats {
    /// Uploads `model` (fresh buffers; call again after densification changes the count).
    pub fn upload(ctx: &GpuContext, model: &Gaussians) -> Result<Self, GpuError> {
        if !model.is_consistent() {
            return Err(GpuError::Invalid(
                "the model's parameter vectors differ in length".into(),
            ));
        }
        let count = check_count(model.len())?;
        Ok(GpuSplats {
            means: chunked_uploaded(ctx, "means", &model.means)?,
            log_scales: chunked_uploaded(ctx, "log_scales", &model.log_scales)?,
            rotations: chunked_uploaded(ctx, "rotations", &model.rotations)?,
            opacity_logits: chunked_uploaded(ctx, "opacity_logits", &model.opacity_logits)?,
            sh: chunked_uploaded(ctx, "sh", &model.sh)?,
            count,
            sh_degree: model.sh_degree.min(3),
            plan: ChunkPlan::new(ctx, count)?,
        })
    }

    /// The parameter buffers with their floats per Gaussian, in [`GaussianGrads`] order.
    pub fn buffers(&self) -> [(&wgpu::Buffer, usize); 5] {
        [
            (&self.means, 3),
            (&self.log_scales, 3),
            (&self.rotations, 4),
            (&self.opacity_logits, 1),
            (&self.sh, SH_FLOATS),
        ]
    }

    /// Reads the parameters back into `model` (blocking), keeping its `trunk_prob` (which must
    /// have the GPU model's length) and setting `sh_degree`.
    pub fn download_into(&self, ctx: &GpuContext, model: &mut Gaussians) -> Result<(), GpuError> {
        let n = self.count as usize;
        if model.trunk_prob.len() != n {
            return Err(GpuError::Invalid(format!(
                "download into a model of {} Gaussians from a GPU model of {n}",
                model.trunk_prob.len()
            )));
        }
        model.means = read_buffer(ctx, &self.means, n)?;
        model.log_scales = read_buffer(ctx, &self.log_scales, n)?;
        model.rotations = read_buffer(ctx, &self.rotations, n)?;
        model.opacity_logits = read_buffer(ctx, &self.opacity_logits, n)?;
        model.sh = read_buffer(ctx, &self.sh, n)?;
        model.sh_degree = self.sh_degree;
        Ok(())
    }
}

/// Gradients of every parameter (same layout as [`GpuSplats`]) plus the densification
/// statistic, accumulated over views until [`GpuGrads::reset_stats`].
pub struct GpuGrads {
    pub means: wgpu::Buffer,
    pub log_scales: wgpu::Buffer,
    pub rotations: wgpu::Buffer,
    pub opacity_logits: wgpu::Buffer,
    pub sh: wgpu::Buffer,
    /// Densification statistics, 3 floats per Gaussian: Σ over views of
    /// `|dL/dm ⊙ (0.5 w, 0.5 h)|` (pixel gradient → the reference's NDC gradient), the
    /// number of views in which the Gaussian was visible (`radius > 0`), and the largest
    /// screen radius in pixels over those views.
    pub densify: wgpu::Buffer,
    /// Number of Gaussians.
    pub count: u32,
}

impl GpuGrads {
    /// The parameter gradients in [`GpuSplats::buffers`]' order (the densification statistics
    /// not included).
    pub fn buffers(&self) -> [&wgpu::Buffer; 5] {
        [
            &self.means,
            &self.log_scales,
            &self.rotations,
            &self.opacity_logits,
            &self.sh,
        ]
    }

    /// Zero gradients and statistics for `count` Gaussians.
    pub fn new(ctx: &GpuContext, count: u32) -> Result<Self, GpuError> {
        let n = count as u64 * 4;
        Ok(GpuGrads {
            means: chunked_zeroed(ctx, "grad means", 3 * n)?,
            log_scales: chunked_zeroed(ctx, "grad log_scales", 3 * n)?,
            rotations: chunked_zeroed(ctx, "grad rotations", 4 * n)?,
            opacity_logits: chunked_zeroed(ctx, "grad opacity_logits", n)?,
            sh: chunked_zeroed(ctx, "grad sh", SH_FLOATS as u64 * n)?,
            densify: chunked_zeroed(ctx, "densify stats", 3 * n)?,
            count,
        })
    }

    /// Records zeroing of the densification statistics.
    pub fn reset_stats(&self, enc: &mut wgpu::CommandEncoder) {
        enc.clear_buffer(&self.densify, 0, None);
    }

    /// Reads the gradients back (blocking).
    pub fn download(&self, ctx: &GpuContext) -> Result<GaussianGrads, GpuError> {
        let n = self.count as usize;
        Ok(GaussianGrads {
            means: read_buffer(ctx, &self.means, n)?,
            log_scales: read_buffer(ctx, &self.log_scales, n)?,
            rotations: read_buffer(ctx, &self.rotations, n)?,
            opacity_logits: read_buffer(ctx, &self.opacity_logits, n)?,
            sh: read_buffer(ctx, &self.sh, n)?,
        })
    }

    /// Reads the densification statistics back (blocking): accumulated gradient norm, views
    /// where visible, and the largest screen radius in pixels.
    pub fn download_stats(&self, ctx: &GpuContext) -> Result<DeviceStats, GpuError> {
        let rows: Vec<[f32; 3]> = read_buffer(ctx, &self.densify, self.count as usize)?;
        Ok(DeviceStats {
            grad_sum: rows.iter().map(|r| r[0]).collect(),
            visible_count: rows.iter().map(|r| r[1] as u32).collect(),
            max_radius: rows.iter().map(|r| r[2]).collect(),
        })
    }
}

/// The densification statistics as the GPU accumulated them (per Gaussian).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceStats {
    /// Σ over views of the NDC positional gradient norm.
    pub grad_sum: Vec<f32>,
    /// Views in which the Gaussian was visible.
    pub visible_count: Vec<u32>,
    /// Largest screen radius over those views, pixels.
    pub max_radius: Vec<f32>,
}
