//! Forest analysis: the ground model, wood/leaf segmentation, stems and their diameters at
//! breast height, the per-tree inventory and its comparison with field data.
//!
//! The pipeline of [`inventory`] follows docs/method.md Stages 3 and 5 on the LiDAR cloud:
//! ground (cloth simulation, [`ground`]) → wood/leaf labels on the non-ground points
//! ([`segment`], paper 3.4) → stems from the trunk points in a band around breast height
//! ([`stems`]) → a robust circle per stem at 1.3 m above ground in the stem's own frame
//! ([`dbh`], [`ransac`], [`circle`]). Built on the geometry room (`geom`); nothing here knows
//! about jobs or HTTP.

pub mod accuracy;
pub mod allometry;
pub mod circle;
pub mod components;
pub mod crowns;
pub mod dbh;
pub mod grid;
pub mod ground;
pub mod inventory;
pub mod kmeans;
pub mod output;
pub mod ransac;
pub mod segment;
mod stem_axis;
mod stem_base;
pub mod stem_labels;
pub mod stems;
pub mod summary;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod unit_tests;

pub use accuracy::{
    FieldComparison, MatchedTree, accuracy_lines, compare_with_field, compare_with_field_file,
};
pub use allometry::{AllometryParams, Equations, TreeAllometry, tree_allometry};
pub use circle::{CircleFit, fit_circle_weighted};
pub use crowns::{
    CrownParams, HeightQuality, TreeCrown, TreeSegmentation, segment_trees, segment_trees_labelled,
};
pub use dbh::{
    DbhParams, FitQuality, SliceCenterPrior, SliceSource, StemDbh, measure_dbh, measure_dbh_of,
    slice_offsets,
};
pub use inventory::{CloudKind, Inventory, InventoryParams, PhaseSeconds, TreeRow, inventory};
pub use output::{
    PLOT_FILE, PlotFile, read_crs, trees_csv, trees_geojson, write_crs, write_trees_csv,
    write_trees_geojson, write_trees_gpkg,
};
pub use ransac::{
    CenterPrior, CircleParams, RobustCircle, fit_circle_robust, fit_circle_robust_weighted,
};
pub use segment::{LEAF, SegmentParams, SegmentSeconds, TRUNK, WoodLeaf, segment_wood_leaf};
pub use stem_labels::{StemLabelParams, label_stem_points};
pub use stems::{Stem, StemParams, detect_stems};
pub use summary::{DbhSource, PlotSummary, SummaryParams, footprint, summarise, summary_lines};

use crate::geom::GeomError;
use crate::io::IoError;
use ground::GroundError;

/// Why a forest analysis could not produce a result.
#[derive(Debug, thiserror::Error)]
pub enum ForestError {
    /// A parameter is outside its valid range; the message names it.
    #[error("invalid forest parameters: {0}")]
    Params(String),
    /// The cloud (or the part of it an operation needs) is too small.
    #[error("not enough points: {0}")]
    NotEnoughPoints(String),
    /// The cloud is not what the inventory can measure as asked (a slice, no ground); the
    /// message says what is missing and what to do.
    #[error("{0}")]
    NotAPlot(String),
    /// The ground filter failed.
    #[error("ground filter: {0}")]
    Ground(GroundError),
    /// A geometry operation (spatial index, features) failed.
    #[error("geometry: {0}")]
    Geom(GeomError),
    /// Reading field data or writing an output failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The progress sink asked to stop.
    #[error("cancelled")]
    Cancelled,
}

impl From<GeomError> for ForestError {
    fn from(e: GeomError) -> Self {
        match e {
            GeomError::Cancelled => ForestError::Cancelled,
            e => ForestError::Geom(e),
        }
    }
}

impl From<GroundError> for ForestError {
    fn from(e: GroundError) -> Self {
        match e {
            GroundError::Cancelled => ForestError::Cancelled,
            e => ForestError::Ground(e),
        }
    }
}
