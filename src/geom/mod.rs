//! Point-cloud geometry core: the spatial index, voxel homogenisation, the statistical outlier
//! filter, normals and eigen features, closed-form similarity (Umeyama) and ICP, and the
//! registration science built on them: the automatic coarse alignment ([`coarse`]), the
//! surface refinement ([`surface`]) and what stage `register` does with them ([`register`]:
//! two-phase ICP, refinement passes, verifying the automatic candidates).
//!
//! Everything here works on plain slices of `glam::Vec3` positions in metres relative to a
//! local origin (f32 keeps sub-millimetre precision over a plot), with optional `[u8; 3]`
//! colours. Solvers (covariances, similarity, ICP normal equations) run in f64 and return
//! `DMat3`/`DVec3`. Whole-cloud passes run on all cores with rayon, report progress through
//! [`crate::progress::Progress`] and stop with [`GeomError::Cancelled`] when asked to.
//!
//! The algorithms follow docs/method.md Stages 1–2 (paper sections 3.3 and registration); where
//! the paper is silent the choice is written down on the function.

pub mod coarse;
mod error;
mod icp;
mod index;
mod linalg;
mod normals;
mod orient;
mod outliers;
mod pca;
pub mod register;
mod similarity;
pub mod surface;
mod voxel;

pub use error::GeomError;
pub use icp::{IcpMethod, IcpParams, IcpResult, IcpWeights, RobustKernel, icp, icp_weighted};
pub use index::{Neighbour, PointIndex};
pub use linalg::gemm;
pub(crate) use linalg::solve3;
pub use normals::{
    EigenFeatures, NormalOrientation, NormalParams, Normals, eigen_features, estimate_normals,
    estimate_normals_with_index,
};
pub use outliers::{
    OutlierFilter, OutlierParams, statistical_outlier_filter, statistical_outlier_filter_with_index,
};
pub use pca::{SymmetricEigen3, covariance, symmetric_eigen3};
pub use similarity::{Similarity, SimilarityFit, similarity_from_pairs, weighted_similarity};
pub use voxel::{VoxelDownsample, voxel_downsample, voxel_members};
