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
mod semantic;
mod sort_scan;
mod timing;
