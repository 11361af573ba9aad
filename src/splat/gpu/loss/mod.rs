//! Fused GPU photometric loss `L = (1 − λ) · L1 + λ · (1 − SSIM)` and its gradient with respect
//! to the rendered image, in WGSL (docs/splatting.md "Loss"; Kerbl et al. 2023: λ = 0.2, 11×11
//! Gaussian window σ = 1.5, C1 = 0.01², C2 = 0.03², zero-padded "same" convolution).
//!
//! Five compute passes, no subgroup operations, no atomics, no readback:
//!
//! 1. horizontal blur of x, y, x², y², xy (per channel);
//! 2. vertical blur, SSIM map, its derivatives with respect to the blurred maps and
//!    per-workgroup partial sums of |x − y| and SSIM;
//! 3. horizontal and
//! 4. vertical adjoint blur of those derivatives (the window is symmetric, so the adjoint of
//!    the zero-padded "same" convolution is itself), then the gradient;
//! 5. one workgroup reduces the partial sums into `loss_out = [loss, l1, ssim, 0]` (f32).
//!
//! The caller copies `loss_out` whenever it likes (e.g. together with other statistics), so the
//! loss costs no extra GPU→CPU read.

mod kernel;

pub use kernel::{LOSS_OUT_BYTES, LossKernel};

use crate::splat::cpu::loss as reference;

/// The window of the CPU reference ([`crate::splat::cpu::loss`]).
pub use reference::{SSIM_SIGMA, SSIM_WINDOW};
/// Weight λ of the D-SSIM term, the CPU reference's in f32.
pub const SSIM_LAMBDA: f32 = reference::SSIM_LAMBDA as f32;
/// SSIM stabiliser C1, the CPU reference's in f32.
pub const SSIM_C1: f32 = reference::SSIM_C1 as f32;
/// SSIM stabiliser C2, the CPU reference's in f32.
pub const SSIM_C2: f32 = reference::SSIM_C2 as f32;

/// Errors of [`LossKernel::encode`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LossError {
    /// Width or height is zero.
    EmptyImage,
    /// A buffer is smaller than the image needs, in bytes.
    BufferTooSmall {
        what: &'static str,
        needed: u64,
        got: u64,
    },
    /// A scratch buffer would exceed the device's storage binding limit, in bytes.
    ImageTooLarge { needed: u64, limit: u64 },
}

impl std::fmt::Display for LossError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LossError::EmptyImage => write!(f, "image width or height is zero"),
            LossError::BufferTooSmall { what, needed, got } => {
                write!(f, "{what} buffer has {got} bytes, needs {needed}")
            }
            LossError::ImageTooLarge { needed, limit } => write!(
                f,
                "loss scratch needs a {needed}-byte storage binding, device limit {limit}"
            ),
        }
    }
}

impl std::error::Error for LossError {}

/// The normalised 1-D Gaussian window (σ = 1.5, 11 taps): the CPU reference's, computed in f64,
/// rounded.
pub fn ssim_window() -> [f32; SSIM_WINDOW] {
    reference::ssim_window().map(|v| v as f32)
}

/// WGSL constants prepended to every pass.
fn shader_header() -> String {
    let win: Vec<String> = ssim_window().iter().map(|v| format!("{v:e}")).collect();
    format!(
        "var<private> WIN: array<f32, {n}> = array<f32, {n}>({w});\n\
         const HALF: i32 = {half};\nconst LAMBDA: f32 = {l:e};\n\
         const C1: f32 = {c1:e};\nconst C2: f32 = {c2:e};\n",
        n = SSIM_WINDOW,
        w = win.join(", "),
        half = SSIM_WINDOW / 2,
        l = SSIM_LAMBDA,
        c1 = SSIM_C1,
        c2 = SSIM_C2,
    )
}

#[cfg(test)]
mod tests;
