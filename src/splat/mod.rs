//! Gaussian splatting: the model, cameras and images, initialisation, the optimiser and the
//! densification strategy, evaluation and export (docs/method.md Stage 4; conventions in
//! docs/splatting.md). The CPU reference of the rasteriser lives in [`cpu`] and the GPU kernels
//! in [`gpu`]; [`trainer`] ties them into the training loop that stage `train` and
//! `sylva train` run.

pub mod adam;
pub mod backend;
pub mod bind;
pub mod budget;
pub mod camera;
pub mod camera_models;
pub mod cameras;
pub mod config;
pub mod cpu;
pub mod dataset;
pub mod depth;
pub mod eval;
pub mod export;
pub mod export_gltf;
pub mod export_splat;
pub mod export_spz;
pub mod exposure;
pub mod gpu;
pub mod init;
pub mod lpips;
pub mod mcmc;
pub mod model;
pub mod packed_image;
pub mod photo;
pub mod plan;
pub mod plot;
pub mod semantic;
pub mod start;
pub mod strategy;
pub mod tiles;
pub mod trainer;
pub mod trunk_diag;
