//! The GPU backend of the trainer (wgpu, WGSL kernels under shaders/).

use super::backend::TrainError;

/// The trainer's GPU backend.
pub enum GpuBackend {}

impl GpuBackend {
    /// Starts the GPU backend; this build has none yet, so it says so.
    pub fn new(_background: [f32; 3]) -> Result<Self, TrainError> {
        Err(TrainError::Device(
            "the GPU trainer is not part of this build yet; use params.train.backend = \"cpu\" for tiny scenes".into(),
        ))
    }
}
