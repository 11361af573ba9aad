//! The GPU kernels against the CPU reference, on whatever adapter the environment gives
//! (lavapipe in CI: WGPU_BACKEND=vulkan). Without an adapter every test prints why it skips.

mod adam;
mod antialias;
mod backward;
mod chunks;
mod common;
mod context;
mod depth;
mod exposure;
mod forward;
mod mcmc;
mod nerf;
mod plan;
mod semantic;
mod sort_scan;
// The scenes and photo sets of the library's CPU tests, the same file (it names the library
// `crate::splat` and `crate::rng`, hence the imports below).
#[allow(dead_code)]
#[path = "../../src/splat/cpu/test_scenes.rs"]
mod test_scenes;
mod timing;

use sylva::{rng, splat};
