//! Sylva: forest plot digital twins from handheld LiDAR and UAV photos.
//!
//! The data flows one way: HTTP in (`api`) → job row (`jobs`) → worker (`worker`) → pipeline
//! stages (`pipeline`, built on `io`) → artifacts (`store`) → HTTP out. Lower rooms never
//! import higher ones: `io` and `gpu` know nothing of the pipeline, the pipeline nothing of
//! HTTP or SQL.
//!
//! The command line (clap) and the benchmarks (`sylva bench …`) are the binary's, in
//! `src/main.rs`; the settings in [`config`] are plain structs, which derive clap's `Args` only
//! under the `cli` feature (on by default) for the binary to flatten into its commands.

// Lets code shared with the integration tests (tests/common/postgres.rs, compiled into the
// job store's unit tests too) name this crate `sylva` from inside it.
extern crate self as sylva;

pub mod api;
pub mod config;
pub mod forest;
pub mod gc;
pub mod geom;
pub mod gpu;
pub mod io;
pub mod jobs;
pub mod nerf;
pub mod pipeline;
pub mod progress;
pub mod rng;
pub mod sfm;
pub mod splat;
pub mod stage;
pub mod store;
pub mod synth;
#[doc(hidden)]
pub mod testing;
pub mod webhooks;
pub mod worker;
