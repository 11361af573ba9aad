//! GPU forward and backward rasteriser of 3D Gaussian splatting, plus Adam, on wgpu/WGSL.
//!
//! Conventions: `SPLATTING.md` at the workspace root (Kerbl et al. 2023; Ye & Kanazawa,
//! "Mathematical Supplement for the gsplat Library", arXiv 2312.02121).
//!
//! One training step: [`Renderer::render`] (two submissions and one 4-byte read-back, the number
//! of tile intersections, which sizes the sort buffers), then the loss kernel, then
//! [`Renderer::encode_backward`] and [`adam::GpuAdam::encode_step`] recorded into one command
//! encoder with no read-back.
//!
//! Capacity: every buffer is a single storage binding, so each must fit the adapter's
//! `max_storage_buffer_binding_size` (128 MiB on lavapipe, e.g. ≈ 699k Gaussians for the
//! 192-byte-per-Gaussian SH buffer, ≈ 33M tile intersections). Chunking into whole-Gaussian
//! ranges is not implemented: a larger buffer fails with [`GpuError::BufferTooLarge`].
//! The projection backward binds 12 storage buffers (the adapter must allow that per stage).

pub mod adam;
pub mod backend;
pub mod buffers;
pub mod context;
pub mod frame;
pub mod loss;
pub mod params;
pub mod project;
pub mod project_bwd;
pub mod raster_bwd;
pub mod raster_fwd;
pub mod renderer;
pub mod scan;
pub mod semantic;
pub mod sort;
pub mod splats;
pub mod timing;

pub use backend::GpuBackend;
pub use context::{AtomicMode, GpuContext, GpuError};
pub use frame::Frame;
pub use renderer::Renderer;
pub use splats::{GpuGrads, GpuSplats};
pub use timing::PassTimings;
