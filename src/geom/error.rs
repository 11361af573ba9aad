//! The one error type of the geometry core.

/// Why a geometry operation could not produce a result.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum GeomError {
    /// The caller cancelled the work through its `Progress`.
    #[error("cancelled")]
    Cancelled,
    /// An input coordinate, weight or parameter was NaN or infinite.
    #[error("non-finite input: {0}; remove NaN/inf values before calling")]
    NonFinite(&'static str),
    /// Two inputs that must have the same length do not.
    #[error("length mismatch: {what} ({left} vs {right})")]
    LengthMismatch {
        what: &'static str,
        left: usize,
        right: usize,
    },
    /// A parameter is outside its valid range.
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    /// The input is empty (or has fewer points than the operation needs).
    #[error("not enough points: {0}")]
    Empty(&'static str),
    /// Fewer than 3 point pairs were given to a similarity fit.
    #[error("a similarity fit needs at least 3 point pairs, got {0}; add control points")]
    TooFewPairs(usize),
    /// The pairs (or correspondences) do not span space: coincident points, or all weight on
    /// one point.
    #[error("degenerate configuration: {0}; the points must be spread out, not coincident")]
    Degenerate(&'static str),
    /// The pairs lie on one line, so the rotation about it is undetermined.
    #[error(
        "collinear point pairs: rotation about their line is undetermined; add a pair off the line"
    )]
    Collinear,
    /// The cloud does not fit in the voxel grid's key space.
    #[error(
        "cloud too large for voxel size {voxel_size} m: extent {extent} m exceeds 2^21 voxels per axis"
    )]
    GridOverflow { voxel_size: f32, extent: f32 },
    /// The k-d tree could not be built.
    #[error("spatial index: {0}")]
    Index(String),
}

impl GeomError {
    /// `Ok` when two inputs that must have the same length do: `left` items of one against
    /// `right` of the other; else [`GeomError::LengthMismatch`] naming them (`what`).
    pub fn check_len(what: &'static str, left: usize, right: usize) -> Result<(), GeomError> {
        if left == right {
            Ok(())
        } else {
            Err(GeomError::LengthMismatch { what, left, right })
        }
    }
}
