//! GPU forward and backward rasteriser of 3D Gaussian splatting, plus Adam, on wgpu/WGSL.
//!
//! Conventions: `docs/splatting.md` (Kerbl et al. 2023; Ye & Kanazawa,
//! "Mathematical Supplement for the gsplat Library", arXiv 2312.02121).
//!
//! One training step: [`Renderer::render`] (two submissions and one 4-byte read-back, the number
//! of tile intersections, which sizes the sort buffers), then the loss kernel, then
//! [`Renderer::encode_backward`] and [`adam::GpuAdam::encode_step`] recorded into one command
//! encoder with no read-back. With per-image exposure compensation ([`exposure`]) the render
//! goes through the image's transform before the loss and back through it after, in the same
//! encoder.
//!
//! Capacity: per-Gaussian buffers (parameters, gradients, Adam moments, densification
//! statistics; up to 192 bytes per Gaussian for the SH block) may exceed one storage binding:
//! kernels bind them in whole-Gaussian chunks ([`chunks`]), so they are limited by the adapter's
//! `max_buffer_size` only. The projected records (48 bytes per Gaussian) and the screen-space
//! gradients (40 bytes), read and written at random by the rasterisers, are bound as up to four
//! whole-Gaussian slots ([`chunks::SlotPlan`]): 4 bindings' worth (on lavapipe's 128 MiB,
//! 11.18M Gaussians). The intersection arrays (4 bytes per intersection each) are split into
//! bands of tile rows that each fit one binding ([`renderer::plan_bands`]), so only one row of
//! 16-pixel tiles must fit (33.5M intersections on lavapipe). Past these, and for the per-pixel
//! images, rendering fails with [`GpuError::BufferTooLarge`], which names the buffer. The
//! raster backward binds 14 storage buffers (the adapter must allow that per stage).

pub mod adam;
pub mod backend;
pub mod chunks;
pub mod depth;
pub mod exposure;
pub mod frame;
pub mod loss;
pub mod mcmc;
pub mod params;
pub mod photos;
pub mod project;
pub mod project_bwd;
pub mod raster_bwd;
pub mod raster_fwd;
pub mod renderer;
pub mod semantic;
pub mod splats;

pub use crate::gpu::{buffers, context, scan, sort, timing};
pub use backend::GpuBackend;
pub use context::{AtomicMode, GpuContext, GpuError};
pub use frame::Frame;
pub use renderer::Renderer;
pub use splats::{GpuGrads, GpuSplats};
pub use timing::PassTimings;
